"""Module 9's canopy part: each plant's outline on the CHM, the ground's noise and thresholds, later dates,
statistics over the canopy pixels only, and the strips that keep a whole field within ``max_memory``. The names
below are the role's face: code outside this folder imports them from here, not from the files."""

from matchplant.spatial_stat_extractor.canopy.dates import measure_offset, templates
from matchplant.spatial_stat_extractor.canopy.ground import (
    GroundSample,
    Thresholds,
    check_chm,
    measure_ground,
    thresholds,
)
from matchplant.spatial_stat_extractor.canopy.memory import (
    DEFAULT_MAX_MEMORY,
    DEFAULT_MEMORY,
    gdal_cache_bytes,
    memory_report,
    memory_stage,
    parse_memory,
)
from matchplant.spatial_stat_extractor.canopy.outlines import Outlines, SegmentSettings
from matchplant.spatial_stat_extractor.canopy.segmentation import segment
from matchplant.spatial_stat_extractor.canopy.stats import canopy_stats, grouped_stats
from matchplant.spatial_stat_extractor.canopy.strips import Measure, outline_field

__all__ = [
    "DEFAULT_MAX_MEMORY",
    "DEFAULT_MEMORY",
    "GroundSample",
    "Measure",
    "Outlines",
    "SegmentSettings",
    "Thresholds",
    "canopy_stats",
    "check_chm",
    "gdal_cache_bytes",
    "grouped_stats",
    "measure_ground",
    "measure_offset",
    "memory_report",
    "memory_stage",
    "outline_field",
    "parse_memory",
    "segment",
    "templates",
    "thresholds",
]
