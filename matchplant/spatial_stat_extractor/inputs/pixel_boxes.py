"""Boxes drawn or detected in pixels of a georeferenced image - a DeepForest CSV
(``image_path,xmin,ymin,xmax,ymax,label[,score]``), a COCO file of boxes on an orthophoto tile, module 7's
predictions on an orthophoto - as map polygons through that image's transform.

The image is the one the file names (``image_path``; COCO's ``file_name``, or ``source_image`` for a
tile, with its ``x0, y0``), looked for next to the file or in ``boxes_image`` (a folder, or the one image
every box is on). Pixel coordinates run from the image's top-left corner (0, 0) to (width, height), as
DeepForest and COCO give them; each box's four corners go through the image's affine transform, so a
rotated image gives the right parallelogram. Boxes that lie outside the image's pixel range but inside
its map bounds are map coordinates already (said in the log).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import rasterio
import shapely

from matchplant.core.formats.coco import (
    bbox_values,
    read_dataset,
    source_name,
    to_source_pixels,
)
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import did_you_mean, read_json

log = get_logger("spatial_stat_extractor")

IMAGE_COLUMN = "image_path"  # DeepForest's: the CSV's boxes are pixels of this image
FIX_IMAGE = "put the image beside the box file, or set boxes_image to the image or to its folder"


def is_box_json(path: Path) -> bool:
    """A COCO dataset or module 7's predictions (not a GeoJSON)."""
    data = read_json(path, what="polygon file")
    return isinstance(data, (dict, list)) and (
        isinstance(data, list) or ("images" in data and ("annotations" in data or "predictions" in data))
    )


def find_image(name: str, box_file: Path, images: Path | None) -> Path:
    """The image ``name`` of ``box_file``: ``images`` when it is a file, else in ``images`` or beside the file
    (the name as given, then its last part)."""
    if images is not None and Path(images).is_file():
        return Path(images)
    folder = Path(images) if images is not None else box_file.parent
    for cand in (folder / name, folder / Path(str(name).replace("\\", "/")).name):
        if cand.is_file():
            return cand
    near = [p.name for p in folder.glob("*") if p.suffix.lower() in (".tif", ".tiff", ".png", ".jpg", ".jpeg")]
    hint = did_you_mean(Path(name).name, near)
    raise InputError(
        f"the image '{name}' that the boxes are drawn on is not in {folder}{'; ' + hint if hint else ''}",
        path=box_file,
        fix=FIX_IMAGE,
    )


class ImageFrame:
    """An image's pixel grid on the map: affine transform, CRS and size."""

    def __init__(self, path: Path, box_file: Path):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)  # said below, in words
                ds = rasterio.open(path)
            with ds:
                self.transform, self.width, self.height = ds.transform, ds.width, ds.height
                self.crs = None if ds.crs is None else parse_crs(ds.crs)
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(
                f"the image '{path.name}' the boxes are drawn on cannot be read: {exc}",
                path=path,
                fix="give the GeoTIFF the boxes were drawn or detected on",
            ) from exc
        if self.crs is None or self.transform.is_identity:
            missing = "CRS" if self.crs is None else "georeference (transform)"
            raise InputError(
                f"the boxes of {box_file.name} are pixels of '{path.name}', which has no {missing}: "
                "they cannot be placed on the map",
                path=path,
                fix="give the GeoTIFF tile the boxes were drawn on (it keeps its georeference; or "
                "add a world file .tfw/.jgw and .prj), or give the boxes in map coordinates",
            )
        self.path = path

    def to_map(self, geoms: np.ndarray, box_file: Path, rows: np.ndarray) -> np.ndarray:
        """Pixel geometries (x right, y down from the top-left corner) as map geometries; geometries already in
        map coordinates (outside the pixel range, inside the map bounds) are kept."""
        b = shapely.bounds(geoms)
        tol = 1.0  # a box drawn to the image's edge may end half a pixel past it
        in_pixels = (
            (b[:, 0] >= -tol) & (b[:, 1] >= -tol) & (b[:, 2] <= self.width + tol) & (b[:, 3] <= self.height + tol)
        )
        left, bottom, right, top = rasterio.transform.array_bounds(self.height, self.width, self.transform)
        on_map = (b[:, 0] >= left) & (b[:, 2] <= right) & (b[:, 1] >= bottom) & (b[:, 3] <= top)
        bad = ~in_pixels & ~on_map
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{int(bad.sum())} box(es) lie outside the image '{self.path.name}' "
                f"({self.width} x {self.height} pixels), e.g. {rows[k]}: "
                f"{np.round(b[k], 2).tolist()}",
                path=box_file,
                fix="check that the boxes belong to this image (image_path / file_name) and are "
                "xmin, ymin, xmax, ymax in its pixels",
            )
        if on_map.all() and not in_pixels.all():
            log.info(
                "%s: the boxes on '%s' are in map coordinates already (outside its %d x %d pixels, inside its "
                "map bounds); kept as they are",
                box_file.name,
                self.path.name,
                self.width,
                self.height,
            )
            return geoms
        if (~in_pixels).any():
            raise InputError(
                f"the boxes on '{self.path.name}' mix pixel and map coordinates",
                path=box_file,
                fix="give every box in the image's pixels",
            )
        t = self.transform
        return shapely.transform(
            geoms,
            lambda xy: np.column_stack([t.a * xy[:, 0] + t.b * xy[:, 1] + t.c, t.d * xy[:, 0] + t.e * xy[:, 1] + t.f]),
        )


