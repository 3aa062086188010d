"""Plots: plant rows to plot rows (docs/DESIGN.md §7).

Plot outlines come from a GIS file (any polygon file module 9 reads, plot id in ``plots.id_column``) or a
grid built from the field's corners, the numbers of plot columns (across the crop rows) and ranges
(along them) and the plot size. Each plant (its top where it was outlined, else its polygon's centre)
joins the plot it stands in. Per plot:

* stand count: the plants in the plot, leaving out second boxes of one plant (``outline_flag``
  ``duplicate``), boxes with no CHM under them (``no_top``), and boxes whose top stays below
  ``canopy.min_top`` (``low``: a weed, soil, or a plant too small for the CHM) or is no local maximum
  (``no_peak``: a box on leaves or between plants), which ``low_boxes`` counts; with
  ``plots.count_unclaimed``, plus the canopies on the CHM that no box claims but that look like plants
  (``unclaimed``: plants the detector missed);
* expected plants and gaps: seeds lie every ``plant_spacing`` along each of the plot's
  ``rows_per_plot`` rows; the sowing phase is estimated from the plants themselves (circular mean of
  their positions modulo the spacing), each plant takes its nearest seed position, and every position
  of the plot left without a plant is a gap (listed with its position in ``plot_gaps.csv``);
* in-row spacing: mean and coefficient of variation of the distances between neighbours in a row;
* canopy cover: the plants' canopy area over the plot's area;
* mean, SD and CV of each trait; and the field book's columns (genotype, rep, ...).

Direction of the rows: the grid's second axis (first corner to last corner), or for plot polygons the
long side of each plot's minimum rotated rectangle. Outputs: ``plots.gpkg`` and ``plots.csv`` (one row
per plot), ``plot_gaps.csv``, ``plots.png`` (the field coloured by a trait).
"""

from __future__ import annotations

import re
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.formats.vectors import write_vector
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.gui import close, figure
from matchplant.core.runtime.io import atomic_path
from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.extract import write_csv
from matchplant.spatial_stat_extractor.plots_config import PlotsConfig
from matchplant.spatial_stat_extractor.polygons import read_polygons

log = get_logger("spatial_stat_extractor")
DEFAULT_TRAITS = re.compile(r"^(chm_max|chm_canopy_p95|canopy_area_m2|(?!chm)\w+_canopy_mean)(_.*)?$")


def plots_wanted(cfg: PlotsConfig) -> bool:
    return cfg.polygons is not None or bool(cfg.corners)


def plot_grid(cfg: PlotsConfig, crs=None) -> gpd.GeoDataFrame:
    """Plot rectangles from the corners: corner 1 -> corner 2 spans the columns, corner 1 -> the last
    corner spans the ranges (a parallelogram); plots of ``plot_width`` x ``plot_length`` centred in their
    cells (0 = the whole cell)."""
    c = np.asarray(cfg.corners, dtype=float)
    if c.ndim != 2 or c.shape[1] != 2 or len(c) not in (3, 4) or cfg.columns < 1 or cfg.ranges < 1:
        raise ConfigError("plots.corners needs 3 or 4 [x, y] corners, and plots.columns and plots.ranges at "
                          "least 1", fix="e.g. corners: [[x1, y1], [x2, y2], [x3, y3], [x4, y4]], columns: 9, "
                                         "ranges: 7")
    a, across, along = c[0], c[1] - c[0], c[-1] - c[0]
    cw, cl = np.linalg.norm(across) / cfg.columns, np.linalg.norm(along) / cfg.ranges
    u, v = across / np.linalg.norm(across), along / np.linalg.norm(along)
    pw, pl = (cfg.plot_width or cw), (cfg.plot_length or cl)
    rng, col = np.divmod(np.arange(cfg.columns * cfg.ranges), cfg.columns)
    if cfg.serpentine:
        col = np.where(rng % 2 == 1, cfg.columns - 1 - col, col)
    centre = a + np.outer(col + 0.5, across / cfg.columns) + np.outer(rng + 0.5, along / cfg.ranges)
    corners = np.stack([centre + s1 * pw / 2 * u + s2 * pl / 2 * v
                        for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))], axis=1)
    geoms = shapely.polygons(corners)
    if cw < pw - 1e-9 or cl < pl - 1e-9:
        log.warning("plot size %.2f x %.2f m is larger than the grid cell %.2f x %.2f m: plots overlap",
                    pw, pl, cw, cl)
    return gpd.GeoDataFrame({"plot_id": np.arange(1, len(geoms) + 1), "range": rng + 1, "column": col + 1,
                             "row_dir_x": v[0], "row_dir_y": v[1]}, geometry=geoms, crs=crs)


