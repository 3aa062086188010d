"""Object sizes in pixels, and the tiling and detector settings they call for (``matchplant inspect``,
``anchor_sizes: auto`` in module 6).

One piece of advice, used everywhere (modules 5 and 6 READMEs say the same):

- **overlap** of neighbouring tiles >= the largest objects (99th percentile of the longer box side), so
  every plant is whole in at least one tile;
- **tile_size** about 8x that overlap (so overlap costs little), a multiple of 64 between 256 and 1024,
  and not above the photos;
- **min_size** (the detector's input scale: a tile is resized so its short side is min_size) = the
  tile size, enlarged when the median object would be smaller than ``MIN_OBJECT_PX`` (24 px) for the
  detector's coarse feature maps. Shrinking the input to save CPU time is fine only while the median
  object stays above 24 px: ``min_size >= tile_size * 24 / median``;
- **anchor_sizes** in the detector's input pixels (after that scaling): the smallest anchor at the
  small objects (5th percentile of sqrt(area), at most median / sqrt 2), each FPN level twice the one
  before, so the object range falls on the first levels (each architecture's
  :class:`~matchplant.detection.architectures.AnchorRule`). Aspect ratios from the boxes' height/width (10th,
  50th, 90th percentiles).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from matchplant.core.formats.coco import read_dataset
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.detection.architectures import ARCHITECTURES, AnchorRule

log = get_logger("inspect")

MIN_OBJECT_PX = 24      # objects smaller than this (in detector input pixels) are hard for FPN detectors
TILE_MIN, TILE_MAX, TILE_STEP = 256, 1024, 64
PERCENTILES = (1, 5, 10, 25, 50, 75, 90, 95, 99)


def box_sizes(dataset: dict, min_size: int | None = None, max_size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(widths, heights)`` of every box of a COCO dataset, in pixels of its image, or (with
    ``min_size``, ``max_size``) in the detector's input pixels after torchvision's resize of each image."""
    sizes = {im["id"]: (im["width"], im["height"]) for im in dataset.get("images", [])}
    anns = [a for a in dataset.get("annotations", []) if a.get("image_id") in sizes]
    b = np.array([a["bbox"] for a in anns], float).reshape(-1, 4)
    w, h = b[:, 2].copy(), b[:, 3].copy()
    if min_size is not None:
        scale = np.array([input_scale(*sizes[a["image_id"]], min_size, max_size or 10 ** 9) for a in anns])
        w, h = w * scale, h * scale
    return w, h


def input_scale(width: float, height: float, min_size: int, max_size: int) -> float:
    """torchvision's resize of an image before detection: short side to min_size, long side <= max_size."""
    return min(min_size / min(width, height), max_size / max(width, height))


def size_stats(widths: Iterable[float], heights: Iterable[float]) -> dict:
    """Counts and percentiles (pixels) of box width, height, sqrt(area), longer side and height/width."""
    w, h = np.asarray(widths, float), np.asarray(heights, float)
    ok = (w > 0) & (h > 0)
    w, h = w[ok], h[ok]
    if not len(w):
        return {"boxes": 0}
    out = {"boxes": int(len(w))}
    for name, v in (("width", w), ("height", h), ("sqrt_area", np.sqrt(w * h)), ("long_side", np.maximum(w, h)),
                    ("aspect_h_over_w", h / w)):
        out[name] = {f"p{p}": round(float(np.percentile(v, p)), 2) for p in PERCENTILES}
        out[name]["mean"] = round(float(v.mean()), 2)
    return out


def _round_to(v: float, step: int) -> int:
    return int(step * math.ceil(v / step))


def smallest_anchor(stats: dict) -> float:
    """The first FPN level's anchor: at the small objects (5th percentile of sqrt(area)) and at most the
    median / sqrt(2), so the median object lies between the first two levels' anchors (IoU >= 0.5 with one)."""
    return min(stats["sqrt_area"]["p5"], stats["sqrt_area"]["p50"] / math.sqrt(2))


