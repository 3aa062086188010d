"""Later dates: how far a date's CHM is shifted against an earlier date's (two flights georeferenced apart).

Plants move a few centimetres between flights (``canopy.max_shift`` covers that); a flight georeferenced
without GCPs is off by metres, and every reused box then sits on soil or on a neighbour. The offset is
measured by normalised cross-correlation of the two CHMs: square windows around up to a dozen plants
spread over the field, each ``TEMPLATE`` wide, are sampled on a map-aligned grid (``resolution``: at most
80 cells across the search radius) from the earlier CHM while it is open (:func:`templates`); the later
CHM is sampled over the same windows widened by the search radius, and the correlation surfaces of all
windows are averaged (:func:`measure_offset`). One window of a regular stand correlates almost as well one
row or one plant off; the sum over windows with their own gaps and heights does not. The peak is refined to
a fraction of a cell (a parabola through its neighbours).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage as ndi

MAX_WINDOWS = 12
SEARCH_M = 3.0  # m: offsets searched (GNSS-only georeferencing is off by 1-3 m); at least 3 x max_shift
TEMPLATE_M = 1.5  # m: half the side of a window, at least 4 plant boxes


@dataclass
class Templates:
    """Windows of the earlier CHM: ``centres`` (k, 2) map x, y, ``half`` (m), ``data`` (k, n, n) on cells of
    ``resolution`` m, and the search radius they were made for."""

    centres: np.ndarray
    half: float
    resolution: float
    search: float
    data: np.ndarray


@dataclass
class Offset:
    """The later CHM's shift against the earlier one (m, map x and y: a plant at (x, y) on the earlier date is
    at (x + dx, y + dy) on the later); ``score``: the mean correlation at the peak, ``near``: the best within
    ``max_shift`` of no shift."""

    dx: float = 0.0
    dy: float = 0.0
    score: float = np.nan
    near: float = np.nan
    windows: int = 0

    @property
    def distance(self) -> float:
        """The offset's length (m)."""
        return float(np.hypot(self.dx, self.dy))

    def report(self) -> dict:
        """The offset for the JSON report: dx, dy and distance in m, rounded to the mm."""
        return {
            "dx": round(self.dx, 3),
            "dy": round(self.dy, 3),
            "distance": round(self.distance, 3),
            "correlation": round(float(self.score), 3),
            "correlation_near_zero": round(float(self.near), 3),
            "windows": self.windows,
        }


def _res(chm) -> float:
    t = chm.transform
    return float(np.sqrt(abs(t.a * t.e - t.b * t.d)))


def _sample(chm, x0: float, y1: float, n: int, r: float) -> np.ndarray:
    """The CHM on an ``n`` x ``n`` grid of cells of ``r`` m whose top-left corner is (x0, y1): the window read
    and averaged in blocks of about a cell, then interpolated at the cell centres; NaN and outside the raster
    are 0 (ground)."""
    inv = ~chm.transform
    cx = x0 + (np.arange(n) + 0.5) * r
    cy = y1 - (np.arange(n) + 0.5) * r
    cols, rows = inv @ (np.array([cx[0], cx[-1], cx[0], cx[-1]]), np.array([cy[0], cy[0], cy[-1], cy[-1]]))
    f = max(1, round(r / _res(chm)))
    R0 = int(max(0, np.floor(rows.min()) - f))
    R1 = int(min(chm.height, np.ceil(rows.max()) + f + 1))
    C0 = int(max(0, np.floor(cols.min()) - f))
    C1 = int(min(chm.width, np.ceil(cols.max()) + f + 1))
    if R1 <= R0 or C1 <= C0:
        return np.zeros((n, n))
    W = np.nan_to_num(np.asarray(chm.read(R0, R1, C0, C1), dtype=float), nan=0.0)
    if f > 1:  # cell means (blocks of f x f pixels): cheaper than a moving average at full resolution
        h, w = (W.shape[0] // f) * f, (W.shape[1] // f) * f
        if h == 0 or w == 0:
            return np.zeros((n, n))
        W = W[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    gx, gy = np.meshgrid(cx, cy)
    pc, pr = inv @ (gx.ravel(), gy.ravel())
    out = ndi.map_coordinates(W, [(pr - R0) / f - 0.5, (pc - C0) / f - 0.5], order=1, mode="constant", cval=0.0)
    return out.reshape(n, n)


def templates(chm, geoms, max_shift: float, max_windows: int = MAX_WINDOWS) -> Templates | None:
    """Windows of the earlier CHM around plants spread over the field (module doc); None without plants."""
    b = shapely.bounds(np.asarray(geoms, dtype=object))
    b = b[np.isfinite(b).all(axis=1)]
    if not len(b):
        return None
    search = max(SEARCH_M, 3 * max_shift)
    r = max(_res(chm), search / 80)
    size = float(np.median(np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])))
    half = max(TEMPLATE_M, 4 * size)
    centre = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], axis=1)
    order = np.lexsort((centre[:, 0], -centre[:, 1]))  # north to south, then west to east
    # no more windows than it takes to cover the raster once (on a small field each window holds most of it)
    res = _res(chm)
    k_max = int(np.clip(np.ceil(chm.height * chm.width * res * res / (2 * (half + search)) ** 2), 4, max_windows))
    picks = order[np.unique(np.linspace(0, len(order) - 1, k_max).round().astype(int))]
    n = round(2 * half / r)
    data = np.stack([_sample(chm, x - half, y + half, n, r) for x, y in centre[picks]])
    return Templates(centres=centre[picks], half=half, resolution=r, search=search, data=data)


