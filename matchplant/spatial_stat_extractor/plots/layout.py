"""Where the plots are: a grid from the field's corners or a plot file, checked against the plants.

Checks that keep a plot table from being silently wrong: corners given as longitude/latitude degrees on a
projected map are reprojected (either axis order, whichever lands on the plants); plots that are the same
polygon (or mostly overlap) are refused, smaller overlaps are warned about with their ids and each plant
joins one plot only; a layout where most plots hold no plant (last year's corners, another field) is
refused naming the key.
"""

from __future__ import annotations

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely
from pyproj import CRS, Transformer

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.inputs import read_polygons
from matchplant.spatial_stat_extractor.plots.config import PlotsConfig
from matchplant.spatial_stat_extractor.plots.rows import bearing_to_vector, canonical

log = get_logger("spatial_stat_extractor")
SAME_PLOT = 0.5  # plots overlapping by this share of the smaller one are one plot given twice


def _source(cfg: PlotsConfig) -> tuple[str, str | None]:
    """(the key that sets the plots, its file) for messages."""
    return ("plots.polygons", str(cfg.polygons)) if cfg.polygons is not None else ("plots.corners", None)


def corners_in_map(cfg: PlotsConfig, crs, pts: np.ndarray | None) -> np.ndarray:
    """The grid's corners in the map CRS: as given, or reprojected from EPSG:4326 when they are degrees on
    a projected map (longitude, latitude or latitude, longitude, whichever lands on the plants)."""
    c = np.asarray(cfg.corners, dtype=float)
    if c.ndim != 2 or c.shape[1] != 2 or len(c) not in (3, 4) or cfg.columns < 1 or cfg.ranges < 1:
        raise ConfigError(
            "plots.corners needs 3 or 4 [x, y] corners, and plots.columns and plots.ranges at least 1",
            fix="e.g. corners: [[x1, y1], [x2, y2], [x3, y3], [x4, y4]], columns: 9, ranges: 7",
        )
    if crs is None or pts is None or not len(pts) or not CRS.from_user_input(crs).is_projected:
        return c
    degrees = (np.abs(c) <= 180).all() and ((np.abs(c[:, 1]) <= 90).all() or (np.abs(c[:, 0]) <= 90).all())
    centre = pts.mean(axis=0)
    if not degrees or np.hypot(*(c.mean(axis=0) - centre)) < 1000.0:
        return c
    to_map = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    best, best_d, best_order = None, np.inf, ""
    for order, (lon, lat) in (("longitude, latitude", (c[:, 0], c[:, 1])), ("latitude, longitude", (c[:, 1], c[:, 0]))):
        if (np.abs(lat) > 90).any():
            continue
        x, y = to_map.transform(lon, lat)
        xy = np.stack([x, y], axis=1)
        if not np.isfinite(xy).all():
            continue
        d = np.hypot(*(xy.mean(axis=0) - centre))
        if d < best_d:
            best, best_d, best_order = xy, d, order
    size = np.hypot(*(pts.max(axis=0) - pts.min(axis=0)))
    if best is None or best_d > size + np.hypot(*(best.max(axis=0) - best.min(axis=0))):
        raise ConfigError(
            f"plots.corners {c.tolist()[:2]}... look like degrees, but the map CRS is "
            f"{CRS.from_user_input(crs).to_string()} (metres) and even as longitude/latitude they "
            f"are not on the plants",
            fix="give the corners in the map CRS (the plants' x, y)",
        )
    log.warning(
        "plots.corners look like degrees (%s) while the map is in %s: reprojected from EPSG:4326 "
        "(give them in the map CRS to silence this)",
        best_order,
        CRS.from_user_input(crs).to_string(),
    )
    return best


