"""Plant polygons in: any vector file, or a CSV of WKT or boxes, with one ``plant_id`` each; or
boxes in pixels of a georeferenced image (a DeepForest CSV, a COCO file, module 7's predictions:
:mod:`~matchplant.spatial_stat_extractor.inputs.pixel_boxes`).

A module-8 CSV carries its CRS in a last column ``crs`` (e.g. ``EPSG:32615``, the same on every row); a CSV
without one needs ``polygons_crs`` (else the rasters' CRS is assumed, with a warning).

Plant ids: ``id_column: auto`` takes the first of plant_id, id, ID, fid, plant (never ``label``: a class name
such as DeepForest's "Tree", not an id), else numbers the plants 1..n in file order; ``id_column: number``
numbers them whatever columns there are.
"""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import did_you_mean
from matchplant.core.runtime.validate_gis import check_vector
from matchplant.spatial_stat_extractor.inputs.pixel_boxes import (
    IMAGE_COLUMN,
    boxes_from_csv,
    boxes_from_json,
    is_box_json,
)

log = get_logger("spatial_stat_extractor")

ID_CANDIDATES = ("plant_id", "id", "ID", "Id", "fid", "FID", "plant")
NUMBER = "number"  # id_column: number the plants 1..n in file order
WKT_CANDIDATES = ("geometry", "wkt", "WKT", "geom", "the_geom")
BOX_COLUMNS = ("xmin", "ymin", "xmax", "ymax")