def recommend(stats: dict, image_sizes: Iterable[tuple[int, int]] = ()) -> dict:
    """Tile size, overlap, min_size, anchors and aspect ratios for objects of ``stats``
    (:func:`size_stats` of the source photos' boxes), with the reasons."""
    if not stats.get("boxes"):
        return {"note": "no boxes: nothing to recommend"}
    median = stats["sqrt_area"]["p50"]
    largest = stats["long_side"]["p99"]
    overlap = _round_to(max(largest * 1.1, 16), 8)
    tile = min(max(_round_to(8 * overlap, TILE_STEP), TILE_MIN), TILE_MAX)
    sides = [min(w, h) for w, h in image_sizes]
    if sides and tile > min(sides):
        tile = max(_round_to(min(sides), TILE_STEP) - TILE_STEP, TILE_STEP) if min(sides) >= TILE_STEP else min(sides)
    overlap = min(overlap, tile // 2)
    upscale = max(1.0, MIN_OBJECT_PX / median) if median > 0 else 1.0
    min_size = _round_to(tile * min(upscale, 4.0), 32)
    scale = min_size / tile
    small = smallest_anchor(stats) * scale
    ratios = sorted({round(float(stats["aspect_h_over_w"][p]), 2) for p in ("p10", "p50", "p90")})
    return {
        "tile_size": int(tile), "overlap": int(overlap),
        "min_size": int(min_size), "max_size": int(min_size),
        "min_size_floor": int(_round_to(tile * MIN_OBJECT_PX / median, 32)) if median > 0 else None,
        "input_scale": round(scale, 3),
        "median_object_px_in_detector": round(median * scale, 1),
        "anchor_sizes": {name: rule.sizes(small) for rule, name in _first_of_each_anchor_rule().items()},
        "aspect_ratios": ratios if len(ratios) > 1 else [0.5, 1.0, 2.0],
        "why": {
            "overlap": f"the longest 1 % of boxes are {largest:.0f} px or more: neighbouring tiles share "
                       f"{overlap} px so such a plant is whole in at least one tile",
            "tile_size": f"about 8x the overlap (overlap costs ~{100 * (1 - ((tile - overlap) / tile) ** 2):.0f} % "
                         f"extra pixels), a multiple of {TILE_STEP} in {TILE_MIN}..{TILE_MAX}",
            "min_size": f"median object {median:.0f} px; the detector input is {scale:.2f}x the tile so the median "
                        f"object is {median * scale:.0f} px (>= {MIN_OBJECT_PX} px); to save CPU time min_size may "
                        f"go down to the floor, not below",
            "anchor_sizes": f"smallest anchor ({small:.0f} px in detector pixels) at the small objects (5th "
                            f"percentile of sqrt(area)) and below the median / sqrt(2), doubling per FPN level",
        },
    }


def _first_of_each_anchor_rule() -> dict[AnchorRule, str]:
    """The advice lists anchors once per anchor rule, under the first architecture that uses it."""
    first: dict[AnchorRule, str] = {}
    for arch in ARCHITECTURES.values():
        first.setdefault(arch.anchors, arch.name)
    return first


def auto_anchor_sizes(widths: np.ndarray, heights: np.ndarray, rule: AnchorRule) -> list[list[int]]:
    """``anchor_sizes: auto`` of module 6: anchors from the training boxes, given in detector input pixels."""
    stats = size_stats(widths, heights)
    if not stats.get("boxes"):
        raise ValueError("no boxes")
    return rule.sizes(smallest_anchor(stats))


@dataclass
class InspectConfig:
    """Object sizes of a COCO dataset and the tile size, overlap, min_size and anchors they call for."""

    annotations: Path | None = param(None, "COCO JSON to measure: module 4's annotations.json (source photos) "
                                           "or a module 5 split (tiles)", path="file", required=True)
    report: Path | None = param(None, "optional JSON file for the statistics and recommendations", path="out")


def inspect_dataset(cfg: InspectConfig) -> dict:
    """Measure the boxes of ``cfg.annotations``, print and return the statistics and the advice."""
    ds = read_dataset(cfg.annotations, validate=False)
    w, h = box_sizes(ds)
    stats = size_stats(w, h)
    if not stats["boxes"]:
        raise InputError("the dataset has no boxes to measure", path=cfg.annotations,
                         fix="give a COCO file with annotations (module 4's annotations.json)")
    sizes = sorted({(int(im["width"]), int(im["height"])) for im in ds["images"]})
    tiles = any("source_image" in im for im in ds["images"])
    advice = recommend(stats, sizes)
    out = {"annotations": str(cfg.annotations), "images": len(ds["images"]), "image_sizes": sizes[:10],
           "tiles": tiles, "objects_px": stats, "recommended": advice}
    print(format_report(out))
    if cfg.report is not None:
        write_json(cfg.report, out)
        log.info("report -> %s", cfg.report)
    return out


def format_report(r: dict) -> str:
    """The report as text for the terminal."""
    s, a = r["objects_px"], r["recommended"]
    rows = [f"{r['boxes'] if 'boxes' in r else s['boxes']} boxes on {r['images']} "
            f"{'tiles' if r['tiles'] else 'images'} ({', '.join(f'{w}x{h}' for w, h in r['image_sizes'][:3])})",
            "object size in pixels       p5     p25    p50    p75    p95    p99"]
    for key in ("width", "height", "sqrt_area", "long_side"):
        rows.append(f"  {key:<24}" + "".join(f"{s[key][p]:7.1f}" for p in ("p5", "p25", "p50", "p75", "p95", "p99")))
    rows.append(f"  height/width{'':<12}" + "".join(f"{s['aspect_h_over_w'][p]:7.2f}"
                                                    for p in ("p5", "p25", "p50", "p75", "p95", "p99")))
    rows += ["recommended (module 5 and module 6 settings):",
             f"  tile_size: {a['tile_size']}    overlap: {a['overlap']}",
             f"  model.min_size: {a['min_size']}    model.max_size: {a['max_size']}    "
             f"(CPU: not below {a['min_size_floor']})",
             f"  model.anchor_sizes: auto  (or, for these objects: {json.dumps(a['anchor_sizes'])})",
             f"  model.aspect_ratios: {a['aspect_ratios']}"]
    rows += [f"  why {k}: {v}" for k, v in a["why"].items()]
    if r["tiles"]:
        rows.append("  (measured on tiles: tile_size and overlap advice is for the photos the tiles came from)")
    return "\n".join(rows)


__all__ = ["InspectConfig", "inspect_dataset", "format_report", "box_sizes", "input_scale", "size_stats", "recommend", "auto_anchor_sizes",
           "smallest_anchor", "MIN_OBJECT_PX"]
