"""The plots' settings (the ``plots`` section): where the plots are, how they were sown, what to report per plot
(docs/DESIGN.md §7)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError
from matchplant.spatial_stat_extractor.zonal import BASIC_STATS


@dataclass
class PlotsConfig:
    """Plots: plot outlines from a GIS file or a grid; stand count, gaps, spacing and trait summaries per plot."""

    polygons: Path | None = param(
        None,
        "plot outlines (GeoPackage, shapefile, GeoJSON, or CSV with WKT); empty = "
        "the grid below, or no plots when it is not set either",
        path="file",
    )
    id_column: str = param("plot_id", "plot id column of the plot file (or of the field book)")
    corners: list[list[float]] = param(
        [],
        "the grid's corners in the map CRS: [[x, y], ...] - plot 1's outer "
        "corner, the far end of the first range across the rows, then (optional) "
        "the two far corners; empty = no grid",
    )
    columns: int = param(0, "plots side by side across the crop rows", min=0)
    ranges: int = param(0, "plots one after another along the crop rows", min=0)
    plot_width: float = param(0.0, "m across the rows of one plot (0 = the grid cell, no alley)", min=0)
    plot_length: float = param(0.0, "m along the rows of one plot (0 = the grid cell, no alley)", min=0)
    serpentine: bool = param(False, "number plots back and forth (serpentine) instead of each range from the same side")
    row_direction: float | None = param(
        None,
        "bearing of the crop rows in degrees clockwise from map north "
        "(0 = rows run north-south, 90 = east-west); null = the grid's, the "
        "plot file's row_dir_x/row_dir_y columns, else from the plants",
        min=-360,
        max=360,
    )
    rows_per_plot: int = param(2, "crop rows in one plot", min=1)
    plant_spacing: float = param(
        0.2, "m between seeds along a row (expected spacing: gaps are counted from it)", min=0.001
    )
    count_unclaimed: bool = param(
        True,
        "count the canopies that no plant box claims (unclaimed_canopies.csv) "
        "that stand at a seed position no counted plant took: plants the "
        "detector missed",
    )
    field_book: Path | None = param(
        None,
        "CSV or .xlsx with one row per plot (plot id -> genotype, rep, ...), joined to the plot table",
        path="file",
    )
    field_book_id_column: str = param(
        "", "plot id column of the field book; '' = id_column (any case or spacing, or a usual name such as Plot)"
    )
    traits: list[str] = param(
        [],
        "plant columns summarised per plot (mean, sd, cv); empty = heights, canopy "
        "area and the canopy indices, or each raster's plant mean without a CHM",
    )
    raster_stats: list[str] = param(
        ["mean", "std", "median"],
        "statistics of every raster over each whole plot "
        "polygon (plot_<trait>_<stat>: plot mean NDVI, "
        "LAI, ...); [] = none",
        choices=BASIC_STATS,
    )
    figure_trait: str = param("", "trait colouring the field figure (plot mean); '' = the first of traits")

    def check(self) -> None:
        """Check the ``plots`` section's keys together (a plot file or a grid, a field book with plots)."""
        if self.field_book is not None and self.polygons is None and not self.corners:
            raise ConfigError(
                "plots.field_book is set but there are no plots to join it to",
                fix="set plots.polygons (a plot file) or plots.corners + columns + ranges (a grid)",
            )
        if self.corners and self.polygons is not None:
            raise ConfigError(
                "both plots.polygons and plots.corners are set", fix="keep one: the plot file, or the grid's corners"
            )
