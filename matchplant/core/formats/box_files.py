"""Box files of other annotation tools, read as ``{image name: [LabelledBox]}`` in pixel-edge
coordinates of that image (``x = 0`` is the left edge of the first pixel; docs/DESIGN.md §3).

- **DeepForest CSV**: ``image_path,xmin,ymin,xmax,ymax,label`` (extra columns such as ``score`` kept as
  the box's score); coordinates as written.
- **Pascal VOC XML** (one ``<annotation>`` per image, a file or a folder of them): ``<bndbox>`` values
  as written, as LabelImg, CVAT/Datumaro and DeepForest write and read them (the original VOC
  devkit counted pixels from 1; such files come out 1 px right and down).
- **CVAT for images 1.1 XML** (one file for the task): ``<image name width height>`` holding
  ``<box label xtl ytl xbr ybr>``, pixel edges.

COCO files exported by CVAT and Label Studio are read by :mod:`matchplant.core.formats.coco` (Label Studio's
``<8 hex digits>-`` upload prefix on file names is removed by :func:`strip_upload_prefix`).
"""

from __future__ import annotations

import csv
import difflib
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from matchplant.core.formats.coco import LabelledBox
from matchplant.core.formats.images import match_name
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import match_names

UPLOAD_PREFIX = re.compile(r"^[0-9a-f]{8}-")


def strip_upload_prefix(name: str) -> str:
    """``3f2a1b7c-photo.jpg`` -> ``photo.jpg`` (Label Studio renames uploaded files so)."""
    return UPLOAD_PREFIX.sub("", name)


def resolve_image_names(names, files) -> tuple[dict[str, str], dict[str, str]]:
    """Which of ``files`` (image file names on disk) each name of an annotation file means.

    Exact or up to ODM's ``.tif`` first, then without Label Studio's upload prefix, then loosely (case and
    extension ignored) when that is unique. Returns ``({name: file}, {unmatched name: "did you mean ..."})``;
    the caller says how many names matched only loosely (``name != file`` after the first two rules).
    """
    files = list(files)
    stems = {}
    for f in files:  # ODM's undistorted <photo>.tif: its loose key is the photo's
        stems[f[:-4] if f.lower().endswith(".tif") and "." in f[:-4] else f] = f
    matched: dict[str, str] = {}
    unmatched: dict[str, str] = {}
    for raw in names:
        base = str(raw).replace("\\", "/").rsplit("/", 1)[-1]
        hit = match_name(raw, files) or match_name(strip_upload_prefix(base), files)
        if hit is None:
            loose, _ = match_names([strip_upload_prefix(base)], list(stems))
            hit = stems[loose[strip_upload_prefix(base)]] if loose else None
        if hit is None:
            unmatched[raw] = _closest(base, files)
        else:
            matched[raw] = hit
    return matched, unmatched


def _closest(name: str, files: list[str]) -> str:
    """"did you mean 'x'?" by the names without extension (``p0.png`` is not like ``x.png``)."""
    stems = {Path(f).stem.casefold(): f for f in files}
    close = difflib.get_close_matches(Path(name).stem.casefold(), list(stems), n=1, cutoff=0.6)
    return f"did you mean '{stems[close[0]]}'?" if close else ""


def read_deepforest_csv(path: str | Path) -> dict[str, list[LabelledBox]]:
    path = Path(path)
    fix = "give a CSV with the header image_path,xmin,ymin,xmax,ymax,label (DeepForest's format)"
    out: dict[str, list[LabelledBox]] = {}
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        need = {"image_path", "xmin", "ymin", "xmax", "ymax"}
        if not reader.fieldnames or not need <= set(reader.fieldnames):
            raise InputError(f"the CSV lacks the column(s) {sorted(need - set(reader.fieldnames or []))}",
                             path=path, fix=fix)
        for row in reader:
            line = reader.line_num
            try:
                xyxy = [float(row[k]) for k in ("xmin", "ymin", "xmax", "ymax")]
                score = float(row["score"]) if row.get("score") not in (None, "") else None
            except (TypeError, ValueError):
                raise InputError(f"line {line}: a coordinate or score is missing or not a number "
                                 f"({', '.join(f'{k}={row.get(k)!r}' for k in ('xmin', 'ymin', 'xmax', 'ymax'))})",
                                 path=path, fix=fix) from None
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
        raise InputError(f"a <{tag}> is missing or not a number", path=path,
                         fix="give Pascal VOC XML files (LabelImg, CVAT 'Pascal VOC' export)") from None


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
            raise InputError("not a Pascal VOC annotation (<annotation> with <filename>)", path=f,
                             fix="give Pascal VOC XML files")
        size = root.find("size")
        if size is not None and size.findtext("width"):
            sizes[name] = (int(_number(size, "width", f)), int(_number(size, "height", f)))
        items = boxes.setdefault(name, [])
        for i, obj in enumerate(root.iter("object"), start=1):
            bb = obj.find("bndbox")
            items.append(LabelledBox([_number(bb, k, f) for k in ("xmin", "ymin", "xmax", "ymax")],
                                     (obj.findtext("name") or "plant").strip(), None, f"{f.name}, object {i}"))
    return boxes, sizes


def read_cvat_xml(path: str | Path) -> tuple[dict[str, list[LabelledBox]], dict[str, tuple[int, int]]]:
    """A 'CVAT for images 1.1' export; returns (boxes, sizes) by image name (polygons etc. are skipped)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"not valid XML ({exc})", path=path, fix="export the task as 'CVAT for images 1.1'") from None
    if root.tag != "annotations":
        raise InputError("not a 'CVAT for images' export (<annotations> root)", path=path,
                         fix="export the task as 'CVAT for images 1.1' (or as COCO, read with import_coco)")
    boxes: dict[str, list[LabelledBox]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    for image in root.iter("image"):
        name = image.get("name", "")
        try:
            sizes[name] = (int(float(image.get("width", 0))), int(float(image.get("height", 0))))
        except ValueError:
            raise InputError(f"<image name='{name}'> has a width or height that is not a number", path=path,
                             fix="re-export the task as 'CVAT for images 1.1'") from None
        items = boxes.setdefault(name, [])
        for i, b in enumerate(image.iter("box"), start=1):
            try:
                xyxy = [float(b.get(k)) for k in ("xtl", "ytl", "xbr", "ybr")]
            except (TypeError, ValueError):
                raise InputError(f"a <box> of {name} lacks xtl/ytl/xbr/ybr", path=path,
                                 fix="re-export the task as 'CVAT for images 1.1'") from None
            items.append(LabelledBox(xyxy, b.get("label", "plant"), None, f"image '{name}', box {i}"))
    return boxes, sizes


__all__ = ["read_deepforest_csv", "read_voc", "read_cvat_xml", "resolve_image_names", "strip_upload_prefix"]
