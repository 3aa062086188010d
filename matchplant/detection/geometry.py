"""The training geometry a checkpoint carries (module 6 writes it, module 7 reads it).

A detector learns plants at one scale: the tiles' size, the resize to the model's input
(``min_size``/``max_size``, :func:`matchplant.detection.objects.input_scale`) and the plants' size in pixels.
``training_geometry`` records them from the training tiles; module 7 then tiles new images as in
training by default, and :func:`scale_ratio` / :func:`check_scale` warn when detection would see plants
at more than ``SCALE_TOLERANCE`` times (or less than 1 / ``SCALE_TOLERANCE``) their training size in the
detector's input.

The dictionary (``checkpoint["training_geometry"]``)::

    tile_size        training tile side in pixels (module 5's tile_size, else the most common tile side)
    overlap          module 5's overlap (null when the tiles did not say)
    min_size, max_size, input_scale   the model's resize; input_scale = detector pixels per tile pixel
    class_names      the classes, in label order
    objects_px       size_stats of the training boxes in tile pixels (= source-photo pixels)
    objects_input_px median sqrt(area) of the training boxes in the detector's input pixels
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from matchplant.core.runtime.log import get_logger
from matchplant.detection.objects import box_sizes, input_scale, size_stats

log = get_logger("geometry")

SCALE_TOLERANCE = 2.0  # warn when plants are > 2x or < 0.5x their training size in the detector's input
FALLBACK_TILE = 1024  # checkpoints written before the geometry was stored


def training_geometry(dataset: dict, min_size: int, max_size: int, class_names: list[str]) -> dict:
    """The geometry of a training set (a COCO dict of tiles) for a model resizing to min_size/max_size."""
    images = dataset.get("images", [])
    info = dataset.get("info") or {}
    sides = Counter(max(int(im["width"]), int(im["height"])) for im in images)
    tile = int(info.get("tile_size") or (sides.most_common(1)[0][0] if sides else 0)) or None
    scales = [input_scale(im["width"], im["height"], min_size, max_size) for im in images]
    w, h = box_sizes(dataset)
    wi, hi = box_sizes(dataset, min_size, max_size)
    return {
        "tile_size": tile,
        "overlap": int(info["overlap"]) if info.get("overlap") is not None else None,
        "min_size": int(min_size),
        "max_size": int(max_size),
        "input_scale": round(float(np.median(scales)), 6) if scales else None,
        "class_names": list(class_names),
        "objects_px": size_stats(w, h),
        "objects_input_px": round(float(np.median(np.sqrt(wi * hi))), 2) if len(wi) else None,
    }


def default_tiling(geometry: dict | None, model_config: dict) -> tuple[int, int, str]:
    """Tile size and overlap for detection when the config leaves them to the checkpoint, and where
    they came from: the training tile size; the training overlap, else 1.1 x the largest training plant
    (99th percentile of the longer side), at most half the tile."""
    if not geometry or not geometry.get("tile_size"):
        tile = FALLBACK_TILE
        return (
            tile,
            tile // 4,
            (
                f"the checkpoint does not record its training tile size (written by an older "
                f"MatchPlant): tile_size {tile}, overlap {tile // 4}; set detect.tile_size"
            ),
        )
    tile = int(geometry["tile_size"])
    overlap = geometry.get("overlap")
    if overlap is None:
        objects = geometry.get("objects_px") or {}
        largest = objects.get("long_side", {}).get("p99")
        overlap = int(np.ceil(1.1 * largest)) if largest else tile // 4
    overlap = int(min(overlap, tile // 2))
    return tile, overlap, f"tile_size {tile} and overlap {overlap} from the checkpoint (its training tiles)"


def scale_ratio(geometry: dict | None, tile_width: int, tile_height: int, model_config: dict) -> float | None:
    """How large plants appear in the detector's input when detecting on tiles of this size, relative to
    training (1 = as trained), for photos of the training's ground resolution; None when unknown."""
    if not geometry or not geometry.get("input_scale"):
        return None
    now = input_scale(tile_width, tile_height, model_config["min_size"], model_config["max_size"])
    return now / float(geometry["input_scale"])


def off_scale(ratio: float | None) -> bool:
    """Whether plants would be more than ``SCALE_TOLERANCE`` times larger or smaller than in training."""
    return ratio is not None and not (1 / SCALE_TOLERANCE <= ratio <= SCALE_TOLERANCE)


def check_scale(ratio: float | None, what: str, fix: str) -> bool:
    """Log a warning when ``ratio`` (from :func:`scale_ratio`) is off scale."""
    if not off_scale(ratio):
        return False
    log.warning(
        "%s: plants would be %.2fx their training size in the detector's input (the model learned one "
        "scale; beyond %gx or 1/%gx it finds far fewer). %s",
        what,
        ratio,
        SCALE_TOLERANCE,
        SCALE_TOLERANCE,
        fix,
    )
    return True
