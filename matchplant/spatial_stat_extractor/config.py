"""Module 9's settings: the plant polygons, the rasters of each date, the statistics, the comparison.

A :class:`RasterSet` turns into :class:`Layer` s, one per trait to measure (a band, a CHM as DSM - DTM,
NDVI), so that reading rasters (:mod:`~matchplant.spatial_stat_extractor.inputs.rasters`) works from layers only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.formats.vectors import VECTOR_FORMATS
from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.errors import ConfigError
from matchplant.spatial_stat_extractor.canopy import DEFAULT_MAX_MEMORY, parse_memory
from matchplant.spatial_stat_extractor.inputs import RGB_INDICES, Layer, check_order
from matchplant.spatial_stat_extractor.plots import PlotsConfig
from matchplant.spatial_stat_extractor.zonal import BASIC_STATS, DEFAULT_STATS, MODES


@dataclass
class BandFile:
    """One band of a raster, statistics under its own name."""

    name: str = param("band", "column name of this trait (letters, digits, _)")
    path: Path | None = param(None, "raster file", path="file")
    band: int | str = param(1, "band number (1 = first), or a band name of band_order (e.g. rededge)", min=1)
    band_order: list[str] = param(
        [], "names of this raster's bands in file order; [] = rasters.band_order when path is the multispectral raster"
    )


@dataclass
class Formula:
    """An index written as a formula of a raster's bands."""

    name: str = param("index", "column name of this index (letters, digits, _)")
    path: Path | None = param(None, "raster file whose bands the formula uses", path="file")
    expression: str = param(
        "",
        "the formula over the bands b1, b2, ... (or their names from band_order), e.g. "
        "(b5 - b3) / (b5 + b3) or (nir - rededge) / (nir + rededge); + - * / ** and "
        "parentheses",
    )
    band_order: list[str] = param(
        [], "names of this raster's bands in file order; [] = rasters.band_order when path is the multispectral raster"
    )


