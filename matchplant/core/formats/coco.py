"""COCO datasets and detection results, with the tile provenance that chains the modules (docs/DESIGN.md §2).

Dataset: ``{"images": [...], "annotations": [...], "categories": [...]}`` with ``bbox = [x, y, w, h]`` in
pixels of that image, ``area = w * h``, ``iscrowd = 0``, categories numbered 1..N. A tile's image entry
also records ``source_image`` (file name of the photo it was cut from) and its offset ``x0``, ``y0``.

Predictions (module 7 -> 8, 4): a JSON object ``{"images": [...], "categories": [...],
"predictions": [{"image_id", "category_id", "bbox", "score"}, ...]}``; each image entry carries
``file_name``, ``width``, ``height`` and, for tiles, ``source_image``, ``x0``, ``y0``, so every box can
be put back in source-image pixels. A plain COCO results list (``[{"image_id", ...}]``) plus a dataset
for the image entries is accepted too.
"""

from __future__ import annotations

import csv
import io
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_json, write_text
from matchplant.core.runtime.validate import read_json

# an image entry's annotated region: a polygon [[x, y], ...] in that image's pixels (pixel edges, as
# boxes); every plant touching it is boxed, plants outside it are not. No key: the whole image.
REGION_KEY = "annotated_region"


class LabelledBox(NamedTuple):
    """A box read from an annotation file: ``[x1, y1, x2, y2]`` pixel edges, a category name, a score."""

    xyxy: list[float]
    category: str
    score: float | None = None
    where: str = ""  # where in its file (line, object), for the report of boxes left out


def new_dataset(categories: Iterable[str], info: dict | None = None) -> dict:
    """An empty COCO dataset with the given category names (ids from 1)."""
    return {
        "info": info or {"description": "MatchPlant dataset"},
        "licenses": [],
        "images": [],
        "annotations": [],
        "categories": [{"id": i + 1, "name": str(name), "supercategory": "plant"} for i, name in enumerate(categories)],
    }


def make_annotation(ann_id: int, image_id: int, bbox: Iterable[float], category_id: int = 1, **extra) -> dict:
    """A COCO annotation of one box ``[x, y, w, h]``, with any extra keys given."""
    x, y, w, h = (float(v) for v in bbox)
    ann = {
        "id": int(ann_id),
        "image_id": int(image_id),
        "category_id": int(category_id),
        "bbox": [x, y, w, h],
        "area": w * h,
        "iscrowd": 0,
    }
    ann.update(extra)
    return ann


def read_dataset(path: str | Path, *, validate: bool = True) -> dict:
    """A COCO dataset (UTF-8 with or without BOM); its lists must hold objects. With ``validate``, every
    problem of :func:`validate_dataset` is an error naming the annotation or image ids."""
    path = Path(path)
    data = read_json(path, what="COCO file")
    if not isinstance(data, dict) or "images" not in data:
        raise InputError(
            "not a COCO dataset (no 'images' list)", path=path, fix="give the COCO JSON written by module 4 or 5"
        )
    data.setdefault("annotations", [])
    data.setdefault("categories", [])
    for key in ("images", "annotations", "categories"):
        items = data[key]
        if not isinstance(items, list) or not all(isinstance(item, dict) for item in items):
            raise InputError(
                f"'{key}' is not a list of objects {{...}}",
                path=path,
                fix="give a COCO dataset (images, annotations, categories are lists of objects)",
            )
    if validate:
        raise_problems(
            data,
            path,
            "correct them, or import the file with module 4 (import_coco), which leaves out "
            "and lists the boxes it cannot use, and use module 4's annotations.json",
        )
    return data


def raise_problems(data: dict, path: Path, fix: str) -> None:
    """An InputError listing the first ten problems :func:`validate_dataset` finds (and how many more), if any."""
    problems = validate_dataset(data)
    if problems:
        shown = "\n".join(f"  - {p}" for p in problems[:10])
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        raise InputError(f"the COCO dataset has {len(problems)} problem(s):\n{shown}{more}", path=path, fix=fix)


def write_dataset(path: str | Path, data: dict) -> Path:
    """Write a COCO dataset as compact JSON, whole or not at all."""
    return write_json(path, data, indent=None)


def validate_dataset(data: dict, *, tolerance: float = 1.0) -> list[str]:
    """Problems in a COCO dataset, each as a sentence; an empty list means valid.

    Checks unique ids, annotations pointing at existing images and categories, positive box sizes,
    and boxes inside their image (within ``tolerance`` pixels).
    """
    problems: list[str] = []
    images = data.get("images", [])
    anns = data.get("annotations", [])
    cats = data.get("categories", [])
    for kind, items in (("image", images), ("annotation", anns), ("category", cats)):
        counts = Counter(item.get("id") for item in items)
        dup = [i for i, c in counts.items() if c > 1]
        if dup:
            problems.append(f"duplicate {kind} ids: {sorted(dup)[:5]}")
        if any(item.get("id") is None for item in items):
            problems.append(f"a {kind} has no id")
    if not cats and anns:
        problems.append("no categories defined")
    by_id = {im.get("id"): im for im in images}
    cat_ids = {c.get("id") for c in cats}
    for im in images:
        if not im.get("file_name"):
            problems.append(f"image {im.get('id')} has no file_name")
        if not (
            isinstance(im.get("width"), (int, float))
            and isinstance(im.get("height"), (int, float))
            and im["width"] > 0
            and im["height"] > 0
        ):
            problems.append(f"image {im.get('id')} ({im.get('file_name')}) has no valid width/height")
    for a in anns:
        im = by_id.get(a.get("image_id"))
        if im is None:
            problems.append(f"annotation {a.get('id')} refers to missing image {a.get('image_id')}")
            continue
        if a.get("category_id") not in cat_ids:
            problems.append(f"annotation {a.get('id')} has unknown category {a.get('category_id')}")
        box = bbox_values(a.get("bbox"))
        if box is None:
            problems.append(
                f"annotation {a.get('id')} has no [x, y, w, h] bbox of finite numbers (got {a.get('bbox')!r})"
            )
            continue
        x, y, w, h = box
        if not (w > 0 and h > 0):
            problems.append(f"annotation {a.get('id')} in {im.get('file_name')} has a box of size {w}x{h}")
        W, H = im.get("width", 0), im.get("height", 0)
        if x < -tolerance or y < -tolerance or x + w > W + tolerance or y + h > H + tolerance:
            problems.append(f"annotation {a.get('id')} box {[x, y, w, h]} lies outside {im.get('file_name')} ({W}x{H})")
    return problems


