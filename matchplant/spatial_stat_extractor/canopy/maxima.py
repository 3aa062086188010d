"""Local maxima of a CHM window (plant tops), in one compiled pass.

A pixel is a local maximum when no pixel within ``half`` rows and columns of it is higher (the window cut
at the raster's edge) and it reaches a threshold: the same pixels as ``a == ndimage.maximum_filter(a,
2 * half + 1)`` (its ``reflect`` border repeats pixels already in the window) with ``a >= threshold``.
Most pixels are soil below the threshold or lie on a slope, where the first higher neighbour ends the
test: four to five times faster than the filter over the whole window (a fifth of the outlining time on a
survey before).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _local_maxima(a, half, threshold):
    rows, cols = a.shape
    out = np.zeros((rows, cols), np.bool_)
    for r in range(rows):
        r0, r1 = max(0, r - half), min(rows, r + half + 1)
        for c in range(cols):
            v = a[r, c]
            if not v >= threshold:  # NaN too
                continue
            c0, c1 = max(0, c - half), min(cols, c + half + 1)
            top = True
            for q in range(r0, r1):
                for d in range(c0, c1):
                    if a[q, d] > v:
                        top = False
                        break
                if not top:
                    break
            out[r, c] = top
    return out


def local_maxima(a: np.ndarray, size: int, threshold: float) -> np.ndarray:
    """Boolean image of the pixels of ``a`` (2-D; holes NaN or -inf, never a maximum and never higher than a
    neighbour) that are the highest in their ``size`` x ``size`` neighbourhood (``size`` odd) and at least
    ``threshold``."""
    return _local_maxima(np.ascontiguousarray(a, dtype=np.float64), size // 2, float(threshold))


@numba.njit(cache=True, nogil=True)
def _line_saddles(a, p, q, s, own):
    rows, cols = a.shape
    out = np.empty(len(p))
    for k in range(len(p)):
        low, seen = np.inf, 0
        for t in s:
            t = np.rint(t * own[k]) / own[k]
            r = np.int64(np.rint(p[k, 0] + (q[k, 0] - p[k, 0]) * t))
            c = np.int64(np.rint(p[k, 1] + (q[k, 1] - p[k, 1]) * t))
            best = -np.inf
            for dr in range(-1, 2):
                rr = min(max(r + dr, 0), rows - 1)
                for dc in range(-1, 2):
                    v = a[rr, min(max(c + dc, 0), cols - 1)]
                    if v > best:  # NaN never is
                        best = v
            if best > -np.inf:
                seen += 1
                low = min(low, best)
        out[k] = low if seen / len(s) >= 0.5 else -np.inf
    return out


def line_saddles(a: np.ndarray, p: np.ndarray, q: np.ndarray, s: np.ndarray, own: np.ndarray) -> np.ndarray:
    """For each line from ``p[k]`` to ``q[k]`` (row, col) sampled at the fractions ``s``, each rounded to the
    line's own ``own[k]`` steps (``rint(s * own) / own``), then to the nearest pixel: the lowest of the samples,
    each the highest of its 3 x 3 pixels (clipped at the edge; holes, NaN or -inf, skipped), or -inf where
    fewer than half the samples see anything. One compiled pass (nine gathers of every sample of every pair
    took a tenth of the outlining time)."""
    return _line_saddles(
        np.ascontiguousarray(a, dtype=np.float64),
        np.ascontiguousarray(p, dtype=np.int64),
        np.ascontiguousarray(q, dtype=np.int64),
        np.ascontiguousarray(s, dtype=np.float64),
        np.ascontiguousarray(own, dtype=np.int64),
    )


@numba.njit(cache=True, nogil=True)
def _box_tops(a, peak, boxes, windows):
    out = np.full((len(boxes), 4), np.nan)
    for k in range(len(boxes)):
        for b, is_peak in ((boxes[k], True), (windows[k], True), (boxes[k], False)):
            best, br, bc, finite = -np.inf, -1, -1, False
            for r in range(max(b[1], 0), min(b[3], a.shape[0])):
                for c in range(max(b[0], 0), min(b[2], a.shape[1])):
                    if is_peak and not peak[r, c]:
                        continue
                    v = a[r, c]
                    finite = finite or np.isfinite(v)
                    if v > best:  # the first of the highest; NaN never is
                        best, br, bc = v, r, c
            if is_peak and br >= 0:
                out[k, 0], out[k, 1], out[k, 2], out[k, 3] = br, bc, best, 1.0
                break
            if not is_peak and finite:
                out[k, 0], out[k, 1], out[k, 2], out[k, 3] = br, bc, best, 0.0
    return out


def box_tops(a: np.ndarray, peak: np.ndarray, boxes: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """(k, 4) row, col and height of each plant's top, and 1 where it is a local maximum (``peak``): the
    highest local maximum in its box (integer ``c0, r0, c1, r1``), else in its window, else the highest pixel
    of its box (holes, NaN, never), first in raster order on ties; NaN where the box holds no finite height.
    One compiled pass (slices and an argmax per plant took half of finding the tops)."""
    return _box_tops(
        np.ascontiguousarray(a, dtype=np.float64),
        np.ascontiguousarray(peak, dtype=np.bool_),
        np.ascontiguousarray(boxes, dtype=np.int64),
        np.ascontiguousarray(windows, dtype=np.int64),
    )
