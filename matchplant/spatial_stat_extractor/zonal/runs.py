"""Runs of values grouped by plant or plot: index ranges, and quantiles per group (numpy's 'linear' method,
as rasterstats and ``numpy.percentile``), without a Python loop over small groups."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, s + l)`` for every pair, without a Python loop."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    shift = np.repeat(np.asarray(starts, dtype=np.int64) - (np.cumsum(lengths) - lengths), lengths)
    return shift + np.arange(total, dtype=np.int64)


def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """numpy's interpolation for percentiles (same rounding as np.percentile)."""
    diff = b - a
    return np.where(t >= 0.5, b - diff * (1 - t), a + diff * t)


LARGE_GROUP = 50_000  # values: a larger group's quantiles come from a partition around them (plot polygons)


def quantiles(
    v: np.ndarray, starts: np.ndarray, counts: np.ndarray, qs: Sequence[float], budget: int = 4_000_000
) -> np.ndarray:
    """Quantiles ``qs`` (0..1) of each group ``v[starts[i]:starts[i] + counts[i]]``, numpy's 'linear'
    method (rasterstats). Groups are sorted in padded matrices of groups of similar size, to bound the
    padding; groups of over ``LARGE_GROUP`` values (a plot's hundred thousand pixels) are partitioned
    around the order statistics wanted instead (linear time, not a sort: the same values)."""
    out = np.full((len(counts), len(qs)), np.nan)
    order = np.argsort(counts, kind="stable")
    order = order[counts[order] > 0]
    big = counts[order] > LARGE_GROUP
    for g in order[big]:  # a plot polygon: the order statistics wanted, not a sort of its every value
        n = int(counts[g])
        pos = np.asarray(qs, float) * (n - 1)
        lo = np.floor(pos).astype(np.int64)
        hi = np.minimum(lo + 1, n - 1)
        vals = np.partition(v[starts[g] : starts[g] + n], np.unique(np.concatenate([lo, hi])))
        out[g] = lerp(vals[lo], vals[hi], pos - lo)
    order = order[~big]
    i = 0
    while i < len(order):
        # as many groups as fit the budget padded to the widest of them (they come in increasing size)
        padded = np.arange(1, len(order) - i + 1) * counts[order[i:]]
        k = max(int(np.searchsorted(padded, budget, side="right")), 1)
        groups = order[i : i + k]
        i += k
        n = counts[groups]
        width = int(n.max())
        idx = ranges(starts[groups], n)
        row = np.repeat(np.arange(len(groups)), n)
        col = idx - np.repeat(starts[groups], n)
        vals = np.full((len(groups), width), np.inf)
        vals[row, col] = v[idx]
        r = np.arange(len(groups))
        vals.sort(axis=1)
        for qi, q in enumerate(qs):
            pos = q * (n - 1)
            lo = np.floor(pos).astype(np.int64)
            hi = np.minimum(lo + 1, n - 1)
            out[groups, qi] = lerp(vals[r, lo], vals[r, hi], pos - lo)
    return out
