"""Module 4's annotation state: every box of every image, its edits, and the session file.

The GUI (:mod:`matchplant.bbox_drawer.gui`) is a thin layer over :class:`AnnotationStore`, so that every
edit can be tested without a window and the session survives the window: the store writes the whole
session to ``<output_dir>/session.json`` atomically after each edit. Reopening the same ``output_dir``
therefore resumes exactly where the user stopped, also after a crash or power cut.

Boxes are kept as ``[x1, y1, x2, y2]`` in pixel-edge coordinates (``x = 0`` is the left edge of the
first pixel, ``x = width`` the right edge of the last; docs/DESIGN.md §3), clipped to the image and
rounded to 0.01 px, so that COCO and YOLO exports round-trip exactly.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from matchplant.core.formats.box_files import RULES, resolve_image_names
from matchplant.core.formats.coco import (
    REGION_KEY,
    DropLog,
    make_annotation,
    new_dataset,
    region_entry,
    write_dataset,
)
from matchplant.core.formats.images import image_size, list_images, whole_image_size
from matchplant.core.formats.yolo import coco_to_yolo
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import read_json, write_text
from matchplant.core.runtime.log import get_logger

log = get_logger("bbox_drawer")

MAX_CATEGORIES = 5
STATE_NAME = "session.json"
STATE_FORMAT = "matchplant-annotation-session"
HISTORY = 500  # undo steps kept (and saved) per session
DECIMALS = 2  # boxes are stored to 0.01 px


# -- boxes ----------------------------------------------------------------------------------------------


# reasons a box is not imported that are no fault of the file (not counted against it)
NOT_A_FAULT = "image already has boxes in this session"
NOT_IN_FOLDER = "image not in the image folder"
EDGE_TOLERANCE = 1.0  # px: boxes reaching further past the image edge are clipped with a warning


def check_image_file(path: Path) -> None:
    """A file named like an image must be a whole one (see :func:`matchplant.core.formats.images.whole_image_size`)."""
    whole_image_size(path)


def clip_box(xyxy: Iterable[float], width: float, height: float) -> list[float]:
    """A box with corners in any order, clipped to the image and rounded to 0.01 px."""
    x1, y1, x2, y2 = (float(v) for v in xyxy)
    x1, x2 = sorted((x1, x2))
    y1, y2 = sorted((y1, y2))
    return [
        round(min(max(x1, 0.0), width), DECIMALS),
        round(min(max(y1, 0.0), height), DECIMALS),
        round(min(max(x2, 0.0), width), DECIMALS),
        round(min(max(y2, 0.0), height), DECIMALS),
    ]


@dataclass
class ImportedBox:
    """A box from another file (COCO, YOLO, predictions), in source-image pixels: its category goes by
    name because each file numbers categories its own way; ``score`` marks a model's detection."""

    xyxy: list[float]
    category: str
    score: float | None = None
    where: str = ""  # where in its file (annotation id, line), for the report of boxes left out


class ImportedBoxes(dict):
    """``{image name as the file writes it: [ImportedBox]}`` plus what the file says besides: ``sizes``
    (image name -> (width, height) it declares) and ``drops`` (boxes the reader already left out)."""

    def __init__(self, items=(), *, sizes: dict | None = None, drops: DropLog | None = None):
        super().__init__(items)
        self.sizes = dict(sizes or {})
        self.drops = drops if drops is not None else DropLog()


# -- the session --------------------------------------------------------------------------------------


