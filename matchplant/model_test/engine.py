"""Module 7's detection as an engine (after module 6's and torchvision's references/detection/engine.py): whole
undistorted photos of any size are cut into overlapping tiles, detected in batches, and the boxes merged across
tiles, so a plant cut by a tile border is found once; ``predictions.json`` (docs/DESIGN.md §2, the input of module
8) holds the boxes in source-image pixels with each photo's name.

:func:`detect` is a short sequence over named parts:

- :func:`prepare`: one :class:`Detection` record with the checkpoint, the settings (a null ``detect.tile_size`` /
  ``overlap`` from the training tiles), the scale check, the model, its runtime (PyTorch or ONNX Runtime), the
  predictor, the batch and the feed (the run's :class:`~matchplant.detection.gpu.Runtime`, chosen once);
- :func:`plan`: the estimate of the run's time (:mod:`~matchplant.model_test.estimate`);
- :func:`photos`: the loop over this process's photos (:func:`~matchplant.model_test.gpu_feed.detections`);
- :func:`record` and :func:`records`: one photo's image entry and boxes, and the COCO lists of every photo;
- :func:`gather`: every process's photos, counts and drawn images (one process: its own);
- :func:`write`: ``predictions.json``, or the reason nothing was found (:func:`diagnose`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from matchplant.core.formats.images import image_size, read_rgb8
from matchplant.core.formats.odm import SUBMODELS_DIR
from matchplant.core.formats.predictions import write_predictions
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.distributed import Shard
from matchplant.detection.evaluate import draw_boxes, write_image
from matchplant.detection.gpu import Runtime
from matchplant.detection.model import set_score_threshold
from matchplant.model_test.config import DetectConfig, ModelTestConfig
from matchplant.model_test.estimate import estimate
from matchplant.model_test.gpu_feed import detect_batch, detections, device_predictor
from matchplant.model_test.inputs import nothing_found
from matchplant.model_test.runtime_onnx import torch_threads, with_runtime
from matchplant.model_test.scale import check_detect_scale, check_found_scale, with_detect_settings
from matchplant.model_test.tiles import Predictor, detect_image, model_predictor

log = get_logger("model_test")


@dataclass(frozen=True)
class Detection:
    """What a detection run works with, prepared once by :func:`prepare` and read by every part."""

    cfg: ModelTestConfig  # the run's settings, detect.tile_size / overlap resolved
    ck: dict  # the checkpoint, as loaded
    scale_ok: bool  # the plants' scale in the detector's input against training (check_detect_scale)
    model: Any  # the detector in eval mode (its convolutions in ONNX Runtime with detect.runtime: onnx)
    runtime: Runtime  # the device, precision and feed
    predictor: Predictor  # tiles to boxes
    batch: int  # tiles per pass
    shard: Shard  # this process's share of the photos (torchrun)
    files: list[Path]  # the photos to detect on (a cover's, with detect.cover)
    every: list[Path] | None  # every photo, when a cover chose fewer
    out: Path  # where the outputs are staged

    @property
    def dcfg(self) -> DetectConfig:
        """The ``detect`` section."""
        return self.cfg.detect

    def tiling(self, score_threshold: float | None = None) -> dict:
        """The keywords of :func:`~matchplant.model_test.tiles.detect_image` for this run."""
        d = self.dcfg
        return dict(
            tile_size=d.tile_size,
            overlap=d.overlap,
            batch_size=self.batch,
            score_threshold=d.score_threshold if score_threshold is None else score_threshold,
            merge_iou=d.merge_iou,
            edge_margin=d.edge_margin,
            merge_containment=d.merge_containment,
        )


def prepare(cfg: ModelTestConfig, runtime: Runtime, shard: Shard, out: Path, ck: dict, files, every) -> Detection:
    """The :class:`Detection` record: settings, scale check, model, runtime, predictor and batch."""
    cfg = with_detect_settings(cfg, ck)  # a null detect.tile_size / overlap: the checkpoint's training tiles'
    dcfg = cfg.detect
    scale_ok = check_detect_scale(dcfg, ck)  # plants >2x or <0.5x their training size in the detector's input
    model, ck = load_detector(ck, runtime.device, source=cfg.checkpoint)
    set_score_threshold(model, dcfg.score_threshold)
    model = with_runtime(model, dcfg.runtime, runtime, torch_threads())
    predictor = device_predictor(model, runtime) or model_predictor(model, runtime)
    batch = detect_batch(cfg.batch_size, runtime, dcfg.tile_size, ck["model_config"])  # CUDA: from free memory
    return Detection(cfg, ck, scale_ok, model, runtime, predictor, batch, shard, files, every, Path(out))


def plan(d: Detection) -> dict:
    """Before hours of work: the actual tiles and network input of every photo, timed on this device."""
    every = d.every if d.every is not None and len(d.every) != len(d.files) else None
    return estimate(
        d.predictor,
        read_rgb8(d.files[0]),
        [image_size(f) for f in d.files],
        d.dcfg.tile_size,
        d.dcfg.overlap,
        d.ck["model_config"],
        d.runtime,
        processes=d.shard.world,
        every=[image_size(f) for f in every] if every is not None else None,
        batch=d.batch if d.runtime.batch_from_memory else 1,  # a CPU's time per tile does not depend on the batch
    )


def photos(d: Detection) -> tuple[list, dict, list[str]]:
    """Detect on this process's photos: ``(records, counts, drawn images)``; each record is :func:`record`'s. The
    runtime's feed decides how: on CUDA photos decoded ahead, two in flight (gpu_feed.py); else one by one."""
    root = Path(d.dcfg.images) if Path(d.dcfg.images).is_dir() else Path(d.dcfg.images).parent
    draw_every = max(1, int(np.ceil(len(d.files) / d.dcfg.drawn_images))) if d.dcfg.drawn_images else 0
    tiling = d.tiling()
    mine, counts, drawn = [], {}, []
    indices = d.shard.take(d.files)

    def detect_one(img, pred, photo_counts):
        return detect_image(img, pred, counts=photo_counts, **tiling)

    found = detections(indices, d.files, d.runtime, d.predictor, detect_one)
    for i, img, (boxes, scores, labels), photo_counts in progress(
        found, desc="detecting", unit="image", total=len(indices)
    ):
        path = d.files[i]
        for key, n in photo_counts.items():
            counts[key] = counts.get(key, 0) + n
        mine.append(record(d, root, i, img, boxes, scores, labels))
        if draw_every and i % draw_every == 0:
            write_image(d.out / "detections" / (path.stem + ".png"), draw_boxes(img, boxes, (230, 30, 30), scores))
            drawn.append(f"detections/{path.stem}.png")
    return mine, counts, drawn


