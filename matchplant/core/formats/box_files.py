"""Box files of other annotation tools, read as ``{image name: [LabelledBox]}`` in pixel-edge
coordinates of that image (``x = 0`` is the left edge of the first pixel; docs/DESIGN.md §3).

- **DeepForest CSV**: ``image_path,xmin,ymin,xmax,ymax,label`` (``score`` or, as older DeepForest releases
  write it, ``scores`` kept as the box's score; other columns such as ``geometry`` ignored); coordinates as
  written. Labels are kept as written (``Tree``, or DeepForest's numeric ``0``); module 4 maps them onto
  its categories (``label_map``).
- **Pascal VOC XML** (one ``<annotation>`` per image, a file or a folder of them): ``<bndbox>`` values
  as written, as LabelImg, CVAT/Datumaro and DeepForest write and read them (the original VOC
  devkit counted pixels from 1; such files come out 1 px right and down).
- **CVAT for images 1.1 XML** (one file for the task): ``<image name width height>`` holding
  ``<box label xtl ytl xbr ybr>``, pixel edges.

COCO files exported by CVAT and Label Studio are read by :mod:`matchplant.core.formats.coco`; the image
names such tools write (a task folder, Label Studio's ``<8 hex digits>-`` upload prefix and local-storage
``?d=`` paths, an extra extension as in ``images/3f2a1b7c-IMG_1.JPG.png``) are matched to the photos by
:func:`resolve_image_names`.
"""

from __future__ import annotations

import csv
import difflib
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from urllib.parse import unquote

from matchplant.core.formats.coco import LabelledBox
from matchplant.core.formats.images import match_name
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import name_key

UPLOAD_PREFIX = re.compile(r"^[0-9a-f]{8}-")
# ways an annotation tool writes a photo's name, tried in this order (the log counts each one used)
RULES = {
    "exact": "the same name",
    "folder": "without the folder the tool wrote before it (CVAT's task paths, images/, obj_train_data/)",
    "upload prefix": "by stripping Label Studio's upload prefix (<8 hex digits>-)",
    "extra suffix": "by removing a second file extension the tool added (IMG_1.JPG.png)",
    "upload prefix + extra suffix": "by stripping Label Studio's upload prefix (<8 hex digits>-) and a second file "
    "extension (3f2a1b7c-IMG_1.JPG.png)",
    "loose": "up to case and extension",
}
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".gif", ".webp", ".dng")


def strip_upload_prefix(name: str) -> str:
    """``3f2a1b7c-photo.jpg`` -> ``photo.jpg`` (Label Studio renames uploaded files so)."""
    return UPLOAD_PREFIX.sub("", name)


def base_name(raw: str) -> str:
    """The file name an annotation file means: URL-decoded, Label Studio's local-storage ``?d=folder/x.jpg``
    read as ``x.jpg``, without the folder (either slash)."""
    text = unquote(str(raw))
    if "?d=" in text:
        text = text.split("?d=", 1)[1]
    return text.replace("\\", "/").rstrip("/").rsplit("/", 1)[-1]


def _without_extra_suffix(name: str) -> str | None:
    """``IMG_1.JPG.png`` -> ``IMG_1.JPG`` (a photo's name with another image extension added), else None."""
    stem, dot, ext = name.rpartition(".")
    if (
        dot
        and "." + ext.lower() in PHOTO_SUFFIXES
        and "." in stem
        and "." + stem.rpartition(".")[2].lower() in PHOTO_SUFFIXES
    ):
        return stem
    return None


