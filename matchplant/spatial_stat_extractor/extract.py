"""Module 9: plant polygons to GIS files, and one row of statistics per plant from rasters.

Inputs: the plants of module 8 (``plants.gpkg`` or ``plants.csv``) or any polygon file (GeoPackage,
shapefile, GeoJSON, or a CSV with a WKT ``geometry`` column or ``xmin,ymin,xmax,ymax`` box columns),
and the rasters of one or more dates: a canopy height model (CHM), or a DSM and DTM pair (CHM = DSM - DTM,
computed window by window), a multispectral raster with its red and near-infrared band numbers (NDVI
computed), and any single bands.

Outputs in ``output_dir``: ``polygons.gpkg`` and ``polygons.shp`` (with their CRS), ``stats.csv`` and
``stats.gpkg`` keyed by ``plant_id`` (wide: one row per plant, columns ``<trait>_<stat>[_<date>]``;
long: one row per plant and date), ``stats_report.json`` (reprojections, plants outside a raster,
plants with only nodata), and with ``compare.polygons`` set, a comparison of two plant sets
(``compare_summary.csv``, ``compare_matches.csv``, ``compare.png``).

Statistics are exact (see :mod:`matchplant.spatial_stat_extractor.zonal`): ``mode: center`` equals rasterstats
(pixel centres inside), ``mode: coverage`` equals exactextract (pixels weighted by covered fraction).

Library use::

    plants = read_polygons("plants.gpkg")
    table, report = extract_stats(plants, [RasterSet(date="w3", dsm="dsm.tif", dtm="dtm.tif")])
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from matchplant.core.config import param, section
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.io import atomic_open, atomic_path, write_json
from matchplant.core.log import get_logger
from matchplant.core.progress import progress
from matchplant.spatial_stat_extractor.zonal import (BASIC_STATS, DEFAULT_STATS, MODES, DifferenceSource, NDVISource, RasterFileSource,
                          pyproj_crs, zonal_stats)

log = get_logger("stats")

ID_CANDIDATES = ("plant_id", "id", "ID", "Id", "fid", "FID", "plant", "label")
WKT_CANDIDATES = ("geometry", "wkt", "WKT", "geom", "the_geom")
BOX_COLUMNS = ("xmin", "ymin", "xmax", "ymax")
ODM_NODATA = -9999.0  # ODM's DEM nodata, masked on elevation rasters even when the file does not declare it


# --------------------------------------------------------------------------------------------------
# configuration


@dataclass
class BandFile:
    """One band of a raster, statistics under its own name."""

    name: str = param("band", "column name of this trait (letters, digits, _)")
    path: Path | None = param(None, "raster file", path="file")
    band: int = param(1, "band number (1 = first)", min=1)


@dataclass
class RasterSet:
    """The rasters of one date."""

    date: str = param("", "label of this date (e.g. week3, 2023-06-14); used in column names when there are several")
    chm: Path | None = param(None, "canopy height model (plant heights)", path="file")
    dsm: Path | None = param(None, "surface model (odm_dem/dsm.tif); with dtm, CHM = DSM - DTM", path="file")
    dtm: Path | None = param(None, "terrain model (odm_dem/dtm.tif, ODM --dtm)", path="file")
    multispectral: Path | None = param(None, "multispectral raster: NDVI from red_band and nir_band", path="file")
    red_band: int = param(1, "band number of red in the multispectral raster", min=1)
    nir_band: int = param(2, "band number of near-infrared in the multispectral raster", min=1)
    bands: list[BandFile] = param([], "more single bands: a list of {name, path, band}")

    def layers(self) -> list["Layer"]:
        """What to measure, one :class:`Layer` per trait."""
        out: list[Layer] = []
        if self.chm is not None and self.dsm is not None:
            raise ConfigError(f"date '{self.date}': give either chm or dsm + dtm, not both",
                              fix="remove chm, or remove dsm and dtm")
        if (self.dsm is None) != (self.dtm is None):
            missing = "dtm" if self.dtm is None else "dsm"
            raise ConfigError(f"date '{self.date}': the CHM needs both a DSM and a DTM; {missing} is not set",
                              fix=f"set {missing} (ODM writes odm_dem/dtm.tif when run with --dtm), or give chm")
        if self.chm is not None:
            out.append(Layer("chm", "band", (self.chm,), elevation=True))
        if self.dsm is not None:
            out.append(Layer("chm", "difference", (self.dsm, self.dtm), elevation=True))
        if self.multispectral is not None:
            if self.red_band == self.nir_band:
                raise ConfigError(f"date '{self.date}': red_band and nir_band are both {self.red_band}",
                                  fix="set the band numbers of red and near-infrared of your camera")
            out.append(Layer("ndvi", "ndvi", (self.multispectral,), bands=(self.red_band, self.nir_band)))
        for b in self.bands:
            if b.path is None:
                raise ConfigError(f"date '{self.date}': band '{b.name}' has no path", fix="set its path")
            out.append(Layer(b.name, "band", (b.path,), bands=(b.band,)))
        names = [layer.name for layer in out]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"date '{self.date}': trait name(s) {dup} used twice",
                              fix="give each band a different name")
        for layer in out:
            if not layer.name.replace("_", "").isalnum():
                raise ConfigError(f"trait name '{layer.name}' must be letters, digits and _",
                                  fix="rename the band, e.g. 'red_edge'")
        return out

    def empty(self) -> bool:
        return not (self.chm or self.dsm or self.dtm or self.multispectral or self.bands)


@dataclass
class CompareConfig:
    """Compare two sets of plants, e.g. manual and predicted (the paper's Figure 10)."""

    polygons: Path | None = param(None, "the second set of plant polygons (e.g. predicted); empty = no comparison",
                                  path="file")
    id_column: str = param("auto", "its plant id column ('auto' as for the first set)")
    layer: str = param("", "its GeoPackage layer ('' = the first)")
    label_a: str = param("manual", "name of the first set (polygons) in tables and figures")
    label_b: str = param("predicted", "name of the second set (compare.polygons)")
    traits: list[str] = param([], "columns to compare, e.g. [chm_max, ndvi_mean]; empty = chm_max, ndvi_mean and "
                                  "<band>_mean for each band measured")
    min_iou: float = param(0.3, "two plants are the same plant when their polygons overlap at least this much "
                                "(intersection over union)", min=0.0, max=1.0)


@dataclass
class StatsConfig:
    """Module 9: plant polygons to GIS files, and per-plant statistics (height, NDVI, any band) from rasters."""

    polygons: Path = param(None, "plant polygons: module 8's plants.gpkg or plants.csv, a shapefile, GeoJSON, or a "
                                 "CSV with a WKT 'geometry' column or xmin,ymin,xmax,ymax", path="file", required=True)
    id_column: str = param("auto", "column holding the plant id ('auto': plant_id, id or fid; else numbered from 1)")
    layer: str = param("", "layer of a GeoPackage ('' = the first)")
    polygons_crs: str = param("", "CRS of the polygons when the file has none (a CSV), e.g. EPSG:32615; '' = from "
                                  "projection_summary.json beside a module-8 CSV, else the raster's CRS")
    rasters: RasterSet = section(RasterSet)
    more_dates: list[RasterSet] = param([], "rasters of further dates for the same polygons: a list of sections "
                                            "like 'rasters' (each with its own date)")
    stats: list[str] = param(list(DEFAULT_STATS), "statistics per plant and raster", choices=BASIC_STATS)
    percentiles: list[float] = param([95.0], "percentiles (0..100) per plant and raster, e.g. [5, 50, 95]",
                                     min=0, max=100)
    mode: str = param("center", "'center': pixels whose centre is in the polygon (as rasterstats); 'coverage': "
                                "pixels weighted by the fraction covered (as exactextract), best for plants only "
                                "a few pixels wide", choices=MODES)
    nodata: float | None = param(None, "one more value to treat as nodata (each file's nodata, NaN, and -9999 on "
                                       "elevation rasters are always masked)")
    layout: str = param("wide", "several dates: 'wide' = one row per plant, columns <trait>_<stat>_<date>; "
                                "'long' = one row per plant and date", choices=("wide", "long"))
    write_polygons: bool = param(True, "write the polygons as polygons.gpkg and polygons.shp (with their CRS)")
    compare: CompareConfig = section(CompareConfig)
    output_dir: Path = param(Path("stats_output"), "output folder", path="out")

    def date_sets(self) -> list[RasterSet]:
        sets = ([] if self.rasters.empty() else [self.rasters]) + list(self.more_dates)
        labels = [s.date for s in sets]
        if len(sets) > 1 and (len(set(labels)) != len(labels) or "" in labels):
            raise ConfigError(f"several dates need distinct, non-empty 'date' labels, got {labels}",
                              fix="set 'date:' in 'rasters' and in every entry of 'more_dates'")
        return sets

    def check(self) -> None:
        sets = self.date_sets()
        if not sets:
            raise ConfigError("no raster given", fix="set rasters.chm, rasters.dsm + rasters.dtm, "
                                                     "rasters.multispectral or rasters.bands")
        for s in sets:
            s.layers()
            for b in s.bands:
                if b.path is not None and not Path(b.path).is_file():
                    raise ConfigError(f"band '{b.name}' of date '{s.date}': file not found", path=b.path,
                                      fix="correct its path (relative paths are relative to the config file)")
        for s in self.more_dates:
            for key in ("chm", "dsm", "dtm", "multispectral"):
                p = getattr(s, key)
                if p is not None and not Path(p).is_file():
                    raise ConfigError(f"more_dates '{s.date}': {key} not found", path=p,
                                      fix=f"correct '{key}' of that date")


@dataclass
class Layer:
    """One trait to measure: a band, a difference of two rasters (CHM) or NDVI."""

    name: str
    kind: str  # "band" | "difference" | "ndvi"
    paths: tuple
    bands: tuple = (1,)
    elevation: bool = False


# --------------------------------------------------------------------------------------------------
# polygons in


def read_polygons(path: str | Path, id_column: str = "auto", layer: str = "", crs: str = ""):
    """A GeoDataFrame with a ``plant_id`` column from a vector file or a CSV (see the module doc)."""
    import geopandas as gpd

    path = Path(path)
    if not path.is_file():
        raise InputError("polygon file not found", path=path, fix="check 'polygons' in your config")
    if path.suffix.lower() in (".csv", ".txt", ".tsv"):
        gdf = _read_polygon_csv(path, crs)
    else:
        try:
            gdf = gpd.read_file(path, layer=layer or None)
        except Exception as exc:  # pyogrio raises several kinds; all mean the file can't be used
            hint = " (is the layer name right?)" if layer else ""
            raise InputError(f"cannot read the polygons{hint}: {exc}", path=path,
                             fix="give a GeoPackage, shapefile, GeoJSON or CSV") from exc
        if crs:
            if gdf.crs is None:
                gdf = gdf.set_crs(_parse_crs(crs, "polygons_crs"))
            elif not gdf.crs.equals(_parse_crs(crs, "polygons_crs")):
                log.warning("polygons_crs=%s ignored: %s declares %s", crs, path.name, gdf.crs.to_string())
    if len(gdf) == 0:
        raise InputError("the polygon file holds no features", path=path, fix="check that it is the right file")
    import shapely

    geom = gdf.geometry.values
    kinds = set(shapely.get_type_id(np.asarray(geom)[~shapely.is_missing(np.asarray(geom))]).tolist())
    if not kinds <= {3, 6}:
        raise InputError("the file holds points or lines, not polygons", path=path,
                         fix="give plant polygons or boxes (module 8's plants.gpkg)")
    gdf = gdf.copy()
    gdf["plant_id"] = _plant_ids(gdf, id_column, path)
    if gdf["plant_id"].duplicated().any():
        dups = gdf["plant_id"][gdf["plant_id"].duplicated()].unique()[:5].tolist()
        raise InputError(f"plant ids are not unique (e.g. {dups})", path=path,
                         fix="set id_column to a column with one value per plant, or 'auto' to number them")
    cols = ["plant_id"] + [c for c in gdf.columns if c not in ("plant_id", gdf.geometry.name)]
    return gdf[cols + [gdf.geometry.name]]


def _plant_ids(gdf, id_column: str, path: Path) -> pd.Series:
    if id_column and id_column != "auto":
        if id_column not in gdf.columns:
            raise InputError(f"id column '{id_column}' not found; columns: {list(gdf.columns)}", path=path,
                             fix="set id_column to one of them, or to 'auto'")
        return gdf[id_column]
    for name in ID_CANDIDATES:
        if name in gdf.columns:
            return gdf[name]
    log.info("%s has no plant id column; plants are numbered 1..%d in file order", path.name, len(gdf))
    return pd.Series(np.arange(1, len(gdf) + 1), index=gdf.index)


def _parse_crs(text: str, key: str):
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(text)
    except CRSError as exc:
        raise ConfigError(f"'{key}' = {text!r} is not a CRS pyproj knows",
                          fix="write it as EPSG:32615 (your UTM zone)") from exc


def _read_polygon_csv(path: Path, crs: str):
    import geopandas as gpd
    import shapely

    try:
        df = pd.read_csv(path, sep=None, engine="python")
    except Exception as exc:
        raise InputError(f"cannot read the CSV: {exc}", path=path, fix="check that it is a CSV with a header") from exc
    wkt = next((c for c in WKT_CANDIDATES if c in df.columns), None)
    if wkt is not None:
        try:
            geom = shapely.from_wkt(df[wkt].astype(str).to_numpy())
        except shapely.errors.GEOSException as exc:
            raise InputError(f"column '{wkt}' holds text that is not WKT: {exc}", path=path,
                             fix="write polygons as WKT, e.g. POLYGON ((x y, ...))") from exc
        df = df.drop(columns=[wkt])
    elif all(c in df.columns for c in BOX_COLUMNS):
        b = df[list(BOX_COLUMNS)].to_numpy(float)
        if np.any(b[:, 2] < b[:, 0]) or np.any(b[:, 3] < b[:, 1]):
            raise InputError("some boxes have xmax < xmin or ymax < ymin", path=path,
                             fix="check the column order xmin,ymin,xmax,ymax")
        geom = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    else:
        raise InputError(f"the CSV has neither a WKT geometry column nor {','.join(BOX_COLUMNS)}; "
                         f"columns: {list(df.columns)}", path=path,
                         fix="add a 'geometry' column (WKT) or box columns xmin,ymin,xmax,ymax")
    if not crs:
        summary = path.parent / "projection_summary.json"  # module 8 writes its CRS there
        if summary.is_file():
            from matchplant.core.io import read_json
            crs = read_json(summary).get("crs") or ""
            if crs:
                log.info("polygon CRS %s taken from %s", crs, summary.name)
    return gpd.GeoDataFrame(df, geometry=geom, crs=_parse_crs(crs, "polygons_crs") if crs else None)


# --------------------------------------------------------------------------------------------------
# rasters


def _open(path: Path, stack: contextlib.ExitStack):
    import rasterio

    path = Path(path)
    if not path.is_file():
        raise InputError("raster not found", path=path, fix="check the raster paths in your config")
    try:
        return stack.enter_context(rasterio.open(path))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"cannot read the raster: {exc}", path=path, fix="give a GeoTIFF") from exc


