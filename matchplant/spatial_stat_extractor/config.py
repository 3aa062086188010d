"""Module 9's settings: the plant polygons, the rasters of each date, the statistics, the comparison.

A :class:`RasterSet` turns into :class:`Layer` s, one per trait to measure (a band, a CHM as DSM - DTM,
NDVI), so that reading rasters (:mod:`~matchplant.spatial_stat_extractor.rasters`) works from layers only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.config import param, section
from matchplant.core.errors import ConfigError
from matchplant.spatial_stat_extractor.zonal import BASIC_STATS, DEFAULT_STATS, MODES


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

