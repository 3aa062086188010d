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
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.formats.coco import bbox_values, read_dataset
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import is_stream, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.detection.architectures import ARCHITECTURES, AnchorRule
from matchplant.detection.tile_objects import distinct_objects

log = get_logger("inspect")

MIN_OBJECT_PX = 24  # objects smaller than this (in detector input pixels) are hard for FPN detectors
TILE_MIN, TILE_MAX, TILE_STEP = 256, 1024, 64
PERCENTILES = (1, 5, 10, 25, 50, 75, 90, 95, 99)


# module 6's time budget: the one setting the CPU recipe needs (6_model_train/README.md: "15 minutes on a CPU")
BUDGET_MINUTES = 15
BUDGET_WHY = (
    "module 6 trains for this many minutes: on a CPU from random weights its recipe (model.architecture: auto) "
    "fits the run to the budget, and more minutes train a better detector; 0 trains the configured epochs "
    "(30; hours on a CPU)"
)


def box_sizes(dataset: dict, min_size: int | None = None, max_size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(widths, heights)`` of every box of a COCO dataset, in pixels of its image, or (with
    ``min_size``, ``max_size``) in the detector's input pixels after torchvision's resize of each image."""
    sizes = {im["id"]: (im["width"], im["height"]) for im in dataset.get("images", [])}
    anns = [a for a in dataset.get("annotations", []) if a.get("image_id") in sizes]
    b = np.array([a["bbox"] for a in anns], float).reshape(-1, 4)
    w, h = b[:, 2].copy(), b[:, 3].copy()
    if min_size is not None:
        scale = np.array([input_scale(*sizes[a["image_id"]], min_size, max_size or 10**9) for a in anns])
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
    out = {"boxes": len(w)}
    for name, v in (
        ("width", w),
        ("height", h),
        ("sqrt_area", np.sqrt(w * h)),
        ("long_side", np.maximum(w, h)),
        ("aspect_h_over_w", h / w),
    ):
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
    longest = max((max(w, h) for w, h in image_sizes), default=0)
    if sides and tile > min(sides) and longest <= TILE_MAX:
        # photos smaller than the tile the objects call for: no tiling (cutting a 400 px photo into four
        # overlapping 320 px tiles would only repeat its pixels); the tile is the whole photo
        tile = int(longest)
    elif sides and tile > min(sides):
        tile = max(_round_to(min(sides), TILE_STEP) - TILE_STEP, TILE_STEP) if min(sides) >= TILE_STEP else min(sides)
    overlap = min(overlap, tile // 2)
    upscale = max(1.0, MIN_OBJECT_PX / median) if median > 0 else 1.0
    min_size = _round_to(tile * min(upscale, 4.0), 32)
    scale = min_size / tile
    small = smallest_anchor(stats) * scale
    ratios = sorted({round(float(stats["aspect_h_over_w"][p]), 2) for p in ("p10", "p50", "p90")})
    return {
        "tile_size": int(tile),
        "overlap": int(overlap),
        "min_size": int(min_size),
        "max_size": int(min_size),
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

    annotations: Path | None = param(
        None,
        "COCO JSON to measure: module 4's annotations.json (source photos) or a module 5 split (tiles)",
        path="file",
        required=True,
    )
    report: Path | None = param(
        None, 'optional JSON file for the statistics and recommendations ("-": standard output)', path="out_file"
    )


def check_structure(ds: dict, path: Path) -> None:
    """The parts of a COCO file that measuring needs: every image a positive width and height, every
    annotation a ``[x, y, w, h]`` bbox of numbers (an error naming the first ones and the count)."""
    bad_images = [
        im
        for im in ds["images"]
        if not all(
            isinstance(im.get(k), (int, float)) and not isinstance(im.get(k), bool) and im[k] > 0
            for k in ("width", "height")
        )
    ]
    if bad_images:
        shown = ", ".join(f"{im.get('id')} ({im.get('file_name')})" for im in bad_images[:3])
        raise InputError(
            f"{len(bad_images)} of the {len(ds['images'])} image(s) have no valid 'width'/'height' "
            f"(e.g. image {shown}): box sizes cannot be put in proportion to the photos",
            path=path,
            fix="add each image's width and height in pixels (module 4's import writes "
            "them), or give module 4's annotations.json",
        )
    bad = [a for a in ds["annotations"] if bbox_values(a.get("bbox")) is None]
    if bad:
        a = bad[0]
        got = "no 'bbox'" if "bbox" not in a else f"'bbox' = {a['bbox']!r} ({type(a['bbox']).__name__})"
        raise InputError(
            f"{len(bad)} of the {len(ds['annotations'])} annotation(s) have no [x, y, w, h] 'bbox' "
            f"of numbers (e.g. annotation {a.get('id')}: {got})",
            path=path,
            fix="give each annotation 'bbox': [x, y, width, height] as a list of numbers, or import "
            "the file with module 4 (import_coco), which lists what it cannot use",
        )


def source_view(ds: dict) -> tuple[dict, list[tuple[int, int]], str]:
    """Tiles seen as the photos they were cut from: ``(dataset of the photos' distinct plants, photo sizes,
    how the sizes are known)``. A plant in the overlap of several tiles is one plant (module 5 clips it to each
    tile; :func:`~matchplant.detection.tile_objects.distinct_objects` joins the copies), its box the union of its
    pieces in photo pixels; a photo's size is ``source_width``/``source_height`` where the tiles record it, else
    the extent of its tiles (module 5's last tile is flush with the photo's edge)."""
    images = {im["id"]: im for im in ds["images"]}
    object_of, _ = distinct_objects(ds)
    union: dict[tuple, list[float]] = {}
    for a in ds["annotations"]:
        im = images.get(a.get("image_id"))
        if im is None or a.get("id") not in object_of:
            continue
        x, y, w, h = bbox_values(a["bbox"])
        x0, y0 = float(im.get("x0", 0)), float(im.get("y0", 0))
        key = (im.get("source_image", f"\0{im['id']}"), object_of[a["id"]])
        b = union.setdefault(key, [x0 + x, y0 + y, x0 + x + w, y0 + y + h])
        b[:] = [min(b[0], x0 + x), min(b[1], y0 + y), max(b[2], x0 + x + w), max(b[3], y0 + y + h)]
    extent: dict[str, list[float]] = {}
    recorded = True
    for im in ds["images"]:
        src = im.get("source_image", f"\0{im['id']}")
        if isinstance(im.get("source_width"), (int, float)) and isinstance(im.get("source_height"), (int, float)):
            size = [float(im["source_width"]), float(im["source_height"])]
        else:
            recorded = False
            size = [float(im.get("x0", 0)) + im["width"], float(im.get("y0", 0)) + im["height"]]
        e = extent.setdefault(src, size)
        e[:] = [max(e[0], size[0]), max(e[1], size[1])]
    photos = {
        "images": [{"id": i + 1, "width": w, "height": h} for i, (w, h) in enumerate(extent.values())],
        "annotations": [
            {"id": k + 1, "image_id": 1, "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]]}
            for k, b in enumerate(union.values())
        ],
    }
    how = (
        "recorded in the tiles (source_width/height)"
        if recorded
        else "the extent of each photo's tiles (at least the photo; exact when its edge tiles are kept)"
    )
    return photos, sorted({(round(w), round(h)) for w, h in extent.values()}), how


def tiles_per_photo(size: tuple[int, int], tile: int, overlap: int) -> int:
    """How many tiles of ``tile`` px overlapping by ``overlap`` cover a photo (module 5's and module 7's grid:
    a step of tile - overlap, the last tile flush with the edge)."""

    def along(length: int) -> int:
        return 1 if length <= tile else math.ceil((length - tile) / (tile - overlap)) + 1

    return along(size[0]) * along(size[1])


def tiling_note(advice: dict, sizes: list[tuple[int, int]]) -> str | None:
    """What the advised tile means for these photos: no tiling (one tile = the whole photo), or how many."""
    if "tile_size" not in advice or not sizes:
        return None
    tile, overlap = advice["tile_size"], advice["overlap"]
    counts = sorted({tiles_per_photo(s, tile, overlap) for s in sizes})
    if counts == [1]:
        same = all(max(s) == tile for s in sizes)
        return (
            f"tile_size {tile} {'equals' if same else 'covers'} the photos ({sizes[0][0]}x{sizes[0][1]}"
            f"{' ...' if len(sizes) > 1 else ''}): no tiling, each photo is one whole tile (module 5 then "
            f"keeps the photos whole; module 7 detects each photo in one pass)"
        )
    shown = "-".join(str(c) for c in (counts[0], counts[-1])) if len(counts) > 1 else str(counts[0])
    return f"{shown} tiles per photo ({sizes[0][0]}x{sizes[0][1]}{' ...' if len(sizes) > 1 else ''})"


def inspect_dataset(cfg: InspectConfig) -> dict:
    """Measure the boxes of ``cfg.annotations``, print and return the statistics and the advice. Tiles (module
    5's splits) are measured as the photos they came from, so both give the same advice."""
    ds = read_dataset(cfg.annotations, validate=False)
    check_structure(ds, Path(cfg.annotations))
    tiles = any("source_image" in im for im in ds["images"])
    photos, sizes, how = (
        source_view(ds) if tiles else (ds, sorted({(int(im["width"]), int(im["height"])) for im in ds["images"]}), "")
    )
    w, h = box_sizes(photos)
    stats = size_stats(w, h)
    if not stats["boxes"]:
        raise InputError(
            "the dataset has no boxes to measure",
            path=cfg.annotations,
            fix="give a COCO file with annotations (module 4's annotations.json)",
        )
    if tiles:
        log.info(
            "measured on tiles: %d tile boxes are %d distinct plants on %d photo(s); photo sizes from %s",
            len(ds["annotations"]),
            stats["boxes"],
            len(photos["images"]),
            how,
        )
    advice = recommend(stats, sizes)
    advice["max_minutes"] = BUDGET_MINUTES
    advice["why"]["max_minutes"] = BUDGET_WHY
    note = tiling_note(advice, sizes)
    if note:
        advice["tiling"] = note
    out = {
        "annotations": str(cfg.annotations),
        "images": len(ds["images"]),
        "image_sizes": sizes[:10],
        "tiles": tiles,
        "objects_px": stats,
        "recommended": advice,
    }
    if tiles:
        out.update(photos=len(photos["images"]), tile_boxes=len(ds["annotations"]), photo_sizes_from=how)
    # the JSON report on standard output (--report -) stays alone there, readable by another program
    print(format_report(out), file=sys.stderr if cfg.report is not None and is_stream(cfg.report) else sys.stdout)
    if cfg.report is not None:
        write_json(cfg.report, out)
        log.info("report -> %s", cfg.report)
    return out


def format_report(r: dict) -> str:
    """The report as text for the terminal."""
    s, a = r["objects_px"], r["recommended"]
    where = (
        f"{r['tile_boxes']} tile boxes on {r['images']} tiles = {s['boxes']} distinct plants on {r['photos']} photo(s)"
        if r["tiles"]
        else f"{s['boxes']} boxes on {r['images']} images"
    )
    rows = [
        f"{where} ({', '.join(f'{w}x{h}' for w, h in r['image_sizes'][:3])})",
        "object size in pixels       p5     p25    p50    p75    p95    p99",
    ]
    for key in ("width", "height", "sqrt_area", "long_side"):
        rows.append(f"  {key:<24}" + "".join(f"{s[key][p]:7.1f}" for p in ("p5", "p25", "p50", "p75", "p95", "p99")))
    rows.append(
        f"  height/width{'':<12}"
        + "".join(f"{s['aspect_h_over_w'][p]:7.2f}" for p in ("p5", "p25", "p50", "p75", "p95", "p99"))
    )
    rows += [
        "recommended (module 5 and module 6 settings):",
        f"  tile_size: {a['tile_size']}    overlap: {a['overlap']}",
        f"  model.min_size: {a['min_size']}    model.max_size: {a['max_size']}    "
        f"(CPU: not below {a['min_size_floor']})",
        f"  model.anchor_sizes: auto  (or, for these objects: {json.dumps(a['anchor_sizes'])})",
        f"  model.aspect_ratios: {a['aspect_ratios']}",
    ]
    if "max_minutes" in a:
        rows.append(f"  max_minutes: {a['max_minutes']}  (module 6: the training's time budget, in minutes)")
    if a.get("tiling"):
        rows.append(f"  tiling: {a['tiling']}")
    rows += [f"  why {k}: {v}" for k, v in a["why"].items()]
    if r["tiles"]:
        rows.append(
            "  (measured on tiles, as the photos they were cut from: the advice is the photos' own; photo "
            f"sizes from {r['photo_sizes_from']})"
        )
    return "\n".join(rows)


__all__ = [
    "MIN_OBJECT_PX",
    "InspectConfig",
    "auto_anchor_sizes",
    "box_sizes",
    "format_report",
    "input_scale",
    "inspect_dataset",
    "recommend",
    "size_stats",
    "smallest_anchor",
]