def _band(ds, band: int, layer: Layer, nodata: float | None) -> RasterFileSource:
    if not 1 <= band <= ds.count:
        raise InputError(f"{layer.name}: band {band} asked for, but the raster has {ds.count} band(s)",
                         path=ds.name, fix="set the band number (1 = first band)")
    extra = [ODM_NODATA] if layer.elevation else []
    if nodata is not None:
        extra.append(nodata)
    return RasterFileSource(ds, band, extra_nodata=extra)


def open_layer(layer: Layer, stack: contextlib.ExitStack, nodata: float | None = None):
    """A raster source (``transform, width, height, crs, read()``) for a layer; files stay open in ``stack``."""
    if layer.kind == "band":
        return _band(_open(layer.paths[0], stack), layer.bands[0], layer, nodata)
    if layer.kind == "ndvi":
        ds = _open(layer.paths[0], stack)
        return NDVISource(_band(ds, layer.bands[0], layer, nodata), _band(ds, layer.bands[1], layer, nodata))
    dsm = _open(layer.paths[0], stack)
    dtm = _open(layer.paths[1], stack)
    if (dsm.crs and dtm.crs and dsm.crs != dtm.crs) or dsm.transform != dtm.transform \
            or dsm.shape != dtm.shape:
        # put the DTM on the DSM's grid (ODM writes them on one grid; other tools may not)
        from rasterio.enums import Resampling
        from rasterio.vrt import WarpedVRT

        log.info("DTM %s is on another grid than the DSM; resampling it (bilinear) onto the DSM grid",
                 Path(layer.paths[1]).name)
        dtm = stack.enter_context(WarpedVRT(dtm, crs=dsm.crs or dtm.crs, transform=dsm.transform,
                                            width=dsm.width, height=dsm.height, resampling=Resampling.bilinear))
    return DifferenceSource(_band(dsm, 1, layer, nodata), _band(dtm, 1, layer, nodata))


