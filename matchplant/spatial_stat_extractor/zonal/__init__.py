"""Module 9's statistics engine: exact zonal statistics of polygons over rasters, the statistics' names, runs per
group, the per-plant table. The names below are the role's face: code outside this folder imports them from here.

The settings use only the statistics' names (``names.py``), which need none of the engine (tests/test_layers.py)."""

from matchplant.spatial_stat_extractor.zonal.engine import zonal_stats
from matchplant.spatial_stat_extractor.zonal.names import BASIC_STATS, DEFAULT_STATS, MODES, percentile_name
from matchplant.spatial_stat_extractor.zonal.runs import LARGE_GROUP, quantiles, ranges
from matchplant.spatial_stat_extractor.zonal.table import extract_stats, polygons_in, write_csv

__all__ = [
    "BASIC_STATS",
    "DEFAULT_STATS",
    "LARGE_GROUP",
    "MODES",
    "extract_stats",
    "percentile_name",
    "polygons_in",
    "quantiles",
    "ranges",
    "write_csv",
    "zonal_stats",
]
