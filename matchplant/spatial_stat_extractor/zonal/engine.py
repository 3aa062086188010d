"""The statistics engine of module 9: exact zonal statistics of polygons over a raster.

Two pixel rules, each equal to a reference tool:

* ``"center"``: a pixel belongs to a polygon when its centre is inside it - GDAL's scanline rule, as used
  by ``rasterio.features.rasterize`` and therefore by rasterstats (``all_touched=False``); vectorised
  numpy: edges cut at row centres are accumulated into a flat buffer of the batch's pixel windows, a
  cumulative sum gives the crossing parity, statistics are ``reduceat`` runs, quantiles padded sorts;
* ``"coverage"``: every pixel is weighted by the exact fraction of its area inside the polygon - the
  coverage-weighted statistics of exactextract (quantiles over its histogram of distinct values); one
  compiled (numba) pass per polygon: edges cut at the pixel grid accumulate signed areas along each
  window row (as font rasterisers do), then the covered pixels are gathered and reduced in place
  (:mod:`~matchplant.spatial_stat_extractor.zonal.coverage`).

Overlapping polygons are independent. Batches of polygons (sorted by row) read only their raster window."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely

from matchplant.spatial_stat_extractor.zonal.coverage import Edges, Pixels, PolygonWindows, coverage_batch
from matchplant.spatial_stat_extractor.zonal.names import BASIC_STATS, DEFAULT_STATS, MODES, percentile_name
from matchplant.spatial_stat_extractor.zonal.runs import quantiles, ranges

# --------------------------------------------------------------------------------------------------
# geometry in pixel space


@dataclass
class PixelPolygons:
    """The polygons' edges in pixel coordinates (column, row as continuous values) and their windows."""

    n: int
    x0: np.ndarray  # per edge
    y0: np.ndarray
    x1: np.ndarray
    y1: np.ndarray
    edge_start: np.ndarray  # per polygon: its edges are edge_start[i]:edge_start[i+1]
    bounds: np.ndarray  # per polygon: min col, min row, max col, max row (pixel space, unclipped)
    empty: np.ndarray  # per polygon: no area

    @classmethod
    def from_geometries(cls, geoms: Sequence, transform) -> PixelPolygons:
        """The polygons' rings in pixel coordinates of ``transform``, exteriors and holes wound opposite ways."""
        geoms = np.asarray(geoms, dtype=object)
        n = len(geoms)
        parts, owner = shapely.get_parts(geoms, return_index=True)
        # exteriors one way round, holes the other: the signed-area accumulation relies on it
        parts = shapely.orient_polygons(parts)
        rings, ring_part = shapely.get_rings(parts, return_index=True)
        coords, point_ring = shapely.get_coordinates(rings, return_index=True)
        inv = ~transform
        px = inv.a * coords[:, 0] + inv.b * coords[:, 1] + inv.c
        py = inv.d * coords[:, 0] + inv.e * coords[:, 1] + inv.f
        point_poly = owner[ring_part[point_ring]]
        # an edge joins consecutive points of the same ring (rings are closed: last point == first)
        e = np.flatnonzero(point_ring[1:] == point_ring[:-1])
        edge_poly = point_poly[e]
        edge_start = np.searchsorted(edge_poly, np.arange(n + 1))
        bounds = np.full((n, 4), np.nan)
        has = np.bincount(point_poly, minlength=n) > 0
        if point_poly.size:
            starts = np.searchsorted(point_poly, np.flatnonzero(has))
            bounds[has, 0] = np.minimum.reduceat(px, starts)
            bounds[has, 1] = np.minimum.reduceat(py, starts)
            bounds[has, 2] = np.maximum.reduceat(px, starts)
            bounds[has, 3] = np.maximum.reduceat(py, starts)
        empty = ~has | (shapely.area(geoms) <= 0)
        return cls(n, px[e], py[e], px[e + 1], py[e + 1], edge_start, bounds, empty)

    def windows(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel windows ``(col0, row0, col1, row1)`` clipped to the raster, and outside/partial flags."""
        b = np.nan_to_num(self.bounds, nan=-1.0)
        full = np.stack([np.floor(b[:, 0]), np.floor(b[:, 1]), np.ceil(b[:, 2]), np.ceil(b[:, 3])], axis=1)
        full = np.clip(full, -(2**40), 2**40).astype(np.int64)
        win = full.copy()
        win[:, [0, 2]] = np.clip(win[:, [0, 2]], 0, width)
        win[:, [1, 3]] = np.clip(win[:, [1, 3]], 0, height)
        outside = self.empty | (win[:, 2] <= win[:, 0]) | (win[:, 3] <= win[:, 1])
        partial = ~outside & np.any(win != full, axis=1)
        win[outside] = 0
        return win, outside, partial


# --------------------------------------------------------------------------------------------------
# per-batch pixel weights


@dataclass
class _Batch:
    polys: np.ndarray  # polygon indices
    col0: np.ndarray
    row0: np.ndarray
    w: np.ndarray  # window width (the buffer rows have w + 1 cells: one spare column on the right)
    h: np.ndarray
    offset: np.ndarray  # start of each polygon's block in the flat buffer (length k + 1)

    @property
    def size(self) -> int:
        return int(self.offset[-1])


def _make_batch(polys: np.ndarray, win: np.ndarray) -> _Batch:
    col0, row0 = win[polys, 0], win[polys, 1]
    w, h = win[polys, 2] - col0, win[polys, 3] - row0
    offset = np.concatenate([[0], np.cumsum(h * (w + 1))])
    return _Batch(polys, col0, row0, w, h, offset)


def _batch_edges(pp: PixelPolygons, b: _Batch):
    """The batch's edges in window-local coordinates, with the batch-local polygon of each edge."""
    starts = pp.edge_start[b.polys]
    counts = pp.edge_start[b.polys + 1] - starts
    idx = ranges(starts, counts)
    j = np.repeat(np.arange(len(b.polys)), counts)
    # subtracting whole numbers is exact, so the local coordinates keep every bit of the global ones
    cx, cy = b.col0[j].astype(float), b.row0[j].astype(float)
    return j, pp.x0[idx] - cx, pp.y0[idx] - cy, pp.x1[idx] - cx, pp.y1[idx] - cy


def _center_weights(pp: PixelPolygons, b: _Batch) -> np.ndarray:
    """1 where a pixel centre is inside the polygon (GDAL's scanline rule), else 0."""
    j, x0, y0, x1, y1 = _batch_edges(pp, b)
    # order each edge from low to high row, as GDAL does before intersecting
    swap = y1 < y0
    ya, yb = np.where(swap, y1, y0), np.where(swap, y0, y1)
    xa, xb = np.where(swap, x1, x0), np.where(swap, x0, x1)
    # rows whose centre line r + 0.5 lies in [ya, yb): half-open, so a vertex is crossed once
    r_lo = np.clip(np.ceil(ya - 0.5), 0, b.h[j]).astype(np.int64)
    r_hi = np.clip(np.ceil(yb - 0.5), 0, b.h[j]).astype(np.int64)
    n = np.maximum(r_hi - r_lo, 0)
    e = np.repeat(np.arange(len(j)), n)
    r = ranges(r_lo, n) if n.size else np.zeros(0, np.int64)
    dy = r + 0.5
    x = (dy - ya[e]) * (xb[e] - xa[e]) / (yb[e] - ya[e]) + xa[e]
    je = j[e]
    col = np.clip(np.floor(x + 0.5), 0, b.w[je]).astype(np.int64)  # first pixel whose centre is past x
    crossings = np.bincount(b.offset[je] + r * (b.w[je] + 1) + col, minlength=b.size)
    # a closed ring crosses each row line an even number of times, so the parity of the running count
    # over the whole buffer restarts at every row by itself
    return (np.cumsum(crossings) & 1).astype(float)


# --------------------------------------------------------------------------------------------------
# statistics over grouped values


def _segment_stats(
    v: np.ndarray, bounds: np.ndarray, stats: Sequence[str], percentiles: Sequence[float]
) -> dict[str, np.ndarray]:
    """Statistics of the runs ``v[bounds[i]:bounds[i + 1]]`` (the pixel-centre rule: every weight 1)."""
    k = len(bounds) - 1
    counts = np.diff(bounds)
    has = counts > 0
    starts = bounds[:-1][has]
    out: dict[str, np.ndarray] = {}

    def per_group(values: np.ndarray, fn=np.add, empty: float = np.nan) -> np.ndarray:
        col = np.full(k, empty)
        if starts.size:
            col[has] = fn.reduceat(values, starts)
        return col

    count = counts.astype(float)
    total = per_group(v)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count
        if "std" in stats:
            dev = v - np.repeat(mean[has], counts[has])
            out["std"] = np.sqrt(per_group(dev * dev) / count)
    out.update(count=count, sum=total, mean=mean)
    if "min" in stats:
        out["min"] = per_group(v, np.minimum)
    if "max" in stats:
        out["max"] = per_group(v, np.maximum)
    qs = [q / 100.0 for q in percentiles] + ([0.5] if "median" in stats else [])
    if qs:
        qv = quantiles(v, bounds[:-1], counts, qs)
        for i, q in enumerate(percentiles):
            out[percentile_name(q)] = qv[:, i]
        if "median" in stats:
            out["median"] = qv[:, -1]
    return out


def _center_stats(
    pp: PixelPolygons,
    b: _Batch,
    window: np.ndarray,
    R0: int,
    C0: int,
    C1: int,
    stats: Sequence[str],
    percentiles: Sequence[float],
) -> dict[str, np.ndarray]:
    """The pixel-centre rule's statistics of one batch over its raster window (NaN = masked)."""
    wbuf = _center_weights(pp, b)
    k = len(b.polys)
    # each buffer row is a run of consecutive cells of the raster window: one repeat maps them all
    row_poly = np.repeat(np.arange(k), b.h)
    row_len = b.w[row_poly] + 1
    row_in_poly = ranges(np.zeros(k, np.int64), b.h)
    row_at = (b.row0[row_poly] + row_in_poly - R0) * (C1 - C0) + (b.col0[row_poly] - C0)
    shift = np.repeat(row_at - (np.cumsum(row_len) - row_len), row_len)
    nz = np.flatnonzero(wbuf)
    v = window.ravel()[shift[nz] + nz]
    w = wbuf[nz]
    bounds = np.searchsorted(nz, b.offset)  # each polygon's run of touched pixels
    ok = np.isfinite(v)
    bad = np.concatenate([[0.0], np.cumsum(np.where(ok, 0.0, w))])
    good = np.concatenate([[0], np.cumsum(ok)])
    got = _segment_stats(v[ok], good[bounds], stats, percentiles)
    got["nodata"] = bad[bounds[1:]] - bad[bounds[:-1]]
    return got


def _coverage_stats(
    pp: PixelPolygons, b: _Batch, window: np.ndarray, R0: int, C0: int, percentiles: Sequence[float]
) -> dict[str, np.ndarray]:
    """The coverage-weighted statistics of one batch over its raster window (compiled kernel)."""
    k = len(b.polys)
    qs = np.array([q / 100.0 for q in percentiles] + [0.5])
    out, quant = np.empty((k, 7)), np.empty((k, len(qs)))
    coverage_batch(
        Edges(pp.x0, pp.y0, pp.x1, pp.y1, pp.edge_start),
        PolygonWindows(b.polys, b.col0, b.row0, b.w, b.h),
        Pixels(window, R0, C0),
        qs,
        out,
        quant,
    )
    got = dict(zip(("count", "sum", "mean", "min", "max", "std", "nodata"), out.T))
    got.update({percentile_name(q): quant[:, i] for i, q in enumerate(percentiles)}, median=quant[:, -1])
    return got


# --------------------------------------------------------------------------------------------------
# driver


@dataclass
class ZonalResult:
    """Per-polygon statistics (arrays in the order of the input polygons) and what went wrong where."""

    stats: dict[str, np.ndarray]
    outside: np.ndarray  # bool: polygon does not overlap the raster (or is empty)
    partial: np.ndarray  # bool: polygon only partly on the raster
    no_valid: np.ndarray  # bool: on the raster but every pixel is nodata/NaN (or too small for the rule)
    columns: list[str] = field(default_factory=list)


def _plan_batches(win: np.ndarray, todo: np.ndarray, max_cells: int, max_window: int) -> list[np.ndarray]:
    """Groups of polygons, in row order, whose buffers and shared raster window stay within budget."""
    if todo.size == 0:
        return []
    order = todo[np.lexsort((win[todo, 0], win[todo, 1]))]
    cells = (win[order, 3] - win[order, 1]) * (win[order, 2] - win[order, 0] + 1)
    batches, i = [], 0
    cum = np.cumsum(cells)
    while i < len(order):
        # largest run from i whose buffer fits; then shrink it until the union window fits too
        base = cum[i - 1] if i else 0
        k = max(int(np.searchsorted(cum, base + max_cells, side="right")) - i, 1)
        while k > 1:
            sel = order[i : i + k]
            area = (win[sel, 3].max() - win[sel, 1].min()) * (win[sel, 2].max() - win[sel, 0].min())
            if area <= max_window:
                break
            k //= 2
        batches.append(order[i : i + k])
        i += k
    return batches


def zonal_stats(
    geoms: Sequence,
    source,
    stats: Iterable[str] = DEFAULT_STATS,
    percentiles: Iterable[float] = (),
    mode: str = "center",
    *,
    max_cells: int = 4_000_000,
    max_window: int = 16_000_000,
    on_progress: Callable[[int, int], None] | None = None,
) -> ZonalResult:
    """Statistics of ``source`` (see :class:`~matchplant.spatial_stat_extractor.inputs.sources.ArraySource`)
    inside each polygon of ``geoms`` (shapely polygons in the raster's CRS).

    ``stats``: any of :data:`BASIC_STATS`; ``percentiles``: 0..100; ``mode``: ``"center"`` (pixel
    centre inside, like rasterstats) or ``"coverage"`` (weighted by covered fraction, like
    exactextract: ``count`` and ``nodata`` are then sums of fractions). NaN pixels are masked.
    ``on_progress(done, total)`` is called after each batch.

    Parameters
    ----------
    geoms : sequence of shapely polygons
        In the raster's CRS.
    source : raster source
        ``transform, width, height, read(row0, row1, col0, col1)`` (an ``ArraySource``, an opened layer).
    stats : iterable of str
        Any of :data:`BASIC_STATS`.
    percentiles : iterable of float
        0..100, each a column ``p<q>``.
    mode : str
        ``"center"`` or ``"coverage"``.
    max_cells, max_window : int
        Pixels one batch of polygons may cover, and its window may span (the memory of a batch).
    on_progress : callable, optional
        ``on_progress(done, total)`` after each batch.

    Returns
    -------
    ZonalResult
        The statistics per polygon, in the order of ``geoms``, and which polygons were outside or partial.
    """
    stats = list(stats)
    percentiles = [float(q) for q in percentiles]
    unknown = [s for s in stats if s not in BASIC_STATS]
    if unknown:
        raise ValueError(f"unknown statistics {unknown}; choose from {BASIC_STATS}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}")
    if any(not 0 <= q <= 100 for q in percentiles):
        raise ValueError("percentiles must be between 0 and 100")
    pp = PixelPolygons.from_geometries(geoms, source.transform)
    n = pp.n
    win, outside, partial = pp.windows(source.width, source.height)
    columns = stats + [percentile_name(q) for q in percentiles]
    result = {c: np.full(n, np.nan) for c in columns}
    for c in ("count", "nodata"):
        if c in result:
            result[c][:] = 0.0
    valid_count = np.zeros(n)
    batches = _plan_batches(win, np.flatnonzero(~outside), max_cells, max_window)
    for bi, polys in enumerate(batches):
        b = _make_batch(polys, win)
        R0, C0 = int(b.row0.min()), int(b.col0.min())
        R1, C1 = int((b.row0 + b.h).max()), int((b.col0 + b.w).max())
        window = source.read(R0, R1, C0, C1)
        if mode == "center":
            got = _center_stats(pp, b, window, R0, C0, C1, stats, percentiles)
        else:
            got = _coverage_stats(pp, b, window, R0, C0, percentiles)
        for c in columns:
            result[c][polys] = got[c]
        valid_count[polys] = got["count"]
        if on_progress is not None:
            on_progress(bi + 1, len(batches))
    no_valid = ~outside & (valid_count == 0)
    return ZonalResult(result, outside, partial, no_valid, columns)