def resolve_image_names(names, files, rules: dict[str, str] | None = None) -> tuple[dict[str, str], dict[str, str]]:
    """Which of ``files`` (image file names on disk) each name of an annotation file means.

    Tried in order (:data:`RULES`): the exact name (or up to ODM's ``.tif``), the name without its folder,
    without Label Studio's upload prefix, without an extra extension, then loosely (case and extension
    ignored) when that is unique. Returns ``({name: file}, {unmatched name: why})``: "why" is a "did you
    mean" hint, or starts with "ambiguous" when the name fits several files. ``rules``, when given, receives
    the rule each matched name needed (name -> key of :data:`RULES`).
    """
    files = list(files)
    stems: dict[str, list[str]] = {}
    for f in files:  # ODM's undistorted <photo>.tif: its loose key is the photo's
        stems.setdefault(name_key(f[:-4] if f.lower().endswith(".tif") and "." in f[:-4] else f), []).append(f)
    matched: dict[str, str] = {}
    unmatched: dict[str, str] = {}
    for raw in names:
        base = base_name(raw)
        bare = strip_upload_prefix(base)
        steps = [("exact", str(raw)), ("folder", base), ("upload prefix", bare)]
        steps += [
            ("extra suffix", _without_extra_suffix(base)),
            ("upload prefix + extra suffix", _without_extra_suffix(bare) if bare != base else None),
        ]
        steps = [(r, n) for r, n in steps if n]
        rule, hit = next(((r, h) for r, n in steps if (h := match_name(n, files)) is not None), (None, None))
        if rule == "exact" and Path(str(raw).replace("\\", "/")).name != str(raw):
            rule = "folder"  # match_name already dropped the folder
        if hit is None:
            keys = {name_key(n) for _, n in steps[2:]} | {name_key(bare)}
            cands = sorted({f for k in keys for f in stems.get(k, [])})
            if len(cands) > 1:
                unmatched[raw] = f"ambiguous: it could be any of {', '.join(cands[:4])}"
                continue
            rule, hit = ("loose", cands[0]) if cands else (None, None)
        if hit is None:
            unmatched[raw] = _closest(base, files)
        else:
            matched[raw] = hit
            if rules is not None:
                rules[raw] = rule
    return matched, unmatched


def _closest(name: str, files: list[str]) -> str:
    """ "did you mean 'x'?" by the names without extension (``p0.png`` is not like ``x.png``)."""
    stems = {Path(f).stem.casefold(): f for f in files}
    close = difflib.get_close_matches(Path(name).stem.casefold(), list(stems), n=1, cutoff=0.6)
    return f"did you mean '{stems[close[0]]}'?" if close else ""


def read_deepforest_csv(path: str | Path) -> dict[str, list[LabelledBox]]:
    """Boxes of a DeepForest CSV (image_path,xmin,ymin,xmax,ymax; label and score optional), by image path."""
    path = Path(path)
    fix = "give a CSV with the header image_path,xmin,ymin,xmax,ymax,label (DeepForest's format)"
    out: dict[str, list[LabelledBox]] = {}
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        need = {"image_path", "xmin", "ymin", "xmax", "ymax"}
        if not reader.fieldnames or not need <= set(reader.fieldnames):
            raise InputError(
                f"the CSV lacks the column(s) {sorted(need - set(reader.fieldnames or []))}", path=path, fix=fix
            )
        # DeepForest's predict_image writes "score" (1.x) or "scores" (older releases)
        score_key = next((k for k in ("score", "scores") if k in reader.fieldnames), None)
        for row in reader:
            line = reader.line_num
            if not any((v or "").strip() for v in row.values()):
                continue  # an empty line (Excel leaves them at the end)
            try:
                xyxy = [float(row[k]) for k in ("xmin", "ymin", "xmax", "ymax")]
                score = float(row[score_key]) if score_key and row.get(score_key) not in (None, "") else None
            except (TypeError, ValueError):
                raise InputError(
                    f"line {line}: a coordinate or score is missing or not a number "
                    f"({', '.join(f'{k}={row.get(k)!r}' for k in ('xmin', 'ymin', 'xmax', 'ymax'))})",
                    path=path,
                    fix=fix,
                ) from None
            if not row.get("image_path"):
                raise InputError(f"line {line}: image_path is empty", path=path, fix=fix)
            label = (row.get("label") or "plant").strip() or "plant"
            out.setdefault(row["image_path"], []).append(LabelledBox(xyxy, label, score, f"line {line}"))
    return out


