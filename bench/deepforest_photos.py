"""A small real aerial detection set for the CPU training benchmark: about 50 photos with about 950 small
objects, cut from the annotated sample images that DeepForest's PyPI package ships (MIT licence).

DeepForest (github weecology/DeepForest, ``pip download deepforest==2.1.0 --no-deps``) ships, inside its wheel
under ``deepforest/data``, NEON airborne RGB orthophotos at 10 cm with hand-drawn tree-crown boxes (Pascal VOC
XML): two Yellowstone crops (2299 x 2472 px, 574 crowns; 1249 x 1035 px, 279 crowns) and two 400 x 400 px tiles
(OSBS_029, 61 crowns; SOAP_061, 37 crowns, labelled Alive/Dead: one class here). The crowns are 15-75 px
(median about 40 px): small objects in photo-sized images, like panicles or plants in UAV photos.

The large crops are cut into a grid of photos of about 400 px (6 x 6 and 3 x 3); a crown crossing a cut goes to
every photo holding at least ``KEEP`` of its area, clipped to it (a smaller piece is left out of the boxes: it
is not a visible crown). The photos are split by a seeded shuffle into train / validation / test (70/15/15 %),
as module 5 splits photos. ``--data`` is the wheel file itself or a folder with its ``deepforest/data`` files.
"""

from __future__ import annotations

import io
import itertools
import random
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import cv2
import numpy as np

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset

# (image, VOC boxes, grid columns x rows)
SOURCES = (
    ("2019_YELL_2_528000_4978000_image_crop2.png", "2019_YELL_2_528000_4978000_image_crop2.xml", (6, 6)),
    ("2019_YELL_2_541000_4977000_image_crop.png", "2019_YELL_2_541000_4977000_image_crop.xml", (3, 3)),
    ("OSBS_029.png", "OSBS_029.xml", (1, 1)),
    ("SOAP_061.png", "SOAP_061.xml", (1, 1)),
)
KEEP = 0.5  # a crown cut by a photo's edge is kept when at least this share of its box is inside
SPLIT = (0.7, 0.15, 0.15)
SEED = 0
LICENCE = "MIT (DeepForest, github weecology/DeepForest; the wheel's deepforest/data)"


class Source:
    """Reads ``deepforest/data/NAME`` from the wheel or from a folder holding those files."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.zip = zipfile.ZipFile(self.path) if self.path.is_file() else None

    def read(self, name: str) -> bytes:
        """Bytes of one of DeepForest's data files."""
        if self.zip is not None:
            return self.zip.read(f"deepforest/data/{name}")
        folder = self.path / "deepforest" / "data" if (self.path / "deepforest").is_dir() else self.path
        return (folder / name).read_bytes()

    def missing(self) -> list[str]:
        """The data files this benchmark needs that the source lacks."""
        names = [n for img, xml, _ in SOURCES for n in (img, xml)]
        out = []
        for n in names:
            try:
                self.read(n)
            except (KeyError, FileNotFoundError):
                out.append(n)
        return out


def voc_boxes(xml: bytes) -> np.ndarray:
    """``(n, 4)`` xmin, ymin, xmax, ymax of a Pascal VOC file."""
    root = ET.parse(io.BytesIO(xml)).getroot()
    return np.array(
        [[float(o.find(f"bndbox/{k}").text) for k in ("xmin", "ymin", "xmax", "ymax")] for o in root.iter("object")],
        float,
    ).reshape(-1, 4)


def cut(img: np.ndarray, boxes: np.ndarray, grid: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The image cut into ``cols x rows`` photos with their clipped boxes (pieces under ``KEEP`` dropped)."""
    h, w = img.shape[:2]
    xs = np.linspace(0, w, grid[0] + 1).round().astype(int)
    ys = np.linspace(0, h, grid[1] + 1).round().astype(int)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    out = []
    for y0, y1 in itertools.pairwise(ys):
        for x0, x1 in itertools.pairwise(xs):
            c = np.stack(
                [
                    np.clip(boxes[:, 0], x0, x1),
                    np.clip(boxes[:, 1], y0, y1),
                    np.clip(boxes[:, 2], x0, x1),
                    np.clip(boxes[:, 3], y0, y1),
                ],
                axis=1,
            )
            inside = (c[:, 2] - c[:, 0]) * (c[:, 3] - c[:, 1])
            keep = inside >= KEEP * np.maximum(area, 1e-9)
            out.append((img[y0:y1, x0:x1], c[keep] - [x0, y0, x0, y0]))
    return out


def photos(source: Source) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Every photo ``(name, RGB image, xyxy boxes)``."""
    out = []
    for image, xml, grid in SOURCES:
        bgr = cv2.imdecode(np.frombuffer(source.read(image), np.uint8), cv2.IMREAD_COLOR)
        for k, (img, boxes) in enumerate(cut(bgr[:, :, ::-1], voc_boxes(source.read(xml)), grid)):
            out.append((f"{Path(image).stem}_{k:02d}.png", img, boxes))
    return out


def write_split(folder: Path, name: str, items: list[tuple[str, np.ndarray, np.ndarray]]) -> Path:
    """A COCO split in module 5's layout (``name.json`` beside ``name/images``)."""
    images = folder / name / "images"
    images.mkdir(parents=True, exist_ok=True)
    data = new_dataset(["tree"])
    for i, (file_name, img, boxes) in enumerate(items, 1):
        cv2.imwrite(str(images / file_name), np.ascontiguousarray(img[:, :, ::-1]))
        data["images"].append({"id": i, "file_name": file_name, "width": img.shape[1], "height": img.shape[0]})
        for b in boxes:
            data["annotations"].append(
                make_annotation(len(data["annotations"]) + 1, i, [b[0], b[1], b[2] - b[0], b[3] - b[1]])
            )
    return write_dataset(folder / f"{name}.json", data)


def build(source_path: Path, work: Path) -> tuple[Path, Path, Path]:
    """``(train.json, val.json, test.json)`` written under ``work``."""
    items = photos(Source(source_path))
    order = list(range(len(items)))
    random.Random(SEED).shuffle(order)
    n_train = round(SPLIT[0] * len(items))
    n_val = round(SPLIT[1] * len(items))
    parts = (order[:n_train], order[n_train : n_train + n_val], order[n_train + n_val :])
    return tuple(
        write_split(work, name, [items[i] for i in sorted(idx)]) for name, idx in zip(("train", "val", "test"), parts)
    )
