"""Module 4: plant boxes on a folder of images - the annotation state, imports and exports.

The GUI (:mod:`matchplant.bbox_drawer.gui`) is a thin layer over :class:`AnnotationStore`, which holds every
box of every image, applies edits (add, move, resize, delete, change category, undo, redo) and writes
the whole session to ``<output_dir>/session.json`` atomically after each edit. Reopening the same
``output_dir`` therefore resumes exactly where the user stopped, also after a crash or power cut.

Boxes are kept as ``[x1, y1, x2, y2]`` in pixel-edge coordinates (``x = 0`` is the left edge of the
first pixel, ``x = width`` the right edge of the last), clipped to the image and rounded to 0.01 px.

Imports (for correcting existing boxes or a model's detections): a COCO dataset, YOLO labels with
``classes.txt``, or module 7's predictions (tiles are put back in source-image pixels). Exports: one
COCO dataset (``annotations.json``) and YOLO labels plus ``classes.txt``.

The area each image "owns" (module 3) can be shown: a JSON file ``{image_name: [[u, v], ...]}``, one
polygon in pixels of that image per image name.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from matchplant.core.coco import make_annotation, new_dataset, read_dataset, read_predictions, source_name, to_source_pixels
from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.io import read_json, write_json, write_text
from matchplant.core.log import get_logger

log = get_logger("annotate")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
MAX_CATEGORIES = 5
STATE_NAME = "session.json"
STATE_FORMAT = "matchplant-annotation-session"
HISTORY = 500  # undo steps kept (and saved) per session
DECIMALS = 2   # boxes are stored to 0.01 px


# -- images ---------------------------------------------------------------------------------------


def list_images(folder: str | Path) -> list[Path]:
    """The image files of a folder (by extension, sorted by name); other files and hidden files are ignored."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("image folder not found", path=folder, fix="set 'images' to the folder of your photos")
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))


def read_image(path: str | Path) -> np.ndarray:
    """Pixels exactly as stored (any bit depth; colour as RGB(A)); works with non-ASCII paths everywhere."""
    import cv2

    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read the image: {exc}", path=path, fix="check that the file exists") from exc
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError("not a readable image", path=path, fix="remove the file or convert it to PNG, JPEG or TIFF")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return img


