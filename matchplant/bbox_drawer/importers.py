"""Module 4's imports: boxes to correct, from a COCO dataset, YOLO labels or module 7's predictions.

Every reader gives ``{source image name: [ImportedBox]}`` in source-image pixels, so that the store
adds boxes one way whatever their origin: tiles (``source_image``, ``x0``, ``y0``; docs/DESIGN.md §2)
are put back in the photo they were cut from.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from matchplant.bbox_drawer.store import ImportedBox
from matchplant.core.coco import read_dataset, read_predictions, source_name, to_source_pixels
from matchplant.core.yolo import read_yolo


def read_coco_boxes(path: str | Path) -> dict[str, list[ImportedBox]]:
    """Boxes of a COCO dataset by source image name; tiles (``source_image``, ``x0``, ``y0``) are put back."""
    ds = read_dataset(path, validate=False)
    return _collect(ds["images"], ds["categories"], ds["annotations"])


def read_yolo_boxes(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> dict[str, list[ImportedBox]]:
    """Boxes of YOLO labels by image name; ``sizes`` (name -> (width, height)) are the session's images."""
    _, boxes = read_yolo(labels_dir, sizes)
    return {name: [ImportedBox(b.xyxy, b.category) for b in items] for name, items in boxes.items()}


def read_prediction_boxes(path: str | Path, min_score: float = 0.5, nms_iou: float = 0.5,
                          images_from: str | Path | None = None) -> dict[str, list[ImportedBox]]:
    """Module 7 predictions above ``min_score``, in source-image pixels; duplicates from overlapping
    tiles are merged by non-maximum suppression (IoU ``nms_iou``)."""
    data = read_predictions(path, images_from)
    preds = [p for p in data["predictions"] if float(p.get("score", 1.0)) >= min_score]
    boxes = _collect(data["images"], data["categories"], preds)
    return {name: _nms(items, nms_iou) for name, items in boxes.items()}


def _collect(images: list[dict], categories: list[dict], anns: list[dict]) -> dict[str, list[ImportedBox]]:
    by_id = {im["id"]: im for im in images}
    cat_names = {c["id"]: str(c.get("name", c["id"])) for c in categories}
    out: dict[str, list[ImportedBox]] = {source_name(im): [] for im in images}
    for a in anns:
        im = by_id.get(a.get("image_id"))
        if im is None or not isinstance(a.get("bbox"), (list, tuple)) or len(a["bbox"]) != 4:
            continue
        x, y, w, h = to_source_pixels(a["bbox"], im)
        if w <= 0 or h <= 0:
            continue
        out[source_name(im)].append(ImportedBox([x, y, x + w, y + h], cat_names.get(a.get("category_id"), "plant"),
                                                a.get("score")))
    return out


def _nms(items: list[ImportedBox], iou: float) -> list[ImportedBox]:
    if len(items) < 2:
        return items
    rects = [[b.xyxy[0], b.xyxy[1], b.xyxy[2] - b.xyxy[0], b.xyxy[3] - b.xyxy[1]] for b in items]
    scores = [float(b.score if b.score is not None else 1.0) for b in items]
    keep = cv2.dnn.NMSBoxes(rects, scores, 0.0, iou)
    return [items[i] for i in sorted(np.asarray(keep).reshape(-1).tolist())]


__all__ = ["read_coco_boxes", "read_yolo_boxes", "read_prediction_boxes"]
