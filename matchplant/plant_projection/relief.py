"""Compiled pieces of the silhouette (:func:`~matchplant.plant_projection.geometry.silhouette_boxes`) that sample
the DSM many times per box: the plant's top inside a box, and rays that skimmed a plant on their way down.

Both are loops with an early exit or a running maximum over a few dozen samples per box; numpy would build
(boxes x samples) temporaries for them, numba walks them once (:func:`matchplant.core.raycast.bilinear`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from matchplant.core.raycast import bilinear


@numba.njit(cache=True, nogil=True)
def _skimmed_kernel(dsm, dsm_inv, gnd, gnd_inv, hits, cam, hidden_height, skim, canopy, samples, out):
    for i in range(hits.shape[0]):
        out[i] = False
        dx, dy, dz = hits[i, 0] - cam[0], hits[i, 1] - cam[1], hits[i, 2] - cam[2]
        dx, dy = dx / -dz, dy / -dz  # per metre of descent
        for k in range(1, samples + 1):
            u = (k / samples) * (canopy + skim)  # height above the hit
            x, y, z = hits[i, 0] - u * dx, hits[i, 1] - u * dy, hits[i, 2] + u
            top = bilinear(dsm, dsm_inv, x, y)
            if z - top < skim and top - bilinear(gnd, gnd_inv, x, y) > hidden_height:  # the ground only if close
                out[i] = True
                break


def skimmed(hits: np.ndarray, cam: np.ndarray, surface, ground, hidden_height: float, skim: float, canopy: float,
            samples: int = 16) -> np.ndarray:
    """Rays (camera to ``hits`` (N, 3) on the soil) that passed less than ``skim`` above a plant (the DSM
    standing ``hidden_height`` above the ground) on their way down, looked at in ``samples`` steps up to
    ``canopy + skim`` above the hit: they went over the plant's top without a ray grazing it, so where they
    landed is not the plant's edge."""
    out = np.zeros(len(hits), dtype=np.bool_)
    if len(hits):
        _skimmed_kernel(surface.data, surface.inverse, ground.data, ground.inverse,
                        np.ascontiguousarray(hits, dtype=np.float64), np.asarray(cam, dtype=np.float64),
                        float(hidden_height), float(skim), float(canopy), int(samples), out)
    return out


@numba.njit(cache=True, nogil=True)
def _apex_kernel(dsm, inv, centre, a, b, lo_a, hi_a, lo_b, hi_b, grid, refine, out):
    for i in range(centre.shape[0]):
        cx, cy = centre[i, 0], centre[i, 1]
        sa, sb = (hi_a[i] - lo_a[i]) / grid, (hi_b[i] - lo_b[i]) / grid  # lattice steps
        best = -math.inf
        ba, bb = lo_a[i] + 0.5 * sa, lo_b[i] + 0.5 * sb
        for jb in range(grid):
            gb = lo_b[i] + (jb + 0.5) * sb
            for ja in range(grid):
                ga = lo_a[i] + (ja + 0.5) * sa
                h = bilinear(dsm, inv, cx + ga * a[i, 0] + gb * b[i, 0], cy + ga * a[i, 1] + gb * b[i, 1])
                if h > best:  # the first highest point; NaN never wins
                    best, ba, bb = h, ga, gb
        for _ in range(refine):  # a finer lattice around the best point, a third of the step
            sa, sb = sa / 3.0, sb / 3.0
            ca, cb = ba, bb
            for jb in range(-1, 2):
                for ja in range(-1, 2):
                    if ja == 0 and jb == 0:
                        continue
                    ga, gb = ca + ja * sa, cb + jb * sb
                    h = bilinear(dsm, inv, cx + ga * a[i, 0] + gb * b[i, 0], cy + ga * a[i, 1] + gb * b[i, 1])
                    if h > best:
                        best, ba, bb = h, ga, gb
        out[i, 0], out[i, 1] = ba, bb


def apex(surface, centre: np.ndarray, a: np.ndarray, b: np.ndarray, lo_a: np.ndarray, hi_a: np.ndarray,
         lo_b: np.ndarray, hi_b: np.ndarray, grid: int = 5, refine: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The highest DSM point of each parallelogram ``centre + ga a + gb b`` (ga in [lo_a, hi_a], gb in [lo_b,
    hi_b]; arrays over M boxes), as its (ga, gb): the best of a ``grid`` x ``grid`` lattice of cell centres,
    then ``refine`` times the best of its 3 x 3 neighbours a third of the step away (a plant's top is one
    smooth dome: 41 samples place it as finely as a 45 x 45 lattice would); the first lattice point when
    every sample is a hole."""
    out = np.empty((len(centre), 2))
    f64 = lambda v: np.ascontiguousarray(v, dtype=np.float64)  # noqa: E731
    _apex_kernel(surface.data, surface.inverse, f64(centre), f64(a), f64(b), f64(lo_a), f64(hi_a), f64(lo_b),
                 f64(hi_b), int(grid), int(refine), out)
    return out[:, 0], out[:, 1]
