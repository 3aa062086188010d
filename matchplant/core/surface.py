"""A DSM (or any elevation raster) in memory: bilinear sampling with holes masked, and ray intersection.

Only the window that is needed is read from the file. Nodata (ODM writes -9999) and NaN are holes:
bilinear interpolation renormalises over the valid neighbours, so hole edges stay usable, and a ray that
meets the surface inside a hole is reported, not placed on an invented height.

The per-ray work (march until the first crossing, then refine) is a loop with an early exit, which numpy
cannot vectorise without evaluating every ray over the whole height range; it is compiled with numba,
and one bilinear rule (:func:`_bilinear`) serves both sampling and intersection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window, from_bounds
from scipy.ndimage import maximum_filter, minimum_filter

from matchplant.core.errors import InputError
from matchplant.core.log import get_logger

log = get_logger("surface")

HIT, NOT_DOWNWARD, OUTSIDE, NODATA, NO_HIT = 0, 1, 2, 3, 4
STATUS_TEXT = {
    HIT: "ok",
    NOT_DOWNWARD: "ray does not point towards the ground",
    OUTSIDE: "ray leaves the DSM before reaching the ground",
    NODATA: "ray meets the ground in a DSM nodata area",
    NO_HIT: "no intersection with the DSM (camera below the surface?)",
}
_REFINE_ITERATIONS = 60  # refinement steps at most
_REFINE_TOLERANCE = 1e-7  # metres (along the ray, and above the surface) at which refinement stops
_DIP_DEPTH = 64  # bisection stack of the search for thin crossings between two march samples
_BLOCK = 8  # cells per side of the blocks whose maxima let rays skip empty space
GROUND_CELL = 0.02  # metres: cell size (at least the DSM's) of the ground estimated from the DSM


def _max_tangent(d: np.ndarray) -> float:
    """Largest horizontal / vertical ratio of ray directions (N, 3)."""
    return float(np.max(np.hypot(d[:, 0], d[:, 1]) / np.maximum(-d[:, 2], 1e-12)))


@numba.njit(cache=True, nogil=True)
def _block_stats(data, block):
    """Lowest and highest valid cell of each ``block`` x ``block`` block (+inf / -inf when it has none) and
    whether it holds a hole: one pass over the raster."""
    rows, cols = data.shape
    br, bc = -(-rows // block), -(-cols // block)
    low = np.full((br, bc), np.inf, dtype=np.float32)
    high = np.full((br, bc), -np.inf, dtype=np.float32)
    hole = np.zeros((br, bc), dtype=np.bool_)
    for r in range(rows):
        for c in range(cols):
            v = data[r, c]
            i, j = r // block, c // block
            if math.isnan(v):
                hole[i, j] = True
            else:
                if v < low[i, j]:
                    low[i, j] = v
                if v > high[i, j]:
                    high[i, j] = v
    return low, high, hole


def _block_max(data: np.ndarray, block: int) -> np.ndarray:
    """Highest cell of each block and its 8 neighbours; +inf where a block holds a hole, so rays march
    through holes cell by cell and are reported, not skipped."""
    _, high, hole = _block_stats(data, block)
    return np.ascontiguousarray(maximum_filter(np.where(hole, np.float32(np.inf), high), size=3, mode="nearest"))


@numba.njit(cache=True, nogil=True)
def _bilinear(data, inv, x, y):
    """Height at map (x, y); NaN outside the raster or when all four neighbours are holes.

    ``inv`` = (a, b, c, d, e, f) of the inverse affine: col = a x + b y + c, row = d x + e y + f, with
    pixel corners at integers, so pixel centres are at +0.5.
    """
    rows, cols = data.shape
    col = inv[0] * x + inv[1] * y + inv[2]
    row = inv[3] * x + inv[4] * y + inv[5]
    if not (col >= 0.0 and col <= cols and row >= 0.0 and row <= rows):
        return math.nan
    cf = col - 0.5
    rf = row - 0.5
    c0 = min(max(int(math.floor(cf)), 0), max(cols - 2, 0))
    r0 = min(max(int(math.floor(rf)), 0), max(rows - 2, 0))
    c1 = min(c0 + 1, cols - 1)
    r1 = min(r0 + 1, rows - 1)
    fc = min(max(cf - c0, 0.0), 1.0)
    fr = min(max(rf - r0, 0.0), 1.0)
    total = 0.0
    weight = 0.0
    w = (1.0 - fr) * (1.0 - fc)
    v = data[r0, c0]
    if not math.isnan(v):
        total += v * w
        weight += w
    w = (1.0 - fr) * fc
    v = data[r0, c1]
    if not math.isnan(v):
        total += v * w
        weight += w
    w = fr * (1.0 - fc)
    v = data[r1, c0]
    if not math.isnan(v):
        total += v * w
        weight += w
    w = fr * fc
    v = data[r1, c1]
    if not math.isnan(v):
        total += v * w
        weight += w
    if weight > 1e-9:
        return total / weight
    return math.nan


@numba.njit(cache=True, nogil=True)
def _sample_many(data, inv, x, y, out):
    for i in range(x.size):
        out[i] = _bilinear(data, inv, x[i], y[i])


@numba.njit(cache=True, nogil=True)
def _inside(data, inv, x, y):
    rows, cols = data.shape
    col = inv[0] * x + inv[1] * y + inv[2]
    row = inv[3] * x + inv[4] * y + inv[5]
    return col >= 0.0 and col <= cols and row >= 0.0 and row <= rows


@numba.njit(cache=True, nogil=True)
def _cells_range(data, inv, x, y):
    """Lowest and highest valid cell of the 3 x 3 cells around map (x, y): the bilinear surface within half a
    cell of the point lies between them, and its slope is at most their difference per cell (x sqrt 2)."""
    rows, cols = data.shape
    col = int(math.floor(inv[0] * x + inv[1] * y + inv[2]))
    row = int(math.floor(inv[3] * x + inv[4] * y + inv[5]))
    lo, hi = math.inf, -math.inf
    for r in range(max(row - 1, 0), min(row + 2, rows)):
        for c in range(max(col - 1, 0), min(col + 2, cols)):
            v = data[r, c]
            if v > hi:
                hi = v
            if v < lo:
                lo = v
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _dip(data, inv, o, d, clearance, a, b, fa, fb, slope):
    """The first s in [a, b] (a half-cell step, f(a) > 0 and f(b) > 0) where the ray comes to the surface,
    or NaN: bisection wherever the bound ``f >= (fa + fb - K (b - a)) / 2`` (K: f's steepest change per unit
    s, from ``slope``) lets a dip below zero hide; a crossing found is refined."""
    k = abs(d[2]) + slope * math.sqrt(d[0] * d[0] + d[1] * d[1])
    tol = 1e-3 * (b - a)
    st = np.empty((_DIP_DEPTH, 4))
    st[0, 0], st[0, 1], st[0, 2], st[0, 3] = a, b, fa, fb
    n = 1
    while n > 0:
        n -= 1
        a, b, fa, fb = st[n, 0], st[n, 1], st[n, 2], st[n, 3]
        if fa + fb >= k * (b - a) or b - a < tol or n + 2 > _DIP_DEPTH:
            continue  # no dip fits here (or one thinner than a thousandth of the step: a touch)
        m = 0.5 * (a + b)
        fm = o[2] + m * d[2] - _bilinear(data, inv, o[0] + m * d[0], o[1] + m * d[1]) - clearance
        if math.isnan(fm):
            continue
        if fm <= 0.0:
            return _refine(data, inv, o, d, clearance, a, m, fa, fm)
        st[n, 0], st[n, 1], st[n, 2], st[n, 3] = m, b, fm, fb  # the right half waits ...
        st[n + 1, 0], st[n + 1, 1], st[n + 1, 2], st[n + 1, 3] = a, m, fa, fm  # ... the left is looked at first
        n += 2
    return math.nan


@numba.njit(cache=True, nogil=True)
def _refine(data, inv, o, d, clearance, a, b, fa, fb):
    """The crossing in [a, b] (f(a) > 0 >= f(b)): regula falsi with the Illinois rule (a few steps where
    bisection needs dozens); a hole inside the bracket counts as below, so the hit stays at its edge."""
    ox, oy, oz = o[0], o[1], o[2]
    dx, dy, dz = d[0], d[1], d[2]
    tol = _REFINE_TOLERANCE / math.sqrt(dx * dx + dy * dy + dz * dz)
    side = 0
    for _ in range(_REFINE_ITERATIONS):
        if b - a < tol:
            break
        if fa - fb > 0.0 and not math.isnan(fb):
            m = b - fb * (b - a) / (fb - fa)
            m = min(max(m, a + 0.01 * (b - a)), b - 0.01 * (b - a))
        else:
            m = 0.5 * (a + b)
        fm = oz + m * dz - _bilinear(data, inv, ox + m * dx, oy + m * dy) - clearance
        if math.isnan(fm):
            b, fb, side = m, math.nan, 0
        elif fm > 0.0:
            a, fa = m, fm
            if side == 1:
                fb *= 0.5
            side = 1
            if fm < _REFINE_TOLERANCE:
                return m
        else:
            b, fb = m, fm
            if side == -1:
                fa *= 0.5
            side = -1
            if -fm < _REFINE_TOLERANCE:
                return m
    return 0.5 * (a + b)


@numba.njit(cache=True, nogil=True)
def _crossing(data, inv, o, d, clearance, s_from, s_to, n, prev_f, status):
    """Fine march from ``s_from`` to ``s_to`` in ``n`` steps; refine the first crossing.

    Returns (s_hit or NaN, last f, status) so the caller can continue after this segment.
    """
    ox, oy, oz = o[0], o[1], o[2]
    dx, dy, dz = d[0], d[1], d[2]
    step = (s_to - s_from) / n
    cell = max(abs(inv[0]), abs(inv[4]))  # 1 / the cell size
    prev_s = s_from
    for k in range(1, n + 1):
        s = s_from + k * step
        x = ox + s * dx
        y = oy + s * dy
        f = oz + s * dz - _bilinear(data, inv, x, y) - clearance
        if math.isnan(f):
            if status == 4:
                status = 2 if not _inside(data, inv, x, y) else 3
        elif prev_f > 0.0 and f <= 0.0:
            return _refine(data, inv, o, d, clearance, prev_s, s, prev_f, f), f, 0
        elif prev_f > 0.0:
            lo, hi = _cells_range(data, inv, ox + (s - 0.5 * step) * dx, oy + (s - 0.5 * step) * dy)
            if oz + s * dz - clearance <= hi:
                # above the surface at both samples, but a cell between them reaches the ray: a thin crossing
                # (a leaf tip) may hide between the samples
                hit = _dip(data, inv, o, d, clearance, prev_s, s, prev_f, f, 1.5 * (hi - lo) * cell)
                if not math.isnan(hit):
                    return hit, f, 0
        prev_f = f
        prev_s = s
    return math.nan, prev_f, status


@numba.njit(cache=True, nogil=True)
def _intersect_many(data, inv, block_max, block, zmin, zmax, pixel, o, d, clearance, max_steps, z_top, z_bottom,
                    out_s, out_status):
    """For each ray: skip, a block at a time, the stretches where it stays above the highest cell of the
    3x3 blocks around it (``block_max``); march the rest in half-pixel horizontal steps (finer where a cell
    reaches the ray between two samples, so a thin crossing is not stepped over); refine the first
    step from above ``clearance`` to at or below it. ``z_top``, ``z_bottom``: per-ray height range to
    search (NaN: the surface's)."""
    margin = 0.01 + 1e-6 * (abs(zmax) + abs(zmin))
    nbr, nbc = block_max.shape
    for i in range(d.shape[0]):
        oz, dz = o[i, 2], d[i, 2]
        out_s[i] = math.nan
        if not dz < -1e-12:
            out_status[i] = 1  # NOT_DOWNWARD
            continue
        top = zmax if not z_top[i] < zmax else z_top[i]  # NaN: the whole height range
        bottom = zmin if not z_bottom[i] > zmin else z_bottom[i]
        s = max(0.0, (oz - (top + clearance + margin)) / -dz)
        s_end = (oz - (bottom - margin)) / -dz
        if not s_end > s:
            out_status[i] = 4  # NO_HIT
            continue
        horiz = max(math.sqrt(d[i, 0] ** 2 + d[i, 1] ** 2), 1e-12)
        # ray length that moves one block less one cell horizontally: from anywhere in a block, the end of the
        # step and its bilinear neighbours stay within the 3 x 3 blocks around it
        coarse = (block - 1) * pixel / horiz
        fine = 0.5 * pixel / horiz
        status = 4
        prev_f = math.nan
        steps = 0
        while s < s_end and steps < max_steps:
            s_next = min(s + coarse, s_end)
            x = o[i, 0] + s * d[i, 0]
            y = o[i, 1] + s * d[i, 1]
            col = inv[0] * x + inv[1] * y + inv[2]
            row = inv[3] * x + inv[4] * y + inv[5]
            bc = int(math.floor(col / block))
            br = int(math.floor(row / block))
            top = math.inf
            if 0 <= br < nbr and 0 <= bc < nbc:
                top = block_max[br, bc]
            elif status == 4:
                status = 2  # outside the raster here; it may still come in later
            if oz + s_next * dz - clearance > top:
                s = s_next  # the whole stretch is above the surface around it
                prev_f = math.nan
                steps += 1
                continue
            n = max(1, int(math.ceil((s_next - s) / fine)))
            if math.isnan(prev_f):
                prev_f = oz + s * dz - _bilinear(data, inv, x, y) - clearance
            hit, prev_f, status = _crossing(data, inv, o[i], d[i], clearance, s, s_next, n, prev_f, status)
            steps += n
            if status == 0:
                out_s[i] = hit
                break
            s = s_next
        out_status[i] = status


@numba.njit(cache=True, nogil=True)
def _drop_many(data, inv, pixel, p, d, depth, out):
    """Each point, left on its ray (direction ``d``) just above the surface: follow the ray down by at most
    ``depth``; where it meets the surface on the way, move the point there."""
    for i in range(p.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = p[i, 0], p[i, 1], p[i, 2]
        dz = d[i, 2]
        if not dz < -1e-12 or math.isnan(p[i, 0]):
            continue
        horiz = max(math.sqrt(d[i, 0] ** 2 + d[i, 1] ** 2), 1e-12)
        s_to = depth / -dz
        n = max(1, int(math.ceil(s_to / (0.5 * pixel / horiz))))
        f0 = p[i, 2] - _bilinear(data, inv, p[i, 0], p[i, 1])
        if not f0 > 0.0:
            continue
        s, _, status = _crossing(data, inv, p[i], d[i], 0.0, 0.0, s_to, n, f0, 4)
        if status == 0:
            out[i, 0], out[i, 1], out[i, 2] = p[i, 0] + s * d[i, 0], p[i, 1] + s * d[i, 1], p[i, 2] + s * dz


@numba.njit(cache=True, nogil=True)
def _intersect_gentle(data, inv, zmin, zmax, o, d, out_s, out_done):
    """Rays over a gentle surface (slope x ray tangent < 1 everywhere, so each ray crosses it once): the
    fixed point s = (z_camera - height(s)) / -dz converges in a few steps. Rays that fail (a hole, the
    raster's edge) are left for the march."""
    h_start = 0.5 * (zmin + zmax)
    for i in range(d.shape[0]):
        out_done[i] = False
        dz = d[i, 2]
        if not dz < -1e-12:
            continue
        s = (o[i, 2] - h_start) / -dz
        for _ in range(30):
            h = _bilinear(data, inv, o[i, 0] + s * d[i, 0], o[i, 1] + s * d[i, 1])
            if math.isnan(h):
                break
            s_new = (o[i, 2] - h) / -dz
            if abs(s_new - s) * -dz < _REFINE_TOLERANCE:
                out_s[i] = s_new
                out_done[i] = True
                h_start = h  # neighbouring rays (one box's outline) meet the ground at about this height
                break
            s = s_new


@dataclass
class Surface:
    data: np.ndarray  # float32 (as ODM writes it), NaN for holes
    transform: "object"  # affine.Affine, north-up
    crs: "object" = None
    path: Path | None = None

    def __post_init__(self):
        t = self.transform
        if abs(t.b) > 1e-12 or abs(t.d) > 1e-12:
            raise InputError("rotated rasters are not supported", path=self.path,
                             fix="warp the raster to a north-up grid (gdalwarp)")
        self.data = np.ascontiguousarray(self.data, dtype=np.float32)  # as ODM writes it: half the memory traffic
        i = ~t
        self._inv = np.array([i.a, i.b, i.c, i.d, i.e, i.f], dtype=np.float64)
        self.zmin, self.zmax = float(np.nanmin(self.data, initial=np.inf)), float(np.nanmax(self.data, initial=-np.inf))
        if not self.zmax >= self.zmin:
            raise InputError("the elevation raster holds no valid data in the area of interest", path=self.path,
                             fix="check that the DSM covers the images (same CRS, same field)")
        self._block_max = _block_max(self.data, _BLOCK)
        self._grounds: dict[float, Surface] = {}
        self._canopy: dict[float, float] = {}
        self._max_slope: float | None = None

    def ground(self, window: float) -> "Surface":
        """The bare ground under the plants, estimated from this surface: a morphological opening (the
        highest flat square of side ``window`` metres that fits under the surface, at each point) removes
        every bump narrower than the window and keeps the soil between them exactly, slopes included.
        Computed on a grid of about :data:`GROUND_CELL` (lowest cell of each block); blocks holding a DSM
        hole are holes. Cached per window."""
        if window not in self._grounds:
            block = max(1, int(round(GROUND_CELL / self.pixel_size)))
            low, high, hole = _block_stats(self.data, block)
            size = max(3, int(math.ceil(window / (block * self.pixel_size))) | 1)
            used = size * block * self.pixel_size
            if used > window * 1.5:
                log.info("ground estimate: window raised from ground_window=%.3g m to %.3g m (%d cells of %.3g m, "
                         "the least the opening needs)", window, used, size, block * self.pixel_size)
            eroded = minimum_filter(low, size=size, mode="nearest")
            opened = maximum_filter(np.where(np.isinf(eroded), -np.inf, eroded), size=size, mode="nearest")
            opened[~np.isfinite(opened) | hole] = np.nan  # DSM holes stay holes: rays meeting them are reported
            with np.errstate(invalid="ignore"):
                self._canopy[window] = float(np.nanmax(high - opened, initial=0.0))
            self._grounds[window] = Surface(opened, self.transform @ Affine.scale(block), self.crs, self.path)
        return self._grounds[window]

    def canopy_height(self, window: float) -> float:
        """The greatest height of this surface above its :meth:`ground` (the tallest plant), metres."""
        self.ground(window)
        return self._canopy[window]

    @classmethod
    def open(cls, path: str | Path, bounds: tuple[float, float, float, float] | None = None,
             band: int = 1) -> "Surface":
        """Read ``path`` (only the window covering ``bounds = (xmin, ymin, xmax, ymax)``, if given)."""
        path = Path(path)
        if not path.is_file():
            raise InputError("elevation raster not found", path=path,
                             fix="run ODM with --dsm, or point the config at the DSM GeoTIFF")
        try:
            with rasterio.open(path) as src:
                if bounds is not None:
                    win = from_bounds(*bounds, transform=src.transform)
                    # whole pixels, one extra on each side so bilinear sampling at the edge has neighbours
                    col0, row0 = int(np.floor(win.col_off)) - 1, int(np.floor(win.row_off)) - 1
                    col1 = int(np.ceil(win.col_off + win.width)) + 1
                    row1 = int(np.ceil(win.row_off + win.height)) + 1
                    win = Window(col0, row0, col1 - col0, row1 - row0).intersection(
                        Window(0, 0, src.width, src.height))
                    transform = src.window_transform(win)
                    arr = src.read(band, window=win, masked=True)
                else:
                    transform = src.transform
                    arr = src.read(band, masked=True)
                crs = src.crs
        except rasterio.errors.WindowError as exc:
            raise InputError("the area of interest does not overlap the raster", path=path,
                             fix="check that the raster and the reconstruction are of the same field and CRS") from exc
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"cannot read the raster: {exc}", path=path, fix="check that it is a GeoTIFF") from exc
        data = arr.astype(np.float32).filled(np.nan)
        data[data <= -9999] = np.nan  # ODM's nodata even when the file does not declare it
        return cls(data=data, transform=transform, crs=crs, path=path)

    @property
    def max_slope(self) -> float:
        """A bound on the slope (rise over run) of the bilinear surface anywhere: the hypotenuse of the steepest
        steps between neighbouring cells along x and along y. Computed once."""
        if self._max_slope is None:
            with np.errstate(invalid="ignore"):
                gx = np.nanmax(np.abs(np.diff(self.data, axis=1)), initial=0.0) / abs(self.transform.a)
                gy = np.nanmax(np.abs(np.diff(self.data, axis=0)), initial=0.0) / abs(self.transform.e)
            self._max_slope = float(math.hypot(gx, gy))
        return self._max_slope

    @property
    def pixel_size(self) -> float:
        return float(min(abs(self.transform.a), abs(self.transform.e)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        t = self.transform
        h, w = self.data.shape
        xs = (t.c, t.c + w * t.a)
        ys = (t.f, t.f + h * t.e)
        return min(xs), min(ys), max(xs), max(ys)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at map points; NaN outside the raster or where every neighbour is a hole."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        out = np.empty(x.shape, dtype=np.float64)
        _sample_many(self.data, self._inv, np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel(),
                     out.reshape(-1))
        return out

    def inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        i = self._inv
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        col, row = i[0] * x + i[1] * y + i[2], i[3] * x + i[4] * y + i[5]
        rows, cols = self.data.shape
        return (col >= 0) & (col <= cols) & (row >= 0) & (row <= rows)

    def drop(self, points: np.ndarray, directions: np.ndarray, depth: float) -> np.ndarray:
        """Points (N, 3) stopped just above the surface on rays along ``directions`` (N, 3): those whose ray
        meets the surface within ``depth`` metres further down move there, the others stay."""
        p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        out = np.empty_like(p)
        _drop_many(self.data, self._inv, self.pixel_size, p, d, float(depth), out)
        return out

    def intersect(self, origins: np.ndarray, directions: np.ndarray, *, clearance: float = 0.0,
                  max_steps: int = 200_000, heights: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First intersection of straight rays (in the raster's CRS) with the surface.

        Each ray is marched in half-pixel horizontal steps (sampled finer wherever a cell between two samples
        reaches the ray, so a thin first crossing such as a leaf tip is not stepped over) between the heights of the highest and lowest
        valid cell (so slopes and plant edges are found, not a flat plane), and the first bracket is
        refined. Over a gentle surface (``max_slope`` x the rays' tangent < 0.8: each ray crosses it once)
        a fixed-point iteration replaces the march. ``clearance`` > 0 stops a ray where it first comes that close above the surface: a ray
        that grazes a plant's top (the edge of its silhouette) then stays on the plant instead of
        continuing to the ground behind it. ``heights`` = (top, bottom) (N,) narrows the height range
        searched per ray when it is known (NaN: the whole range). Returns ``points (N, 3)``, ``s (N,)``
        (the ray parameter) and ``status (N,)`` (:data:`STATUS_TEXT`); points without a hit are NaN.
        """
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        if o.shape[0] == 1 and d.shape[0] > 1:
            o = np.repeat(o, d.shape[0], axis=0)
        o = np.ascontiguousarray(o)
        s = np.empty(d.shape[0], dtype=np.float64)
        status = np.empty(d.shape[0], dtype=np.int8)
        z_top, z_bottom = (np.full(d.shape[0], np.nan), np.full(d.shape[0], np.nan)) if heights is None else \
            (np.asarray(h, dtype=np.float64).reshape(-1) for h in heights)
        todo = slice(None)
        if clearance == 0.0 and d.shape[0] and self.max_slope * _max_tangent(d) < 0.8:
            done = np.empty(d.shape[0], dtype=np.bool_)
            _intersect_gentle(self.data, self._inv, self.zmin, self.zmax, o, d, s, done)
            status[done] = 0  # HIT
            todo = np.flatnonzero(~done)
            o, d = np.ascontiguousarray(o[todo]), np.ascontiguousarray(d[todo])
            z_top, z_bottom = z_top[todo], z_bottom[todo]
        s_m = np.empty(d.shape[0], dtype=np.float64)
        st_m = np.empty(d.shape[0], dtype=np.int8)
        _intersect_many(self.data, self._inv, self._block_max, _BLOCK, self.zmin, self.zmax, self.pixel_size,
                        o, d, float(clearance), int(max_steps), np.ascontiguousarray(z_top),
                        np.ascontiguousarray(z_bottom), s_m, st_m)
        s[todo], status[todo] = s_m, st_m
        o, d = np.asarray(origins, dtype=np.float64).reshape(-1, 3), np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        points = o + s[:, None] * d
        return points, s, status
