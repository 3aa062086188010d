"""Compiled kernels under :class:`~matchplant.core.geometry.surface.Surface`: bilinear sampling and ray/surface
crossings.

The surface is the bilinear interpolation of the raster's cell centres. Between four valid centres it is one
bilinear patch, and along a straight ray a bilinear patch is a quadratic in the ray parameter, so a ray's
first crossing inside a patch is a root of that quadratic: exact, however thin the crossing (a leaf tip
that a ray clips for a millimetre), with no step size to choose. A ray is walked patch by patch (a grid
traversal, one patch per cell boundary crossed), skipping patches it passes above, and whole blocks of
cells it passes above (``block_max``). Patches that touch a hole (nodata) or lie on the raster's outer
half-cell are not bilinear (the interpolation renormalises over the valid neighbours); there the ray is
sampled every quarter cell and a bracketed crossing refined.

The per-ray work is a loop with an early exit, which numpy cannot vectorise without evaluating every ray
over the whole height range; it is compiled with numba, and one bilinear rule (:func:`bilinear`) serves
sampling, the fallback and the refinement. The walk's pieces are inlined into their callers (``inline=
"always"``): a call inside the walk's loop costs a fifth of its time (measured), at the price of a longer
first compilation (cached afterwards).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

HIT, NOT_DOWNWARD, OUTSIDE, NODATA, NO_HIT = 0, 1, 2, 3, 4
REFINE_ITERATIONS = 60  # refinement steps at most (fallback patches)
REFINE_TOLERANCE = 1e-7  # metres (along the ray, and above the surface) at which refinement stops
REFINE_MARGIN = 0.01  # share of the bracket a regula falsi step keeps from its ends (so the bracket shrinks)
GENTLE_TOLERANCE = 1e-4  # metres of height error (bounded) at which the fixed point stops: 1 % of a 1 cm DSM cell
GENTLE_ITERATIONS = 30  # fixed-point steps at most; a ray not settled by then is left for the walk
FALLBACK_SAMPLES = 4  # samples per cell crossed, on patches that are not bilinear
LEVEL = 1e-12  # a ray whose downward component (unit direction) is not below -LEVEL counts as level
MIN_WEIGHT = 1e-9  # bilinear weights of the valid neighbours below this sum: the point is a hole
FLAT_PATCH = 1e-12  # a patch's quadratic term this small against its linear ones: solved as linear
TINY = 1e-300  # guards a division by a length or slope that can be zero; a height just above 0
ODM_NODATA = -9999.0  # ODM writes this (or less) for cells without data, declared as nodata or not
HEIGHT_MARGIN = 0.01  # metres added to the height range a ray is walked through (rounding of zmin, zmax) ...
HEIGHT_MARGIN_REL = 1e-6  # ... plus this share of the heights' magnitude (float32 DSM cells)


class Raster(NamedTuple):
    """A raster as the compiled kernels take it, built once per surface
    (:attr:`~matchplant.core.geometry.surface.Surface.raster`)."""

    data: np.ndarray  # float32 heights (rows, cols), NaN for holes
    inv: np.ndarray  # the inverse affine (a, b, c, d, e, f): col = a x + b y + c, row = d x + e y + f
    bmax: np.ndarray  # the highest point of each block of patches (patch_block_max), +inf at holes
    block: int  # patches per side of those blocks
    zmin: float  # the lowest and highest valid cell
    zmax: float


class Rays(NamedTuple):
    """Rays for :func:`intersect_many`: one origin (1, 3) or one each (N, 3), directions (N, 3), and per ray the
    heights between which the surface is searched (NaN: the surface's own)."""

    origins: np.ndarray
    directions: np.ndarray
    top: np.ndarray
    bottom: np.ndarray


class Hits(NamedTuple):
    """Where rays met a surface: the ray parameter (NaN: no hit) and the status (HIT, OUTSIDE, ...) per ray."""

    s: np.ndarray
    status: np.ndarray


@numba.njit(cache=True, nogil=True)
def block_stats(data, block):
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


@numba.njit(cache=True, nogil=True)
def holes_to_nan(data, nodata):
    """Cells equal to ``nodata`` (NaN: none) or at or below -9999 (ODM's nodata, declared or not) become NaN, in
    place: one pass, no temporary masks over a raster of tens of millions of cells."""
    flat = data.reshape(-1)
    for k in range(flat.shape[0]):
        v = flat[k]
        if v == nodata or v <= ODM_NODATA:
            flat[k] = math.nan


@numba.njit(cache=True, nogil=True)
def ray_points(o, d, s, out):
    """Points ``o + s d`` (N, 3) of rays with one origin (1, 3) or one each (N, 3), in one pass."""
    for i in range(d.shape[0]):
        k = i if o.shape[0] > 1 else 0
        for a in range(3):
            out[i, a] = o[k, a] + s[i] * d[i, a]


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def _cell(data, inv, x, y):
    """Where map (x, y) falls for :func:`bilinear`: ``(inside, r0, c0, r1, c1, fr, fc)``."""
    rows, cols = data.shape
    col = inv[0] * x + inv[1] * y + inv[2]
    row = inv[3] * x + inv[4] * y + inv[5]
    if not (col >= 0.0 and col <= cols and row >= 0.0 and row <= rows):
        return False, 0, 0, 0, 0, 0.0, 0.0
    cf = col - 0.5
    rf = row - 0.5
    c0 = min(max(int(math.floor(cf)), 0), max(cols - 2, 0))
    r0 = min(max(int(math.floor(rf)), 0), max(rows - 2, 0))
    c1 = min(c0 + 1, cols - 1)
    r1 = min(r0 + 1, rows - 1)
    fc = min(max(cf - c0, 0.0), 1.0)
    fr = min(max(rf - r0, 0.0), 1.0)
    return True, r0, c0, r1, c1, fr, fc


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def _blend(v00, v01, v10, v11, fr, fc):
    """:func:`bilinear`'s weighted mean of the four neighbours, renormalised over those that are not holes."""
    total = 0.0
    weight = 0.0
    w = (1.0 - fr) * (1.0 - fc)
    if not math.isnan(v00):
        total += v00 * w
        weight += w
    w = (1.0 - fr) * fc
    if not math.isnan(v01):
        total += v01 * w
        weight += w
    w = fr * (1.0 - fc)
    if not math.isnan(v10):
        total += v10 * w
        weight += w
    w = fr * fc
    if not math.isnan(v11):
        total += v11 * w
        weight += w
    if weight > MIN_WEIGHT:
        return total / weight
    return math.nan


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def bilinear(data, inv, x, y):
    """Height at map (x, y); NaN outside the raster or when all four neighbours are holes.

    ``inv`` = (a, b, c, d, e, f) of the inverse affine: col = a x + b y + c, row = d x + e y + f, with
    pixel corners at integers, so pixel centres are at +0.5.
    """
    inside, r0, c0, r1, c1, fr, fc = _cell(data, inv, x, y)
    if not inside:
        return math.nan
    return _blend(data[r0, c0], data[r0, c1], data[r1, c0], data[r1, c1], fr, fc)


@numba.njit(cache=True, nogil=True)
def bilinear_batch(data, inv, xs, ys, n, scratch, out):
    """:func:`bilinear` at the first ``n`` points of ``xs``, ``ys`` into ``out``: every point's four values are
    read first, then blended. The reads do not depend on each other, so the CPU overlaps their cache misses
    (a DSM is far larger than the cache), which one point at a time it cannot. ``scratch``: (>= n, 6)."""
    for k in range(n):
        inside, r0, c0, r1, c1, fr, fc = _cell(data, inv, xs[k], ys[k])
        if inside:
            scratch[k, 0], scratch[k, 1] = data[r0, c0], data[r0, c1]
            scratch[k, 2], scratch[k, 3] = data[r1, c0], data[r1, c1]
            scratch[k, 4], scratch[k, 5] = fr, fc
        else:
            scratch[k, 4] = -1.0
    for k in range(n):
        if scratch[k, 4] < 0.0:
            out[k] = math.nan
        else:
            out[k] = _blend(scratch[k, 0], scratch[k, 1], scratch[k, 2], scratch[k, 3], scratch[k, 4], scratch[k, 5])


@numba.njit(cache=True, nogil=True)
def sample_many(data, inv, x, y, out):
    """Bilinear heights at many map points into ``out`` (NaN outside the raster or where all four are holes)."""
    for i in range(x.size):
        out[i] = bilinear(data, inv, x[i], y[i])


@numba.njit(cache=True, nogil=True)
def max_tangent(d):
    """Largest horizontal / vertical ratio of ray directions (N, 3) (looking down; 1 / LEVEL for a level ray)."""
    out = 0.0
    for i in range(d.shape[0]):
        t = math.sqrt(d[i, 0] * d[i, 0] + d[i, 1] * d[i, 1]) / max(-d[i, 2], LEVEL)
        if t > out or math.isnan(t):
            out = t
    return out


@numba.njit(cache=True, nogil=True)
def _inside(data, inv, x, y):
    rows, cols = data.shape
    col = inv[0] * x + inv[1] * y + inv[2]
    row = inv[3] * x + inv[4] * y + inv[5]
    return col >= 0.0 and col <= cols and row >= 0.0 and row <= rows


@numba.njit(cache=True, nogil=True)
def _refine(r, o, d, clearance, a, b, fa, fb):
    """The crossing in [a, b] (f(a) > 0 >= f(b)) on :class:`Raster` ``r``: regula falsi with the Illinois rule (a
    few steps where bisection needs dozens); a hole inside the bracket counts as below, so the hit stays at its
    edge."""
    data, inv = r.data, r.inv
    ox, oy, oz = o[0], o[1], o[2]
    dx, dy, dz = d[0], d[1], d[2]
    tol = REFINE_TOLERANCE / math.sqrt(dx * dx + dy * dy + dz * dz)
    side = 0
    for _ in range(REFINE_ITERATIONS):
        if b - a < tol:
            break
        if fa - fb > 0.0 and not math.isnan(fb):
            m = b - fb * (b - a) / (fb - fa)
            m = min(max(m, a + REFINE_MARGIN * (b - a)), b - REFINE_MARGIN * (b - a))
        else:
            m = 0.5 * (a + b)
        fm = oz + m * dz - bilinear(data, inv, ox + m * dx, oy + m * dy) - clearance
        if math.isnan(fm):
            b, fb, side = m, math.nan, 0
        elif fm > 0.0:
            a, fa = m, fm
            if side == 1:
                fb *= 0.5
            side = 1
            if fm < REFINE_TOLERANCE:
                return m
        else:
            b, fb = m, fm
            if side == -1:
                fa *= 0.5
            side = -1
            if -fm < REFINE_TOLERANCE:
                return m
    return 0.5 * (a + b)


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def _patch_root(fa, q1, q2, length):
    """The first ``t`` in [0, length] where f(t) = fa + q1 t + q2 t^2 comes down to 0 from above, or NaN.

    ``fa`` > 0: the smallest root (f(length) <= 0 guarantees one, whatever the rounding). ``fa`` <= 0 (the
    ray enters the patch below the surface, after a hole or at its start): only a concave f rises above 0
    and comes back, at its larger root.
    """
    f_end = fa + (q1 + q2 * length) * length
    if fa > 0.0 and f_end > 0.0 and (q2 <= 0.0 or q1 >= 0.0):
        return math.nan  # f is above 0 at both ends, and a dip needs a convex f going down at the start
    lo, hi = math.nan, math.nan
    if abs(q2) * length <= FLAT_PATCH * (abs(q1) + abs(fa) / max(length, TINY)):
        if q1 != 0.0:
            lo = -fa / q1
    else:
        disc = q1 * q1 - 4.0 * q2 * fa
        if disc >= 0.0:
            q = -0.5 * (q1 + math.copysign(math.sqrt(disc), q1))
            r1 = q / q2
            r2 = fa / q if q != 0.0 else r1
            lo, hi = min(r1, r2), max(r1, r2)
    if fa > 0.0:
        if lo >= 0.0 and lo <= length:
            return lo
        if hi >= 0.0 and hi <= length and not lo >= 0.0:
            return hi
        if f_end <= 0.0:  # a crossing exists; rounding put the root just outside the patch
            return length if not lo >= 0.0 else min(max(lo, 0.0), length)
        return math.nan
    if q2 < 0.0 and hi > 0.0 and hi <= length and lo < hi:
        return hi
    return math.nan


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def _axis_start(a, b, s):
    """One axis of a grid traversal along the grid coordinate ``a + s b`` from ``s``: the cell index, the ray
    parameter of the next cell boundary, the ray length between boundaries and the index step."""
    k = int(math.floor(a + s * b))
    if b > 0.0:
        return k, (k + 1 - a) / b, 1.0 / b, 1
    if b < 0.0:
        return k, (k - a) / b, -1.0 / b, -1
    return k, math.inf, math.inf, 1


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def _next_cell(across, c, tc, dtc, stc, r, tr, dtr, str_):
    """One step of a grid traversal (:func:`_axis_start`): into the next column when the ray crosses a column
    boundary first (``across``), else into the next row. Returns ``(c, tc, r, tr)``."""
    if across:
        return c + stc, tc + dtc, r, tr
    return c, tc, r + str_, tr + dtr


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def first_crossing(ras, o, d, clearance, s0, s1, f0, status, budget):
    """The first ray parameter in [s0, s1] where the ray comes down to ``clearance`` above the surface of
    :class:`Raster` ``ras``.

    ``f0``: the ray's height above surface + clearance at ``s0`` (NaN: unknown, no crossing can be claimed
    at ``s0``). Returns ``(s or NaN, f at the end, status, patches walked)``; ``status`` (as given, normally
    NO_HIT) becomes OUTSIDE or NODATA where the ray first meets a part without data, HIT on a crossing.
    """
    data, inv = ras.data, ras.inv
    rows, cols = data.shape
    ox, oy, oz = o[0], o[1], o[2]
    dx, dy, dz = d[0], d[1], d[2]
    ca = inv[0] * ox + inv[1] * oy + inv[2] - 0.5  # column of cell centres (patch coordinates) at s = 0
    cb = inv[0] * dx + inv[1] * dy
    ra = inv[3] * ox + inv[4] * oy + inv[5] - 0.5
    rb = inv[3] * dx + inv[4] * dy
    s = s0
    c, tc, dtc, stc = _axis_start(ca, cb, s)
    r, tr, dtr, str_ = _axis_start(ra, rb, s)
    f = f0
    walked = 0
    while s < s1 and walked < budget:
        walked += 1
        across = tc <= tr  # the next cell boundary the ray crosses: a column's (else a row's)
        se = min(max(tc if across else tr, s), s1)
        if 0 <= c <= cols - 2 and 0 <= r <= rows - 2:
            h00, h01, h10, h11 = data[r, c], data[r, c + 1], data[r + 1, c], data[r + 1, c + 1]
            valid = not (math.isnan(h00) or math.isnan(h01) or math.isnan(h10) or math.isnan(h11))
        else:
            valid = False
        if valid:
            if oz + se * dz - clearance > max(max(h00, h01), max(h10, h11)):
                f = 1.0  # above the whole patch at its lowest point on the ray (the ray descends)
            else:
                u0 = ca + s * cb - c
                v0 = ra + s * rb - r
                bu, bv, buv = h01 - h00, h10 - h00, h00 - h01 - h10 + h11
                fa = oz + s * dz - clearance - (h00 + bu * u0 + bv * v0 + buv * u0 * v0)
                q1 = dz - (bu * cb + bv * rb + buv * (u0 * rb + v0 * cb))
                q2 = -buv * cb * rb
                length = se - s
                # entering below the surface just after being above it is a crossing at the entry (rounding)
                t = _patch_root(fa if (fa > 0.0 or not f > 0.0) else TINY, q1, q2, length)
                if not math.isnan(t):
                    return s + t, 0.0, HIT, walked
                f = fa + (q1 + q2 * length) * length
        elif c < -1 or c > cols - 1 or r < -1 or r > rows - 1:
            if status == NO_HIT:
                status = OUTSIDE  # wholly outside the raster here; the ray may still come in later
            f = math.nan
        else:  # a hole's edge or the raster's outer half-cell: sample and refine
            fine = 1.0 / (FALLBACK_SAMPLES * max(abs(cb), abs(rb), TINY))  # ray length per quarter cell
            n = max(1, int(math.ceil((se - s) / fine)))
            step = (se - s) / n
            prev = s
            if math.isnan(f):
                f = oz + s * dz - bilinear(data, inv, ox + s * dx, oy + s * dy) - clearance
            for k in range(1, n + 1):
                sk = s + k * step
                x, y = ox + sk * dx, oy + sk * dy
                fk = oz + sk * dz - bilinear(data, inv, x, y) - clearance
                if math.isnan(fk):
                    if status == NO_HIT:
                        status = OUTSIDE if not _inside(data, inv, x, y) else NODATA
                elif f > 0.0 and fk <= 0.0:
                    return _refine(ras, o, d, clearance, prev, sk, f, fk), fk, HIT, walked
                f, prev = fk, sk
        c, tc, r, tr = _next_cell(across, c, tc, dtc, stc, r, tr, dtr, str_)
        s = se
    return math.nan, f, status, walked


@numba.njit(cache=True, nogil=True)
def patch_block_max(data, block):
    """Highest point of the bilinear surface over each ``block`` x ``block`` patches (the highest of the
    ``block + 1`` x ``block + 1`` cell centres they interpolate); +inf where one is a hole, so rays walk
    through holes patch by patch and are reported, not skipped."""
    rows, cols = data.shape
    br, bc = max(1, -(-(rows - 1) // block)), max(1, -(-(cols - 1) // block))
    out = np.full((br, bc), -np.inf, dtype=np.float32)
    for i in range(br):
        for j in range(bc):
            m = -np.inf
            for r in range(i * block, min(i * block + block + 1, rows)):
                for c in range(j * block, min(j * block + block + 1, cols)):
                    v = data[r, c]
                    if math.isnan(v):
                        m = np.inf
                    elif v > m:
                        m = v
            out[i, j] = m
    return out


@numba.njit(cache=True, nogil=True)
def above_block_max(ras, x, y, z):
    """Whether height ``z`` is at or above the bilinear surface's highest point around map (x, y): the highest
    point of the block of patches holding (x, y) (:func:`patch_block_max`, :class:`Raster` ``ras``). One value
    read, no interpolation: a cheap way to rule out a sample. False off the raster's patches."""
    inv, bmax, block = ras.inv, ras.bmax, ras.block
    pc = inv[0] * x + inv[1] * y + inv[2] - 0.5  # patch coordinates
    pr = inv[3] * x + inv[4] * y + inv[5] - 0.5
    if not (pc >= 0.0 and pr >= 0.0):
        return False
    i, j = int(pr) // block, int(pc) // block
    return i < bmax.shape[0] and j < bmax.shape[1] and bmax[i, j] <= z


@numba.njit(cache=True, nogil=True, inline="always")  # inlined: see the module docstring
def march(ras, o, d, clearance, s0, s1, status, budget):
    """:func:`first_crossing` over [s0, s1], block by block (a coarser grid traversal): a block of patches
    that the ray leaves while still above its highest point (``ras.bmax``, :func:`patch_block_max`) is skipped
    whole. Returns ``(s or NaN, status, patches walked)``."""
    inv, bmax, block = ras.inv, ras.bmax, ras.block
    nbr, nbc = bmax.shape
    ca = (inv[0] * o[0] + inv[1] * o[1] + inv[2] - 0.5) / block  # block coordinates at s = 0
    cb = (inv[0] * d[0] + inv[1] * d[1]) / block
    ra = (inv[3] * o[0] + inv[4] * o[1] + inv[5] - 0.5) / block
    rb = (inv[3] * d[0] + inv[4] * d[1]) / block
    s = s0
    c, tc, dtc, stc = _axis_start(ca, cb, s)
    r, tr, dtr, str_ = _axis_start(ra, rb, s)
    f = math.nan
    walked = 0
    while s < s1 and walked < budget:
        across = tc <= tr
        se = min(max(tc if across else tr, s), s1)
        top = bmax[r, c] if (0 <= r < nbr and 0 <= c < nbc) else math.inf
        if o[2] + se * d[2] - clearance > top:
            f = 1.0  # above the block's highest point all through it (the ray descends)
            walked += 1
        else:
            hit, f, status, n = first_crossing(ras, o, d, clearance, s, se, f, status, budget - walked)
            walked += n
            if status == HIT:
                return hit, status, walked
        c, tc, r, tr = _next_cell(across, c, tc, dtc, stc, r, tr, dtr, str_)
        s = se
    return math.nan, status, walked


@numba.njit(cache=True, nogil=True)
def intersect_many(ras, rays, clearance, settle, max_steps, out):
    """For each of the :class:`Rays`: the first point ``clearance`` above the surface of :class:`Raster` ``ras``
    (:func:`march`) between the ray's heights ``top`` and ``bottom``, into the :class:`Hits` ``out``.
    ``settle`` > 0: a ray stopped there that goes on to meet the surface within ``settle`` metres further down
    moves there (an exact hit: soil at a leaf tip, a plant's side; one that would fall further grazed a plant's
    top and stays)."""
    zmin, zmax = ras.zmin, ras.zmax
    o, d, z_top, z_bottom = rays.origins, rays.directions, rays.top, rays.bottom
    out_s, out_status = out.s, out.status
    margin = HEIGHT_MARGIN + HEIGHT_MARGIN_REL * (abs(zmax) + abs(zmin))
    for i in range(d.shape[0]):
        oi = o[i] if o.shape[0] > 1 else o[0]  # one origin for every ray, or one each
        oz, dz = oi[2], d[i, 2]
        out_s[i] = math.nan
        if not dz < -LEVEL:
            out_status[i] = NOT_DOWNWARD
            continue
        top = zmax if not z_top[i] < zmax else z_top[i]  # NaN: the whole height range
        bottom = zmin if not z_bottom[i] > zmin else z_bottom[i]
        s = max(0.0, (oz - (top + clearance + margin)) / -dz)
        s_end = (oz - (bottom - margin)) / -dz
        if not s_end > s:
            out_status[i] = NO_HIT
            continue
        hit, status, _ = march(ras, oi, d[i], clearance, s, s_end, NO_HIT, max_steps)
        if status == HIT and settle > 0.0 and clearance > 0.0:
            low, _, st2, _ = first_crossing(ras, oi, d[i], 0.0, hit, hit + settle / -dz, clearance, NO_HIT, max_steps)
            if st2 == HIT:
                hit = low
        out_s[i] = hit
        out_status[i] = status


@numba.njit(cache=True, nogil=True)
def intersect_gentle(ras, slope, o, d, out_s, out_done):
    """Rays over a gentle surface (:class:`Raster` ``ras``; ``slope``, a bound on its slope, x ray tangent < 1
    everywhere, so each ray crosses it once): the fixed point s = (z_camera - height(s)) / -dz converges in a few
    steps. Its map contracts by L = slope x tangent, so the height error after a step is at most L / (1 - L)
    times that step: the iteration stops as soon as that bound is below GENTLE_TOLERANCE. Rays that fail (a
    hole, the raster's edge) are left for the walk."""
    data, inv = ras.data, ras.inv
    h_start = 0.5 * (ras.zmin + ras.zmax)
    for i in range(d.shape[0]):
        oi = o[i] if o.shape[0] > 1 else o[0]  # one origin for every ray, or one each
        out_done[i] = False
        dz = d[i, 2]
        if not dz < -LEVEL:
            continue
        lip = slope * math.sqrt(d[i, 0] * d[i, 0] + d[i, 1] * d[i, 1]) / -dz
        if not lip < 1.0:
            continue
        bound = -dz * lip / (1.0 - lip)  # height error per unit of step
        s = (oi[2] - h_start) / -dz
        for _ in range(GENTLE_ITERATIONS):
            h = bilinear(data, inv, oi[0] + s * d[i, 0], oi[1] + s * d[i, 1])
            if math.isnan(h):
                break
            s_new = (oi[2] - h) / -dz
            if abs(s_new - s) * bound < GENTLE_TOLERANCE:
                out_s[i] = s_new
                out_done[i] = True
                h_start = h  # neighbouring rays (one box's outline) meet the ground at about this height
                break
            s = s_new
