"""The plot table: plant rows to plot rows (docs/DESIGN.md §7).

Plot outlines come from a GIS file (any polygon file module 9 reads, plot id in ``plots.id_column``) or a
grid built from the field's corners, the numbers of plot columns (across the crop rows) and ranges
(along them) and the plot size (:mod:`~matchplant.spatial_stat_extractor.plots.layout`, with its checks:
degrees for corners, plots given twice or overlapping, plots holding no plant). Each plant (its top
where it was outlined, else its polygon's centre) joins the one plot it stands in. Per plot:

* stand count: the plants in the plot, leaving out second boxes of one plant (``outline_flag``
  ``duplicate``), boxes with no CHM under them (``no_top``), and boxes whose top stays below
  ``canopy.min_top`` (``low``: a weed, soil, or a plant too small for the CHM) or is no local maximum
  (``no_peak``: a box on leaves or between plants), which ``low_boxes`` counts; with
  ``plots.count_unclaimed``, plus the canopies on the CHM that no box claims and that stand at a seed
  position no counted plant took (``unclaimed``: plants the detector missed; :func:`at_free_seeds`);
* expected plants and gaps: seeds lie every ``plant_spacing`` along each of the plot's
  ``rows_per_plot`` rows, each row clipped by the plot polygon (:mod:`~matchplant.spatial_stat_extractor.plots.rows`:
  the row direction from the grid, ``plots.row_direction`` or the plants' own alignment); the sowing
  phase is estimated from the plants themselves (circular mean of their positions modulo the spacing),
  each plant takes its nearest seed position, and every position of the plot left without a plant is a
  gap (listed with its position in ``plot_gaps.csv``);
* in-row spacing: mean and coefficient of variation of the distances between neighbours in a row;
* canopy cover: the plants' canopy area over the plot's area;
* mean, SD and CV of each plant trait; statistics of every raster over the whole plot polygon
  (``plot_<trait>_<stat>``: plot mean NDVI, LAI, height); and the field book's columns
  (:mod:`~matchplant.spatial_stat_extractor.plots.fieldbook`).

Outputs: ``plots.gpkg`` (with each plot's row direction ``row_dir_x``/``row_dir_y``, so that the file
read back gives the same rows) and ``plots.csv`` (one row per plot), ``plot_gaps.csv``, ``plots.png``.
"""

from __future__ import annotations

import re
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd

from matchplant.core.formats.vectors import write_vector
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.plots.config import PlotsConfig
from matchplant.spatial_stat_extractor.plots.fieldbook import join_field_book
from matchplant.spatial_stat_extractor.plots.figure import field_figure
from matchplant.spatial_stat_extractor.plots.layout import (
    check_overlaps,
    check_plants_in_plots,
    join_plants,
    plants_outside,
    plot_grid,
    read_plots,
)
from matchplant.spatial_stat_extractor.plots.rows import (
    canonical,
    direction_from_plants,
    long_side,
    row_segments,
    seed_grid,
    seed_layout,
    seed_slot,
)
from matchplant.spatial_stat_extractor.zonal import extract_stats, write_csv

log = get_logger("spatial_stat_extractor")
DEFAULT_TRAITS = re.compile(r"^(chm_max|chm_canopy_p95|canopy_area_m2|(?!chm)\w+_canopy_mean)(_.*)?$")
PLANT_MEAN = re.compile(r"^(?P<t>\w+?)_mean(?P<d>_\w+)?$")
NOT_PLANTS = ("duplicate", "no_top", "outside", "low", "no_peak", "leaf")
MIN_LINE = 3  # plants in a row that place its line (their median across it); with fewer, the row's centre
REACH_SIGMAS = 4.0  # an unclaimed canopy stands at a seed within this many sigmas of the counted plants' scatter
MIN_REACH_PLANTS = 20  # counted plants needed to measure that scatter; with fewer, a quarter of the spacing
RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median distance of a 2-D normal scatter, in sigmas

__all__ = ["default_traits", "plot_grid", "plot_table", "plots_wanted", "read_plots", "run_plots"]


def plots_wanted(cfg: PlotsConfig) -> bool:
    """Whether the settings ask for plots (a plot file or a grid's corners)."""
    return cfg.polygons is not None or bool(cfg.corners)


def default_traits(columns) -> list[str]:
    """Heights, canopy area and canopy indices; and for a trait measured only over the plant polygon (no
    CHM, no canopy) its plant mean (``ndvi_mean``, ``lai_mean``), so that plots get traits without a CHM."""
    cols = list(columns)
    out = [c for c in cols if DEFAULT_TRAITS.match(c)]
    for c in cols:
        m = PLANT_MEAN.match(c)
        if (
            m
            and m["t"] != "chm"
            and not m["t"].endswith("_canopy")
            and "canopy" not in m["t"]
            and f"{m['t']}_canopy_mean{m['d'] or ''}" not in cols
            and c not in out
        ):
            out.append(c)
    return out