def read_plots(cfg: PlotsConfig, crs=None) -> gpd.GeoDataFrame:
    if cfg.polygons is None:
        return plot_grid(cfg, crs)
    g = read_polygons(cfg.polygons, cfg.id_column)  # (the id column comes back as plant_id)
    g = g.drop(columns=[c for c in ("plot_id", cfg.id_column) if c in g.columns and c != "plant_id"])
    g = g.rename(columns={"plant_id": "plot_id"})
    if g.crs is None and crs is not None:
        g = g.set_crs(crs)
    elif crs is not None and not g.crs.equals(crs):
        g = g.to_crs(crs)
    rect = shapely.oriented_envelope(g.geometry.values)
    xy = shapely.get_coordinates(rect).reshape(len(g), 5, 2)
    e1, e2 = xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 1]
    long = np.where((np.hypot(*e1.T) >= np.hypot(*e2.T))[:, None], e1, e2)
    long /= np.linalg.norm(long, axis=1, keepdims=True)
    return g.assign(row_dir_x=long[:, 0], row_dir_y=long[:, 1])


def _plant_points(table: pd.DataFrame) -> np.ndarray:
    """(n, 2) each plant's position: its (first date's) top, else its polygon's centre."""
    xs = [c for c in table.columns if c == "top_x" or c.startswith("top_x_")]
    x, y = table["x"].to_numpy(float), table["y"].to_numpy(float)
    if xs:
        tx, ty = table[xs[0]].to_numpy(float), table[xs[0].replace("top_x", "top_y")].to_numpy(float)
        ok = np.isfinite(tx) & np.isfinite(ty)
        x, y = np.where(ok, tx, x), np.where(ok, ty, y)
    return np.stack([x, y], axis=1)


def _row_positions(along: np.ndarray, across: np.ndarray, width: float, length: float, cfg: PlotsConfig):
    """Rows, seed positions and gaps of one plot from its plants' local coordinates."""
    sp, nrow = cfg.plant_spacing, cfg.rows_per_plot
    row = np.clip(np.floor(across / (width / nrow)), 0, nrow - 1).astype(int)
    if len(along):
        ang = 2 * np.pi * along / sp
        phase = (np.arctan2(np.sin(ang).mean(), np.cos(ang).mean()) / (2 * np.pi) * sp) % sp
    else:
        phase = sp / 2
    first = phase if phase > 1e-9 else sp
    n_slots = int(np.floor((length - first) / sp + 1e-6)) + 1 if length >= first else 0
    slot = np.clip(np.round((along - phase) / sp).astype(int), 0, max(n_slots - 1, 0))
    filled = np.zeros((nrow, max(n_slots, 1)), bool)
    filled[row, slot] = True
    gaps = np.argwhere(~filled[:, :n_slots]) if n_slots else np.zeros((0, 2), int)
    spacing = np.concatenate([np.diff(np.sort(along[row == r])) for r in range(nrow)]) if len(along) else []
    return {"expected": nrow * n_slots, "gaps": gaps, "spacing": np.asarray(spacing, float), "phase": phase,
            "row_width": width / nrow}