def record(d: Detection, root: Path, i: int, img: np.ndarray, boxes, scores, labels) -> tuple:
    """One photo's ``(index, image entry, [(category id, COCO bbox, score)])``, rounded as written."""
    path = d.files[i]
    name = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
    if (root / SUBMODELS_DIR).is_dir():
        name = path.name  # <shot>.tif: one image of a split-merge project, whichever submodel holds it
    entry = {
        "id": i + 1,
        "file_name": name,
        "width": int(img.shape[1]),
        "height": int(img.shape[0]),
        "source_image": name,
        "x0": 0,
        "y0": 0,
    }
    cat_ids = [int(c) for c in d.ck["category_ids"]]
    found = [
        (
            cat_ids[int(lab) - 1],
            [round(float(b[0]), 2), round(float(b[1]), 2), round(float(b[2] - b[0]), 2), round(float(b[3] - b[1]), 2)],
            round(float(s), 5),
        )
        for b, s, lab in zip(boxes, scores, labels)
    ]
    return i, entry, found


def gather(d: Detection, mine: list, counts: dict, drawn: list[str]) -> tuple[list, int, list[str]]:
    """Every process's records in photo order, the nested boxes merged in all, and every drawn image."""
    gathered = sorted(d.shard.gather(mine), key=lambda r: r[0])  # a single process's order
    merged = sum(c.get("nested_merged", 0) for c in d.shard.gather([counts]))
    return gathered, merged, d.shard.gather(drawn)