def read_polygons(
    path: str | Path, id_column: str = "auto", layer: str = "", crs: str = "", images: str | Path | None = None
):
    """A GeoDataFrame with a ``plant_id`` column from a vector file or a CSV (see the module doc of
    :mod:`~matchplant.spatial_stat_extractor.zonal.table` for the formats), or from boxes in pixels of georeferenced
    images (``images``: the image, or their folder; default: beside the file).

    Parameters
    ----------
    path : str or Path
        A vector file (GeoPackage, shapefile, GeoJSON...) or a CSV (module 8's, WKT, boxes or pixel boxes).
    id_column : str
        The plant id column; ``auto`` (the first of the usual names, else 1..n) or ``number`` (1..n).
    layer : str
        The layer of a multi-layer file (default: its only or first).
    crs : str
        The CRS of a CSV without a ``crs`` column (e.g. ``EPSG:32615``).
    images : str or Path, optional
        For boxes in image pixels: the georeferenced image or their folder.

    Returns
    -------
    geopandas.GeoDataFrame
        One row per plant, with ``plant_id``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("polygon file not found", path=path, fix="check 'polygons' in your config")
    if path.suffix.lower() in (".csv", ".txt", ".tsv"):
        gdf = _read_polygon_csv(path, crs, images)
        crs_source = gdf.attrs.get("crs_source")
    elif path.suffix.lower() == ".json" and is_box_json(path):
        gdf = boxes_from_json(path, images)
        crs_source = gdf.attrs.get("crs_source")
        _ignored_crs(crs, gdf, path)
    else:
        if layer:  # an unknown layer: the layers there, with "did you mean"
            check_vector(path, layer=layer, require_crs=False, allow_empty=True, what="polygon file")
        try:
            gdf = gpd.read_file(path, layer=layer or None)
        except Exception as exc:  # pyogrio raises several kinds; all mean the file can't be used
            hint = " (is the layer name right?)" if layer else ""
            raise InputError(
                f"cannot read the polygons{hint}: {exc}", path=path, fix="give a GeoPackage, shapefile, GeoJSON or CSV"
            ) from exc
        crs_source = "the polygon file" if gdf.crs is not None else None
        if crs:
            if gdf.crs is None:
                gdf = gdf.set_crs(parse_crs(crs, key="polygons_crs"))
                crs_source = "polygons_crs"
            elif not gdf.crs.equals(parse_crs(crs, key="polygons_crs")):
                log.warning("polygons_crs=%s ignored: %s declares %s", crs, path.name, gdf.crs.to_string())
    if len(gdf) == 0:
        raise InputError("the polygon file holds no features", path=path, fix="check that it is the right file")
    geom = gdf.geometry.values
    kinds = set(shapely.get_type_id(np.asarray(geom)[~shapely.is_missing(np.asarray(geom))]).tolist())
    if not kinds <= {3, 6}:
        raise InputError(
            "the file holds points or lines, not polygons",
            path=path,
            fix="give plant polygons or boxes (module 8's plants.gpkg)",
        )
    gdf = gdf.copy()
    gdf["plant_id"] = _plant_ids(gdf, id_column, path)
    if gdf["plant_id"].duplicated().any():
        dups = gdf["plant_id"][gdf["plant_id"].duplicated()].unique()[:5].tolist()
        which = "id_column" if id_column not in ("", "auto") else "the column id_column: auto chose"
        raise InputError(
            f"plant ids are not unique (e.g. {dups}; from {which})",
            path=path,
            fix="set id_column to a column with one value per plant, or id_column: number to number "
            "the plants 1..n in file order",
        )
    cols = ["plant_id"] + [c for c in gdf.columns if c not in ("plant_id", gdf.geometry.name)]
    gdf = gdf[cols + [gdf.geometry.name]]
    gdf.attrs.update(source=str(path), crs_source=crs_source)
    return gdf


def with_crs(gdf, crs, source: str | Path | None):
    """The polygons with a CRS: their own, else ``crs`` (taken from ``source``, said in the log); none at all
    is an error (GIS files without a CRS land in the wrong place)."""
    if gdf.crs is not None:
        return gdf
    path = gdf.attrs.get("source")
    if crs is None:
        raise InputError(
            "the polygons have no CRS, and neither polygons_crs, a 'crs' column, nor the rasters give one",
            path=path,
            fix="set polygons_crs to the CRS of the coordinates (e.g. EPSG:32615, your UTM zone)",
        )
    log.warning(
        "%s has no CRS; using %s of the raster %s (set polygons_crs if that is wrong)",
        Path(path).name if path else "the polygons",
        crs.to_string(),
        source,
    )
    out = gdf.set_crs(crs)
    out.attrs.update(gdf.attrs, crs_source=f"raster {source}")
    return out


def _ignored_crs(crs: str, gdf, path: Path) -> None:
    if crs and gdf.crs is not None and not gdf.crs.equals(parse_crs(crs, key="polygons_crs")):
        log.warning(
            "polygons_crs=%s ignored: the boxes of %s are placed by their image's georeference (%s)",
            crs,
            path.name,
            gdf.crs.to_string(),
        )


def _plant_ids(gdf, id_column: str, path: Path) -> pd.Series:
    numbered = pd.Series(np.arange(1, len(gdf) + 1), index=gdf.index)
    if id_column == NUMBER and NUMBER not in gdf.columns:
        log.info("plants of %s numbered 1..%d in file order (id_column: number)", path.name, len(gdf))
        return numbered
    if id_column and id_column != "auto":
        if id_column not in gdf.columns:
            names = [str(c) for c in gdf.columns if c != gdf.geometry.name]
            hint = did_you_mean(id_column, names)
            raise InputError(
                f"id column '{id_column}' not found; {hint or 'columns: ' + ', '.join(names)}",
                path=path,
                fix="set id_column to one of the columns, or to 'number' to number the plants 1..n in file order",
            )
        return gdf[id_column]
    for name in ID_CANDIDATES:
        if name in gdf.columns:
            log.info("plant ids of %s from its column '%s' (id_column: auto)", path.name, name)
            return gdf[name]
    log.info(
        "%s has no plant id column (%s); plants are numbered 1..%d in file order",
        path.name,
        ", ".join(ID_CANDIDATES[:5]),
        len(gdf),
    )
    return numbered


def _numbers(col: pd.Series, name: str, path: Path) -> np.ndarray:
    """A box column as floats; decimal commas (a European spreadsheet's export) are read; the first value
    that is not a finite number is named with its line."""
    text = col.astype(str).str.strip().str.replace(",", ".", regex=False)
    values = pd.to_numeric(text, errors="coerce").to_numpy(float)
    bad = np.flatnonzero(~np.isfinite(values))
    if len(bad):
        raise InputError(
            f"column '{name}', line {bad[0] + 2}: {col.iloc[bad[0]]!r} is not a number ({len(bad)} such value(s))",
            path=path,
            fix="give every box as numbers (coordinates in metres); remove or fill the empty cells",
        )
    return values


def _crs_column(df: pd.DataFrame, path: Path) -> str:
    """The CRS in a ``crs`` column (module 8 writes one in plants.csv, the same on every row), taken out of the
    table; '' when there is none."""
    if "crs" not in df.columns:
        return ""
    values = [v for v in df.pop("crs").dropna().astype(str).str.strip().unique() if v]
    if len(values) > 1:
        raise InputError(
            f"column 'crs' holds several CRSs ({', '.join(values[:3])})",
            path=path,
            fix="give every plant in one CRS (reproject in a GIS), or remove the column and set polygons_crs",
        )
    return values[0] if values else ""


def _read_polygon_csv(path: Path, crs: str, images=None):
    try:
        df = pd.read_csv(path, sep=None, engine="python", encoding="utf-8-sig")
    except Exception as exc:
        raise InputError(f"cannot read the CSV: {exc}", path=path, fix="check that it is a CSV with a header") from exc
    df.columns = [str(c).strip() for c in df.columns]
    if len(df) == 0:
        raise InputError(
            "the polygon CSV has a header but no data rows",
            path=path,
            fix="point 'polygons' at the file that holds the plants",
        )
    wkt = next((c for c in WKT_CANDIDATES if c in df.columns), None)
    if wkt is not None:
        try:
            geom = shapely.from_wkt(df[wkt].astype(str).to_numpy())
        except shapely.errors.GEOSException as exc:
            raise InputError(
                f"column '{wkt}' holds text that is not WKT: {exc}",
                path=path,
                fix="write polygons as WKT, e.g. POLYGON ((x y, ...))",
            ) from exc
        df = df.drop(columns=[wkt])
    elif all(c in df.columns for c in BOX_COLUMNS):
        b = np.column_stack([_numbers(df[c], c, path) for c in BOX_COLUMNS])
        if np.any(b[:, 2] < b[:, 0]) or np.any(b[:, 3] < b[:, 1]):
            raise InputError(
                "some boxes have xmax < xmin or ymax < ymin",
                path=path,
                fix="check the column order xmin,ymin,xmax,ymax",
            )
        geom = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    else:
        raise InputError(
            f"the CSV has neither a WKT geometry column nor {','.join(BOX_COLUMNS)}; columns: {list(df.columns)}",
            path=path,
            fix="add a 'geometry' column (WKT) or box columns xmin,ymin,xmax,ymax",
        )
    if IMAGE_COLUMN in df.columns or images is not None:  # boxes in pixels of a georeferenced image
        gdf = boxes_from_csv(df, geom, path, images)
        _ignored_crs(crs, gdf, path)
        return gdf
    own = _crs_column(df, path)
    if crs:
        the_crs, source = parse_crs(crs, key="polygons_crs"), "polygons_crs"
    elif own:
        the_crs, source = parse_crs(own, source=path), f"the 'crs' column of {path}"
        log.info("polygon CRS %s taken from the 'crs' column of %s", own, path.name)
    else:
        the_crs = source = None
    gdf = gpd.GeoDataFrame(df, geometry=geom, crs=the_crs)
    gdf.attrs["crs_source"] = source
    return gdf