class AnnotationStore:
    """Every box of every image in a folder, saved atomically after each edit.

    ``store = AnnotationStore(images_dir, output_dir, ["plant"])`` opens (or resumes) the session in
    ``output_dir``. Edits name the image and the box id; each returns what changed and is undoable.
    """

    def __init__(
        self,
        images_dir: str | Path,
        output_dir: str | Path,
        categories: Iterable[str] = ("plant",),
        *,
        min_box_size: float = 2.0,
        resume_from: str | Path | None = None,
        label_map: dict[str, str] | None = None,
    ):
        self.images_dir = Path(images_dir)
        self.output_dir = Path(output_dir)
        self.path = self.output_dir / STATE_NAME
        self.min_box_size = float(min_box_size)
        self.label_map = {str(k): str(v) for k, v in (label_map or {}).items()}  # imported label -> category
        files = list_images(self.images_dir, min_count=0)
        if not files:
            raise InputError(
                "no images (.jpg, .png, .tif, ...) in the image folder",
                path=self.images_dir,
                fix="set 'images' to the folder that holds the photos to annotate",
            )
        for p in files:
            check_image_file(p)
        self.files = {p.name: p for p in files}
        self.state = self._load(Path(resume_from) if resume_from is not None else self.path)
        self._merge_categories(list(categories))
        for name in self.files:
            self.state["images"].setdefault(name, {"boxes": [], "seen": False})
        if self.state.get("current") not in self.files:
            self.state["current"] = next(iter(self.files))
        self.save()

    # -- persistence
    def _load(self, path: Path) -> dict:
        empty = {
            "format": STATE_FORMAT,
            "version": 1,
            "categories": [],
            "current": None,
            "next_id": 1,
            "images": {},
            "undo": [],
            "redo": [],
            "imports": [],
        }
        if not path.is_file():
            return empty
        data = read_json(path)
        if not isinstance(data, dict) or data.get("format") != STATE_FORMAT:
            raise InputError(
                "this file is not a MatchPlant annotation session",
                path=path,
                fix="choose another output_dir, or move the file away",
            )
        for key, value in empty.items():
            data.setdefault(key, value)
        if not isinstance(data["images"], dict) or not isinstance(data["categories"], list):
            raise InputError(
                "the annotation session is damaged ('images' or 'categories' of the wrong kind)",
                path=path,
                fix="move the file away (a new session starts), or restore a backup",
            )
        log.info("resumed the annotation session in %s", path)
        return data

    def save(self) -> None:
        """Write the session file now, with the time of saving."""
        self.state["saved"] = _dt.datetime.now().isoformat(timespec="seconds")
        # one C-encoded string (json.dump streams thousands of small writes: slow with 3,000 boxes)
        write_text(self.path, json.dumps(self.state, separators=(",", ":")) + "\n")

    def _merge_categories(self, categories: list[str]) -> None:
        cats = self.state["categories"]
        for name in categories:
            if str(name) not in cats:
                cats.append(str(name))
        if not cats:
            cats.append("plant")
        if len(cats) > MAX_CATEGORIES:
            raise ConfigError(
                f"at most {MAX_CATEGORIES} categories are supported, this session has {cats}",
                fix="list at most 5 names under 'categories' (or start a new output_dir)",
            )

    # -- queries
    @property
    def categories(self) -> list[str]:
        """Category names in id order: category id i is ``categories[i - 1]``."""
        return list(self.state["categories"])

    @property
    def images(self) -> list[str]:
        """Names of the session's photos, in the order they are shown."""
        return list(self.files)

    @property
    def current(self) -> str:
        """Name of the photo being annotated."""
        return self.state["current"]

    def size(self, name: str) -> tuple[int, int]:
        """Width and height in pixels of photo ``name`` (read once from the file, then kept in the session)."""
        entry = self.state["images"][name]
        if "width" not in entry:
            entry["width"], entry["height"] = image_size(self.files[name])
        return entry["width"], entry["height"]

    def boxes(self, name: str) -> list[dict]:
        """``[{"id", "xyxy", "category_id", ...}]`` of one image (copies)."""
        return [dict(b) for b in self.state["images"][name]["boxes"]]

    def box(self, name: str, box_id: int) -> dict:
        """A copy of box ``box_id`` of photo ``name``; KeyError when there is no such box."""
        for b in self.state["images"][name]["boxes"]:
            if b["id"] == box_id:
                return dict(b)
        raise KeyError(f"no box {box_id} in {name}")

    def count(self) -> int:
        """Number of boxes on all photos."""
        return sum(len(self.state["images"][n]["boxes"]) for n in self.files)

    # -- navigation
    def set_current(self, name: str) -> None:
        """Make ``name`` the photo being annotated and record it as seen."""
        if name not in self.files:
            raise KeyError(name)
        self.state["current"] = name
        self.state["images"][name]["seen"] = True
        self.save()

    def step(self, delta: int) -> str:
        """Move ``delta`` photos on (wrapping round) and return the new photo's name."""
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
        """Delete box ``box_id`` of photo ``name`` (undoable)."""
        self._apply(name, self.box(name, box_id), None)

    def set_category(self, name: str, box_id: int, category_id: int) -> dict:
        """Give box ``box_id`` category ``category_id``, making a prediction a human label (undoable); the new box."""
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
        """Redo the last undone edit; returns the image it touched (None when there is nothing to redo)."""
        return self._history("redo", "undo")

    # -- internals
    def _check_category(self, category_id: int) -> None:
        if not 1 <= int(category_id) <= len(self.categories):
            raise ConfigError(
                f"category {category_id} does not exist; categories are "
                f"{', '.join(f'{i + 1}={c}' for i, c in enumerate(self.categories))}",
                fix="add the category name to 'categories' in the config",
            )

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
    def import_boxes(self, boxes: dict[str, list[ImportedBox]], source: str, drops: DropLog | None = None) -> int:
        """Add imported boxes to images that have none yet; each source file is imported once per session.

        Returns the number of boxes added. Boxes that cannot be used (image not in the folder, size <= 0,
        outside the image) are left out and listed in ``drops`` (the reader's own, by default) with the
        reason; boxes reaching past the image edge are clipped. A file whose image sizes disagree with the
        photos on disk is an error. Imports are not undoable edits (delete boxes to reject them).
        """
        key = str(Path(source).resolve()) if Path(source).exists() else str(source)
        if key in self.state["imports"]:
            log.info("%s was already imported into this session; skipped", source)
            return 0
        drops = drops if drops is not None else getattr(boxes, "drops", DropLog())
        matched, unmatched = self._match_names(boxes, source)
        labels = self._resolve_labels(boxes, source)
        self._check_sizes(getattr(boxes, "sizes", {}), matched, source)
        added = clipped = 0
        for raw_name, items in boxes.items():
            name = matched.get(raw_name)
            if name is None:
                for item in items:
                    drops.add(
                        source,
                        item.where,
                        raw_name,
                        item.xyxy,
                        NOT_IN_FOLDER,
                        unmatched[raw_name] or f"no photo named like it in {self.images_dir}",
                    )
                continue
            if self.state["images"][name]["boxes"]:
                for item in items:
                    drops.add(
                        source,
                        item.where,
                        name,
                        item.xyxy,
                        NOT_A_FAULT,
                        "delete them first (GUI), or import into a new output_dir",
                    )
                continue
            for item in items:
                box, why, was_clipped = self._import_box(name, item.xyxy)
                if box is None:
                    drops.add(source, item.where, name, item.xyxy, why[0], why[1])
                    continue
                clipped += was_clipped
                new = {
                    "id": int(self.state["next_id"]),
                    "xyxy": box,
                    "category_id": self.categories.index(labels[item.category]) + 1,
                }
                if item.score is not None:
                    new["score"] = round(float(item.score), 4)
                self.state["next_id"] += 1
                self.state["images"][name]["boxes"].append(new)  # ids grow: the list stays sorted
                added += 1
        if clipped:
            log.warning(
                "%d box(es) of %s reached more than %g px past their image's edge and were clipped to it",
                clipped,
                Path(source).name,
                EDGE_TOLERANCE,
            )
        self.state["imports"].append(key)
        self.save()
        log.info("imported %d box(es) from %s", added, source)
        return added

    def _check_sizes(self, sizes: dict, matched: dict[str, str], source: str) -> None:
        """The image sizes a file declares must be those of the photos: else its boxes would land elsewhere."""
        for raw, size in sizes.items():
            name = matched.get(raw)
            try:
                w, h = (round(float(v)) for v in size)
            except (TypeError, ValueError):
                continue
            if name is None or w <= 0 or h <= 0:
                continue  # no size given (VOC writes 0 for unknown)
            if (w, h) != self.size(name):
                W, H = self.size(name)
                raise InputError(
                    f"image '{raw}' is {w}x{h} px in the imported file but {name} is {W}x{H} px on "
                    f"disk: the boxes were drawn on another version of the photo",
                    path=source,
                    fix="import boxes made on these same (not resized, not rotated) images, or point "
                    "'images' at the photos the boxes were drawn on",
                )

    def _import_box(self, name: str, xyxy) -> tuple[list[float] | None, tuple[str, str], bool]:
        """(the box clipped to the image, or None; (reason, detail) when None; True when it was clipped)."""
        try:
            x1, y1, x2, y2 = (float(v) for v in xyxy)
        except (TypeError, ValueError):
            return None, ("box is not four numbers", f"{xyxy!r}"), False
        if not all(math.isfinite(v) for v in (x1, y1, x2, y2)):
            return None, ("box is not four finite numbers", f"{xyxy!r}"), False
        if x2 <= x1 or y2 <= y1:
            return None, ("zero or negative size", f"width {x2 - x1:g}, height {y2 - y1:g} px"), False
        w, h = self.size(name)
        if x2 <= 0 or y2 <= 0 or x1 >= w or y1 >= h:
            return None, ("outside the image", f"the image is {w}x{h} px"), False
        box = self._clipped(name, xyxy, min_size=0.0)  # keep thin boxes cut by the image edge
        if box is None:
            return None, ("outside the image", f"nothing left inside the {w}x{h} px image"), False
        t = EDGE_TOLERANCE
        return box, ("", ""), x1 < -t or y1 < -t or x2 > w + t or y2 > h + t

    def _match_names(self, boxes: dict, source: str) -> tuple[dict[str, str], dict[str, str]]:
        """The photo each image name of an import means (:func:`resolve_image_names`), each rule beyond the
        exact name counted in the log; a name that fits several photos, or two names that fit one, are errors."""
        rules: dict[str, str] = {}
        matched, unmatched = resolve_image_names(list(boxes), self.files, rules)
        ambiguous = {raw: why for raw, why in unmatched.items() if why.startswith("ambiguous")}
        if ambiguous:
            raw, why = next(iter(ambiguous.items()))
            raise InputError(
                f"{len(ambiguous)} image name(s) fit more than one photo, e.g. '{raw}' ({why})",
                path=source,
                fix="give the photos distinct names, or import a file whose image names are the photos' file names",
            )
        by_photo: dict[str, list[str]] = {}
        for raw, name in matched.items():
            by_photo.setdefault(name, []).append(raw)
        twice = {name: raws for name, raws in by_photo.items() if len(raws) > 1}
        if twice:
            name, raws = next(iter(twice.items()))
            raise InputError(
                f"{len(twice)} photo(s) are named by more than one image of the file, e.g. {name} by "
                f"{', '.join(repr(r) for r in raws[:3])}: their boxes would be mixed",
                path=source,
                fix="import the boxes of each folder of photos on its own (photos with the same name "
                "in different folders), or rename the photos",
            )
        used = Counter(rules.values())
        for rule, n in used.items():
            if rule != "exact":
                example = next(raw for raw, r in rules.items() if r == rule)
                log.info(
                    "%s: matched %d image name(s) %s (e.g. '%s' -> %s)",
                    Path(source).name,
                    n,
                    RULES[rule],
                    example,
                    matched[example],
                )
        return matched, unmatched

    def _resolve_labels(self, boxes: dict, source: str) -> dict[str, str]:
        """Imported label -> session category: the same name, a ``label_map`` entry, or the same name up to case
        (said in the log). Labels that are none of these are an error that names them and the keys to set."""
        counts = Counter(item.category for items in boxes.values() for item in items)
        cats = self.categories
        folded = {c.casefold(): c for c in cats}
        out, unknown, by_case = {}, {}, []
        for label, n in counts.items():
            label = str(label)
            if label in self.label_map:
                out[label] = self.label_map[label]
            elif label in cats:
                out[label] = label
            elif label.casefold() in folded:
                out[label] = folded[label.casefold()]
                by_case.append(f"'{label}' -> {out[label]}")
            else:
                unknown[label] = n
        if by_case:
            log.info(
                "%s: label(s) %s taken as the categories of the same name up to case",
                Path(source).name,
                ", ".join(by_case),
            )
        mapped = [f"'{k}' -> {v}" for k, v in out.items() if k != v and k in self.label_map]
        if mapped:
            log.info("%s: label(s) %s mapped by label_map", Path(source).name, ", ".join(mapped))
        if unknown:
            names = ", ".join(f"'{k}' ({n} box{'es' if n != 1 else ''})" for k, n in sorted(unknown.items()))
            first = min(unknown)
            key = repr(first) if first.lstrip("-").isdigit() else first
            extended = ", ".join(cats + [k for k in sorted(unknown) if k not in cats])
            raise InputError(
                f"the imported label(s) {names} are not among the categories [{', '.join(cats)}]",
                path=source,
                fix=f"map them onto a category (label_map: {{{key}: {cats[0]}}}) or add "
                f"them to the categories (categories: [{extended}])",
            )
        return out

    # -- exports
    def to_coco(self, include_unseen: bool = False, regions: dict[str, Any] | None = None) -> dict:
        """One COCO dataset of the images that were looked at or have boxes (all with ``include_unseen``).

        ``regions`` (image name -> polygon in its pixels) records the part of each image that was
        annotated (``annotated_region``, :mod:`matchplant.core.formats.coco`); images without one were annotated whole.
        """
        regions = regions or {}
        ds = new_dataset(
            self.categories,
            info={"description": "MatchPlant annotations (module 4)", "images_dir": str(self.images_dir)},
        )
        ann_id = 1
        for image_id, name in enumerate(self.images, start=1):
            entry = self.state["images"][name]
            if not (include_unseen or entry.get("seen") or entry["boxes"]):
                continue
            w, h = self.size(name)
            ds["images"].append({"id": image_id, "file_name": name, "width": w, "height": h})
            if regions.get(name) is not None:
                ds["images"][-1][REGION_KEY] = region_entry(regions[name])
            for b in entry["boxes"]:
                x1, y1, x2, y2 = b["xyxy"]
                extra = {"score": b["score"]} if "score" in b else {}
                ds["annotations"].append(
                    make_annotation(
                        ann_id,
                        image_id,
                        [x1, y1, round(x2 - x1, DECIMALS), round(y2 - y1, DECIMALS)],
                        b["category_id"],
                        **extra,
                    )
                )
                ann_id += 1
        return ds

    def export(
        self, coco: bool = True, yolo: bool = False, include_unseen: bool = False, regions: dict[str, Any] | None = None
    ) -> dict[str, Path]:
        """Write the boxes as COCO annotations.json (``coco``) and/or a YOLO folder (``yolo``); the paths by kind.

        ``include_unseen`` also lists the photos never opened and without boxes; ``regions`` (image name ->
        polygon in its pixels) records the part of each image that was annotated.
        """
        ds = self.to_coco(include_unseen, regions)
        out: dict[str, Path] = {}
        if coco:
            out["coco"] = write_dataset(self.output_dir / "annotations.json", ds)
        if yolo:
            out["yolo"] = coco_to_yolo(ds, self.output_dir / "yolo")
        return out


__all__ = [
    "MAX_CATEGORIES",
    "NOT_A_FAULT",
    "NOT_IN_FOLDER",
    "AnnotationStore",
    "ImportedBox",
    "ImportedBoxes",
    "check_image_file",
    "clip_box",
]
