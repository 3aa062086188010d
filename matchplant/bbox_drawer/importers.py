"""Module 4's imports: boxes to correct, from a COCO dataset (CVAT and Label Studio exports included),
YOLO labels, module 7's predictions, masks (label images), DeepForest CSV, Pascal VOC or CVAT XML.

Every reader gives ``{source image name: [ImportedBox]}`` in source-image pixels, so that the store
adds boxes one way whatever their origin: tiles (``source_image``, ``x0``, ``y0``; docs/DESIGN.md §2)
are put back in the photo they were cut from.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import numpy as np

from matchplant.bbox_drawer.store import ImportedBox, ImportedBoxes
from matchplant.core.formats.box_files import (
    read_cvat_xml,
    read_deepforest_csv,
    read_voc,
    strip_upload_prefix,
)
from matchplant.core.formats.coco import (
    DropLog,
    LabelledBox,
    bbox_values,
    read_dataset,
    to_source_pixels,
)
from matchplant.core.formats.masks import MASK_SUFFIXES, mask_objects, read_mask
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.formats.yolo import read_yolo
from matchplant.core.geometry.boxes import nms
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("bbox_drawer")


def read_coco_boxes(path: str | Path) -> ImportedBoxes:
    """Boxes of a COCO dataset by source image name; tiles (``source_image``, ``x0``, ``y0``) are put back.

    Boxes that cannot be used (unknown image or category id, no finite bbox, size <= 0, a repeated box) are
    left out and listed in the result's ``drops``; ambiguous files (an image or category id used twice) are
    errors.

    Parameters
    ----------
    path : str or Path
        The COCO ``.json`` file (CVAT and Label Studio COCO exports included).

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
    ds = read_dataset(path, validate=False)
    return _collect(Path(path), ds["images"], ds["categories"], ds["annotations"])


