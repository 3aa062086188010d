"""Module 4's imports: boxes to correct, from a COCO dataset (CVAT and Label Studio exports included),
YOLO labels, module 7's predictions, masks (label images), DeepForest CSV, Pascal VOC or CVAT XML.

Every reader gives ``{source image name: [ImportedBox]}`` in source-image pixels, so that the store
adds boxes one way whatever their origin: tiles (``source_image``, ``x0``, ``y0``; docs/DESIGN.md §2)
are put back in the photo they were cut from.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from matchplant.bbox_drawer.store import ImportedBox, ImportedBoxes
from matchplant.core.formats.box_files import read_cvat_xml, read_deepforest_csv, read_voc
from matchplant.core.formats.coco import (
    DropLog,
    LabelledBox,
    bbox_values,
    read_dataset,
    to_source_pixels,
)
from matchplant.core.formats.images import IMAGE_SUFFIXES, read_image
from matchplant.core.formats.masks import mask_boxes
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.formats.yolo import read_yolo
from matchplant.core.geometry.boxes import nms
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("bbox_drawer")


def read_coco_boxes(path: str | Path) -> ImportedBoxes:
    """Boxes of a COCO dataset by source image name; tiles (``source_image``, ``x0``, ``y0``) are put back.
    Boxes that cannot be used (unknown image or category id, no finite bbox, size <= 0, a repeated box) are
    left out and listed in the result's ``drops``; ambiguous files (an image or category id used twice) are
    errors."""
    ds = read_dataset(path, validate=False)
    return _collect(Path(path), ds["images"], ds["categories"], ds["annotations"])


def read_yolo_boxes(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> ImportedBoxes:
    """Boxes of YOLO labels by image name; ``sizes`` (name -> (width, height)) are the session's images."""
    drops = DropLog()
    _, boxes = read_yolo(labels_dir, sizes, drops)
    return ImportedBoxes({name: [ImportedBox(b.xyxy, b.category) for b in items] for name, items in boxes.items()},
                         drops=drops)


def read_prediction_boxes(path: str | Path, min_score: float = 0.5, nms_iou: float = 0.5,
                          images_from: str | Path | None = None) -> ImportedBoxes:
    """Module 7 predictions above ``min_score``, in source-image pixels; duplicates from overlapping
    tiles are merged by non-maximum suppression (IoU ``nms_iou``)."""
    path = Path(path)
    data = read_predictions(path, images_from)
    scores = []
    for p in data["predictions"]:
        try:
            scores.append(float(p.get("score", 1.0)))
        except (TypeError, ValueError):
            scores.append(float("nan"))
    preds = [p for p, s in zip(data["predictions"], scores) if s >= min_score]
    if data["predictions"] and not preds:
        best = max((s for s in scores if s == s), default=float("nan"))
        raise InputError(f"none of the {len(scores)} predictions has a score >= min_score {min_score:g} "
                         f"(the highest is {best:g})", path=path,
                         fix=f"lower min_score (e.g. --set min_score={max(0.0, round(best, 2) - 0.05):g})")
    boxes = _collect(path, data["images"], data["categories"], preds, kind="prediction")
    return ImportedBoxes({name: _nms(items, nms_iou) for name, items in boxes.items()}, sizes=boxes.sizes,
                         drops=boxes.drops)


def read_deepforest_boxes(path: str | Path) -> ImportedBoxes:
    """A DeepForest CSV (``image_path,xmin,ymin,xmax,ymax,label``, optional ``score``)."""
    return _imported(read_deepforest_csv(path))


def read_voc_boxes(path: str | Path) -> ImportedBoxes:
    """Pascal VOC XML: one file, or a folder of them (one per image)."""
    return _imported(*read_voc(path))


def read_cvat_boxes(path: str | Path) -> ImportedBoxes:
    """A 'CVAT for images 1.1' XML export (boxes; other shapes are skipped)."""
    return _imported(*read_cvat_xml(path))


def read_mask_boxes(masks_dir: str | Path, images: list[str], min_area: int = 20, category: str = "plant",
                    sizes: dict[str, tuple[int, int]] | None = None) -> ImportedBoxes:
    """Boxes from label images: for each image, a mask named ``<image stem>.<ext>`` or ``<image name>.png``
    in ``masks_dir`` (instance ids or a binary mask; objects under ``min_area`` pixels dropped). With
    ``sizes`` (image name -> (width, height)), a mask of another size than its photo is an error."""
    masks_dir = Path(masks_dir)
    if not masks_dir.is_dir():
        raise InputError("mask folder not found", path=masks_dir, fix="set import_masks to the folder of label images")
    out = ImportedBoxes()
    for name in images:
        stem = Path(name).stem
        for candidate in [masks_dir / (stem + s) for s in IMAGE_SUFFIXES] + [masks_dir / (name + ".png"),
                                                                             masks_dir / (Path(stem).stem + ".png")]:
            if candidate.is_file() and candidate.name != name:  # never the photo itself
                mask = read_image(candidate)
                if sizes and name in sizes and (mask.shape[1], mask.shape[0]) != tuple(sizes[name]):
                    raise InputError(f"the mask is {mask.shape[1]}x{mask.shape[0]} px but its photo {name} is "
                                     f"{sizes[name][0]}x{sizes[name][1]} px", path=candidate,
                                     fix="give masks of the same size as the photos (not resized)")
                out[name] = [ImportedBox(b.xyxy, b.category, where=candidate.name)
                             for b in mask_boxes(mask, min_area, category)]
                break
    if not out:
        raise InputError("no mask matches an image (masks are named like their image: <stem>.png)", path=masks_dir,
                         fix="name each mask after its photo, e.g. IMG_0001.png for IMG_0001.JPG")
    return out