@dataclass
class RasterSet:
    """The rasters of one date."""

    date: str = param("", "label of this date (e.g. week3, 2023-06-14); used in column names when there are several")
    chm: Path | None = param(None, "canopy height model (plant heights)", path="file")
    dsm: Path | None = param(None, "surface model (odm_dem/dsm.tif); with dtm, CHM = DSM - DTM", path="file")
    dtm: Path | None = param(None, "terrain model (odm_dem/dtm.tif, ODM --dtm)", path="file")
    multispectral: Path | None = param(None, "multispectral raster: NDVI from red_band and nir_band", path="file")
    red_band: int | str | None = param(
        None,
        "band of red in the multispectral raster: a number (1 = first), a "
        "name of band_order, or null = named by band_order or by the "
        "raster's band descriptions (a 2-band raster: 1)",
        min=1,
    )
    nir_band: int | str | None = param(
        None, "band of near-infrared in the multispectral raster (as red_band; a 2-band raster: 2)", min=1
    )
    band_order: list[str] = param(
        [],
        "names of the multispectral raster's bands in file order, e.g. [blue, green, "
        "red, rededge, nir]: they overrule the file's own colour labels, give red_band "
        "and nir_band when unset, and name the bands in formulas; [] = the file's band "
        "descriptions (colour labels count only on 8-bit RGB images)",
    )
    bands: list[BandFile] = param([], "more single bands: a list of {name, path, band}")
    rgb: Path | None = param(
        None,
        "RGB orthophoto (ODM's odm_orthophoto/odm_orthophoto.tif): RGB vegetation "
        "indices for drones without a multispectral camera",
        path="file",
    )
    rgb_bands: list[int] = param([1, 2, 3], "band numbers of red, green and blue in the RGB raster", min=1)
    indices: list[str] = param(
        ["exg", "vari", "gli"],
        "RGB indices from 'rgb': exg (excess green), exgr (ExG - ExR), vari, gli (green leaf index), ngrdi",
        choices=tuple(RGB_INDICES),
    )
    formulas: list[Formula] = param([], "more indices as band formulas: a list of {name, path, expression}")

    def layers(self) -> list[Layer]:
        """What to measure, one :class:`Layer` per trait."""
        out: list[Layer] = []
        if self.chm is not None and self.dsm is not None:
            raise ConfigError(
                f"date '{self.date}': give either chm or dsm + dtm, not both", fix="remove chm, or remove dsm and dtm"
            )
        if (self.dsm is None) != (self.dtm is None):
            missing = "dtm" if self.dtm is None else "dsm"
            raise ConfigError(
                f"date '{self.date}': the CHM needs both a DSM and a DTM; {missing} is not set",
                fix=f"set {missing} (ODM writes odm_dem/dtm.tif when run with --dtm), or give chm",
            )
        if self.chm is not None:
            out.append(Layer("chm", "band", (self.chm,), elevation=True))
        if self.dsm is not None:
            out.append(Layer("chm", "difference", (self.dsm, self.dtm), elevation=True))
        order = check_order(self.band_order, "band_order")

        def order_of(path, own, key):  # a band or formula on the multispectral raster shares its band_order
            if own:
                return check_order(own, key)
            same = self.multispectral is not None and path is not None and Path(path) == Path(self.multispectral)
            return order if same else ()

        if self.multispectral is not None:
            if self.red_band is not None and self.red_band == self.nir_band:
                raise ConfigError(
                    f"date '{self.date}': red_band and nir_band are both {self.red_band}",
                    fix="set the band numbers of red and near-infrared of your camera",
                )
            out.append(
                Layer(
                    "ndvi",
                    "ndvi",
                    (self.multispectral,),
                    bands=(self.red_band, self.nir_band),
                    index=True,
                    band_order=order,
                )
            )
        for b in self.bands:
            if b.path is None:
                raise ConfigError(f"date '{self.date}': band '{b.name}' has no path", fix="set its path")
            out.append(
                Layer(
                    b.name,
                    "band",
                    (b.path,),
                    bands=(b.band,),
                    band_order=order_of(b.path, b.band_order, f"bands '{b.name}' band_order"),
                )
            )
        if self.rgb is not None:
            if len(self.rgb_bands) != 3 or len(set(self.rgb_bands)) != 3:
                raise ConfigError(
                    f"date '{self.date}': rgb_bands must be three different band numbers, got {self.rgb_bands}",
                    fix="set rgb_bands: [red, green, blue], e.g. [1, 2, 3]",
                )
            for name in dict.fromkeys(self.indices):
                out.append(
                    Layer(
                        name,
                        "formula",
                        (self.rgb,),
                        bands=tuple(self.rgb_bands),
                        expression=RGB_INDICES[name],
                        index=True,
                    )
                )
        for f in self.formulas:
            if f.path is None or not f.expression.strip():
                raise ConfigError(
                    f"date '{self.date}': formula '{f.name}' needs a path and an expression",
                    fix="set both, e.g. {name: ndre, path: ms.tif, expression: (b5 - b4) / (b5 + b4)}",
                )
            out.append(
                Layer(
                    f.name,
                    "formula",
                    (f.path,),
                    expression=f.expression,
                    index=True,
                    band_order=order_of(f.path, f.band_order, f"formula '{f.name}' band_order"),
                )
            )
        names = [layer.name for layer in out]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(
                f"date '{self.date}': trait name(s) {dup} used twice", fix="give each band a different name"
            )
        for layer in out:
            if not layer.name.replace("_", "").isalnum():
                raise ConfigError(
                    f"trait name '{layer.name}' must be letters, digits and _", fix="rename the band, e.g. 'red_edge'"
                )
        return out

    def empty(self) -> bool:
        """Whether no raster at all is set for this date."""
        return not (self.chm or self.dsm or self.dtm or self.multispectral or self.bands or self.rgb or self.formulas)


@dataclass
class CompareConfig:
    """Compare two sets of plants, e.g. manual and predicted (the paper's Figure 10)."""

    polygons: Path | None = param(
        None, "the second set of plant polygons (e.g. predicted); empty = no comparison", path="file"
    )
    id_column: str = param("auto", "its plant id column ('auto' as for the first set)")
    layer: str = param("", "its GeoPackage layer ('' = the first)")
    label_a: str = param("manual", "name of the first set (polygons) in tables and figures")
    label_b: str = param("predicted", "name of the second set (compare.polygons)")
    traits: list[str] = param(
        [],
        "columns to compare, e.g. [chm_max, ndvi_mean]; empty = chm_max, ndvi_mean and "
        "<band>_mean for each band measured",
    )
    min_iou: float = param(
        0.3,
        "two plants are the same plant when their polygons overlap at least this much (intersection over union)",
        min=0.0,
        max=1.0,
    )


