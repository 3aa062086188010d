"""Module 6's settings (the folder's train_config.yaml and transfer_config.yaml are generated from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.cores import usable_cores
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.data import AugmentConfig
from matchplant.detection.device import DEVICE_CHOICES
from matchplant.detection.model import PARTS, ModelConfig

log = get_logger("model_train")

SCHEDULES = ("step", "multistep", "cosine", "constant")


@dataclass
class LearningRates:
    """Learning rate of each part of the detector (the paper: backbone 0.005, RPN and ROI heads 0.01)."""

    backbone: float = param(0.005, "ResNet/MobileNet feature extractor", min=0)
    fpn: float = param(0.005, "feature pyramid (part of the backbone in the paper)", min=0)
    rpn: float = param(0.01, "region proposal network", min=0)
    roi_heads: float = param(0.01, "box classification and regression heads", min=0)


@dataclass
class ModelTrainConfig:
    """Module 6: train a plant detector (Faster R-CNN, RetinaNet or FCOS) on module 5's train and val tiles (COCO)."""

    train_json: Path = param(None, "COCO JSON of the training tiles (module 5)", path="file", required=True)
    train_images: Path | None = param(None, "folder of the training tiles; null = the JSON's folder", path="dir")
    val_json: Path | None = param(
        None,
        "COCO JSON of the validation tiles; null = no validation (then the last epoch counts as best)",
        path="file",
    )
    val_images: Path | None = param(None, "folder of the validation tiles; null = the JSON's folder", path="dir")
    output_dir: Path = param(Path("runs/train"), "where checkpoints, curves and the summary go", path="out")
    resume: bool | Literal["fresh"] = param(
        False,
        "true: continue the run in output_dir from checkpoints/last.pt "
        "(after a crash, Ctrl-C or max_minutes; exactly where it stopped, "
        "mid-epoch too), the --resume flag; fresh: start a new run there "
        "(the --fresh flag), replacing its checkpoints",
    )
    model: ModelConfig = section(ModelConfig)
    trainable_backbone_layers: int = param(
        3,
        "backbone stages trained, counted from the top (0 = backbone frozen; ResNet-50 has 5, MobileNetV3 6)",
        min=0,
        max=6,
    )
    freeze: list[str] = param(
        [], "whole parts kept fixed (transfer learning): any of backbone, fpn, rpn, roi_heads", choices=PARTS
    )
    lr: LearningRates = section(LearningRates)
    optimizer: str = param(
        "sgd", "sgd (the paper) or adamw (use about 10x smaller learning rates)", choices=("sgd", "adamw")
    )
    momentum: float = param(0.9, "SGD momentum", min=0, max=1)
    weight_decay: float = param(5e-4, "L2 weight decay", min=0)
    schedule: str = param(
        "step",
        "learning-rate schedule after warm-up: step (x gamma every step_size "
        "epochs), multistep (x gamma at each milestone), cosine, constant",
        choices=SCHEDULES,
    )
    step_size: int = param(10, "epochs between decays (schedule: step)", min=1)
    gamma: float = param(0.1, "decay factor (step, multistep)", min=0, max=1)
    milestones: list[int] = param(
        [20, 27],
        "epochs at which to decay (schedule: multistep), of the 'epochs' "
        "configured; a shorter planned run (max_minutes) moves them in proportion",
        min=1,
    )
    milestone_fractions: list[float] | None = param(
        None,
        "decay points as fractions of the planned iterations, "
        "e.g. [0.67, 0.9] (schedule: multistep); null = milestones",
        min=0,
        max=1,
    )
    min_lr_factor: float = param(0.0, "final fraction of the learning rate (schedule: cosine)", min=0, max=1)
    warmup_iters: int | None = param(
        None,
        "iterations of linear warm-up at the start (0 = none); null = warmup_fraction of the planned iterations",
        min=0,
    )
    warmup_fraction: float = param(
        0.05,
        "warm-up as a fraction of the planned iterations (scales with the "
        "dataset and the budget; used when warmup_iters is null)",
        min=0,
        max=0.5,
    )
    warmup_factor: float = param(0.001, "learning-rate fraction at the first iteration of the warm-up", min=0, max=1)
    epochs: int = param(30, "training epochs", min=1)
    max_minutes: float = param(
        0.0,
        "time budget in minutes for the whole run (0 = none): a short probe "
        "measures the speed, the iterations that fit are planned and the learning-rate "
        "schedule fitted to them; training stops inside an epoch when the budget ends, "
        "validates and writes a checkpoint that --resume continues from",
        min=0,
    )
    threads: int = param(
        0,
        "CPU threads for torch (0 = auto: the cores this process may use less those busy with other work, logged)",
        min=0,
    )
    batch_size: int = param(4, "tiles per batch (per GPU under torchrun)", min=1)
    num_workers: int = param(
        2,
        "processes loading tiles (0 = in the main process); at most the usable cores less one (the main process "
        "trains on one), so 0 on one core",
        min=0,
    )
    augment: AugmentConfig = section(AugmentConfig)
    val_score_threshold: float = param(
        0.05, "boxes below this score are dropped during validation (the paper's 0.05)", min=0, max=1
    )
    val_every: int = param(1, "validate every N epochs (and always after the last)", min=1)
    best_metric: str = param("AP50", "validation metric that picks best.pt", choices=("AP50", "AP"))
    save_every: int | Literal["auto"] = param(
        "auto",
        "also keep checkpoints/epoch_NNN.pt every N epochs, all of them (0 = only last and best); auto: every 5 "
        "epochs, and only the last 3 of them when max_minutes sets the run's length (a budget of epochs: 1000 "
        "would fill the disk)",
        min=0,
    )
    device: str = param("auto", "auto picks CUDA, then Apple MPS, then CPU; or cpu, cuda, cuda:N, mps")
    amp: bool = param(True, "mixed precision on CUDA GPUs (faster, less memory); ignored elsewhere")
    seed: int = param(0, "random seed (data order, augmentation, new layers)")

    def check(self) -> None:
        """Lower ``num_workers`` to the free cores, reject an unknown ``device`` and check the crop settings."""
        cores, source = usable_cores()
        if self.num_workers > cores - 1:  # more loaders than free cores only compete (PyTorch: "might freeze")
            log.info("num_workers %d -> %d: %d usable core(s) (%s)", self.num_workers, cores - 1, cores, source)
            self.num_workers = cores - 1
        if self.device.split(":")[0] not in DEVICE_CHOICES:
            raise ConfigError(
                f"device '{self.device}' is not one of auto, cpu, cuda, cuda:N, mps", fix="set device: auto"
            )
        self.check_crop()

    def check_crop(self) -> None:
        """A setting never silently changes another: a crop larger than the detector's input would raise the
        input itself (each window padded with black up to crop x crop), and crop_on_plant without crops does
        nothing."""
        crop, side = self.augment.crop, self.model.min_size
        if crop and crop > side:
            raise ConfigError(
                f"augment.crop ({crop}) is larger than the detector's input (model.min_size = {side} px on the "
                f"short side): every training window would be padded with black to {crop} x {crop} px, "
                f"{(crop / side) ** 2:.0f}x the pixels of a {side} px input (as much slower, as much more memory), "
                "while detection sees the tiles at their own size",
                fix=f"set augment.crop to at most {side} (or 0 to train on whole tiles), or raise model.min_size",
            )
        if crop == 0 and self.augment.crop_on_plant > 0:
            raise ConfigError(
                f"augment.crop_on_plant ({self.augment.crop_on_plant:g}) has no effect with augment.crop: 0 "
                "(training on whole tiles)",
                fix="set augment.crop (e.g. 256, or null for auto) to train on crops, or augment.crop_on_plant: 0",
            )
