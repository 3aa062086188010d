"""The coverage-weighted rule's compiled kernels: one pass per polygon cuts its edges at the pixel grid,
accumulates signed areas along each window row, then gathers and reduces the covered pixels in place.

The kernels take their arrays in a few named bundles (:class:`Edges`, :class:`PolygonWindows`,
:class:`Pixels`: NamedTuples, which numba passes as tuples at no cost), as module 8's ``Raster`` and
``Scene`` do, instead of a dozen positional arrays that are easy to give in the wrong order."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

_EPS_COVER = 1e-6  # coverage below this is rounding noise (e.g. an edge on a grid line), not a touched pixel


class Edges(NamedTuple):
    """The polygons' edges in pixel coordinates (column, row as continuous values)."""

    x0: np.ndarray  # per edge: from (x0, y0) to (x1, y1)
    y0: np.ndarray
    x1: np.ndarray
    y1: np.ndarray
    start: np.ndarray  # per polygon: its edges are start[p]:start[p + 1]


class PolygonWindows(NamedTuple):
    """The polygons of one batch and the pixel window each covers."""

    polys: np.ndarray  # per polygon of the batch: its index into Edges.start
    col0: np.ndarray  # its window's first column and row on the raster
    row0: np.ndarray
    w: np.ndarray  # its window's width and height, pixels
    h: np.ndarray


class Pixels(NamedTuple):
    """The raster window read for a batch (NaN = masked) and where it starts on the raster."""

    values: np.ndarray  # (rows, cols) float64
    row0: int
    col0: int


@numba.njit(cache=True, nogil=True)
def _edge_cuts(a: float, b: float, buf: np.ndarray) -> int:
    """Parameters t in (0, 1) where the segment a -> b crosses a whole number, in increasing t."""
    lo, hi = min(a, b), max(a, b)
    first = math.floor(lo) + 1.0
    n = max(int(math.ceil(hi) - first), 0)
    for i in range(n):
        k = first + i if b >= a else first + (n - 1 - i)
        buf[i] = (k - a) / (b - a)
    return n


@numba.njit(cache=True, nogil=True)
def _polygon_coverage(edges, e0, e1, cell, acc, cuts):
    """Exact covered fraction of each pixel of a ``h`` x ``w`` window (into ``acc``, rows of w + 1).

    Each edge is cut at the pixel grid; a piece in one cell adds its signed height to the cells right
    of it (the part of its own cell right of its midpoint): the running sum along a row is then the
    covered area, as font rasterisers accumulate it. ``cell``: the window's corner (column, row) and size
    (w, h); ``cuts``: two scratch buffers for the cuts along x and y."""
    cx, cy, w, h = cell
    tx, ty = cuts
    x0, y0, x1, y1 = edges.x0, edges.y0, edges.x1, edges.y1
    stride = w + 1
    acc[: h * stride] = 0.0
    for e in range(e0, e1):
        ax, ay, bx, by = x0[e] - cx, y0[e] - cy, x1[e] - cx, y1[e] - cy
        if ay == by:
            continue  # a horizontal edge covers nothing
        nx = _edge_cuts(ax, bx, tx)
        ny = _edge_cuts(ay, by, ty)
        dx, dy = bx - ax, by - ay
        i = j = 0
        ta = 0.0
        while True:
            if i < nx and (j >= ny or tx[i] <= ty[j]):
                tb = tx[i]
                i += 1
            elif j < ny:
                tb = ty[j]
                j += 1
            else:
                tb = 1.0
            d = (tb - ta) * dy
            if d != 0.0:
                ym = ay + 0.5 * (ta + tb) * dy
                r = int(math.floor(ym))
                if 0 <= r < h:
                    xm = ax + 0.5 * (ta + tb) * dx
                    c = math.floor(xm)
                    base = r * stride
                    if c < 0:
                        acc[base] += d
                    elif c >= w:
                        acc[base + w] += d
                    else:
                        frac = xm - c
                        acc[base + int(c)] += d * (1.0 - frac)
                        acc[base + int(c) + 1] += d * frac
            if tb == 1.0 and i >= nx and j >= ny:
                break
            ta = tb
    for r in range(h):
        run = 0.0
        base = r * stride
        for c in range(w):
            run += acc[base + c]
            v = abs(run)
            acc[base + c] = 0.0 if v < _EPS_COVER else min(v, 1.0)