def _plant_points(table: pd.DataFrame) -> np.ndarray:
    """(n, 2) each plant's position: its (first date's) top, else its polygon's centre."""
    xs = [c for c in table.columns if c == "top_x" or c.startswith("top_x_")]
    x, y = table["x"].to_numpy(float), table["y"].to_numpy(float)
    if xs:
        tx, ty = table[xs[0]].to_numpy(float), table[xs[0].replace("top_x", "top_y")].to_numpy(float)
        ok = np.isfinite(tx) & np.isfinite(ty)
        x, y = np.where(ok, tx, x), np.where(ok, ty, y)
    return np.stack([x, y], axis=1)


def row_directions(
    plots: gpd.GeoDataFrame, pts: np.ndarray, plant_i: np.ndarray, plot_i: np.ndarray, cfg: PlotsConfig
) -> np.ndarray:
    """(n, 2) each plot's row direction: its own (grid, file columns, ``plots.row_direction``), else from
    its plants' alignment, else the field's consensus of those, else (with a warning) its long side."""
    v = (
        np.array(plots[["row_dir_x", "row_dir_y"]], dtype=float)
        if "row_dir_x" in plots.columns
        else np.full((len(plots), 2), np.nan)
    )
    todo = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if not len(todo):
        return v
    geoms = plots.geometry.values
    clear = []
    for k in todo:
        d, _ = direction_from_plants(pts[plant_i[plot_i == k]], cfg.plant_spacing, geoms[k], cfg.rows_per_plot)
        if d is not None:
            v[k] = d
            clear.append(k)
    bearings = np.degrees(np.arctan2(v[clear, 0], v[clear, 1])) % 180 if clear else np.array([])
    rest = [k for k in todo if k not in set(clear)]
    if clear:
        doubled = np.radians(bearings * 2)
        mean = np.degrees(np.arctan2(np.sin(doubled).mean(), np.cos(doubled).mean())) / 2 % 180
        spread = (
            np.degrees(np.sqrt(-2 * np.log(min(np.hypot(np.sin(doubled).mean(), np.cos(doubled).mean()), 1.0)))) / 2
        )
        log.info(
            "row direction from the plants' alignment in %d plots: bearing %.1f deg (spread %.1f deg)%s",
            len(clear),
            mean,
            spread,
            f"; {len(rest)} plots with too few plants take it" if rest else "",
        )
        if rest:
            v[rest] = canonical(np.array([np.sin(np.radians(mean)), np.cos(np.radians(mean))]))
    elif rest:
        log.warning(
            "the row direction of %d plots cannot be told from the plants (too few, or in-row and "
            "across-row spacing alike): taken along each plot's long side; set plots.row_direction "
            "(degrees from north) if the rows run across",
            len(rest),
        )
        v[rest] = np.array([long_side(geoms[k]) for k in rest])
    return v


def _plot_rows(geom, v: np.ndarray, p: np.ndarray, nrow: int):
    """The plot's rows along ``v`` (:func:`row_segments`) and, for the points ``p``, each one's row and its
    position along and across the rows."""
    u = np.array([v[1], -v[0]])
    n0, rw, start, end = row_segments(geom, v, nrow)
    across = p @ u
    row = np.clip(np.floor((across - n0) / rw), 0, nrow - 1).astype(int) if rw > 0 else np.zeros(len(p), int)
    return n0, rw, start, end, row, p @ v, across