# --------------------------------------------------------------------------------------------------
# extraction


def _polygons_in(gdf, crs, layer_label: str, report: dict):
    """The polygons in the raster's CRS (reprojected when they differ)."""
    if crs is None:
        if gdf.crs is not None:
            log.warning("%s has no CRS; assuming it is in the polygons' CRS %s", layer_label, gdf.crs.to_string())
        return gdf.geometry.values
    if gdf.crs is None:
        log.warning("the polygons have no CRS; assuming they are in the raster's CRS %s (set polygons_crs "
                    "if not)", crs.to_string())
        return gdf.geometry.values
    if gdf.crs.equals(crs):
        return gdf.geometry.values
    log.info("%s is in %s, the polygons in %s: reprojecting the polygons", layer_label, crs.to_string(),
             gdf.crs.to_string())
    report["reprojected_from"] = gdf.crs.to_string()
    return gdf.to_crs(crs).geometry.values


def extract_stats(polygons, date_sets: Sequence[RasterSet], stats: Sequence[str] = DEFAULT_STATS,
                  percentiles: Sequence[float] = (95,), mode: str = "center", *, nodata: float | None = None,
                  layout: str = "wide",
                  on_progress: Callable[[float, str], None] | None = None) -> tuple[pd.DataFrame, dict]:
    """Per-plant statistics of every trait of every date; returns the table and a report.

    ``polygons``: from :func:`read_polygons`. Wide layout: one row per plant, columns
    ``<trait>_<stat>`` (``_<date>`` appended when there are several dates); long: one row per plant and
    date with a ``date`` column. ``on_progress(fraction, message)`` is called as work proceeds.
    """
    import shapely

    jobs = [(s, layer) for s in date_sets for layer in s.layers()]
    if not jobs:
        raise ConfigError("no raster given", fix="set a CHM, a DSM + DTM, a multispectral raster or bands")
    several = len(date_sets) > 1
    ids = polygons["plant_id"].to_numpy()
    per_date: dict[str, pd.DataFrame] = {}
    report = {"plants": int(len(ids)), "mode": mode, "layers": []}
    bar = progress(None, desc="statistics", total=len(jobs), unit="raster")
    try:
        for k, (s, layer) in enumerate(jobs):
            label = f"{layer.name}" + (f" ({s.date})" if s.date else "")
            entry = {"date": s.date, "trait": layer.name, "kind": layer.kind,
                     "files": [str(p) for p in layer.paths]}

            def step(done, total, k=k, label=label):
                if on_progress is not None:
                    on_progress((k + done / max(total, 1)) / len(jobs), f"{label}: batch {done}/{total}")

            with contextlib.ExitStack() as stack:
                src = open_layer(layer, stack, nodata)
                geoms = _polygons_in(polygons, src.crs, f"raster {Path(layer.paths[0]).name}", entry)
                res = zonal_stats(geoms, src, stats, percentiles, mode=mode, on_progress=step)
            _report_problems(entry, res, ids, label)
            report["layers"].append(entry)
            table = per_date.setdefault(s.date, pd.DataFrame({"plant_id": ids}))
            for c in res.columns:
                table[f"{layer.name}_{c}"] = res.stats[c]
            bar.update(1)
    finally:
        bar.close()
    centroids = shapely.centroid(polygons.geometry.values)
    xy = pd.DataFrame({"x": shapely.get_x(centroids), "y": shapely.get_y(centroids)})
    if layout == "long" and several:
        frames = []
        for date, t in per_date.items():
            t = t.copy()
            t.insert(1, "date", date)
            frames.append(pd.concat([t.iloc[:, :2], xy, t.iloc[:, 2:]], axis=1))
        table = pd.concat(frames, ignore_index=True)
    else:
        table = pd.concat([pd.DataFrame({"plant_id": ids}), xy], axis=1)
        for date, t in per_date.items():
            suffix = f"_{date}" if several else ""
            table = pd.concat([table, t.drop(columns="plant_id").add_suffix(suffix)], axis=1)
    if on_progress is not None:
        on_progress(1.0, "done")
    return table, report


