"""YOLO labels: the second box format that modules 4 and 5 read and write, converted to and from COCO.

A labels folder holds one ``<image stem>.txt`` per image, a line ``class cx cy w h`` per box (class index
into ``classes.txt``; centre and size as fractions of the image), and ``classes.txt`` with one class
name per line, in the folder or its parent. The label files carry no image size, so every reader here
takes ``sizes`` (image name -> (width, height)) to come back to pixels.

:func:`match_name` is here because label and annotation files name their images loosely (a path, or
ODM's undistorted ``<photo>.tif`` for a photo); every reader of such files resolves names with it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

from matchplant.core.formats.coco import DropLog, make_annotation, new_dataset
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_text
from matchplant.core.runtime.validate import did_you_mean, read_text

CLASSES_NAME = "classes.txt"
TOLERANCE = 1e-3  # YOLO values this far outside [0, 1] are rounding, not an error
LINE_FORMAT = "'class cx cy w h' (five values: a class index, then the box centre and size as fractions 0..1)"


class YoloBox(NamedTuple):
    """One YOLO label line as a box in image pixels and its class name."""

    xyxy: list[float]  # [x1, y1, x2, y2] in pixels of the image
    category: str  # class name from classes.txt


def coco_to_yolo(dataset: dict, out_dir: str | Path, labels_subdir: str = "") -> Path:
    """Write YOLO labels (``class cx cy w h``, normalised) per image and ``classes.txt``.

    Class index = position of the category in id order. Every image gets a label file (empty for an
    image without boxes, so that YOLO trainers read it as a negative).
    """
    out_dir = Path(out_dir)
    cats = sorted(dataset["categories"], key=lambda c: c["id"])
    index = {c["id"]: i for i, c in enumerate(cats)}
    by_image: dict[int, list[str]] = {im["id"]: [] for im in dataset["images"]}
    sizes = {im["id"]: (im["width"], im["height"]) for im in dataset["images"]}
    for a in dataset["annotations"]:
        w_im, h_im = sizes[a["image_id"]]
        x, y, w, h = a["bbox"]
        by_image[a["image_id"]].append(
            f"{index[a['category_id']]} {(x + w / 2) / w_im:.8f} {(y + h / 2) / h_im:.8f} {w / w_im:.8f} {h / h_im:.8f}"
        )
    labels = out_dir / labels_subdir
    for im in dataset["images"]:
        write_text(labels / (Path(im["file_name"]).stem + ".txt"), "".join(line + "\n" for line in by_image[im["id"]]))
    write_text(out_dir / CLASSES_NAME, "".join(c["name"] + "\n" for c in cats))
    return out_dir


def find_classes_file(labels_dir: Path) -> Path:
    """The classes.txt of a YOLO labels folder (in it or its parent); an error when there is none."""
    for candidate in (labels_dir / CLASSES_NAME, labels_dir.parent / CLASSES_NAME):
        if candidate.is_file():
            return candidate
    raise InputError(
        "YOLO labels need a classes.txt (one class name per line)",
        path=labels_dir / CLASSES_NAME,
        fix="put classes.txt in the labels folder or its parent",
    )


def read_classes(labels_dir: Path) -> list[str]:
    """The class names of ``classes.txt`` (BOM, CRLF accepted); a repeated or missing name is an error."""
    path = find_classes_file(labels_dir)
    classes = [line.strip() for line in read_text(path, what="classes.txt").splitlines() if line.strip()]
    if not classes:
        raise InputError("classes.txt is empty", path=path, fix="write one class name per line, e.g. plant")
    repeated = sorted({c for c in classes if classes.count(c) > 1})
    if repeated:
        raise InputError(
            f"classes.txt names {repeated} more than once",
            path=path,
            fix="give each class one line (the line number is the class index, from 0)",
        )
    return classes


def label_files(labels_dir: Path) -> list[Path]:
    """The ``.txt`` label files of a folder (not ``classes.txt``, hidden files or macOS ``._*`` forks)."""
    return sorted(
        p for p in labels_dir.glob("*.txt") if p.is_file() and p.name != CLASSES_NAME and not p.name.startswith(".")
    )


def read_yolo(
    labels_dir: str | Path, sizes: dict[str, tuple[int, int]], drops: DropLog | None = None
) -> tuple[list[str], dict[str, list[YoloBox]]]:
    """Read YOLO labels for the images in ``sizes`` (name -> (width, height)); returns (classes, boxes).

    Only images with a label file are in ``boxes`` (an empty label file is an image without plants).
    A line without five values or with an unknown class is an error naming the file and line. Lines whose
    values lie outside [0, 1] (or with a size <= 0), and label files that match no image, are left out and
    listed in ``drops`` (with a warning by the caller); when every box is left out it is an error.
    """
    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise InputError("YOLO labels folder not found", path=labels_dir, fix="set it to the folder of .txt labels")
    classes = read_classes(labels_dir)
    drops = DropLog() if drops is None else drops
    before = len(drops)
    files = label_files(labels_dir)
    by_stem = {Path(name).stem: (name, size) for name, size in sizes.items()}
    out: dict[str, list[YoloBox]] = {}
    n_lines = 0
    for path in files:
        lines = _label_lines(path, len(classes))
        n_lines += len(lines)
        if path.stem not in by_stem:
            hint = did_you_mean(path.stem, by_stem)
            for number, _cls, values in lines:
                drops.add(
                    path,
                    f"line {number}",
                    path.stem,
                    values,
                    "label file matches no image",
                    f"no image named {path.stem}.*{'; ' + hint if hint else ''}",
                )
            continue
        name, (w_im, h_im) = by_stem[path.stem]
        items = []
        for number, cls, (cx, cy, w, h) in lines:
            bad = [
                f"{k}={v:g}"
                for k, v in zip(("cx", "cy", "w", "h"), (cx, cy, w, h))
                if not -TOLERANCE <= v <= 1 + TOLERANCE
            ]
            if w <= 0 or h <= 0:
                drops.add(path, f"line {number}", name, [cx, cy, w, h], "zero or negative size", f"w={w:g}, h={h:g}")
                continue
            if bad:
                drops.add(
                    path,
                    f"line {number}",
                    name,
                    [cx, cy, w, h],
                    "YOLO value outside [0, 1]",
                    ", ".join(bad) + " (pixels instead of fractions of the image?)",
                )
                continue
            items.append(
                YoloBox(
                    [(cx - w / 2) * w_im, (cy - h / 2) * h_im, (cx + w / 2) * w_im, (cy + h / 2) * h_im], classes[cls]
                )
            )
        out[name] = items
    if not files:
        raise InputError(
            "no YOLO label files (<image stem>.txt) in the folder",
            path=labels_dir,
            fix="point the config at the folder that holds the .txt labels",
        )
    if n_lines and len(drops) - before == n_lines:
        first = drops.rows[before]
        raise InputError(
            f"none of the {n_lines} YOLO boxes can be used: {drops.summary()} (first: {first['source']}, "
            f"{first['where']}: {first['detail']})",
            path=labels_dir,
            fix="YOLO lines are " + LINE_FORMAT + ", in files named like the images",
        )
    return classes, out


def _label_lines(path: Path, n_classes: int) -> list[tuple[int, int, list[float]]]:
    """``(line number, class, [cx, cy, w, h])`` of one label file; a malformed line is an error."""
    out = []
    for number, line in enumerate(read_text(path, what="YOLO label file").splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 5:
            extra = (
                " (a polygon: YOLO segmentation labels are not boxes)"
                if len(parts) > 6
                else " (a sixth value, e.g. a confidence?)"
                if len(parts) == 6
                else ""
            )
            raise InputError(
                f"line {number} has {len(parts)} values{extra}; expected {LINE_FORMAT}",
                path=path,
                fix="write each box as 'class cx cy w h' (export 'YOLO detection' labels)",
            )
        try:
            cls = int(parts[0])
            values = [float(v) for v in parts[1:]]
        except ValueError:
            raise InputError(
                f"line {number} is not numbers: {line.strip()!r}; expected {LINE_FORMAT}",
                path=path,
                fix="correct the line",
            ) from None
        if not 0 <= cls < n_classes:
            raise InputError(
                f"line {number}: class {cls} is not in classes.txt (classes 0..{n_classes - 1})",
                path=path,
                fix="correct the class index or add the class name to classes.txt",
            )
        if not all(math.isfinite(v) for v in values):
            raise InputError(
                f"line {number}: a value is not a finite number: {line.strip()!r}", path=path, fix="correct the line"
            )
        out.append((number, cls, values))
    return out


def yolo_to_coco(labels_dir: str | Path, sizes: dict[str, tuple[int, int]], drops: DropLog | None = None) -> dict:
    """A COCO dataset from YOLO labels; ``sizes`` maps each image name to (width, height). Only images
    with a label file are in it (an empty label file is an image without plants); see :func:`read_yolo`."""
    classes, boxes = read_yolo(labels_dir, sizes, drops)
    ds = new_dataset(classes)
    ann_id = 1
    for image_id, name in enumerate(boxes, start=1):
        w, h = sizes[name]
        ds["images"].append({"id": image_id, "file_name": name, "width": w, "height": h})
        for item in boxes.get(name, []):
            x1, y1, x2, y2 = item.xyxy
            ds["annotations"].append(
                make_annotation(ann_id, image_id, [x1, y1, x2 - x1, y2 - y1], classes.index(item.category) + 1)
            )
            ann_id += 1
    return ds


__all__ = ["YoloBox", "coco_to_yolo", "find_classes_file", "label_files", "read_classes", "read_yolo", "yolo_to_coco"]