def plot_grid(cfg: PlotsConfig, crs=None, pts: np.ndarray | None = None) -> gpd.GeoDataFrame:
    """Plot rectangles from the corners: corner 1 -> corner 2 spans the columns, corner 1 -> the last
    corner spans the ranges (a parallelogram); plots of ``plot_width`` x ``plot_length`` centred in their
    cells (0 = the whole cell). The rows run along the ranges' axis (``row_dir_x``, ``row_dir_y``)."""
    c = corners_in_map(cfg, crs, pts)
    a, across, along = c[0], c[1] - c[0], c[-1] - c[0]
    cw, cl = np.linalg.norm(across) / cfg.columns, np.linalg.norm(along) / cfg.ranges
    if cw <= 0 or cl <= 0:
        raise ConfigError(
            "plots.corners: the first, second and last corners must differ",
            fix="corner 1 = plot 1's outer corner, corner 2 = across the rows, last = along them",
        )
    u, v = across / np.linalg.norm(across), along / np.linalg.norm(along)
    if abs(u[0] * v[1] - u[1] * v[0]) < 0.05:
        raise ConfigError("plots.corners: the corners lie on one line", fix="give the field's corners in order")
    pw, pl = (cfg.plot_width or cw), (cfg.plot_length or cl)
    rng, col = np.divmod(np.arange(cfg.columns * cfg.ranges), cfg.columns)
    if cfg.serpentine:
        col = np.where(rng % 2 == 1, cfg.columns - 1 - col, col)
    centre = a + np.outer(col + 0.5, across / cfg.columns) + np.outer(rng + 0.5, along / cfg.ranges)
    corners = np.stack(
        [centre + s1 * pw / 2 * u + s2 * pl / 2 * v for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))], axis=1
    )
    geoms = shapely.polygons(corners)
    if cw < pw - 1e-9 or cl < pl - 1e-9:
        log.warning("plot size %.2f x %.2f m is larger than the grid cell %.2f x %.2f m: plots overlap", pw, pl, cw, cl)
    v = canonical(v)
    return gpd.GeoDataFrame(
        {
            "plot_id": np.arange(1, len(geoms) + 1),
            "range": rng + 1,
            "column": col + 1,
            "row_dir_x": v[0],
            "row_dir_y": v[1],
        },
        geometry=geoms,
        crs=crs,
    )


def _polygonal(geoms: np.ndarray, ids, path) -> np.ndarray:
    """Invalid plot polygons (a hand-drawn ring crossing itself) repaired to their polygonal parts."""
    bad = ~shapely.is_valid(geoms)
    if bad.any():
        fixed = shapely.make_valid(geoms[bad])
        parts = [
            shapely.multipolygons([p for p in shapely.get_parts(g) if shapely.get_type_id(p) == 3])
            if shapely.get_type_id(g) == 7
            else g
            for g in fixed
        ]
        geoms = geoms.copy()
        geoms[bad] = parts
        log.warning(
            "%d plot polygons were invalid (a ring crossing itself, e.g. plot ids %s in %s): repaired",
            int(bad.sum()),
            list(np.asarray(ids)[bad][:5]),
            path,
        )
    return geoms


def read_plots(cfg: PlotsConfig, crs=None, pts: np.ndarray | None = None) -> gpd.GeoDataFrame:
    """The plots with ``plot_id`` and, where known, their row direction (``row_dir_x``, ``row_dir_y``: from
    the file's own columns, as module 9 writes them, else from ``plots.row_direction``; NaN = from the plants)."""
    if cfg.polygons is None:
        return plot_grid(cfg, crs, pts)
    g = read_polygons(cfg.polygons, cfg.id_column)  # (the id column comes back as plant_id)
    g = g.drop(columns=[c for c in ("plot_id", cfg.id_column) if c in g.columns and c != "plant_id"])
    g = g.rename(columns={"plant_id": "plot_id"})
    if g.crs is None and crs is not None:
        g = g.set_crs(crs)
    elif crs is not None and not g.crs.equals(crs):
        log.info(
            "plots: %s is in %s, the plants in %s: reprojected",
            cfg.polygons,
            g.crs.to_string(),
            CRS.from_user_input(crs).to_string(),
        )
        g = g.to_crs(crs)
    g = g.set_geometry(_polygonal(np.asarray(g.geometry.values), g["plot_id"], cfg.polygons))
    own = file_row_directions(g, cfg)
    if cfg.row_direction is not None:
        given = bearing_to_vector(cfg.row_direction)
        if np.isfinite(own).all(axis=1).any():
            log.info("plots.row_direction = %g overrides the file's row_dir_x/row_dir_y", cfg.row_direction)
        own[:] = canonical(given)
    return g.assign(row_dir_x=own[:, 0], row_dir_y=own[:, 1])