def display_rgb(img: np.ndarray) -> np.ndarray:
    """8-bit RGB for showing an image of any bit depth (16-bit and float images are stretched)."""
    if img.ndim == 3 and img.shape[2] > 3:
        img = img[..., :3]
    if img.dtype == np.uint8:
        return img
    a = img.astype(np.float32)
    finite = a[np.isfinite(a)]
    lo, hi = (np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0))
    return (np.clip((np.nan_to_num(a, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


def image_size(path: str | Path) -> tuple[int, int]:
    from matchplant.core.odm import image_size as _size
    return _size(path)


def _readable(path: Path) -> bool:
    """False (with a warning) for a file named like an image that is not one."""
    try:
        image_size(path)
        return True
    except InputError:
        log.warning("skipped %s: not a readable image", path.name)
        return False


def match_name(name: str, known: Iterable[str]) -> str | None:
    """The image of ``known`` that ``name`` refers to: same file name, or the same up to ODM's ``.tif``."""
    known = set(known)
    base = Path(str(name).replace("\\", "/")).name
    for candidate in (base, base + ".tif", base[:-4] if base.lower().endswith(".tif") else None):
        if candidate in known:
            return candidate
    return None


def clip_box(xyxy: Iterable[float], width: float, height: float) -> list[float]:
    """A box with corners in any order, clipped to the image and rounded to 0.01 px."""
    x1, y1, x2, y2 = (float(v) for v in xyxy)
    x1, x2 = sorted((x1, x2))
    y1, y2 = sorted((y1, y2))
    return [round(min(max(x1, 0.0), width), DECIMALS), round(min(max(y1, 0.0), height), DECIMALS),
            round(min(max(x2, 0.0), width), DECIMALS), round(min(max(y2, 0.0), height), DECIMALS)]


# -- the session --------------------------------------------------------------------------------------


@dataclass
class ImportedBox:
    xyxy: list[float]
    category: str
    score: float | None = None


class AnnotationStore:
    """Every box of every image in a folder, saved atomically after each edit.

    ``store = AnnotationStore(images_dir, output_dir, ["plant"])`` opens (or resumes) the session in
    ``output_dir``. Edits name the image and the box id; each returns what changed and is undoable.
    """

    def __init__(self, images_dir: str | Path, output_dir: str | Path, categories: Iterable[str] = ("plant",),
                 *, min_box_size: float = 2.0):
        self.images_dir = Path(images_dir)
        self.output_dir = Path(output_dir)
        self.path = self.output_dir / STATE_NAME
        self.min_box_size = float(min_box_size)
        files = [p for p in list_images(self.images_dir) if _readable(p)]
        if not files:
            raise InputError("no images (.jpg, .png, .tif, ...) in the image folder", path=self.images_dir,
                             fix="set 'images' to the folder that holds the photos to annotate")
        self.files = {p.name: p for p in files}
        self.state = self._load()
        self._merge_categories(list(categories))
        for name in self.files:
            self.state["images"].setdefault(name, {"boxes": [], "seen": False})
        if self.state.get("current") not in self.files:
            self.state["current"] = next(iter(self.files))
        self.save()

    # -- persistence
    def _load(self) -> dict:
        empty = {"format": STATE_FORMAT, "version": 1, "categories": [], "current": None, "next_id": 1,
                 "images": {}, "undo": [], "redo": [], "imports": []}
        if not self.path.is_file():
            return empty
        data = read_json(self.path)
        if not isinstance(data, dict) or data.get("format") != STATE_FORMAT:
            raise InputError("this file is not a MatchPlant annotation session", path=self.path,
                             fix="choose another output_dir, or move the file away")
        for key, value in empty.items():
            data.setdefault(key, value)
        log.info("resumed the annotation session in %s", self.path)
        return data

    def save(self) -> None:
        self.state["saved"] = _dt.datetime.now().isoformat(timespec="seconds")
        write_json(self.path, self.state, indent=None)

    def _merge_categories(self, categories: list[str]) -> None:
        cats = self.state["categories"]
        for name in categories:
            if str(name) not in cats:
                cats.append(str(name))
        if not cats:
            cats.append("plant")
        if len(cats) > MAX_CATEGORIES:
            raise ConfigError(f"at most {MAX_CATEGORIES} categories are supported, this session has {cats}",
                              fix="list at most 5 names under 'categories' (or start a new output_dir)")

    # -- queries
    @property
    def categories(self) -> list[str]:
        return list(self.state["categories"])

    @property
    def images(self) -> list[str]:
        return list(self.files)

    @property
    def current(self) -> str:
        return self.state["current"]

    def size(self, name: str) -> tuple[int, int]:
        entry = self.state["images"][name]
        if "width" not in entry:
            entry["width"], entry["height"] = image_size(self.files[name])
        return entry["width"], entry["height"]

    def boxes(self, name: str) -> list[dict]:
        """``[{"id", "xyxy", "category_id", ...}]`` of one image (copies)."""
        return [dict(b) for b in self.state["images"][name]["boxes"]]

    def box(self, name: str, box_id: int) -> dict:
        for b in self.state["images"][name]["boxes"]:
            if b["id"] == box_id:
                return dict(b)
        raise KeyError(f"no box {box_id} in {name}")

    def count(self) -> int:
        return sum(len(self.state["images"][n]["boxes"]) for n in self.files)

    # -- navigation
    def set_current(self, name: str) -> None:
        if name not in self.files:
            raise KeyError(name)
        self.state["current"] = name
        self.state["images"][name]["seen"] = True
        self.save()

    def step(self, delta: int) -> str:
        names = self.images
        i = (names.index(self.current) + delta) % len(names)
        self.set_current(names[i])
        return names[i]

    # -- edits (each saved at once and undoable)
    def add(self, name: str, xyxy: Iterable[float], category_id: int = 1) -> int | None:
        """Add a box (clipped to the image); None when it is smaller than ``min_box_size`` after clipping."""
        self._check_category(category_id)
        box = self._clipped(name, xyxy)
        if box is None:
            return None
        new = {"id": int(self.state["next_id"]), "xyxy": box, "category_id": int(category_id)}
        self.state["next_id"] += 1
        self._apply(name, None, new)
        return new["id"]

    def move(self, name: str, box_id: int, dx: float, dy: float) -> dict:
        """Shift a box, keeping its size; it stops at the image edges."""
        old = self.box(name, box_id)
        w, h = self.size(name)
        x1, y1, x2, y2 = old["xyxy"]
        dx = min(max(float(dx), -x1), w - x2)
        dy = min(max(float(dy), -y1), h - y2)
        return self._replace(name, old, [x1 + dx, y1 + dy, x2 + dx, y2 + dy])

    def resize(self, name: str, box_id: int, xyxy: Iterable[float]) -> dict:
        """Give a box new corners (clipped); a resize that makes it vanish is refused (box unchanged)."""
        return self._replace(name, self.box(name, box_id), xyxy)

    def delete(self, name: str, box_id: int) -> None:
        self._apply(name, self.box(name, box_id), None)

    def set_category(self, name: str, box_id: int, category_id: int) -> dict:
        self._check_category(category_id)
        old = self.box(name, box_id)
        new = dict(old, category_id=int(category_id))
        new.pop("score", None)  # a corrected prediction is a human label now
        self._apply(name, old, new)
        return new

    def undo(self) -> str | None:
        """Undo the last edit; returns the image it touched (None when there is nothing to undo)."""
        return self._history("undo", "redo")

    def redo(self) -> str | None:
        return self._history("redo", "undo")

    # -- internals
    def _check_category(self, category_id: int) -> None:
        if not 1 <= int(category_id) <= len(self.categories):
            raise ConfigError(f"category {category_id} does not exist; categories are "
                              f"{', '.join(f'{i + 1}={c}' for i, c in enumerate(self.categories))}",
                              fix="add the category name to 'categories' in the config")

    def _clipped(self, name: str, xyxy: Iterable[float], min_size: float | None = None) -> list[float] | None:
        w, h = self.size(name)
        box = clip_box(xyxy, w, h)
        min_size = self.min_box_size if min_size is None else min_size
        if box[2] - box[0] < min_size or box[3] - box[1] < min_size or box[2] <= box[0] or box[3] <= box[1]:
            return None
        return box

    def _replace(self, name: str, old: dict, xyxy: Iterable[float]) -> dict:
        box = self._clipped(name, xyxy)
        if box is None or box == old["xyxy"]:
            return old
        new = dict(old, xyxy=box)
        self._apply(name, old, new)
        return new

    def _apply(self, name: str, before: dict | None, after: dict | None, record: bool = True) -> None:
        self._swap(name, before, after)
        if record:
            self.state["undo"] = (self.state["undo"] + [{"image": name, "before": before, "after": after}])[-HISTORY:]
            self.state["redo"] = []
        self.state["images"][name]["seen"] = True
        self.save()

    def _swap(self, name: str, before: dict | None, after: dict | None) -> None:
        boxes = self.state["images"][name]["boxes"]
        if before is not None:
            boxes[:] = [b for b in boxes if b["id"] != before["id"]]
        if after is not None:
            boxes.append(dict(after))
            boxes.sort(key=lambda b: b["id"])

    def _history(self, source: str, target: str) -> str | None:
        if not self.state[source]:
            return None
        step = self.state[source].pop()
        before, after = (step["before"], step["after"]) if source == "redo" else (step["after"], step["before"])
        self._swap(step["image"], before, after)
        self.state[target].append(step)
        self.save()
        return step["image"]

    # -- imports
    def import_boxes(self, boxes: dict[str, list[ImportedBox]], source: str) -> int:
        """Add imported boxes to images that have none yet; each source file is imported once per session.

        Returns the number of boxes added. Imports are not undoable edits (delete boxes to reject them).
        """
        key = str(Path(source).resolve()) if Path(source).exists() else str(source)
        if key in self.state["imports"]:
            log.info("%s was already imported into this session; skipped", source)
            return 0
        added, skipped = 0, []
        for raw_name, items in boxes.items():
            name = match_name(raw_name, self.files)
            if name is None:
                skipped.append(raw_name)
                continue
            if self.state["images"][name]["boxes"]:
                log.info("%s already has boxes; imported boxes for it are skipped", name)
                continue
            for item in items:
                cat = self._category_for(item.category)
                box = self._clipped(name, item.xyxy, min_size=0.0)  # keep thin boxes cut by the image edge
                if box is None:
                    continue
                new = {"id": int(self.state["next_id"]), "xyxy": box, "category_id": cat}
                if item.score is not None:
                    new["score"] = round(float(item.score), 4)
                self.state["next_id"] += 1
                self._swap(name, None, new)
                added += 1
        if skipped:
            log.warning("%d image(s) of %s are not in the image folder and were skipped (e.g. %s)",
                        len(skipped), Path(source).name, skipped[0])
        self.state["imports"].append(key)
        self.save()
        log.info("imported %d box(es) from %s", added, source)
        return added

    def _category_for(self, name: str) -> int:
        cats = self.state["categories"]
        if name not in cats:
            if len(cats) >= MAX_CATEGORIES:
                raise InputError(f"imported category '{name}' is not one of {cats} and there is no room "
                                 f"for a sixth", fix="rename the categories in the imported file")
            cats.append(name)
        return cats.index(name) + 1

    # -- exports
    def to_coco(self, include_unseen: bool = False) -> dict:
        """One COCO dataset of the images that were looked at or have boxes (all with ``include_unseen``)."""
        ds = new_dataset(self.categories, info={"description": "MatchPlant annotations (module 4)",
                                                "images_dir": str(self.images_dir)})
        ann_id = 1
        for image_id, name in enumerate(self.images, start=1):
            entry = self.state["images"][name]
            if not (include_unseen or entry.get("seen") or entry["boxes"]):
                continue
            w, h = self.size(name)
            ds["images"].append({"id": image_id, "file_name": name, "width": w, "height": h})
            for b in entry["boxes"]:
                x1, y1, x2, y2 = b["xyxy"]
                extra = {"score": b["score"]} if "score" in b else {}
                ds["annotations"].append(make_annotation(ann_id, image_id, [x1, y1, round(x2 - x1, DECIMALS),
                                                                            round(y2 - y1, DECIMALS)],
                                                         b["category_id"], **extra))
                ann_id += 1
        return ds

    def export(self, coco: bool = True, yolo: bool = False, include_unseen: bool = False) -> dict[str, Path]:
        ds = self.to_coco(include_unseen)
        out: dict[str, Path] = {}
        if coco:
            from matchplant.core.coco import write_dataset
            out["coco"] = write_dataset(self.output_dir / "annotations.json", ds)
        if yolo:
            out["yolo"] = coco_to_yolo(ds, self.output_dir / "yolo")
        return out


# -- YOLO -----------------------------------------------------------------------------------------------


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
    write_text(out_dir / "classes.txt", "".join(c["name"] + "\n" for c in cats))
    return out_dir


def find_classes_file(labels_dir: Path) -> Path:
    for candidate in (labels_dir / "classes.txt", labels_dir.parent / "classes.txt"):
        if candidate.is_file():
            return candidate
    raise InputError("YOLO labels need a classes.txt (one class name per line)", path=labels_dir / "classes.txt",
                     fix="put classes.txt in the labels folder or its parent")


def read_yolo(labels_dir: str | Path, sizes: dict[str, tuple[int, int]]) -> tuple[list[str], dict[str, list[ImportedBox]]]:
    """Read YOLO labels for the images in ``sizes`` (name -> (width, height)); returns (classes, boxes)."""
    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise InputError("YOLO labels folder not found", path=labels_dir, fix="set it to the folder of .txt labels")
    classes = [line.strip() for line in find_classes_file(labels_dir).read_text(encoding="utf-8").splitlines()
               if line.strip()]
    out: dict[str, list[ImportedBox]] = {}
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
            items.append(ImportedBox([(cx - w / 2) * w_im, (cy - h / 2) * h_im, (cx + w / 2) * w_im,
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


# -- imports from COCO and predictions ----------------------------------------------------------------


def read_coco_boxes(path: str | Path) -> dict[str, list[ImportedBox]]:
    """Boxes of a COCO dataset by source image name; tiles (``source_image``, ``x0``, ``y0``) are put back."""
    ds = read_dataset(path, validate=False)
    return _collect(ds["images"], ds["categories"], ds["annotations"])


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
    import cv2

    rects = [[b.xyxy[0], b.xyxy[1], b.xyxy[2] - b.xyxy[0], b.xyxy[3] - b.xyxy[1]] for b in items]
    scores = [float(b.score if b.score is not None else 1.0) for b in items]
    keep = cv2.dnn.NMSBoxes(rects, scores, 0.0, iou)
    return [items[i] for i in sorted(np.asarray(keep).reshape(-1).tolist())]


# -- configuration and the module's entry points --------------------------------------------------------


@dataclass
class AnnotateConfig:
    """Module 4 - draw plant boxes on images; import COCO, YOLO or predictions; export COCO and YOLO."""

    images: Path | None = param(None, "folder of images to annotate (e.g. module 3's selected undistorted images)",
                         path="dir", required=True)
    output_dir: Path | None = param(None, "folder for the session (session.json, saved after every edit) and exports",
                             path="out", required=True)
    categories: list[str] = param(["plant"], "category names (1 to 5); keys 1-5 choose them in the GUI")
    owned_areas: Path | None = param(None, "optional JSON {image_name: [[u, v], ...]}: the area each image "
                                           "owns (module 3), drawn as a dashed outline", path="file")
    import_coco: Path | None = param(None, "optional COCO dataset whose boxes are loaded for correction",
                                     path="file")
    import_yolo: Path | None = param(None, "optional folder of YOLO labels (<image stem>.txt + classes.txt) "
                                           "loaded for correction", path="dir")
    import_predictions: Path | None = param(None, "optional module 7 predictions JSON loaded for correction "
                                                  "(model-assisted labelling)", path="file")
    min_score: float = param(0.5, "imported predictions below this score are left out", min=0.0, max=1.0)
    min_box_size: float = param(2.0, "smaller boxes (px, after clipping to the image) are not created; "
                                     "a click without drag selects instead", min=0.0)
    export_yolo: bool = param(True, "also write YOLO labels and classes.txt to <output_dir>/yolo")
    include_unseen: bool = param(False, "export images never opened and without boxes too (as negatives)")

    def check(self) -> None:
        if not 1 <= len(self.categories) <= MAX_CATEGORIES:
            raise ConfigError(f"'categories' must list 1 to {MAX_CATEGORIES} names, got {self.categories}",
                              fix="for example: categories: [plant, weed]")
        if len(set(self.categories)) != len(self.categories):
            raise ConfigError(f"'categories' has a repeated name: {self.categories}", fix="make the names unique")


def open_session(cfg: AnnotateConfig) -> AnnotationStore:
    """Open or resume the session and apply the imports named in the config (each once)."""
    store = AnnotationStore(cfg.images, cfg.output_dir, cfg.categories, min_box_size=cfg.min_box_size)
    if cfg.import_coco is not None:
        store.import_boxes(read_coco_boxes(cfg.import_coco), str(cfg.import_coco))
    if cfg.import_yolo is not None:
        _, boxes = read_yolo(cfg.import_yolo, {n: store.size(n) for n in store.images})
        store.import_boxes(boxes, str(cfg.import_yolo))
    if cfg.import_predictions is not None:
        store.import_boxes(read_prediction_boxes(cfg.import_predictions, cfg.min_score), str(cfg.import_predictions))
    return store


def run(cfg: AnnotateConfig) -> dict[str, Path]:
    """Without the GUI: open or resume the session, apply imports, write the exports."""
    store = open_session(cfg)
    out = store.export(coco=True, yolo=cfg.export_yolo, include_unseen=cfg.include_unseen)
    n_images = len(read_json(out["coco"])["images"])
    log.info("%d box(es) on %d image(s) -> %s", store.count(), n_images, out["coco"])
    if "yolo" in out:
        log.info("YOLO labels and classes.txt -> %s", out["yolo"])
    return out


__all__ = ["AnnotationStore", "AnnotateConfig", "ImportedBox", "list_images", "read_image", "display_rgb",
           "clip_box", "coco_to_yolo", "yolo_to_coco", "read_yolo", "read_coco_boxes", "read_prediction_boxes",
           "open_session", "run"]