@dataclass
class CanopyConfig:
    """Plant outlines from the CHM and canopy-only statistics (docs/DESIGN.md §2)."""

    enabled: bool = param(
        True,
        "cut each plant's canopy out of the CHM (needs chm, or dsm + dtm): outlines, "
        "tops, canopy area and volume, and statistics over the canopy pixels",
    )
    margin: float = param(0.05, "m around each box where the canopy may reach", min=0)
    relative: float = param(0.1, "canopy pixels reach at least this share of the plant's own top height", min=0, max=1)
    min_height: float | Literal["auto"] = param(
        "auto",
        "m above the ground: lower pixels are soil; auto = from the CHM's own ground noise (median + 3 SD "
        "of the CHM between the plants, or + 1 SD where NDVI tells leaves from soil; at least 0.02), logged",
        min=0,
    )
    min_top: float | Literal["auto"] = param(
        "auto",
        "m: a plant's top must reach this height to be outlined; lower ones (weeds, soil, plants too "
        "small for the CHM) keep their box, flagged 'low', and are left out of stand counts; auto = median "
        "+ 4 SD of the ground noise (or + 2 SD with NDVI), at least 0.05 (canopies no box claims need median "
        "+ 6 SD, or + 3 SD with NDVI)",
        min=0,
    )
    min_pixels: int = param(4, "canopies smaller than this many pixels keep their box (flagged 'small')", min=1)
    ndvi_threshold: float | Literal["auto"] | None = param(
        "auto",
        "canopy pixels also need NDVI at least this (a multispectral raster on the CHM's grid); auto = "
        "from the NDVI of the soil between the plants and of their tops: above the soil's median + 3 SD, "
        "and each plant's pixels at least halfway from the soil's to its top's; used when it separates "
        "the two, logged; null = height only",
        min=-1,
        max=1,
    )
    traits: list[str] = param(
        [],
        "traits measured over the canopy too, as <trait>_canopy_<stat>; empty = the "
        "indices (ndvi, RGB indices, formulas); the CHM's canopy percentiles are "
        "always given",
    )
    height_percentiles: list[float] = param(
        [50.0, 90.0, 95.0], "canopy height percentiles (chm_canopy_pNN)", min=0, max=100
    )
    recentre: bool = param(
        True,
        "later dates: re-centre each plant on that date's CHM (the local maximum "
        "nearest to its earlier top moved by the median shift of the plants around) "
        "and re-outline it; the shift is reported",
    )
    max_shift: float = param(
        0.1, "m: how far a plant's top may move between dates (less than the plant spacing)", min=0
    )
    register: bool = param(
        False,
        "later dates: when a date's CHM is shifted against the first date's by more "
        "than max_shift (a flight georeferenced without GCPs), move it by the measured "
        "offset instead of stopping with an error",
    )
    max_height: float = param(
        10.0,
        "m: the tallest plausible plant; taller median tops stop the run (a CHM in centimetres); raise it for trees",
        min=0.1,
    )


