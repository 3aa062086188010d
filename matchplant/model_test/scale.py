"""Module 7 detects at the scale the model was trained at (the checkpoint's training geometry).

``detect.tile_size`` and ``detect.overlap`` left null come from the checkpoint
(:func:`matchplant.detection.geometry.default_tiling`). Warnings, before and after detection, when plants
would be more than 2x (or less than 0.5x) their training size in the detector's input: before, from the
tile size (for photos of the training's ground resolution); after, from the size of the plants found
(which also catches photos of another ground resolution: another flight height or camera); and on test
tiles, from their annotated plants.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.geometry import check_scale, default_tiling, scale_ratio
from matchplant.detection.objects import box_sizes, input_scale

log = get_logger("model_test")


def detect_settings(dcfg, ck: dict):
    """``dcfg`` (a DetectConfig) with a null tile_size / overlap taken from the checkpoint."""
    if dcfg.tile_size is not None and dcfg.overlap is not None:
        return dcfg
    tile, overlap, where = default_tiling(ck.get("training_geometry"), ck["model_config"])
    if dcfg.tile_size is not None:
        tile, where = dcfg.tile_size, f"overlap {min(overlap, dcfg.tile_size // 2)} from the checkpoint"
    overlap = dcfg.overlap if dcfg.overlap is not None else min(overlap, tile // 2)
    if overlap >= tile:
        raise ConfigError(
            f"detect.overlap ({overlap}) must be smaller than the tile size ({tile}, from the checkpoint)",
            fix="lower detect.overlap, or set detect.tile_size",
        )
    known = bool((ck.get("training_geometry") or {}).get("tile_size")) or dcfg.tile_size is not None
    (log.info if known else log.warning)("detect: %s", where)
    return dataclasses.replace(dcfg, tile_size=int(tile), overlap=int(overlap))


def with_detect_settings(cfg, ck: dict):
    """A ModelTestConfig whose detect section has the checkpoint's tile size / overlap where null."""
    if cfg.detect.images is None:
        return cfg
    return dataclasses.replace(cfg, detect=detect_settings(cfg.detect, ck))


def _training_tile(ck: dict) -> str:
    geometry = ck.get("training_geometry") or {}
    return f"{geometry['tile_size']} px" if geometry.get("tile_size") else "unknown"


def check_detect_scale(dcfg, ck: dict) -> bool:
    """Warn when tiles of ``dcfg.tile_size`` would show plants off their training scale in the detector's
    input (for photos of the training's ground resolution); images smaller than a tile are detected whole
    (module 7 warns about those separately)."""
    ratio = scale_ratio(ck.get("training_geometry"), dcfg.tile_size, dcfg.tile_size, ck["model_config"])
    return check_scale(
        ratio,
        f"detect.tile_size {dcfg.tile_size} (the model was trained on {_training_tile(ck)} tiles)",
        "Set detect.tile_size to the training tile size (or null: from the checkpoint)",
    )


def check_found_scale(ck: dict, found: list[tuple[np.ndarray, int, int]], tile_size: int) -> float | None:
    """After detection: the median plant found, in the detector's input, against the training plants
    (``found``: boxes xyxy, image width, height per image). Returns the ratio (None when unknown)."""
    geometry = ck.get("training_geometry") or {}
    ref = geometry.get("objects_input_px")
    mc = ck["model_config"]
    sides = [
        np.sqrt(np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None))
        * input_scale(min(tile_size, w), min(tile_size, h), mc["min_size"], mc["max_size"])
        for b, w, h in found
        if len(b)
    ]
    if not ref or not sides:
        return None
    ratio = float(np.median(np.concatenate(sides))) / float(ref)
    check_scale(
        ratio,
        "the plants found",
        f"The photos may have another ground resolution than the training "
        f"photos (flight height, camera): try detect.tile_size about {int(round(tile_size * ratio))}, "
        f"which shows them at their training size",
    )
    return ratio


def check_test_scale(dataset: dict, ck: dict) -> float | None:
    """The annotated plants of test tiles, in the detector's input, against the training plants."""
    ref = (ck.get("training_geometry") or {}).get("objects_input_px")
    w, h = box_sizes(dataset, ck["model_config"]["min_size"], ck["model_config"]["max_size"])
    if not ref or not len(w):
        return None
    ratio = float(np.median(np.sqrt(w * h))) / float(ref)
    check_scale(
        ratio,
        "the test tiles' plants",
        "Evaluate on tiles cut like the training tiles (module 5, same "
        "tile_size, photos of the same ground resolution)",
    )
    return ratio
