"""YOLO labels: the second box format that modules 4 and 5 read and write, converted to and from COCO.

A labels folder holds one ``<image stem>.txt`` per image, a line ``class cx cy w h`` per box (class index
into ``classes.txt``; centre and size as fractions of the image), and ``classes.txt`` with one class
name per line, in the folder or its parent. The label files carry no image size, so every reader here
takes ``sizes`` (image name -> (width, height)) to come back to pixels.

:func:`match_name` is here because label and annotation files name their images loosely (a path, or
ODM's undistorted ``<photo>.tif`` for a photo); every reader of such files resolves names with it.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from matchplant.core.coco import make_annotation, new_dataset
from matchplant.core.errors import InputError
from matchplant.core.io import write_text

CLASSES_NAME = "classes.txt"


class YoloBox(NamedTuple):
    xyxy: list[float]   # [x1, y1, x2, y2] in pixels of the image
    category: str       # class name from classes.txt


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
        by_image[a["image_id"]].append(f"{index[a['category_id']]} {(x + w / 2) / w_im:.8f} "
                                       f"{(y + h / 2) / h_im:.8f} {w / w_im:.8f} {h / h_im:.8f}")
    labels = out_dir / labels_subdir
    for im in dataset["images"]:
        write_text(labels / (Path(im["file_name"]).stem + ".txt"), "".join(l + "\n" for l in by_image[im["id"]]))
    write_text(out_dir / CLASSES_NAME, "".join(c["name"] + "\n" for c in cats))
    return out_dir


def find_classes_file(labels_dir: Path) -> Path:
    for candidate in (labels_dir / CLASSES_NAME, labels_dir.parent / CLASSES_NAME):
        if candidate.is_file():
            return candidate
    raise InputError("YOLO labels need a classes.txt (one class name per line)", path=labels_dir / CLASSES_NAME,
                     fix="put classes.txt in the labels folder or its parent")


def read_yolo(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> tuple[list[str], dict[str, list[YoloBox]]]:
    """Read YOLO labels for the images in ``sizes`` (name -> (width, height)); returns (classes, boxes).

    Only images with a label file are in ``boxes`` (an empty label file is an image without plants).
    """
    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise InputError("YOLO labels folder not found", path=labels_dir, fix="set it to the folder of .txt labels")
    classes = [line.strip() for line in find_classes_file(labels_dir).read_text(encoding="utf-8").splitlines()
               if line.strip()]
    out: dict[str, list[YoloBox]] = {}
    for name, (w_im, h_im) in sizes.items():
        path = labels_dir / (Path(name).stem + ".txt")
        if not path.is_file():
            continue
        items = []
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            parts = line.split()
            if not parts:
                continue
            try:
                cls = int(parts[0])
                cx, cy, w, h = (float(v) for v in parts[1:5])
                if len(parts) < 5 or not 0 <= cls < len(classes):
                    raise ValueError
            except ValueError:
                raise InputError(f"line {number} is not 'class cx cy w h' with a class in 0..{len(classes) - 1}",
                                 path=path, fix="correct the line or the classes.txt") from None
            items.append(YoloBox([(cx - w / 2) * w_im, (cy - h / 2) * h_im, (cx + w / 2) * w_im,
                                  (cy + h / 2) * h_im], classes[cls]))
        out[name] = items
    return classes, out


def yolo_to_coco(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> dict:
    """A COCO dataset from YOLO labels; ``sizes`` maps each image name to (width, height). Only images
    with a label file are in it (an empty label file is an image without plants)."""
    classes, boxes = read_yolo(labels_dir, sizes)
    ds = new_dataset(classes)
    ann_id = 1
    for image_id, name in enumerate(boxes, start=1):
        w, h = sizes[name]
        ds["images"].append({"id": image_id, "file_name": name, "width": w, "height": h})
        for item in boxes.get(name, []):
            x1, y1, x2, y2 = item.xyxy
            ds["annotations"].append(make_annotation(ann_id, image_id, [x1, y1, x2 - x1, y2 - y1],
                                                     classes.index(item.category) + 1))
            ann_id += 1
    return ds


__all__ = ["YoloBox", "coco_to_yolo", "find_classes_file", "read_yolo", "yolo_to_coco"]