def records(gathered: list) -> tuple[list[dict], list[dict]]:
    """The COCO images and predictions of every photo's record."""
    images, predictions = [], []
    for i, entry, found in gathered:
        images.append(entry)
        predictions += [
            {"id": len(predictions) + k + 1, "image_id": i + 1, "category_id": c, "bbox": b, "score": s}
            for k, (c, b, s) in enumerate(found)
        ]
    return images, predictions


def check_found(d: Detection, gathered: list, merged: int) -> None:
    """The nested boxes merged, and the plants' scale found against training, logged."""
    log.info(
        "%d nested box(es) merged: of two boxes of a class on a photo, one >= %.0f %% inside the other "
        "(detect.merge_containment), the lower-scoring one dropped (on equal scores, the inner one)",
        merged,
        100 * d.dcfg.merge_containment,
    )
    boxes = [
        (
            np.asarray([[x, y, x + w, y + h] for _, (x, y, w, h), _ in found], float).reshape(-1, 4),
            entry["width"],
            entry["height"],
        )
        for _, entry, found in gathered
    ]
    check_found_scale(d.ck, boxes, d.dcfg.tile_size)


def diagnose(d: Detection) -> Exception:
    """Why nothing was found (the best score at any threshold, the scale), rather than an empty file."""
    set_score_threshold(d.model, 0.0)
    _, scores, _ = detect_image(read_rgb8(d.files[0]), d.predictor, **d.tiling(score_threshold=0.0))
    return nothing_found(
        len(d.files),
        d.files[0],
        float(scores.max()) if len(scores) else None,
        d.dcfg.score_threshold,
        d.dcfg.tile_size,
        d.ck["model_config"],
        Path(d.cfg.checkpoint),
    )


def write(d: Detection, images: list[dict], predictions: list[dict], p: dict, seconds: float) -> None:
    """``predictions.json`` with the run's settings and timing."""
    categories = [
        {"id": int(cid), "name": name, "supercategory": "plant"}
        for cid, name in zip(d.ck["category_ids"], d.ck["class_names"])
    ]
    dcfg = d.dcfg
    info = {
        "description": "MatchPlant module 7 detections (source-image pixels)",
        "checkpoint": str(d.cfg.checkpoint),
        "tile_size": dcfg.tile_size,
        "overlap": dcfg.overlap,
        "score_threshold": dcfg.score_threshold,
        "cover": dcfg.cover,
        "timing": {
            "estimated_s": round(p["seconds"], 3),
            "detection_s": round(seconds, 3),
            "tiles": p["tiles"],
            "input_megapixels": round(p["input_megapixels"], 3),
            "device": p["device"],
        },
    }
    write_predictions(d.out / "predictions.json", images, categories, predictions, info=info)


def detect(cfg: ModelTestConfig, runtime: Runtime, shard: Shard, out: Path, *, ck: dict, files, every, listed) -> Path:
    """Detect plants on ``files``; writes ``predictions.json`` and drawn images into ``out``. A run that finds no
    plant at all is an error that says why. ``listed`` gets the drawn images of every process (relative paths, on
    the main process)."""
    d = prepare(cfg, runtime, shard, out, ck, files, every)
    p = plan(d)
    started = time.perf_counter()
    mine, counts, drawn = photos(d)
    seconds = time.perf_counter() - started
    gathered, merged, drawn_by_all = gather(d, mine, counts, drawn)
    path = Path(cfg.output_dir) / "predictions.json"
    if not shard.main:
        shard.barrier()
        return path
    check_found(d, gathered, merged)
    images, predictions = records(gathered)
    if not predictions:
        error = diagnose(d)
        shard.barrier()
        raise error
    write(d, images, predictions, p, seconds)
    listed += drawn_by_all
    log.info(
        "%d plants found on %d image(s)%s: %s",
        len(predictions),
        len(files),
        f" by {shard.world} processes" if shard.world > 1 else "",
        path,
    )
    shard.barrier()
    return path