ROW_DIR = ("row_dir_x", "row_dir_y")


def check_plot_file(cfg: PlotsConfig) -> None:
    """The plot file's errors that can be known before any work (:func:`file_row_directions`; warnings wait for
    the plots themselves)."""
    if cfg.polygons is not None:
        g = read_polygons(cfg.polygons, cfg.id_column).rename(columns={"plant_id": "plot_id"})
        file_row_directions(g, cfg, warn=False)


def file_row_directions(g: gpd.GeoDataFrame, cfg: PlotsConfig, warn: bool = True) -> np.ndarray:
    """(n, 2) each plot's row direction from the plot file's ``row_dir_x``/``row_dir_y`` columns (a unit vector,
    east and north), NaN where the file has none (empty: found from the plants). Values present but unusable
    (zero vectors, text, one column of the two) were ignored without a word: a warning naming the file, the
    columns and the plots; an error when every value given is unusable (and ``plots.row_direction`` is not set)."""
    n = len(g)
    own = np.full((n, 2), np.nan)
    have = [c for c in ROW_DIR if c in g.columns]
    if not have:
        return own
    raw = np.stack([pd.to_numeric(g[c], errors="coerce").to_numpy(float) for c in have], axis=1)
    filled = np.stack([g[c].notna().to_numpy() & (g[c].astype(str).str.strip() != "") for c in have], axis=1)
    given = filled.any(axis=1)
    if len(have) == 1:
        bad, why = given, f"only {have[0]} is in the file, not {({*ROW_DIR} - {*have}).pop()}"
    else:
        norm = np.hypot(raw[:, 0], raw[:, 1])
        good = np.isfinite(raw).all(axis=1) & (norm > 1e-6)
        own[good] = raw[good] / norm[good, None]  # a direction: its length does not matter
        bad = given & ~good
        kinds = {
            "text where a number belongs": (filled & ~np.isfinite(raw)).any(axis=1),
            "a zero vector": np.isfinite(raw).all(axis=1) & (norm <= 1e-6),
            "one component empty": filled.sum(axis=1) == 1,
        }
        why = ", ".join(f"{k} in {int((v & bad).sum())}" for k, v in kinds.items() if (v & bad).any())
    used = int(np.isfinite(own[:, 0]).sum())
    if not bad.any() or cfg.row_direction is not None:  # (plots.row_direction overrides the columns anyway)
        if used and cfg.row_direction is None and warn:
            log.info("plots: row direction of %d plots from the file's row_dir_x/row_dir_y columns", used)
        return own
    ids = g["plot_id"].to_numpy()[bad][:5].tolist()
    what = (
        f"plots.polygons {cfg.polygons}: the row direction columns {'/'.join(have)} of {int(bad.sum())} of {n} "
        f"plots cannot be used ({why}; e.g. plots {ids})"
    )
    fix = (
        "give each plot's row direction as a unit vector (row_dir_x east, row_dir_y north, e.g. 0 and 1 for rows "
        "running north), leave them empty (found from the plants), or set plots.row_direction (degrees from north)"
    )
    if not used:  # every value given is unusable: the file meant something no plot gets
        raise InputError(what, path=cfg.polygons, fix=fix)
    if warn:
        log.warning("%s: the row direction of those plots is found from their plants; %s", what, fix)
    return own