@dataclass
class SpatialStatExtractorConfig:
    """Module 9: plant polygons to GIS files, and per-plant statistics (height, NDVI, any band) from rasters."""

    renamed_keys = {"write_polygons": ("vector_formats", "[gpkg, shp] for write_polygons: true, [] for false")}

    polygons: Path = param(
        None,
        "plant polygons: module 8's plants.gpkg or plants.csv, a shapefile, GeoJSON, or a "
        "CSV with a WKT 'geometry' column or xmin,ymin,xmax,ymax; or boxes in pixels of a "
        "georeferenced image: a DeepForest CSV (image_path,xmin,ymin,xmax,ymax,label), a "
        "COCO file, module 7's predictions.json",
        path="file",
        required=True,
    )
    id_column: str = param(
        "auto",
        "column holding the plant id ('auto': plant_id, id or fid, never a class 'label'; "
        "else numbered from 1; 'number': numbered 1..n in file order)",
    )
    layer: str = param("", "layer of a GeoPackage ('' = the first)")
    boxes_image: Path | None = param(
        None,
        "boxes in pixels of a georeferenced image (a DeepForest CSV's image_path, a "
        "COCO file's or module 7's file_name): that image, or the folder holding "
        "them; null = beside the polygon file",
        path="exists",
    )
    polygons_crs: str = param(
        "",
        "CRS of the polygons when the file has none (a CSV), e.g. EPSG:32615; '' = the "
        "CSV's 'crs' column (module 8 writes one), else the raster's CRS",
    )
    rasters: RasterSet = section(RasterSet)
    more_dates: list[RasterSet] = param(
        [], "rasters of further dates for the same polygons: a list of sections like 'rasters' (each with its own date)"
    )
    stats: list[str] = param(list(DEFAULT_STATS), "statistics per plant and raster", choices=BASIC_STATS)
    percentiles: list[float] = param(
        [95.0], "percentiles (0..100) per plant and raster, e.g. [5, 50, 95]", min=0, max=100
    )
    mode: str = param(
        "center",
        "'center': pixels whose centre is in the polygon (as rasterstats); 'coverage': "
        "pixels weighted by the fraction covered (as exactextract), best for plants only "
        "a few pixels wide",
        choices=MODES,
    )
    nodata: float | None = param(
        None,
        "one more value to treat as nodata (each file's nodata, NaN, and -9999 on elevation rasters are always masked)",
    )
    layout: str = param(
        "wide",
        "several dates: 'wide' = one row per plant, columns <trait>_<stat>_<date>; 'long' = one row per plant and date",
        choices=("wide", "long"),
    )
    vector_formats: list[str] = param(
        ["gpkg", "shp"],
        "write the polygons (with their CRS) as polygons.gpkg, "
        "polygons.shp (only plant_id) and/or polygons.geojson; "
        "[] = none (stats.gpkg is always written)",
        choices=VECTOR_FORMATS,
    )
    compare: CompareConfig = section(CompareConfig)
    canopy: CanopyConfig = section(CanopyConfig)
    plots: PlotsConfig = section(PlotsConfig)
    max_memory: str = param(
        DEFAULT_MAX_MEMORY,
        "memory module 9 may use (e.g. 3GB, 512MB): the rasters are read in strips "
        "sized to fit, so any field size runs; lower it if the computer runs short",
    )
    workers: int = param(0, "processes outlining strips in parallel (0 = one per core; 1 = this process only)", min=0)
    output_dir: Path = param(Path("runs/spatial_stat_extractor"), "output folder", path="out")

    def memory_bytes(self) -> int:
        """``max_memory`` in bytes (a clear error naming the key when it cannot be read)."""
        return parse_memory(self.max_memory)

    def date_sets(self) -> list[RasterSet]:
        """The raster sets of every date, in order (the main one first); labels must be unique."""
        sets = ([] if self.rasters.empty() else [self.rasters]) + list(self.more_dates)
        labels = [s.date for s in sets]
        if len(sets) > 1 and (len(set(labels)) != len(labels) or "" in labels):
            raise ConfigError(
                f"several dates need distinct, non-empty 'date' labels, got {labels}",
                fix="set 'date:' in 'rasters' and in every entry of 'more_dates'",
            )
        return sets

    def check(self) -> None:
        """Check the settings together (memory, dates, layers, band and formula files) before any work."""
        self.memory_bytes()
        sets = self.date_sets()
        if not sets:
            raise ConfigError(
                "no raster given",
                fix="set rasters.chm, rasters.dsm + rasters.dtm, rasters.multispectral, rasters.rgb or rasters.bands",
            )
        for s in sets:
            s.layers()
            for b in s.bands:
                if b.path is not None and not Path(b.path).is_file():
                    raise ConfigError(
                        f"band '{b.name}' of date '{s.date}': file not found",
                        path=b.path,
                        fix="correct its path (relative paths are relative to the config file)",
                    )
            for f in s.formulas:
                if f.path is not None and not Path(f.path).is_file():
                    raise ConfigError(
                        f"formula '{f.name}' of date '{s.date}': file not found",
                        path=f.path,
                        fix="correct its path (relative paths are relative to the config file)",
                    )
        for s in self.more_dates:
            for key in ("chm", "dsm", "dtm", "multispectral", "rgb"):
                p = getattr(s, key)
                if p is not None and not Path(p).is_file():
                    raise ConfigError(
                        f"more_dates '{s.date}': {key} not found", path=p, fix=f"correct '{key}' of that date"
                    )
