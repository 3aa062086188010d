"""Module 9 as one step: read the polygons, extract the statistics, write the files, compare two sets.

Outputs in ``output_dir``: the polygons in each of ``vector_formats`` (``polygons.gpkg``, ``polygons.shp``),
``stats.csv`` and ``stats.gpkg`` keyed by ``plant_id``, ``stats_report.json``, and the plots', canopy's and
comparison's files where those are set.

The command line and the window (:mod:`~matchplant.spatial_stat_extractor.gui`) both go through
:func:`extract_and_write`, so a run from either writes the same files.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import geopandas as gpd
import pandas as pd
import rasterio

from matchplant.core.formats.vectors import write_formats, write_vector
from matchplant.core.runtime.guard import staged_outputs
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.manifest import previous_files, remove_stale, write_manifest
from matchplant.spatial_stat_extractor.canopy import gdal_cache_bytes, memory_report, memory_stage
from matchplant.spatial_stat_extractor.compare import run_comparison
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.inputs import check_elevation, raster_crs, read_polygons, with_crs
from matchplant.spatial_stat_extractor.plots import check_plot_file, plots_wanted, run_plots
from matchplant.spatial_stat_extractor.traits import canopy_traits, merge_columns
from matchplant.spatial_stat_extractor.zonal import extract_stats, write_csv

log = get_logger("spatial_stat_extractor")


def extract_and_write(cfg: SpatialStatExtractorConfig, on_progress: Callable[[float, str], None] | None = None):
    """Everything module 9 does for ``cfg``; returns ``(polygons, table, report, written files)``."""
    budget = cfg.memory_bytes()
    # GDAL's block cache counts against max_memory too (its default is 5% of the computer's memory); in bytes:
    # rasterio hands a small number to GDAL as bytes, and a cache smaller than a row of tiles makes every
    # decimated or windowed read decompress the same tiles again and again (100x slower)
    with rasterio.Env(GDAL_CACHEMAX=gdal_cache_bytes(budget)):
        return _extract_and_write(cfg, budget, on_progress)


def _extract_and_write(cfg: SpatialStatExtractorConfig, budget: int, on_progress):
    out = Path(cfg.output_dir)
    sets = cfg.date_sets()
    check_elevation(sets)  # a CHM in feet or of one value: named before any work
    if plots_wanted(cfg.plots):
        check_plot_file(cfg.plots)
    polygons = read_polygons(cfg.polygons, cfg.id_column, cfg.layer, cfg.polygons_crs, cfg.boxes_image)
    if polygons.crs is None:
        polygons = with_crs(polygons, *raster_crs(sets))
    log.info("%d plants from %s", len(polygons), cfg.polygons)
    stages: dict[str, dict] = {}

    def done(stage: str, t0: float, c0: float) -> None:
        stages[stage] = {
            "wall_s": round(time.perf_counter() - t0, 3),
            "cpu_s": round(time.process_time() - c0, 3),
            **memory_report(budget),
        }
        log.info(
            "%s: %.1f s (CPU %.1f s), peak memory so far %s MB",
            stage,
            stages[stage]["wall_s"],
            stages[stage]["cpu_s"],
            stages[stage]["peak_mb"],
        )

    t0, c0 = time.perf_counter(), time.process_time()
    with memory_stage("the box statistics", budget):
        table, report = extract_stats(
            polygons,
            sets,
            cfg.stats,
            cfg.percentiles,
            cfg.mode,
            nodata=cfg.nodata,
            layout=cfg.layout,
            on_progress=on_progress,
        )
    done("box statistics", t0, c0)
    report["polygons_crs"] = {
        "crs": polygons.crs.to_string() if polygons.crs is not None else None,
        "from": polygons.attrs.get("crs_source"),
    }
    outlines = unclaimed = None
    if cfg.canopy.enabled:
        if on_progress is not None:
            on_progress(1.0, "plant outlines and canopy statistics")
        t0, c0 = time.perf_counter(), time.process_time()
        with memory_stage("the plant outlines and canopy statistics", budget):
            per_date, outlines, unclaimed, report["canopy"] = canopy_traits(
                polygons,
                sets,
                cfg.canopy,
                cfg.stats,
                cfg.percentiles,
                cfg.nodata,
                max_memory=budget,
                workers=cfg.workers,
            )
            table = merge_columns(table, per_date, cfg.layout, len(sets))
        done("outlines and canopy statistics", t0, c0)
    if on_progress is not None:
        on_progress(1.0, "writing files")
    report["memory"] = {**memory_report(budget), "stages": stages}
    t0, c0 = time.perf_counter(), time.process_time()
    with memory_stage("writing the files", budget):
        written = write_outputs(polygons, table, report, out, vector_formats=cfg.vector_formats)
        if outlines is not None:
            written["outlines_gpkg"] = write_vector(outlines, out / "outlines.gpkg", layer="outlines")
            written["outlines_csv"] = write_csv(pd.DataFrame(outlines.drop(columns="geometry")), out / "outlines.csv")
            written["unclaimed_csv"] = write_csv(unclaimed, out / "unclaimed_canopies.csv")
    done("writing files", t0, c0)
    if plots_wanted(cfg.plots):
        t0, c0 = time.perf_counter(), time.process_time()
        with memory_stage("the plots", budget):
            written.update(run_plots(cfg.plots, table, unclaimed, polygons, out, sets, cfg.mode, cfg.nodata))
        done("plots", t0, c0)
    if cfg.compare.polygons is not None:
        with memory_stage("the comparison", budget):
            written.update(run_comparison(cfg, polygons, table, sets, out))
    report["memory"] = {**memory_report(budget), "stages": stages}
    log.info(
        "peak memory %s MB (largest worker process %s MB; max_memory %s)",
        report["memory"]["peak_mb"],
        report["memory"]["peak_worker_mb"],
        cfg.max_memory,
    )
    return polygons, table, report, written


def run(cfg: SpatialStatExtractorConfig) -> dict:
    """Run module 9: per-plant statistics (and outlines, plots) into ``cfg.output_dir``, all files or none.

    Parameters
    ----------
    cfg : SpatialStatExtractorConfig
        The settings (``matchplant spatial_stat_extractor --help`` lists every key).

    Returns
    -------
    dict
        The report: the files written (by name) and what was measured.
    """
    # all files or none: written in a temporary folder, moved into output_dir at the end
    before = previous_files(cfg.output_dir)
    with staged_outputs(cfg.output_dir) as stage:
        polygons, _, report, written = extract_and_write(replace(cfg, output_dir=stage))
        now = write_manifest(stage)
    remove_stale(Path(cfg.output_dir), before, now)  # only once the new outputs are in place
    written = {k: Path(cfg.output_dir) / Path(v).relative_to(stage) for k, v in written.items()}
    for key, path in written.items():
        log.info("%-14s %s", key, path)
    return {"plants": len(polygons), "outputs": {k: str(v) for k, v in written.items()}, "report": report}


def write_outputs(
    polygons, table: pd.DataFrame, report: dict, out_dir: Path, *, vector_formats: Sequence[str] = ("gpkg", "shp")
) -> dict[str, Path]:
    """The polygons in each of ``vector_formats`` (``polygons.gpkg``, ``.shp`` with only ``plant_id``,
    ``.geojson``), stats.csv, stats.gpkg (polygons + statistics) and stats_report.json."""
    out_dir = Path(out_dir)
    formats = write_formats({"plants": polygons}, out_dir / "polygons", vector_formats, shapefile_columns=["plant_id"])
    written: dict[str, Path] = {f"polygons_{fmt}": path for fmt, path in formats.items()}
    written["stats_csv"] = write_csv(table, out_dir / "stats.csv")
    geom = polygons.set_index("plant_id").geometry
    stats_gdf = gpd.GeoDataFrame(table.copy(), geometry=geom.reindex(table["plant_id"]).values, crs=polygons.crs)
    written["stats_gpkg"] = write_vector(stats_gdf, out_dir / "stats.gpkg", layer="stats")
    written["report"] = write_json(out_dir / "stats_report.json", report)
    return written
