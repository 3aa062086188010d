"""Crop rows inside a plot: which way they run, where each row starts and ends, and its seed positions.

The row direction of a plot comes from (in this order) the grid that built it (its second axis, kept in
``plots.gpkg`` as ``row_dir_x``/``row_dir_y``), the ``plots.row_direction`` key, or the plants themselves:
rows are the direction along which the plant centres, projected across it, pile up into a few narrow
lines (a Hough transform of the centres, one angle per half degree, refined by a pooled fit within the
rows). A plot's long side says nothing about its rows (wide plots of many short rows), so it is only the
last resort, with a warning, when the plants cannot tell (a square planting pattern).

Each row is the line at its offset across the plot, clipped by the plot polygon, so the seed positions
of a skewed (parallelogram) plot or a hand-drawn one stay inside it.
"""

from __future__ import annotations

import numpy as np
import shapely

from matchplant.core.runtime.log import get_logger

log = get_logger("spatial_stat_extractor")

COARSE = np.deg2rad(np.arange(0.0, 180.0, 0.5))
MIN_PLANTS = 6  # fewer plants in a plot: its direction is the field's consensus
AMBIGUOUS = 0.85  # the rows' score at 90 degrees reaches this share of the best: the plants cannot tell


def bearing_to_vector(degrees: float) -> np.ndarray:
    """Unit vector of a bearing in degrees clockwise from map north (the +y axis)."""
    a = np.deg2rad(degrees)
    return np.array([np.sin(a), np.cos(a)])


def _sharpness(p: np.ndarray, angles: np.ndarray, h: float) -> np.ndarray:
    """How narrowly the points pile up across each direction: the sum of squared counts of their
    projections on the direction's normal in bins of ``h`` (two bin phases, against edge effects)."""
    normals = np.stack([-np.sin(angles), np.cos(angles)])
    proj = p @ normals
    proj = proj - proj.min(axis=0)
    score = np.zeros(len(angles))
    for shift in (0.0, 0.5):
        idx = np.floor(proj / h + shift).astype(np.int64)
        nb = int(idx.max()) + 1
        counts = np.bincount((idx + np.arange(len(angles)) * nb).ravel(), minlength=nb * len(angles))
        score += (counts.reshape(len(angles), nb).astype(float) ** 2).sum(axis=1)
    return score


def _pooled_direction(p: np.ndarray, v: np.ndarray, geom, nrow: int) -> np.ndarray:
    """The direction refined by a least-squares fit of parallel lines: the points' principal axis after
    removing each row's mean (the plot's width across ``v`` split into its ``nrow`` rows)."""
    u = np.array([v[1], -v[0]])
    lu = shapely.get_coordinates(geom) @ u
    rw = max((lu.max() - lu.min()) / nrow, 1e-9)
    row = np.floor((p @ u - lu.min()) / rw).astype(int)
    q = p.copy()
    for r in np.unique(row):
        q[row == r] -= q[row == r].mean(axis=0)
    _, vec = np.linalg.eigh(q.T @ q)
    d = vec[:, -1]
    return d if d @ v >= 0 else -d