def plot_table(plots: gpd.GeoDataFrame, table: pd.DataFrame, cfg: PlotsConfig, unclaimed: pd.DataFrame | None = None):
    """One row per plot (see the module doc) and the gaps (plot_id, row, x, y). ``unclaimed``: canopies no
    plant box claims (x, y), counted as plants with ``plots.count_unclaimed``."""
    pts = _plant_points(table)
    n_table = len(pts)
    if unclaimed is not None and cfg.count_unclaimed and len(unclaimed):
        pts = np.concatenate([pts, unclaimed[["x", "y"]].to_numpy(float)])
    tree = shapely.STRtree(plots.geometry.values)
    plant_i, plot_i = tree.query(shapely.points(pts), predicate="within")
    # a second box of one plant (same top), a box with no CHM or no top under it, is not a plant of the stand
    flags = next((table[c].fillna("").astype(str).to_numpy() for c in table.columns
                  if c == "outline_flag" or c.startswith("outline_flag_")), np.full(n_table, ""))
    flags = np.concatenate([flags, np.full(len(pts) - n_table, "")])
    real = ~np.isin(flags, ("duplicate", "no_top", "outside", "low", "no_peak"))
    low_i = plot_i[np.isin(flags[plant_i], ("low", "no_peak"))]
    plant_i, plot_i = plant_i[real[plant_i]], plot_i[real[plant_i]]
    traits = cfg.traits or [c for c in table.columns if DEFAULT_TRAITS.match(c)]
    missing = [t for t in traits if t not in table.columns]
    if missing:
        raise ConfigError(f"plots.traits {missing} are not columns of the plant table",
                          fix=f"choose from {[c for c in table.columns if c not in ('plant_id', 'x', 'y')]}")
    area_col = next((c for c in table.columns if c == "canopy_area_m2" or c.startswith("canopy_area_m2_")), None)
    rows, gap_rows = [], []
    for k, (pid, geom) in enumerate(zip(plots["plot_id"], plots.geometry.values)):
        v = np.array([plots["row_dir_x"].iloc[k], plots["row_dir_y"].iloc[k]])
        u = np.array([v[1], -v[0]])
        ring = shapely.get_coordinates(geom)[:-1]
        lu, lv = ring @ u, ring @ v
        if (lu.max() - lu.min()) <= 0 or (lv.max() - lv.min()) <= 0:
            continue
        origin_u, origin_v = lu.min(), lv.min()
        mine = plant_i[plot_i == k]
        p = pts[mine]
        along, across = p @ v - origin_v, p @ u - origin_u
        width, length = lu.max() - origin_u, lv.max() - origin_v
        r = _row_positions(along, across, width, length, cfg)
        sp = r["spacing"]
        in_table = mine[mine < n_table]
        rec = {"plot_id": pid, "stand_count": len(mine), "expected": r["expected"], "gaps": len(r["gaps"]),
               "unclaimed": int((mine >= n_table).sum()), "low_boxes": int((low_i == k).sum()),
               "spacing_mean_m": float(sp.mean()) if sp.size else np.nan,
               "spacing_cv": float(sp.std() / sp.mean()) if sp.size > 1 and sp.mean() > 0 else np.nan,
               "canopy_cover": float(np.nansum(table[area_col].to_numpy(float)[in_table]) / geom.area)
               if area_col else np.nan}
        for t in traits:
            vals = table[t].to_numpy(float)[in_table]
            vals = vals[np.isfinite(vals)]
            m = float(vals.mean()) if vals.size else np.nan
            sd = float(vals.std(ddof=1)) if vals.size > 1 else np.nan
            rec.update({f"{t}_mean": m, f"{t}_sd": sd, f"{t}_cv": sd / m if m else np.nan})
        rows.append(rec)
        for row, slot in r["gaps"]:
            a = origin_v + r["phase"] + slot * cfg.plant_spacing
            b = origin_u + (row + 0.5) * r["row_width"]
            xy = a * v + b * u
            gap_rows.append({"plot_id": pid, "row": int(row) + 1, "x": xy[0], "y": xy[1]})
    out = pd.DataFrame(rows)
    keep = [c for c in ("plot_id", "range", "column") if c in plots.columns]
    out = plots[keep].merge(out, on="plot_id", how="left")
    return out, pd.DataFrame(gap_rows, columns=["plot_id", "row", "x", "y"]), traits


