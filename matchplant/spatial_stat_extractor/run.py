"""Module 9 as one step: read the polygons, extract the statistics, write the files, compare two sets.

The command line and the window (:mod:`~matchplant.spatial_stat_extractor.gui`) both go through
:func:`extract_and_write`, so a run from either writes the same files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from matchplant.core.log import get_logger
from matchplant.spatial_stat_extractor.compare import run_comparison
from matchplant.spatial_stat_extractor.config import StatsConfig
from matchplant.spatial_stat_extractor.extract import extract_stats, write_outputs
from matchplant.spatial_stat_extractor.polygons import read_polygons

log = get_logger("stats")


def extract_and_write(cfg: StatsConfig, on_progress: Callable[[float, str], None] | None = None):
    """Everything module 9 does for ``cfg``; returns ``(polygons, table, report, written files)``."""
    out = Path(cfg.output_dir)
    sets = cfg.date_sets()
    polygons = read_polygons(cfg.polygons, cfg.id_column, cfg.layer, cfg.polygons_crs)
    log.info("%d plants from %s", len(polygons), cfg.polygons)
    table, report = extract_stats(polygons, sets, cfg.stats, cfg.percentiles, cfg.mode, nodata=cfg.nodata,
                                  layout=cfg.layout, on_progress=on_progress)
    if on_progress is not None:
        on_progress(1.0, "writing files")
    written = write_outputs(polygons, table, report, out, write_polygons=cfg.write_polygons)
    if cfg.compare.polygons is not None:
        written.update(run_comparison(cfg, polygons, table, sets, out))
    return polygons, table, report, written


def run(cfg: StatsConfig) -> dict:
    polygons, _, report, written = extract_and_write(cfg)
    for key, path in written.items():
        log.info("%-14s %s", key, path)
    return {"plants": len(polygons), "outputs": {k: str(v) for k, v in written.items()}, "report": report}