def direction_from_plants(p: np.ndarray, spacing: float, geom, nrow: int) -> tuple[np.ndarray | None, float]:
    """(unit row direction, clarity) from one plot's plant positions; (None, clarity) when they cannot tell.

    Clarity is the best score over the score 90 degrees away (below 1/AMBIGUOUS: unclear)."""
    if len(p) < MIN_PLANTS:
        return None, 0.0
    h = max(spacing / 4.0, 1e-3)
    s = _sharpness(p - p.mean(axis=0), COARSE, h)
    best = int(np.argmax(s))
    perp = s[(best + len(COARSE) // 2) % len(COARSE)]
    clarity = float(s[best] / perp) if perp > 0 else np.inf
    if clarity * AMBIGUOUS < 1.0:
        return None, clarity
    fine = COARSE[best] + np.deg2rad(np.arange(-0.5, 0.5001, 0.05))
    a = fine[int(np.argmax(_sharpness(p - p.mean(axis=0), fine, h)))]
    v = np.array([np.cos(a), np.sin(a)])
    return canonical(_pooled_direction(p, v, geom, nrow)), clarity


def canonical(v: np.ndarray) -> np.ndarray:
    """A direction's sign fixed (rows have no head): +y first, +x for east-west rows."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    return -v if (v[1] < -1e-12 or (abs(v[1]) <= 1e-12 and v[0] < 0)) else v


def long_side(geom) -> np.ndarray:
    """The direction of the long side of a polygon's minimum rotated rectangle."""
    xy = shapely.get_coordinates(shapely.oriented_envelope(geom))
    e1, e2 = xy[1] - xy[0], xy[2] - xy[1]
    e = e1 if np.hypot(*e1) >= np.hypot(*e2) else e2
    return canonical(e)


def row_segments(geom, v: np.ndarray, nrow: int):
    """The plot's rows along ``v``: (offset of the plot's edge across, row width, per row the start and end
    along ``v``); a row the polygon does not reach has start = end = NaN."""
    u = np.array([v[1], -v[0]])
    ring = shapely.get_coordinates(geom)
    lu, lv = ring @ u, ring @ v
    n0 = lu.min()
    rw = (lu.max() - n0) / nrow
    centres = n0 + (np.arange(nrow) + 0.5) * rw
    far0, far1 = lv.min() - 1.0, lv.max() + 1.0
    ends = np.stack([centres[:, None] * u + far0 * v, centres[:, None] * u + far1 * v], axis=1)
    segs = shapely.intersection(shapely.linestrings(ends), geom)
    start, end = np.full(nrow, np.nan), np.full(nrow, np.nan)
    for r, s in enumerate(segs):
        if not shapely.is_empty(s):
            a = shapely.get_coordinates(s) @ v
            start[r], end[r] = a.min(), a.max()
    return n0, rw, start, end


def _phase(offsets: np.ndarray, sp: float) -> tuple[float, float]:
    """Circular mean of positions modulo the spacing, and its strength (0..1)."""
    ang = 2 * np.pi * offsets / sp
    c, s = np.cos(ang).mean(), np.sin(ang).mean()
    return float((np.arctan2(s, c) / (2 * np.pi) * sp) % sp), float(np.hypot(c, s))


def seed_grid(along: np.ndarray, row: np.ndarray, start: np.ndarray, end: np.ndarray, sp: float) -> dict:
    """Seed positions of one plot. Seeds lie every ``sp`` along each row; the sowing phase is taken from the
    plants (positions ``along`` the rows, row index ``row``), either from each row's own start (a planter
    starting at a slanted edge) or from one line across the plot (seeds side by side), whichever the plants
    follow more closely. Returns per row the position of seed 0 (``base``), the first seed's number
    (``kmin``) and the number of seeds (``n_slots``)."""
    ok = np.isfinite(start)
    s0 = np.where(ok, start, 0.0)
    common = np.nanmin(start) if ok.any() else 0.0
    if len(along):
        ph_edge, r_edge = _phase(along - s0[row], sp)
        ph_line, r_line = _phase(along - common, sp)
        edge = r_edge >= r_line - 1e-9
        phase = ph_edge if edge else ph_line
    else:
        edge, phase = True, sp / 2
    base = np.where(edge, s0, common) + phase
    kmin = np.floor((s0 - base) / sp + 1e-9).astype(int) + 1
    kmax = np.floor((np.where(ok, end, 0.0) - base) / sp + 1e-6).astype(int)
    return {"base": base, "kmin": kmin, "n_slots": np.where(ok, np.maximum(kmax - kmin + 1, 0), 0)}


def seed_slot(along: np.ndarray, row: np.ndarray, grid: dict, sp: float) -> tuple[np.ndarray, np.ndarray]:
    """Each plant's nearest seed in its row (its number from the row's first seed; clipped to the row's
    seeds) and its offset along the row from that seed's position."""
    k = np.round((along - grid["base"][row]) / sp).astype(int)
    slot = np.clip(k - grid["kmin"][row], 0, np.maximum(grid["n_slots"][row] - 1, 0))
    return slot, along - (grid["base"][row] + (grid["kmin"][row] + slot) * sp)


def seed_layout(
    along: np.ndarray, row: np.ndarray, start: np.ndarray, end: np.ndarray, sp: float, grid: dict | None = None
) -> dict:
    """Seed positions (``grid``, else :func:`seed_grid` from these plants) and gaps of one plot: each plant
    takes its nearest seed, and every seed left without a plant is a gap.

    Returns expected count, the gaps (row, position along), the spacings between neighbours in a row."""
    nrow = len(start)
    g = grid or seed_grid(along, row, start, end, sp)
    n_slots = g["n_slots"]
    width = max(int(n_slots.max()) if nrow else 0, 1)
    filled = np.zeros((nrow, width), bool)
    if len(along):
        slot, _ = seed_slot(along, row, g, sp)
        has = n_slots[row] > 0
        filled[row[has], slot[has]] = True
    valid = np.arange(width)[None, :] < n_slots[:, None]
    gr, gs = np.nonzero(valid & ~filled)
    spacing = np.concatenate([np.diff(np.sort(along[row == r])) for r in range(nrow)]) if len(along) else []
    return {
        "expected": int(n_slots.sum()),
        "gap_row": gr,
        "gap_along": g["base"][gr] + (g["kmin"][gr] + gs) * sp,
        "spacing": np.asarray(spacing, float),
    }
