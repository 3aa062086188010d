"""Module 7's settings (the folder's test_config.yaml is generated from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.errors import ConfigError
from matchplant.model_test.cover import cover_project
from matchplant.model_test.inputs import check_device
from matchplant.model_test.runtime_onnx import MISSING_FIX, RUNTIMES, available


@dataclass
class EvalConfig:
    """Evaluation on annotated tiles (module 5's test split)."""

    dataset_json: Path | None = param(None, "COCO JSON of the test tiles; null = no evaluation", path="file")
    images: Path | None = param(None, "folder of the test tiles; null = the JSON's folder", path="dir")
    max_detections: int = param(
        300, "boxes per tile kept and scored (COCOeval maxDets; COCO's 100 loses plants on dense tiles)", min=1
    )
    operating_threshold: float = param(0.5, "score threshold for precision, recall, F1 and drawn boxes", min=0, max=1)
    drawn_images: int = param(8, "how many tiles to draw with their true (green) and found (red) boxes", min=0)


@dataclass
class DetectConfig:
    """Detection on whole new images (undistorted photos), tiled with overlap and merged."""

    images: Path | None = param(
        None,
        "an image or a folder of images (e.g. ODM's opensfm/undistorted/images); null = no detection",
        path="exists",
    )
    tile_size: int | None = param(
        None,
        "tile side in pixels; null = the training tile size the checkpoint "
        "records (a warning when another size makes plants >2x or <0.5x their "
        "training size in the detector's input)",
        min=32,
    )
    overlap: int | None = param(
        None,
        "overlap between tiles in pixels, larger than the largest plant; null = "
        "the training tiles' overlap from the checkpoint (at most half the tile)",
        min=0,
    )
    score_threshold: float = param(0.5, "keep boxes scoring at least this", min=0, max=1)
    merge_iou: float = param(
        0.5, "boxes of the same class from overlapping tiles with IoU above this are one plant", min=0, max=1
    )
    merge_containment: float = param(
        0.8,
        "a box lying at least this share inside a larger box of the same "
        "class (from another tile, or on the photo's final boxes) is the same "
        "plant (nested duplicate): the lower-scoring box of the two is dropped "
        "(on equal scores, the inner one); 1 = only boxes wholly inside",
        min=0.01,
        max=1,
    )
    edge_margin: float = param(
        2.0,
        "a box within this many pixels of a tile border inside the image is "
        "'cut'; it is dropped when another tile sees the whole plant",
        min=0,
    )
    drawn_images: int = param(4, "how many images to draw with their detections", min=0)
    cover: int = param(
        0,
        "0 = detect on every photo; k >= 1 = only on the fewest photos that see every point of the field at least "
        "k times (from their footprints on the DSM; k = 2 keeps module 8's plants at a fraction of the time; the "
        "estimates for the cover and for every photo are logged before work starts)",
        min=0,
    )
    runtime: Literal["auto", "torch", "onnx"] = param(
        "auto",
        "what runs the detector on new images on a CPU: onnx (its convolutions in ONNX Runtime: same boxes, "
        "faster; bench/bench_detect_runtime.py), torch, or auto (onnx when onnxruntime is installed, else torch); "
        "evaluation always runs in PyTorch",
        choices=list(RUNTIMES),
    )
    project_dir: Path | None = param(
        None,
        "the ODM project whose footprints choose detect.cover's photos; null = detect.images when it is an ODM "
        "project folder",
        path="dir",
    )


@dataclass
class ModelTestConfig:
    """Module 7: COCO evaluation of a trained detector and detection on new images."""

    checkpoint: Path = param(
        None, "model checkpoint from module 6 (e.g. runs/train/checkpoints/best.pt)", path="file", required=True
    )
    class_names: list[str] = param(
        [],
        "for a checkpoint from outside MatchPlant (the paper's layout or a bare "
        "torchvision state_dict): its class names, in the order it was trained "
        "with (e.g. [maize]); [] = a module 6 checkpoint, which holds them",
    )
    output_dir: Path = param(Path("runs/test"), "where metrics, figures and predictions go", path="out")
    evaluate: EvalConfig = section(EvalConfig)
    detect: DetectConfig = section(DetectConfig)
    batch_size: int = param(4, "tiles per batch", min=1)
    num_workers: int = param(0, "processes loading test tiles (0 = in the main process)", min=0)
    device: str = param("auto", "auto picks CUDA, then Apple MPS, then CPU; or cpu, cuda, cuda:N, mps")
    threads: int = param(
        0,
        "CPU threads for torch (0 = auto: the cores this process may use less those busy with other work, logged)",
        min=0,
    )
    amp: bool = param(True, "mixed precision on CUDA GPUs")

    def check(self) -> None:
        """Clear errors for what no single key's check sees: the device, overlap vs tile, nothing to do, onnx, cover."""
        check_device(self.device)
        if None not in (self.detect.overlap, self.detect.tile_size) and self.detect.overlap >= self.detect.tile_size:
            raise ConfigError(
                f"detect.overlap ({self.detect.overlap}) must be smaller than detect.tile_size "
                f"({self.detect.tile_size})",
                fix="lower detect.overlap (e.g. a quarter of the tile)",
            )
        if self.evaluate.dataset_json is None and self.detect.images is None:
            raise ConfigError(
                "nothing to do: neither evaluate.dataset_json nor detect.images is set",
                fix="set evaluate.dataset_json (test tiles) and/or detect.images (new images)",
            )
        if self.detect.runtime == "onnx" and not available():
            raise ConfigError("detect.runtime: onnx, but onnxruntime is not installed", fix=MISSING_FIX)
        if self.detect.cover and self.detect.images is not None:
            cover_project(self.detect.images, self.detect.project_dir)  # an error now, not after the model loads