def bbox_values(bbox: Any) -> list[float] | None:
    """``[x, y, w, h]`` as four finite floats, or None when it is not that (missing, text, NaN, 5 values)."""
    if not isinstance(bbox, (list, tuple)) or len(bbox) != 4:
        return None
    try:
        values = [float(v) for v in bbox]
    except (TypeError, ValueError):
        return None
    return values if all(math.isfinite(v) for v in values) else None


# -- what an import or a tiling run left out, and why ---------------------------------------------------

DROP_COLUMNS = ("source", "where", "image", "box", "reason", "detail")


@dataclass
class DropLog:
    """Boxes (or images) left out of a run, one row each: the file they came from, where in it (annotation
    id, line), the image, the box, a short reason (counted in the warning) and details. Written as CSV."""

    rows: list[dict] = field(default_factory=list)

    def add(self, source: Any, where: Any, image: Any, box: Any, reason: str, detail: str = "") -> None:
        """Record one box (or image) left out and why."""
        shown = box if isinstance(box, str) else ("" if box is None else "[" + ", ".join(_short(v) for v in box) + "]")
        self.rows.append(
            {
                "source": str(source),
                "where": str(where),
                "image": str(image),
                "box": shown,
                "reason": reason,
                "detail": detail,
            }
        )

    def __len__(self) -> int:
        return len(self.rows)

    def count(self, source: Any = None) -> int:
        """Number of rows left out, from one source or from all."""
        return sum(1 for r in self.rows if source is None or r["source"] == str(source))

    def summary(self, source: Any = None) -> str:
        """``"12 box outside the image, 3 unknown category id"`` (most frequent first)."""
        counts = Counter(r["reason"] for r in self.rows if source is None or r["source"] == str(source))
        return ", ".join(f"{n} {reason}" for reason, n in counts.most_common())

    def first(self, source: Any = None) -> dict | None:
        """The first row left out, from one source or from all; None when there is none."""
        return next((r for r in self.rows if source is None or r["source"] == str(source)), None)

    def write_csv(self, path: str | Path) -> Path:
        """Write the rows as CSV (the columns of ``DROP_COLUMNS``)."""
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=DROP_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.rows)
        return write_text(path, buf.getvalue())


def _short(v: Any) -> str:
    try:
        return f"{float(v):g}"
    except (TypeError, ValueError):
        return repr(v)


def annotations_by_image(data: dict) -> dict[int, list[dict]]:
    """Each image id's annotations (an empty list for an image without any)."""
    out: dict[int, list[dict]] = {im["id"]: [] for im in data.get("images", [])}
    for a in data.get("annotations", []):
        out.setdefault(a["image_id"], []).append(a)
    return out


def boxes_xyxy(anns: list[dict]) -> np.ndarray:
    """(N, 4) array of ``[x1, y1, x2, y2]`` from COCO annotations or predictions."""
    if not anns:
        return np.zeros((0, 4))
    b = np.asarray([a["bbox"] for a in anns], dtype=float)
    return np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], axis=1)


def to_source_pixels(bbox: Iterable[float], image: dict) -> list[float]:
    """A box in tile pixels moved to its source image using the tile's ``x0``, ``y0``."""
    x, y, w, h = (float(v) for v in bbox)
    return [x + float(image.get("x0", 0)), y + float(image.get("y0", 0)), w, h]


def annotated_region(image: dict) -> np.ndarray | None:
    """The image entry's annotated region as an (N, 2) polygon, or None when the whole image was annotated."""
    poly = image.get(REGION_KEY)
    if poly is None:
        return None
    try:
        arr = np.asarray(poly, dtype=float)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3 or not np.isfinite(arr).all():
        raise InputError(
            f"the {REGION_KEY} of image '{image.get('file_name')}' is not a list of at least 3 [x, y] points",
            fix=f"remove '{REGION_KEY}' (whole image annotated) or re-export the annotations with module 4",
        )
    return arr


def region_entry(polygon) -> list[list[float]]:
    """A polygon as stored under :data:`REGION_KEY` (rounded to 0.01 px)."""
    return [[round(float(x), 2), round(float(y), 2)] for x, y in np.asarray(polygon, dtype=float)]


def source_name(image: dict) -> str:
    """Name of the photo a COCO image was cut from (``source_image``), else its own file name."""
    return image.get("source_image") or image["file_name"]