def place(
    table: pd.DataFrame, geoms: np.ndarray, names: np.ndarray, box_file: Path, images: Path | None, rows: np.ndarray
) -> gpd.GeoDataFrame:
    """Pixel geometries of several images (``names``) on the map, in the CRS of the first image (the others
    reprojected to it)."""
    out = np.empty(len(geoms), dtype=object)
    crs = None
    frames = {}
    for name in dict.fromkeys(names.tolist()):
        if not str(name).strip() or name is None:
            k = int(np.flatnonzero(names == name)[0])
            raise InputError(f"{rows[k]} names no image", path=box_file, fix="give every box its image")
        frame = frames[name] = ImageFrame(find_image(str(name), box_file, images), box_file)
        sel = names == name
        placed = frame.to_map(geoms[sel], box_file, rows[sel])
        if crs is None:
            crs = frame.crs
        elif not frame.crs.equals(crs):
            placed = gpd.GeoSeries(placed, crs=frame.crs).to_crs(crs).values
        out[sel] = placed
    log.info(
        "%s: %d boxes in pixels of %d image(s) (%s) placed on the map through their georeference, %s",
        box_file.name,
        len(geoms),
        len(frames),
        ", ".join(f.path.name for f in list(frames.values())[:3]),
        crs.to_string(),
    )
    gdf = gpd.GeoDataFrame(table.reset_index(drop=True), geometry=list(out), crs=crs)
    gdf.attrs["crs_source"] = f"the image {next(iter(frames.values())).path}"
    return gdf


def boxes_from_csv(df: pd.DataFrame, geoms: np.ndarray, path: Path, images: Path | None) -> gpd.GeoDataFrame:
    """A DeepForest CSV (pixel boxes or pixel WKT of ``image_path``), or any box CSV with ``boxes_image``."""
    if IMAGE_COLUMN in df.columns:
        names = df.pop(IMAGE_COLUMN).astype(str).str.strip().to_numpy(dtype=object)
        df.insert(0, "image", names)
    else:
        names = np.full(len(df), Path(images).name if images is not None else "", dtype=object)
    if "score" not in df.columns and "scores" in df.columns:  # DeepForest's predict_image writes 'scores'
        df = df.rename(columns={"scores": "score"})
    rows = np.array([f"line {i + 2}" for i in range(len(df))], dtype=object)
    return place(df, np.asarray(geoms, dtype=object), names, path, images, rows)


def boxes_from_json(path: Path, images: Path | None) -> gpd.GeoDataFrame:
    """A COCO dataset's boxes (``annotations``) or module 7's ``predictions``, each on its image (a tile's
    boxes moved to its source image by ``x0, y0``)."""
    data = read_json(path, what="box file")
    if isinstance(data, dict) and "predictions" in data or isinstance(data, list):
        data = read_predictions(path)
        items, kind = data["predictions"], "prediction"
    else:
        data = read_dataset(path, validate=False)
        items, kind = data["annotations"], "annotation"
    if not items:
        raise InputError(f"the file holds no {kind}s", path=path, fix="check that it is the right file")
    by_id = {im.get("id"): im for im in data["images"]}
    cats = {c.get("id"): c.get("name") for c in data.get("categories", [])}
    boxes, names, rows, records = [], [], [], []
    for i, a in enumerate(items):
        where = f"{kind} {i} (id {a.get('id', '-')})"
        box = bbox_values(a.get("bbox"))
        image = by_id.get(a.get("image_id"))
        if box is None or box[2] <= 0 or box[3] <= 0 or image is None:
            what = "has no image entry" if image is None else f"has no usable bbox [x, y, w, h]: {a.get('bbox')!r}"
            raise InputError(
                f"{where} {what}",
                path=path,
                fix="give every box as bbox [x, y, width, height] in pixels of a listed image",
            )
        x, y, w, h = to_source_pixels(box, image) if image.get("source_image") else box
        boxes.append((x, y, x + w, y + h))
        names.append(source_name(image) if image.get("source_image") else image.get("file_name", ""))
        rows.append(where)
        rec = {"image": names[-1], "label": cats.get(a.get("category_id"), a.get("category_id"))}
        if "id" in a:
            rec = {"id": a["id"], **rec}
        if "score" in a:
            rec["score"] = a["score"]
        records.append(rec)
    if any(a.get("segmentation") for a in items):
        log.info("%s: plant polygons from the boxes (bbox); segmentations are not used", path.name)
    b = np.asarray(boxes, dtype=float)
    geoms = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    return place(
        pd.DataFrame(records), geoms, np.asarray(names, dtype=object), path, images, np.asarray(rows, dtype=object)
    )