def at_free_seeds(
    plots: gpd.GeoDataFrame,
    dirs: np.ndarray,
    pts: np.ndarray,
    plant_i: np.ndarray,
    plot_i: np.ndarray,
    n_table: int,
    cfg: PlotsConfig,
) -> np.ndarray:
    """Which canopies no box claims (``pts`` from ``n_table`` on) count as plants: those standing at a seed
    position that no counted plant took, as near to it as the counted plants stand to theirs: they scatter
    round their seeds like a 2-D normal (sowing precision, the tops' position error) whose sigma follows
    from their median distance, and ``REACH_SIGMAS`` sigmas leave out one plant in 3,000 (the row's line is
    where its plants stand). A crop is sown in rows at a fixed spacing: the plant
    the detector missed stands at an empty seed, while the other canopies no box claims stand where no
    plant is expected: weeds between the rows, and a counted plant's leaf cut off by the thresholds, next
    to the seed that plant already took. One canopy per empty seed (the nearest)."""
    sp, nrow = cfg.plant_spacing, cfg.rows_per_plot
    seen, near = [], []
    for k, geom in enumerate(plots.geometry.values):
        mine = plant_i[plot_i == k]
        box = mine < n_table
        if box.all():
            continue
        n0, rw, start, end, row, along, across = _plot_rows(geom, dirs[k], pts[mine], nrow)
        grid = seed_grid(along[box], row[box], start, end, sp)
        slot, off = seed_slot(along, row, grid, sp)
        line = n0 + (np.arange(nrow) + 0.5) * rw
        for r in range(nrow):
            if (box & (row == r)).sum() >= MIN_LINE:
                line[r] = np.median(across[box & (row == r)])
        dist = np.hypot(off, across - line[row])
        dist[grid["n_slots"][row] == 0] = np.inf
        seen.append(dist[box])
        near.append((mine, box, row * (int(grid["n_slots"].max()) + 1) + slot, dist))
    seen = np.concatenate(seen) if seen else np.zeros(0)
    seen = seen[np.isfinite(seen)]
    sigma = float(np.median(seen)) / RAYLEIGH_MEDIAN if len(seen) >= MIN_REACH_PLANTS else sp / 4 / REACH_SIGMAS
    reach = min(REACH_SIGMAS * sigma, sp / 2)
    take = np.zeros(len(pts), bool)
    for mine, box, seed, dist in near:
        cand = np.flatnonzero(~box & ~np.isin(seed, seed[box]) & (dist <= reach))
        cand = cand[np.argsort(dist[cand], kind="stable")]
        take[mine[cand[np.unique(seed[cand], return_index=True)[1]]]] = True
    log.info(
        "plots: %d of %d canopies no box claims stand at an empty seed position (within %.3f m) and are "
        "counted as plants the detector missed",
        int(take.sum()),
        len(pts) - n_table,
        reach,
    )
    return take


def plot_table(plots: gpd.GeoDataFrame, table: pd.DataFrame, cfg: PlotsConfig, unclaimed: pd.DataFrame | None = None):
    """One row per plot (see the module doc) and the gaps (plot_id, row, x, y). ``unclaimed``: canopies no
    plant box claims (x, y), counted as plants with ``plots.count_unclaimed``."""
    pts = _plant_points(table)
    n_table = len(pts)
    if unclaimed is not None and cfg.count_unclaimed and len(unclaimed):
        pts = np.concatenate([pts, unclaimed[["x", "y"]].to_numpy(float)])
    check_overlaps(plots, cfg)
    plant_i, plot_i = join_plants(plots, pts)
    # a second box of one plant (same top), a box with no CHM or no top under it, is not a plant of the stand
    flags = next(
        (
            table[c].fillna("").astype(str).to_numpy()
            for c in table.columns
            if c == "outline_flag" or c.startswith("outline_flag_")
        ),
        np.full(n_table, ""),
    )
    flags = np.concatenate([flags, np.full(len(pts) - n_table, "")])
    real = ~np.isin(flags, NOT_PLANTS)
    low_i = plot_i[np.isin(flags[plant_i], ("low", "no_peak"))]
    plant_i, plot_i = plant_i[real[plant_i]], plot_i[real[plant_i]]
    check_plants_in_plots(plots, pts, plot_i, cfg)
    plants_outside(pts[real], plant_i)
    traits = cfg.traits or default_traits(table.columns)
    missing = [t for t in traits if t not in table.columns]
    if missing:
        raise ConfigError(
            f"plots.traits {missing} are not columns of the plant table",
            fix=f"choose from {[c for c in table.columns if c not in ('plant_id', 'x', 'y')]}",
        )
    area_col = next((c for c in table.columns if c == "canopy_area_m2" or c.startswith("canopy_area_m2_")), None)
    boxed = plant_i < n_table
    dirs = row_directions(plots, pts, plant_i[boxed], plot_i[boxed], cfg)
    if not boxed.all():
        keep = boxed | at_free_seeds(plots, dirs, pts, plant_i, plot_i, n_table, cfg)[plant_i]
        plant_i, plot_i = plant_i[keep], plot_i[keep]
    rows, gap_rows = [], []
    for k, (pid, geom) in enumerate(zip(plots["plot_id"], plots.geometry.values)):
        v = dirs[k]
        u = np.array([v[1], -v[0]])
        mine = plant_i[plot_i == k]
        n0, rw, start, end, row, along, _ = _plot_rows(geom, v, pts[mine], cfg.rows_per_plot)
        r = seed_layout(along, row, start, end, cfg.plant_spacing)
        sp = r["spacing"]
        in_table = mine[mine < n_table]
        rec = {
            "plot_id": pid,
            "stand_count": len(mine),
            "expected": r["expected"],
            "gaps": len(r["gap_row"]),
            "unclaimed": int((mine >= n_table).sum()),
            "low_boxes": int((low_i == k).sum()),
            "spacing_mean_m": float(sp.mean()) if sp.size else np.nan,
            "spacing_cv": float(sp.std() / sp.mean()) if sp.size > 1 and sp.mean() > 0 else np.nan,
            "canopy_cover": float(np.nansum(table[area_col].to_numpy(float)[in_table]) / geom.area)
            if area_col
            else np.nan,
            "row_dir_x": v[0],
            "row_dir_y": v[1],
        }
        for t in traits:
            vals = table[t].to_numpy(float)[in_table]
            vals = vals[np.isfinite(vals)]
            m = float(vals.mean()) if vals.size else np.nan
            sd = float(vals.std(ddof=1)) if vals.size > 1 else np.nan
            rec.update({f"{t}_mean": m, f"{t}_sd": sd, f"{t}_cv": sd / m if m else np.nan})
        rows.append(rec)
        b = n0 + (r["gap_row"] + 0.5) * rw
        xy = r["gap_along"][:, None] * v + b[:, None] * u
        gap_rows += [{"plot_id": pid, "row": int(g) + 1, "x": x, "y": y} for g, (x, y) in zip(r["gap_row"], xy)]
    out = pd.DataFrame(rows)
    keep = [c for c in ("plot_id", "range", "column") if c in plots.columns]
    out = plots[keep].merge(out, on="plot_id", how="left")
    return out, pd.DataFrame(gap_rows, columns=["plot_id", "row", "x", "y"]), traits