def _number(node: ET.Element | None, tag: str, path: Path) -> float:
    text = node.findtext(tag) if node is not None else None
    try:
        return float(text)
    except (TypeError, ValueError):
        raise InputError(
            f"a <{tag}> is missing or not a number",
            path=path,
            fix="give Pascal VOC XML files (LabelImg, CVAT 'Pascal VOC' export)",
        ) from None


def read_voc(path: str | Path) -> tuple[dict[str, list[LabelledBox]], dict[str, tuple[int, int]]]:
    """A VOC XML file or a folder of them; returns (boxes, sizes) by image file name."""
    path = Path(path)
    files = sorted(path.glob("*.xml")) if path.is_dir() else [path]
    if not files:
        raise InputError("no .xml files in the folder", path=path, fix="point import_voc at the VOC Annotations folder")
    boxes: dict[str, list[LabelledBox]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    for f in files:
        try:
            root = ET.parse(f).getroot()
        except ET.ParseError as exc:
            raise InputError(f"not valid XML ({exc})", path=f, fix="re-export the annotations") from None
        name = root.findtext("filename")
        if root.tag != "annotation" or not name:
            raise InputError(
                "not a Pascal VOC annotation (<annotation> with <filename>)", path=f, fix="give Pascal VOC XML files"
            )
        size = root.find("size")
        if size is not None and size.findtext("width"):
            sizes[name] = (int(_number(size, "width", f)), int(_number(size, "height", f)))
        items = boxes.setdefault(name, [])
        for i, obj in enumerate(root.iter("object"), start=1):
            bb = obj.find("bndbox")
            items.append(
                LabelledBox(
                    [_number(bb, k, f) for k in ("xmin", "ymin", "xmax", "ymax")],
                    (obj.findtext("name") or "plant").strip(),
                    None,
                    f"{f.name}, object {i}",
                )
            )
    return boxes, sizes


def read_cvat_xml(path: str | Path) -> tuple[dict[str, list[LabelledBox]], dict[str, tuple[int, int]]]:
    """A 'CVAT for images 1.1' export; returns (boxes, sizes) by image name (polygons etc. are skipped)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"not valid XML ({exc})", path=path, fix="export the task as 'CVAT for images 1.1'") from None
    if root.tag != "annotations":
        raise InputError(
            "not a 'CVAT for images' export (<annotations> root)",
            path=path,
            fix="export the task as 'CVAT for images 1.1' (or as COCO, read with import_coco)",
        )
    boxes: dict[str, list[LabelledBox]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    for image in root.iter("image"):
        name = image.get("name", "")
        try:
            sizes[name] = (int(float(image.get("width", 0))), int(float(image.get("height", 0))))
        except ValueError:
            raise InputError(
                f"<image name='{name}'> has a width or height that is not a number",
                path=path,
                fix="re-export the task as 'CVAT for images 1.1'",
            ) from None
        items = boxes.setdefault(name, [])
        for i, b in enumerate(image.iter("box"), start=1):
            try:
                xyxy = [float(b.get(k)) for k in ("xtl", "ytl", "xbr", "ybr")]
            except (TypeError, ValueError):
                raise InputError(
                    f"a <box> of {name} lacks xtl/ytl/xbr/ybr",
                    path=path,
                    fix="re-export the task as 'CVAT for images 1.1'",
                ) from None
            items.append(LabelledBox(xyxy, b.get("label", "plant"), None, f"image '{name}', box {i}"))
    return boxes, sizes


__all__ = [
    "RULES",
    "base_name",
    "read_cvat_xml",
    "read_deepforest_csv",
    "read_voc",
    "resolve_image_names",
    "strip_upload_prefix",
]
