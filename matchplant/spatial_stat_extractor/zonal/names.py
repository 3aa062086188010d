"""The statistics' names: what module 9 can compute per plant, the pixel rules, the percentile columns.

Apart from the engine (:mod:`~matchplant.spatial_stat_extractor.zonal.engine`) so that the settings, which
list and check these names, do not import the engine to read them."""

BASIC_STATS = ("count", "min", "max", "mean", "median", "std", "sum", "nodata")
DEFAULT_STATS = ("count", "min", "max", "mean", "median", "std", "sum")
MODES = ("center", "coverage")


def percentile_name(q: float) -> str:
    """Column suffix of a percentile: 95 -> 'p95', 2.5 -> 'p2.5'."""
    return f"p{float(q):g}"