def plot_raster_stats(
    plots: gpd.GeoDataFrame, rasters, stats, percentiles=(), mode: str = "center", nodata: float | None = None
) -> pd.DataFrame:
    """Statistics of every raster of every date over each whole plot polygon: ``plot_id`` and
    ``plot_<trait>_<stat>[_<date>]`` (reprojected where a raster is in another CRS, as for the plants)."""
    g = gpd.GeoDataFrame({"plant_id": plots["plot_id"].to_numpy()}, geometry=plots.geometry.values, crs=plots.crs)
    table, _ = extract_stats(g, rasters, stats, percentiles, mode, nodata=nodata, layout="wide")
    table = table.drop(columns=["x", "y"]).rename(columns={"plant_id": "plot_id"})
    log.info("plots: %d raster statistics over each of the %d plot polygons", table.shape[1] - 1, len(plots))
    return table.rename(columns={c: f"plot_{c}" for c in table.columns if c != "plot_id"})


def run_plots(
    cfg: PlotsConfig,
    table: pd.DataFrame,
    unclaimed: pd.DataFrame | None,
    polygons,
    out: Path,
    rasters=(),
    mode: str = "center",
    nodata: float | None = None,
) -> dict[str, Path]:
    """Per-plot table, gaps and figure in ``out`` (see the module doc); ``rasters``: the date sets whose
    rasters are also summarised over each plot polygon (``plots.raster_stats``)."""
    if cfg.plant_spacing <= 0:
        raise ConfigError("plots.plant_spacing must be positive", fix="set the seed spacing along the rows, m")
    if "date" in table.columns:  # long layout: the plants of the first date
        table = table[table["date"] == table["date"].iloc[0]].reset_index(drop=True)
    plots = read_plots(cfg, polygons.crs, _plant_points(table))
    per_plot, gaps, traits = plot_table(plots, table, cfg, unclaimed)
    if cfg.raster_stats and len(rasters):
        per_plot = per_plot.merge(
            plot_raster_stats(plots, rasters, cfg.raster_stats, (), mode, nodata), on="plot_id", how="left"
        )
    if cfg.field_book is not None:
        per_plot = join_field_book(per_plot, Path(cfg.field_book), cfg.field_book_id_column or cfg.id_column)
    geoms = plots.set_index("plot_id").geometry.reindex(per_plot["plot_id"]).values
    gdf = gpd.GeoDataFrame(per_plot, geometry=geoms, crs=plots.crs)
    trait = cfg.figure_trait or (traits[0] if traits else "")
    col = f"{trait}_mean" if f"{trait}_mean" in gdf.columns else (trait if trait in gdf.columns else "stand_count")
    log.info(
        "%d plots: %d plants in plots, %d gaps", len(per_plot), int(per_plot["stand_count"].fillna(0).sum()), len(gaps)
    )
    return {
        "plots_gpkg": write_vector(gdf, out / "plots.gpkg", layer="plots"),
        "plots_csv": write_csv(per_plot, out / "plots.csv"),
        "plot_gaps_csv": write_csv(gaps, out / "plot_gaps.csv"),
        "plots_figure": field_figure(gdf, _plant_points(table), gaps, col, out / "plots.png", cfg.plant_spacing),
    }
