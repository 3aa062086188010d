"""Module 9's plots: plant rows to plot rows - the plot table, where the plots are, crop rows within a plot,
the field figure, field books, and the ``plots`` settings section. The names below are the role's face: code
outside this folder imports them from here, not from the files."""

from matchplant.spatial_stat_extractor.plots.config import PlotsConfig
from matchplant.spatial_stat_extractor.plots.fieldbook import join_field_book
from matchplant.spatial_stat_extractor.plots.figure import colour_norm, describe, draw_field, field_figure, unit_of
from matchplant.spatial_stat_extractor.plots.layout import check_plot_file, join_plants, plot_grid, read_plots
from matchplant.spatial_stat_extractor.plots.table import (
    plot_raster_stats,
    plot_table,
    plots_wanted,
    row_directions,
    run_plots,
)

__all__ = [
    "PlotsConfig",
    "check_plot_file",
    "colour_norm",
    "describe",
    "draw_field",
    "field_figure",
    "join_field_book",
    "join_plants",
    "plot_grid",
    "plot_raster_stats",
    "plot_table",
    "plots_wanted",
    "read_plots",
    "row_directions",
    "run_plots",
    "unit_of",
]
