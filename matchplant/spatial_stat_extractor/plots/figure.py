"""``plots.png``: the field coloured by a plot column, with the plants and the gaps.

Made to stay readable on any field: the colour bar names its unit and keeps a single value (one plot,
or plots all alike) mid-scale instead of at its minimum; a few ticks in plain metres, the x labels
slanted so that long map coordinates do not run into each other on a small extent; the gap markers sized
from the seed spacing on the page, thin and half transparent, so that they never hide the plots.
"""

from __future__ import annotations

import re
from pathlib import Path
from textwrap import fill
from typing import TYPE_CHECKING

import geopandas as gpd
import numpy as np
import pandas as pd

from matchplant.core.runtime.gui import close, figure
from matchplant.core.runtime.io import atomic_path

if TYPE_CHECKING:
    from matplotlib.colors import Normalize

UNITS = (
    (r"^(stand_count|expected|gaps|unclaimed|low_boxes)$", "plants"),
    (r"^canopy_cover$", "share of the plot area"),
    (r"_cv(_|$)", "coefficient of variation"),
    (r"area_m2", "m²"),
    (r"volume_m3", "m³"),
    (r"(^|_)(chm|height)|_m(_|$)", "m"),
    (r"(^|_)(ndvi|ndre|gndvi|exg|exgr|vari|gli|ngrdi|savi|evi|lai)(_|$)", "index, no unit"),
)


# the figure's marks, named once: drawn with these and described with them (``field_caption``, which the demo's
# report prints under the figure)
PLANT_COLOUR, GAP_COLOUR = "black", "red"
# how a column's words read in a title: indices and rasters in capitals, percentiles as P95
WORDS = {
    **{w: w.upper() for w in ("ndvi", "ndre", "gndvi", "vari", "gli", "ngrdi", "savi", "evi", "lai", "chm", "dsm")},
    "exg": "ExG",
    "exgr": "ExGR",
    "sd": "SD",
    "cv": "CV",
    "m2": "m²",
    "m3": "m³",
}
PLOT_AGGREGATES = {"mean": "mean", "sd": "SD", "cv": "coefficient of variation"}
PLANT_STATISTIC = r"(mean|max|min|median|sd|std|cv|sum|count|p\d+|area_m2|volume_m3|height|cover)"


def _words(name: str) -> str:
    return " ".join(WORDS.get(w, w.upper() if re.fullmatch(r"p\d+", w) else w) for w in name.split("_") if w)


def describe(column: str) -> str:
    """A plot column in words: ``ndvi_canopy_mean_mean`` -> "plot mean of the plants' NDVI canopy mean"."""
    name = re.sub(r"^plot_", "", column)
    m = re.fullmatch(rf"(.+_{PLANT_STATISTIC})_(mean|sd|cv)", name)
    if m:  # a plant column summarised per plot (plots.traits)
        return f"plot {PLOT_AGGREGATES[m[3]]} of the plants' {_words(m[1])}"
    return _words(name)


def field_caption(column: str) -> str:
    """What ``plots.png`` shows, in the words and colours it is drawn with."""
    return (
        f"plots coloured by the {describe(column)} ({unit_of(column)}); {PLANT_COLOUR} dots: plants, "
        f"{GAP_COLOUR} crosses: gaps"
    )


def unit_of(column: str) -> str:
    """The unit of a plot column, from its name ('' when it cannot be told: a raw band)."""
    name = re.sub(r"^plot_", "", column)
    return next((u for pattern, u in UNITS if re.search(pattern, name)), "raster value")


def colour_norm(values: pd.Series) -> Normalize:
    """The colour scale of the plot values; a single value sits in the middle of a small range."""
    from matplotlib.colors import Normalize  # matplotlib on first use, as core.runtime.gui (a run without
    # plots, or a box-statistics run, does not pay for its import: issue 30)

    v = values.to_numpy(float)
    lo, hi = np.nanmin(v), np.nanmax(v)
    if not hi > lo:
        pad = max(abs(lo) * 0.05, 1e-3) if np.isfinite(lo) else 1.0
        lo, hi = lo - pad, hi + pad
    return Normalize(vmin=lo, vmax=hi)


def field_figure(
    plots: gpd.GeoDataFrame, pts: np.ndarray, gaps: pd.DataFrame, column: str, path: Path, spacing: float = 0.2
) -> Path:
    """Draw the field's plots coloured by ``column``, with the plants and the gaps, into ``path`` (PNG)."""
    # "compressed": the constrained layout made for an equal-aspect axes beside a colour bar (the plain one
    # placed the y label out of the figure)
    fig = figure(headless=True, figsize=(8, 7), layout="compressed")
    try:
        draw_field(fig, plots, pts, gaps, column, spacing)
        with atomic_path(path) as tmp:
            # the caption travels in the PNG (its Description), for the demo's report to print as it is
            fig.savefig(tmp, dpi=120, format="png", metadata={"Description": field_caption(column)})
    finally:
        close(fig)
    return Path(path)


def draw_field(fig, plots: gpd.GeoDataFrame, pts: np.ndarray, gaps: pd.DataFrame, column: str, spacing: float):
    """The figure's one axes (returned) drawn on ``fig``."""
    ax = fig.add_subplot(1, 1, 1)
    if column in plots.columns and plots[column].notna().any():
        unit = unit_of(column)
        plots.plot(
            column=column,
            ax=ax,
            cmap="viridis",
            norm=colour_norm(plots[column]),
            edgecolor="white",
            linewidth=0.6,
            legend=True,
            legend_kwds={"label": f"{column} ({unit})", "shrink": 0.7},
        )
    else:
        plots.plot(ax=ax, color="lightgrey", edgecolor="white")
    if len(pts):
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=1.5, color=PLANT_COLOUR, label="plants", zorder=2)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    from matplotlib.ticker import MaxNLocator  # on first use (see colour_norm)

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=4, min_n_ticks=2))
    ax.tick_params(axis="x", labelrotation=30)
    crs = plots.crs.to_string() if plots.crs is not None else "map units"
    ax.set_xlabel(f"x (m, {crs})")
    ax.set_ylabel("y (m)")
    if len(gaps):
        # the scale on the page (an equal-aspect axes takes at most ~70 % of the figure's width or height),
        # to size the gap markers from the seed spacing without drawing the figure twice
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        w, h = fig.get_size_inches()
        points_per_m = 72.0 * min(0.7 * w / max(x1 - x0, 1e-9), 0.7 * h / max(y1 - y0, 1e-9))
        ms = float(np.clip(0.6 * spacing * points_per_m, 1.0, 5.0))
        ax.plot(gaps["x"], gaps["y"], "x", ms=ms, mew=0.7, alpha=0.7, color=GAP_COLOUR, label="gaps", zorder=3)
    if len(plots) <= 200:
        for pid, g in zip(plots["plot_id"], plots.geometry.values):
            c = g.representative_point()
            ax.annotate(
                str(pid),
                (c.x, c.y),
                fontsize=6,
                ha="center",
                va="center",
                color="white",
                bbox={"boxstyle": "round,pad=0.1", "fc": "black", "alpha": 0.35, "lw": 0},
            )
    ax.set_title(fill(field_caption(column)[0].upper() + field_caption(column)[1:], 70), fontsize=10)
    ax.legend(loc="upper right", fontsize=7)
    return ax