def read_yolo_boxes(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> ImportedBoxes:
    """Boxes of YOLO labels by image name; ``sizes`` (name -> (width, height)) are the session's images.

    Parameters
    ----------
    labels_dir : str or Path
        The folder of YOLO ``.txt`` label files.
    sizes : dict
        Image name -> (width, height) in pixels of the session's photos: YOLO boxes are fractions of them.

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
    drops = DropLog()
    _, boxes = read_yolo(labels_dir, sizes, drops)
    return ImportedBoxes(
        {name: [ImportedBox(b.xyxy, b.category) for b in items] for name, items in boxes.items()}, drops=drops
    )


def read_prediction_boxes(
    path: str | Path, min_score: float = 0.5, nms_iou: float = 0.5, images_from: str | Path | None = None
) -> ImportedBoxes:
    """Module 7 predictions above ``min_score``, in source-image pixels, to correct by hand.

    Duplicates from overlapping tiles are merged by non-maximum suppression (IoU ``nms_iou``); no
    prediction at or above ``min_score`` is an error that names the highest score.

    Parameters
    ----------
    path : str or Path
        Module 7's predictions file, or a plain COCO results list (then give ``images_from``).
    min_score : float
        Predictions scoring less are left out.
    nms_iou : float
        Overlap (IoU) above which two boxes of one photo count as the same plant.
    images_from : str or Path, optional
        A COCO dataset giving the image entries of a plain COCO results list.

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
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
        best = max((s for s in scores if not np.isnan(s)), default=float("nan"))
        raise InputError(
            f"none of the {len(scores)} predictions has a score >= min_score {min_score:g} (the highest is {best:g})",
            path=path,
            fix=f"lower min_score (e.g. --set min_score={max(0.0, round(best, 2) - 0.05):g})",
        )
    boxes = _collect(path, data["images"], data["categories"], preds, kind="prediction")
    return ImportedBoxes(
        {name: _nms(items, nms_iou) for name, items in boxes.items()}, sizes=boxes.sizes, drops=boxes.drops
    )


def read_deepforest_boxes(path: str | Path) -> ImportedBoxes:
    """Boxes of a DeepForest CSV (``image_path,xmin,ymin,xmax,ymax,label``, optional ``score``).

    Parameters
    ----------
    path : str or Path
        The CSV file.

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
    return _imported(read_deepforest_csv(path))


def read_voc_boxes(path: str | Path) -> ImportedBoxes:
    """Boxes of Pascal VOC XML: one file, or a folder of them (one per image).

    Parameters
    ----------
    path : str or Path
        An ``.xml`` file or a folder of them.

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
    return _imported(*read_voc(path))


def read_cvat_boxes(path: str | Path) -> ImportedBoxes:
    """Boxes of a 'CVAT for images 1.1' XML export (other shapes are skipped).

    Parameters
    ----------
    path : str or Path
        The exported ``annotations.xml``.

    Returns
    -------
    ImportedBoxes
        Source image name -> its boxes in source-image pixels, with the sizes the file declares and the
        boxes left out (``drops``).
    """
    return _imported(*read_cvat_xml(path))


def _check_mask_size(mask, path: Path, name: str, size: tuple[int, int]) -> None:
    """A mask of another size than its photo (``size``: width, height) is an error."""
    if (mask.shape[1], mask.shape[0]) != tuple(size):
        raise InputError(
            f"the mask is {mask.shape[1]}x{mask.shape[0]} px but its photo {name} is {size[0]}x{size[1]} px",
            path=path,
            fix="give masks of the same size as the photos (not resized)",
        )


def read_mask_boxes(
    masks_dir: str | Path,
    images: list[str],
    min_area: int = 20,
    category: str = "plant",
    sizes: dict[str, tuple[int, int]] | None = None,
    mode: str = "auto",
    threshold: float | None = None,
) -> ImportedBoxes:
    """Boxes from label images: for each image, the mask named after it in ``masks_dir`` (``<stem>.<ext>`` in
    any image format, ``<image name>.png``, ``<stem>_mask.png``, Label Studio's upload prefix ignored).

    Each mask is read as instances or as a binary mask (``mode`` "auto": decided from its pixels and said in
    the log, :func:`matchplant.core.formats.masks.decide_mode`); objects under ``min_area`` pixels are
    dropped and counted. With ``sizes`` (image name -> (width, height)), a mask of another size than its
    photo is an error.

    Parameters
    ----------
    masks_dir : str or Path
        The folder of label images.
    images : list of str
        The session's photo names, to match masks to.
    min_area : int
        Objects of fewer pixels are dropped (specks).
    category : str
        Category name given to every object found.
    sizes : dict, optional
        Image name -> (width, height) of the photos, to check each mask's size.
    mode : str
        "auto", "binary" or "instance": how to read each mask.
    threshold : float, optional
        Pixel value at or above which a binary mask is foreground; with ``mode`` "auto", masks are then read
        as binary.

    Returns
    -------
    ImportedBoxes
        Image name -> the boxes of its mask's objects, in pixels.
    """
    masks_dir = Path(masks_dir)
    if not masks_dir.is_dir():
        raise InputError("mask folder not found", path=masks_dir, fix="set import_masks to the folder of label images")
    found = _mask_files(masks_dir, images)
    out = ImportedBoxes()
    modes: Counter = Counter()
    reasons: dict[str, str] = {}
    dropped = total = 0
    below: dict[str, float] = {}  # masks whose every value lies under mask_threshold: file -> top value
    for name, path in found.items():
        mask = read_mask(path)
        if sizes and name in sizes:
            _check_mask_size(mask, path, name, sizes[name])
        objects = mask_objects(mask, min_area, category, mode, threshold)
        log.debug(
            "%s: read as %s (%s): %d object(s), %d under mask_min_area",
            path.name,
            objects.mode,
            objects.reason,
            len(objects.boxes),
            objects.dropped,
        )
        modes[objects.mode] += 1
        reasons.setdefault(objects.mode, f"{path.name}: {objects.reason}")
        for warning in objects.warnings:
            log.warning("mask %s: %s; if so, set mask_mode: binary (and mask_threshold)", path.name, warning)
        if threshold is not None and 0 < objects.top < threshold:
            below[path.name] = objects.top
        dropped += objects.dropped
        total += objects.dropped + len(objects.boxes)
        out[name] = [ImportedBox(b.xyxy, b.category, where=path.name) for b in objects.boxes]
    if below:
        _threshold_above(masks_dir, threshold, below, total)
    for kind, n in sorted(modes.items()):
        log.info(
            "%d mask(s) read as %s (%s), e.g. %s",
            n,
            kind,
            "mask_mode" if mode != "auto" or threshold is not None else "decided from the pixels",
            reasons[kind],
        )
    if len(modes) > 1:
        log.warning(
            "the masks of %s were read as %s: %s; set mask_mode: binary or instance if they are all of one kind",
            masks_dir,
            " and ".join(f"{kind} ({n})" for kind, n in sorted(modes.items())),
            "; ".join(reasons.values()),
        )
    if dropped:
        log.info(
            "mask_min_area %d: %d of the %d mask object(s) were smaller and not imported (specks)",
            min_area,
            dropped,
            total,
        )
    return out


def _threshold_above(masks_dir: Path, threshold: float, below: dict[str, float], total: int) -> None:
    """``mask_threshold`` above every value of some masks: they give no object. An error when no mask gave one,
    else a warning naming them."""
    tops = sorted(set(below.values()))
    names = ", ".join(list(below)[:5]) + (f" and {len(below) - 5} more" if len(below) > 5 else "")
    what = (
        f"mask_threshold = {threshold:g} is above every value of {len(below)} mask(s) ({names}: their values "
        f"reach {tops[0]:g}" + (f"-{tops[-1]:g}" if len(tops) > 1 else "") + "), so they give no plant"
    )
    fix = (
        f"set mask_threshold to the plants' value or below (half the foreground value, e.g. {tops[0] / 2:g}, "
        "for an anti-aliased binary mask), or remove it (empty: decided from each mask's pixels)"
    )
    if not total:
        raise ConfigError(what, path=masks_dir, fix=fix)
    log.warning("%s; %s", what, fix)


MASK_WORDS = ("_mask", "-mask", "_masks", "_label", "-label", "_labels", "_seg", "_gt", "_instances")


def _mask_key(name: str) -> str:
    """The photo a mask file's name means, loosely: without folder, upload prefix, extensions and a trailing
    ``_mask``/``_label``-like word, case ignored (``3f2a1b7c-IMG_1.JPG_mask.png`` -> ``img_1``)."""
    stem = strip_upload_prefix(str(name).replace("\\", "/").rsplit("/", 1)[-1]).casefold()
    stem = re.sub(r"\.[a-z][a-z0-9]{0,4}$", "", stem)  # the file's own extension, whatever it is
    for _ in range(3):  # IMG_1.JPG.tif_mask.png
        base, dot, ext = stem.rpartition(".")
        if dot and "." + ext in MASK_SUFFIXES + (".dng",):
            stem = base
        for word in MASK_WORDS:
            stem = stem.removesuffix(word)
    return stem


def _mask_files(masks_dir: Path, images: list[str]) -> dict[str, Path]:
    """Image name -> its mask file; a mask format that is not read, or two masks for one photo, are errors."""
    by_key: dict[str, list[Path]] = {}
    for p in sorted(masks_dir.iterdir()):
        if p.is_file() and not p.name.startswith("."):
            by_key.setdefault(_mask_key(p.name), []).append(p)
    found: dict[str, Path] = {}
    unread: list[Path] = []
    for name in images:
        cands = [p for p in by_key.get(_mask_key(name), []) if p.name != name]  # never the photo itself
        masks = [p for p in cands if p.suffix.lower() in MASK_SUFFIXES]
        unread += [p for p in cands if p.suffix.lower() not in MASK_SUFFIXES]
        if len(masks) > 1:
            raise InputError(
                f"{len(masks)} masks fit the photo {name}: {', '.join(p.name for p in masks)}",
                path=masks_dir,
                fix="keep one mask per photo in the folder (move the others away)",
            )
        if masks:
            found[name] = masks[0]
    if not found:
        kinds = "/".join(s.lstrip(".").upper() for s in MASK_SUFFIXES)
        if unread:
            raise InputError(
                f"the masks named after the photos are {', '.join(sorted({p.suffix for p in unread}))} "
                f"files (e.g. {unread[0].name}), which are not read as images ({kinds} are)",
                path=masks_dir,
                fix="save the masks as PNG (grey ids, a binary mask or RGB colours)",
            )
        files = sorted(p.name for p in masks_dir.iterdir() if p.is_file())
        example = f"; the folder holds e.g. {', '.join(files[:3])}" if files else "; the folder is empty"
        raise InputError(
            f"no mask is named after any of the {len(images)} photos (e.g. {images[0] if images else '-'}){example}",
            path=masks_dir,
            fix="name each mask after its photo, e.g. IMG_0001.png for IMG_0001.JPG",
        )
    if unread:
        log.warning(
            "%d file(s) in %s named after a photo are not read as masks (e.g. %s): convert them to PNG",
            len(unread),
            masks_dir,
            unread[0].name,
        )
    missing = [n for n in images if n not in found]
    if missing:
        log.info(
            "%d of the %d photos have no mask in %s (e.g. %s): no boxes imported for them",
            len(missing),
            len(images),
            masks_dir,
            missing[0],
        )
    return found


def _imported(boxes: dict[str, list[LabelledBox]], sizes: dict[str, tuple[int, int]] | None = None) -> ImportedBoxes:
    return ImportedBoxes(
        {
            name: [ImportedBox(list(b.xyxy), b.category, b.score, b.where) for b in items]
            for name, items in boxes.items()
        },
        sizes=sizes,
    )


def _unique_ids(items: list[dict], kind: str, path: Path) -> None:
    counts = Counter(item.get("id") for item in items)
    dup = sorted((i for i, c in counts.items() if c > 1), key=str)
    if dup:
        raise InputError(
            f"{kind} id(s) {dup[:5]} are used by more than one {kind} entry, so the boxes cannot be told apart",
            path=path,
            fix=f"give every {kind} its own id (re-export the file from the annotation tool)",
        )


def _collect(
    path: Path, images: list[dict], categories: list[dict], anns: list[dict], kind: str = "annotation"
) -> ImportedBoxes:
    _unique_ids(images, "image", path)
    _unique_ids(categories, "category", path)
    if anns and not categories:
        raise InputError(
            f"the file defines no categories, but its {kind}s use category ids "
            f"{sorted({a.get('category_id') for a in anns}, key=str)[:5]}",
            path=path,
            fix='add the categories, e.g. "categories": [{"id": 1, "name": "plant"}]',
        )
    by_id = {im.get("id"): im for im in images}
    cat_names = {c.get("id"): str(c.get("name", c.get("id"))) for c in categories}
    known = ", ".join(f"{i}={n}" for i, n in cat_names.items())
    drops = DropLog()
    out = ImportedBoxes(
        {_name(im): [] for im in images if _name(im)},
        drops=drops,
        sizes={
            im["file_name"]: (im.get("width"), im.get("height"))
            for im in images
            if im.get("file_name") and "source_image" not in im
        },
    )
    seen: dict[tuple, str] = {}
    ids: set = set()
    repeated_ids = 0
    for i, a in enumerate(anns, start=1):
        where = f"{kind} {a['id']}" if "id" in a else f"{kind} #{i}"
        im = by_id.get(a.get("image_id"))
        box = bbox_values(a.get("bbox"))
        if im is None or not _name(im):
            drops.add(
                path,
                where,
                a.get("image_id"),
                box or repr(a.get("bbox")),
                "image id not in the file",
                f"image_id {a.get('image_id')!r} is not one of the file's images (with a file_name)",
            )
            continue
        name = _name(im)
        if box is None:
            drops.add(
                path, where, name, repr(a.get("bbox")), "bbox is not [x, y, w, h] numbers", f"bbox {a.get('bbox')!r}"
            )
            continue
        if a.get("category_id") not in cat_names:
            drops.add(
                path,
                where,
                name,
                box,
                "unknown category id",
                f"category_id {a.get('category_id')!r}; the file's categories: {known}",
            )
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
        log.warning(
            "%s: %d %s id(s) are used more than once (different boxes, all imported; module 4 numbers the boxes anew)",
            path.name,
            repeated_ids,
            kind,
        )
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


__all__ = [
    "read_coco_boxes",
    "read_cvat_boxes",
    "read_deepforest_boxes",
    "read_mask_boxes",
    "read_prediction_boxes",
    "read_voc_boxes",
    "read_yolo_boxes",
]