def check_overlaps(plots: gpd.GeoDataFrame, cfg: PlotsConfig) -> None:
    """Refuse plots given twice (or overlapping by more than half the smaller one); warn about smaller
    overlaps, naming the plot ids (their plants are each counted in one plot only)."""
    geoms = np.asarray(plots.geometry.values)
    i, j = shapely.STRtree(geoms).query(geoms, predicate="intersects")
    keep = i < j
    i, j = i[keep], j[keep]
    if not len(i):
        return
    share = shapely.area(shapely.intersection(geoms[i], geoms[j])) / np.minimum(
        shapely.area(geoms[i]), shapely.area(geoms[j])
    )
    ids = plots["plot_id"].to_numpy()
    key, path = _source(cfg)
    same = share >= SAME_PLOT
    if same.any():
        pairs = [f"{ids[a]} and {ids[b]} ({s:.0%})" for a, b, s in zip(i[same], j[same], share[same])][:5]
        raise InputError(
            f"{int(same.sum())} pairs of plots are the same plot or nearly (overlap of the smaller "
            f"one): plots {', '.join(pairs)}; their plants would be counted twice",
            path=path,
            fix=f"remove the duplicate plots from {key} (or correct their outlines)",
        )
    some = share > 1e-3
    if some.any():
        pairs = [f"{ids[a]}/{ids[b]} ({s:.0%})" for a, b, s in zip(i[some], j[some], share[some])][:5]
        log.warning(
            "%d pairs of plots overlap (e.g. plots %s of the smaller one); a plant in an overlap is "
            "counted once, in the plot whose centre is nearest",
            int(some.sum()),
            ", ".join(pairs),
        )


def join_plants(plots: gpd.GeoDataFrame, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(plant index, plot index) of each plant inside a plot; one plot per plant (the nearest centre)."""
    geoms = np.asarray(plots.geometry.values)
    plant_i, plot_i = shapely.STRtree(geoms).query(shapely.points(pts), predicate="within")
    if len(plant_i) and np.bincount(plant_i).max() > 1:
        c = shapely.get_coordinates(shapely.centroid(geoms))
        d = np.hypot(*(pts[plant_i] - c[plot_i]).T)
        order = np.lexsort((d, plant_i))
        first = np.r_[True, np.diff(plant_i[order]) != 0]
        plant_i, plot_i = plant_i[order][first], plot_i[order][first]
    return plant_i, plot_i


def check_plants_in_plots(plots: gpd.GeoDataFrame, pts: np.ndarray, plot_i: np.ndarray, cfg: PlotsConfig) -> None:
    """Refuse a layout where most plots hold no plant (the plots are elsewhere); warn about empty plots."""
    n = len(plots)
    held = np.bincount(plot_i, minlength=n) > 0
    if held.all() or not len(pts):
        return
    key, path = _source(cfg)
    empty = plots["plot_id"].to_numpy()[~held]
    if held.sum() <= n // 2:
        c_plots = shapely.get_coordinates(shapely.centroid(shapely.union_all(plots.geometry.values)))[0]
        off = pts.mean(axis=0) - c_plots
        raise InputError(
            f"{n - int(held.sum())} of the {n} plots hold no plant (e.g. plot ids "
            f"{list(empty[:5])}): the plots' centre is {np.hypot(*off):.1f} m from the plants' "
            f"(dx {off[0]:.1f}, dy {off[1]:.1f} m)",
            path=path,
            fix=f"check {key}: this season's corners, the map CRS of the plants, "
            f"{'plots.columns/ranges' if key == 'plots.corners' else 'the plot file'}",
        )
    log.warning(
        "%d of %d plots hold no plant (plot ids %s): counted with stand count 0", len(empty), n, list(empty[:10])
    )


def plants_outside(pts: np.ndarray, plant_i: np.ndarray) -> int:
    """How many plants stand in no plot (logged)."""
    outside = len(pts) - len(np.unique(plant_i))
    if outside:
        log.info("%d of %d plants stand in no plot", outside, len(pts))
    return outside