@numba.njit(cache=True, nogil=True)
def _weighted_quantile(vals: np.ndarray, wts: np.ndarray, n: int, total: float, q: float) -> float:
    """exactextract's weighted quantile of sorted distinct ``vals[:n]``: s_k = k w_k + (n - 1) sum_{i<k} w_i,
    interpolated at q (n - 1) sum w."""
    target = q * total * (n - 1)
    cum = 0.0
    s_prev = 0.0
    for k in range(n):
        s = k * wts[k] + (n - 1) * cum
        if s > target:
            return vals[k - 1] + (target - s_prev) * (vals[k] - vals[k - 1]) / (s - s_prev)
        s_prev = s
        cum += wts[k]
    return vals[n - 1]


@numba.njit(cache=True, nogil=True)
def coverage_batch(edges, wins, pixels, qs, out, quant):
    """Coverage-weighted statistics of each polygon of a batch over ``window`` (NaN = masked).

    ``out[k]``: count, sum, mean, min, max, std, nodata (sums of covered fractions for count and
    nodata); ``quant[k]``: the quantiles ``qs``. ``edges``: :class:`Edges`; ``wins``: :class:`PolygonWindows`;
    ``pixels``: :class:`Pixels`."""
    x0, y0, x1, y1, edge_start = edges
    polys, col0, row0, w, h = wins
    window, R0, C0 = pixels
    big = 0
    for k in range(len(polys)):
        big = max(big, h[k] * (w[k] + 1))
    acc = np.empty(big)
    vals = np.empty(big)
    wts = np.empty(big)
    tx, ty = np.empty(1024), np.empty(1024)
    for k in range(len(polys)):
        p = polys[k]
        e0, e1 = edge_start[p], edge_start[p + 1]
        span = 2
        for e in range(e0, e1):
            span = max(span, int(abs(x1[e] - x0[e])) + 2, int(abs(y1[e] - y0[e])) + 2)
        if span > tx.size:
            tx, ty = np.empty(2 * span), np.empty(2 * span)
        wk, hk = w[k], h[k]
        _polygon_coverage(edges, e0, e1, (float(col0[k]), float(row0[k]), wk, hk), acc, (tx, ty))
        n = 0
        count = total = nodata = 0.0
        lo, hi = np.inf, -np.inf
        for r in range(hk):
            wr = row0[k] - R0 + r
            for c in range(wk):
                f = acc[r * (wk + 1) + c]
                if f == 0.0:
                    continue
                v = window[wr, col0[k] - C0 + c]
                if math.isnan(v):
                    nodata += f
                    continue
                vals[n] = v
                wts[n] = f
                n += 1
                count += f
                total += f * v
                lo = min(lo, v)
                hi = max(hi, v)
        out[k, 0], out[k, 1], out[k, 6] = count, total, nodata
        if n == 0:
            out[k, 2:6] = np.nan
            quant[k, :] = np.nan
            continue
        mean = total / count
        dev = 0.0
        for i in range(n):
            dev += wts[i] * (vals[i] - mean) ** 2
        out[k, 2], out[k, 3], out[k, 4], out[k, 5] = mean, lo, hi, math.sqrt(dev / count)
        if qs.size:
            order = np.argsort(vals[:n])
            sv, sw = vals[:n][order], wts[:n][order]
            m = 1  # equal values are one entry with their summed weight, as exactextract's histogram
            for i in range(1, n):
                if sv[i] == sv[m - 1]:
                    sw[m - 1] += sw[i]
                else:
                    sv[m], sw[m] = sv[i], sw[i]
                    m += 1
            for qi in range(qs.size):
                quant[k, qi] = _weighted_quantile(sv, sw, m, count, qs[qi])