def _box_sums(a: np.ndarray, n: int) -> np.ndarray:
    """Sums over every n x n window of ``a`` (an integral image)."""
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = a.cumsum(0).cumsum(1)
    return c[n:, n:] - c[:-n, n:] - c[n:, :-n] + c[:-n, :-n]


def _parabola(c_minus: float, c0: float, c_plus: float) -> float:
    d = c_minus - 2 * c0 + c_plus
    return 0.0 if d >= 0 else float(np.clip(0.5 * (c_minus - c_plus) / d, -0.5, 0.5))


def measure_offset(t: Templates, chm, max_shift: float) -> Offset:
    """The later CHM's offset against the templates of the earlier one (module doc)."""
    # on demand: scipy.signal pulls scipy.stats, ~2.5 s of CPU at every start of module 9; only later dates
    # need it
    from scipy.signal import fftconvolve

    r, half = t.resolution, t.half
    s = int(np.ceil(t.search / r))
    n = t.data.shape[1]
    total = np.zeros((2 * s + 1, 2 * s + 1))
    used = 0
    for (x, y), a in zip(t.centres, t.data):
        a = a - a.mean()
        norm_a = np.sqrt((a * a).sum())
        if norm_a < 1e-6:  # no plant in the window
            continue
        big = _sample(chm, x - half - s * r, y + half + s * r, n + 2 * s, r)
        # Pearson correlation at every offset: sums over the template's footprint by FFT
        num = fftconvolve(big, a[::-1, ::-1], mode="valid")
        s1, s2 = _box_sums(big, n), _box_sums(big * big, n)
        var_b = np.maximum(s2 - s1 * s1 / (n * n), 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            ncc = np.where(var_b > 1e-9, num / (norm_a * np.sqrt(var_b)), 0.0)
        total += ncc
        used += 1
    if not used:
        return Offset()
    total /= used
    i, j = np.unravel_index(int(np.argmax(total)), total.shape)
    di = _parabola(total[i - 1, j], total[i, j], total[i + 1, j]) if 0 < i < 2 * s else 0.0
    dj = _parabola(total[i, j - 1], total[i, j], total[i, j + 1]) if 0 < j < 2 * s else 0.0
    # the big window's cell (i, j) is the template moved by (j - s) cells east and (i - s) cells south
    dx, dy = (j + dj - s) * r, -(i + di - s) * r
    ii, jj = np.mgrid[-s : s + 1, -s : s + 1]
    near = np.hypot(ii, jj) * r <= max_shift + r
    return Offset(dx=float(dx), dy=float(dy), score=float(total[i, j]), near=float(total[near].max()), windows=used)