def _report_problems(entry: dict, res, ids: np.ndarray, label: str) -> None:
    def listed(mask):
        return [v.item() if hasattr(v, "item") else v for v in ids[mask][:50]]

    entry.update(outside=int(res.outside.sum()), outside_ids=listed(res.outside),
                 partly_outside=int(res.partial.sum()), partly_outside_ids=listed(res.partial),
                 only_nodata=int(res.no_valid.sum()), only_nodata_ids=listed(res.no_valid))
    n = len(ids)
    if res.outside.all():
        raise InputError(f"none of the {n} plants overlaps the raster of {label}", path=entry["files"][0],
                         fix="check that the raster is of the same field, and the CRS of the polygons "
                             "(polygons_crs) and of the raster")
    if res.outside.any():
        log.warning("%s: %d of %d plants are outside the raster (e.g. ids %s); their statistics are empty",
                    label, res.outside.sum(), n, entry["outside_ids"][:5])
    if res.partial.any():
        log.info("%s: %d plants are only partly on the raster", label, res.partial.sum())
    if res.no_valid.any():
        log.warning("%s: %d plants cover only nodata pixels (e.g. ids %s)", label, res.no_valid.sum(),
                    entry["only_nodata_ids"][:5])


def preview_layer(layer: Layer, max_side: int = 800, nodata: float | None = None):
    """The layer at reduced resolution (at most ``max_side`` pixels a side), for a quick look: rasterio
    reads overviews or decimates while reading, so the full raster is never in memory.
    Returns ``(array with NaN holes, extent (left, right, bottom, top), crs)``."""
    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling

    with contextlib.ExitStack() as stack:
        ds = _open(layer.paths[0], stack)
        scale = max(ds.width, ds.height) / max_side
        h, w = (ds.height, ds.width) if scale <= 1 else (max(int(ds.height / scale), 1), max(int(ds.width / scale), 1))

        def small(dataset, band):
            src = _band(dataset, band, layer, nodata)
            arr = dataset.read(band, out_shape=(h, w), resampling=Resampling.nearest).astype(float)
            for v in src.nodata:
                arr[arr == v] = np.nan
            return arr

        if layer.kind == "band":
            arr = small(ds, layer.bands[0])
        elif layer.kind == "ndvi":
            red, nir = small(ds, layer.bands[0]), small(ds, layer.bands[1])
            with np.errstate(invalid="ignore", divide="ignore"):
                arr = np.where(nir + red != 0, (nir - red) / (nir + red), np.nan)
        else:
            dtm = _open(layer.paths[1], stack)
            arr = small(ds, 1) - (small(dtm, 1) if dtm.shape == ds.shape else np.nan)
        t: Affine = ds.transform
        b = rasterio.transform.array_bounds(ds.height, ds.width, t)
        return arr, (b[0], b[2], b[1], b[3]), pyproj_crs(ds.crs)


