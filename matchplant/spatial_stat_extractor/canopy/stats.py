"""Canopy-only statistics: every trait over each plant's canopy pixels (:class:`~.outlines.Outlines`)
instead of its whole box.

A layer on the CHM's grid is read in strips of rows and its values gathered at the canopy pixels; the
statistics are then reductions over each plant's run of values (``bincount``, ``reduceat``; percentiles
by sorting each plant's run (:mod:`.grouping`) and linear interpolation between order statistics, as
``numpy.percentile``). A layer on another grid (a multispectral camera at its own resolution) is measured over
the outline polygons with :func:`~matchplant.spatial_stat_extractor.zonal.engine.zonal_stats` (pixel centres inside).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from matchplant.spatial_stat_extractor.canopy.grid import STRIP_ROWS
from matchplant.spatial_stat_extractor.canopy.grouping import pixel_window, sort_within_groups, values_at
from matchplant.spatial_stat_extractor.canopy.outlines import Outlines
from matchplant.spatial_stat_extractor.zonal import percentile_name, zonal_stats


def gather(outlines: Outlines, source, strip_rows: int = STRIP_ROWS) -> np.ndarray:
    """The values of ``source`` (same grid) at every canopy pixel, in the order of ``outlines.pix``."""
    pix = outlines.pix
    out = np.full(len(pix), np.nan)
    if not len(pix):
        return out
    r0, r1, c0, c1 = pixel_window(pix, outlines.width)
    if r1 - r0 <= strip_rows:  # one window (a band of strips: the window its outlines read)
        return values_at(source.read(r0, r1, c0, c1), pix, outlines.width, r0, c0)
    rows, cols = np.divmod(pix, outlines.width)
    block = rows // strip_rows
    order = np.argsort(block, kind="stable")
    edges = np.flatnonzero(np.diff(block[order])) + 1
    for part in np.split(order, edges):
        r, c = rows[part], cols[part]
        r0, r1, c0, c1 = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
        win = source.read(r0, r1, c0, c1)
        out[part] = win[r - r0, c - c0]
    return out


def grouped_stats(
    values: np.ndarray, start: np.ndarray, stats: Sequence[str], percentiles: Sequence[float] = ()
) -> dict[str, np.ndarray]:
    """Statistics of ``values[start[k]:start[k + 1]]`` for every group ``k``, NaN values left out
    (percentiles: linear interpolation between order statistics, as ``numpy.percentile``)."""
    n = len(start) - 1
    group = np.repeat(np.arange(n), np.diff(start))
    ok = np.isfinite(values)
    v, g = (values, group) if ok.all() else (values[ok], group[ok])  # canopy heights: all finite, no copies
    cnt = np.bincount(g, minlength=n).astype(float)
    has = cnt > 0
    first = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    total = np.bincount(g, weights=v, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(has, total / cnt, np.nan)
    out: dict[str, np.ndarray] = {}

    def reduce(fn) -> np.ndarray:
        res = np.full(n, np.nan)
        if has.any():
            res[has] = fn.reduceat(v, first[:-1][has])
        return res

    sorted_v = None

    def pct(q: float) -> np.ndarray:
        nonlocal sorted_v
        if sorted_v is None:
            sorted_v = sort_within_groups(v, first)
        # the position within each group, so the interpolation does not depend on where the group lies in the
        # array (a strip's or a field's: an offset of millions costs the fraction its last digits)
        rel = q / 100.0 * np.maximum(cnt - 1, 0)
        whole = np.floor(rel)
        lo = np.clip(first[:-1] + whole.astype(np.int64), 0, max(v.size - 1, 0))
        hi = np.clip(np.minimum(lo + 1, first[1:] - 1), 0, max(v.size - 1, 0))
        res = np.full(n, np.nan)
        if v.size:
            res[has] = (sorted_v[lo] + (sorted_v[hi] - sorted_v[lo]) * (rel - whole))[has]
        return res

    for name in stats:
        if name == "count":
            out[name] = cnt
        elif name == "mean":
            out[name] = mean
        elif name == "sum":
            out[name] = np.where(has, total, np.nan)
        elif name == "nodata":
            out[name] = np.diff(start) - cnt
        elif name == "min":
            out[name] = reduce(np.minimum)
        elif name == "max":
            out[name] = reduce(np.maximum)
        elif name == "std":
            dev = v - np.nan_to_num(mean)[g]
            with np.errstate(invalid="ignore", divide="ignore"):
                out[name] = np.sqrt(np.where(has, np.bincount(g, weights=dev * dev, minlength=n) / cnt, np.nan))
        elif name == "median":
            out[name] = pct(50.0)
        else:
            raise ValueError(f"unknown statistic '{name}'")
    for q in percentiles:
        out[percentile_name(q)] = pct(float(q))
    return out


def canopy_stats(outlines: Outlines, source, stats: Sequence[str], percentiles: Sequence[float] = ()):
    """Per-plant statistics of ``source`` over the canopy pixels (see the module doc).

    Parameters
    ----------
    outlines : Outlines
        From :func:`~.segmentation.segment` (with its canopy pixels).
    source : raster source
        On the CHM's grid its canopy pixels are read directly; on another grid, the pixels whose centre lies in
        each outline polygon.
    stats : sequence of str
        Any of the engine's statistics (``mean``, ``max``, ``median``...).
    percentiles : sequence of float
        0..100, each a column ``p<q>``.

    Returns
    -------
    dict
        Column name to an array over the plants.
    """
    if outlines.same_grid(source):
        return grouped_stats(gather(outlines, source), outlines.start, stats, percentiles)
    res = zonal_stats(outlines.geometry, source, stats, percentiles, mode="center")
    return {c: res.stats[c] for c in res.columns}