def _imported(boxes: dict[str, list[LabelledBox]], sizes: dict[str, tuple[int, int]] | None = None) -> ImportedBoxes:
    return ImportedBoxes({name: [ImportedBox(list(b.xyxy), b.category, b.score, b.where) for b in items]
                          for name, items in boxes.items()}, sizes=sizes)


def _unique_ids(items: list[dict], kind: str, path: Path) -> None:
    counts = Counter(item.get("id") for item in items)
    dup = sorted((i for i, c in counts.items() if c > 1), key=str)
    if dup:
        raise InputError(f"{kind} id(s) {dup[:5]} are used by more than one {kind} entry, so the boxes "
                         f"cannot be told apart", path=path,
                         fix=f"give every {kind} its own id (re-export the file from the annotation tool)")


def _collect(path: Path, images: list[dict], categories: list[dict], anns: list[dict],
             kind: str = "annotation") -> ImportedBoxes:
    _unique_ids(images, "image", path)
    _unique_ids(categories, "category", path)
    if anns and not categories:
        raise InputError(f"the file defines no categories, but its {kind}s use category ids "
                         f"{sorted({a.get('category_id') for a in anns}, key=str)[:5]}", path=path,
                         fix="add the categories, e.g. \"categories\": [{\"id\": 1, \"name\": \"plant\"}]")
    by_id = {im.get("id"): im for im in images}
    cat_names = {c.get("id"): str(c.get("name", c.get("id"))) for c in categories}
    known = ", ".join(f"{i}={n}" for i, n in cat_names.items())
    drops = DropLog()
    out = ImportedBoxes({_name(im): [] for im in images if _name(im)}, drops=drops,
                        sizes={im["file_name"]: (im.get("width"), im.get("height")) for im in images
                               if im.get("file_name") and "source_image" not in im})
    seen: dict[tuple, str] = {}
    ids: set = set()
    repeated_ids = 0
    for i, a in enumerate(anns, start=1):
        where = f"{kind} {a['id']}" if "id" in a else f"{kind} #{i}"
        im = by_id.get(a.get("image_id"))
        box = bbox_values(a.get("bbox"))
        if im is None or not _name(im):
            drops.add(path, where, a.get("image_id"), box or repr(a.get("bbox")), "image id not in the file",
                      f"image_id {a.get('image_id')!r} is not one of the file's images (with a file_name)")
            continue
        name = _name(im)
        if box is None:
            drops.add(path, where, name, repr(a.get("bbox")), "bbox is not [x, y, w, h] numbers",
                      f"bbox {a.get('bbox')!r}")
            continue
        if a.get("category_id") not in cat_names:
            drops.add(path, where, name, box, "unknown category id",
                      f"category_id {a.get('category_id')!r}; the file's categories: {known}")
            continue
        x, y, w, h = to_source_pixels(box, im)
        if not (w > 0 and h > 0):
            drops.add(path, where, name, box, "zero or negative size", f"w={w:g}, h={h:g}")
            continue
        key = (name, round(x, 2), round(y, 2), round(w, 2), round(h, 2), a.get("category_id"))
        if key in seen:
            drops.add(path, where, name, box, "duplicate box", f"the same box as {seen[key]}")
            continue
        if "id" in a:
            repeated_ids += repr(a["id"]) in ids
            ids.add(repr(a["id"]))
        score = a.get("score")
        if score is not None and not isinstance(score, (int, float)):
            drops.add(path, where, name, box, "score is not a number", f"score {score!r}")
            continue
        seen[key] = where
        out[name].append(ImportedBox([x, y, x + w, y + h], cat_names[a["category_id"]], score, where))
    if repeated_ids:
        log.warning("%s: %d %s id(s) are used more than once (different boxes, all imported; module 4 numbers "
                    "the boxes anew)", path.name, repeated_ids, kind)
    return out


def _name(image: dict) -> str:
    """The photo an image entry means (a tile's source photo); "" when the entry names none."""
    return str(image.get("source_image") or image.get("file_name") or "")


def _nms(items: list[ImportedBox], iou: float) -> list[ImportedBox]:
    if len(items) < 2:
        return items
    scores = np.array([float(b.score if b.score is not None else 1.0) for b in items])
    # a box without a positive score goes, as with OpenCV's NMSBoxes (used here before)
    scored = np.flatnonzero(scores > 0)
    boxes = np.array([b.xyxy for b in items], dtype=float)
    keep = scored[nms(boxes[scored], scores[scored], iou)]
    return [items[i] for i in sorted(keep.tolist())]


__all__ = ["read_coco_boxes", "read_yolo_boxes", "read_prediction_boxes", "read_deepforest_boxes", "read_voc_boxes",
           "read_cvat_boxes", "read_mask_boxes"]