def join_field_book(table: pd.DataFrame, path: Path, id_column: str) -> pd.DataFrame:
    book = pd.read_csv(path, sep=None, engine="python")
    if id_column not in book.columns:
        raise InputError(f"the field book has no '{id_column}' column; columns: {list(book.columns)}", path=path,
                         fix="set plots.id_column to its plot id column")
    if book[id_column].duplicated().any():
        raise InputError("plot ids repeat in the field book", path=path, fix="one row per plot")
    book = book.rename(columns={id_column: "plot_id"})
    unknown = set(book["plot_id"].astype(str)) - set(table["plot_id"].astype(str))
    if unknown:
        log.warning("%d field-book plots are not in the plot layout (e.g. %s)", len(unknown), sorted(unknown)[:3])
    table = table.assign(_key=table["plot_id"].astype(str))
    book = book.assign(_key=book["plot_id"].astype(str)).drop(columns="plot_id")
    return table.merge(book, on="_key", how="left").drop(columns="_key")


def field_figure(plots: gpd.GeoDataFrame, pts: np.ndarray, gaps: pd.DataFrame, trait: str, path: Path) -> Path:
    fig = figure(headless=True, figsize=(8, 7), constrained_layout=True)
    try:
        ax = fig.add_subplot(1, 1, 1)
        if trait in plots.columns and plots[trait].notna().any():
            plots.plot(column=trait, ax=ax, cmap="viridis", edgecolor="white", linewidth=0.6, legend=True,
                       legend_kwds={"label": f"{trait} (plot mean)", "shrink": 0.7})
        else:
            plots.plot(ax=ax, color="lightgrey", edgecolor="white")
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=1.5, color="black", label="plants")
        if len(gaps):
            ax.plot(gaps["x"], gaps["y"], "x", ms=4, color="red", label="gaps")
        for pid, g in zip(plots["plot_id"], plots.geometry.values):
            c = g.centroid
            ax.annotate(str(pid), (c.x, c.y), fontsize=6, ha="center", color="white")
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.set_title(f"plots: {trait} (plot mean), plants and gaps")
        ax.legend(loc="upper right", fontsize=7)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120, format="png")
    finally:
        close(fig)
    return Path(path)


def run_plots(cfg: PlotsConfig, table: pd.DataFrame, unclaimed: pd.DataFrame | None, polygons,
              out: Path) -> dict[str, Path]:
    """Per-plot table, gaps and figure in ``out`` (see the module doc)."""
    if cfg.plant_spacing <= 0:
        raise ConfigError("plots.plant_spacing must be positive", fix="set the seed spacing along the rows, m")
    plots = read_plots(cfg, polygons.crs)
    if "date" in table.columns:  # long layout: the plants of the first date
        table = table[table["date"] == table["date"].iloc[0]].reset_index(drop=True)
    per_plot, gaps, traits = plot_table(plots, table, cfg, unclaimed)
    if cfg.field_book is not None:
        per_plot = join_field_book(per_plot, Path(cfg.field_book), cfg.id_column)
    gdf = gpd.GeoDataFrame(per_plot, geometry=plots.set_index("plot_id").geometry.reindex(per_plot["plot_id"]).values,
                           crs=plots.crs)
    trait = cfg.figure_trait or (traits[0] if traits else "")
    col = f"{trait}_mean" if f"{trait}_mean" in gdf.columns else ("stand_count" if not trait else trait)
    log.info("%d plots: %d plants in plots, %d gaps", len(per_plot), int(per_plot["stand_count"].fillna(0).sum()),
             len(gaps))
    return {"plots_gpkg": write_vector(gdf, out / "plots.gpkg", layer="plots"),
            "plots_csv": write_csv(per_plot, out / "plots.csv"),
            "plot_gaps_csv": write_csv(gaps, out / "plot_gaps.csv"),
            "plots_figure": field_figure(gdf, _plant_points(table), gaps, col, out / "plots.png")}