# --------------------------------------------------------------------------------------------------
# outputs


def write_shapefile(gdf, path: Path) -> Path:
    """A shapefile is several files: written in a temporary folder, then each moved into place.
    Only ``plant_id`` is kept (shapefile column names are limited to 10 characters)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".shp_", dir=path.parent))
    try:
        gdf[["plant_id", gdf.geometry.name]].to_file(tmp / path.name, driver="ESRI Shapefile")
        for f in tmp.iterdir():
            os.replace(f, path.parent / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_gpkg(gdf, path: Path, layer: str) -> Path:
    with atomic_path(path) as tmp:
        gdf.to_file(tmp, layer=layer, driver="GPKG")
    return Path(path)


def write_csv(df: pd.DataFrame, path: Path) -> Path:
    with atomic_open(path) as fh:
        df.to_csv(fh, index=False, float_format="%.12g")
    return Path(path)


def write_outputs(polygons, table: pd.DataFrame, report: dict, out_dir: Path, *,
                  write_polygons: bool = True) -> dict[str, Path]:
    """polygons.gpkg/.shp, stats.csv, stats.gpkg (polygons + statistics) and stats_report.json."""
    import geopandas as gpd

    out_dir = Path(out_dir)
    written: dict[str, Path] = {}
    if write_polygons:
        written["polygons_gpkg"] = write_gpkg(polygons, out_dir / "polygons.gpkg", "plants")
        written["polygons_shp"] = write_shapefile(polygons, out_dir / "polygons.shp")
    written["stats_csv"] = write_csv(table, out_dir / "stats.csv")
    geom = polygons.set_index("plant_id").geometry
    stats_gdf = gpd.GeoDataFrame(table.copy(), geometry=geom.reindex(table["plant_id"]).values, crs=polygons.crs)
    written["stats_gpkg"] = write_gpkg(stats_gdf, out_dir / "stats.gpkg", "stats")
    written["report"] = write_json(out_dir / "stats_report.json", report)
    return written


# --------------------------------------------------------------------------------------------------
# run


def run(cfg: StatsConfig) -> dict:
    out = Path(cfg.output_dir)
    sets = cfg.date_sets()
    polygons = read_polygons(cfg.polygons, cfg.id_column, cfg.layer, cfg.polygons_crs)
    log.info("%d plants from %s", len(polygons), cfg.polygons)
    table, report = extract_stats(polygons, sets, cfg.stats, cfg.percentiles, cfg.mode, nodata=cfg.nodata,
                                  layout=cfg.layout)
    written = write_outputs(polygons, table, report, out, write_polygons=cfg.write_polygons)
    if cfg.compare.polygons is not None:
        from matchplant.spatial_stat_extractor.compare import run_comparison

        written.update(run_comparison(cfg, polygons, table, sets, out))
    for key, path in written.items():
        log.info("%-14s %s", key, path)
    return {"plants": len(polygons), "outputs": {k: str(v) for k, v in written.items()}, "report": report}
