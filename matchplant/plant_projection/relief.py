"""Compiled pieces of the silhouette (:mod:`~matchplant.plant_projection.silhouette`) that sample
the DSM many times per box: the plant's top inside a box, and rays that skimmed a plant on their way down.

Both are loops with an early exit or a running maximum over a few dozen samples per box; numpy would build
(boxes x samples) temporaries for them, numba walks them once (:func:`matchplant.core.geometry.raycast.bilinear`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from matchplant.core.geometry.raycast import above_block_max, bilinear, bilinear_batch


@numba.njit(cache=True, nogil=True)
def skimmed_one(dsm, dsm_inv, bmax, block, gnd, gnd_inv, hx, hy, hz, cam, hidden_height, skim, canopy, samples):
    """:func:`skimmed` for one hit (compiled callers); ``bmax``, ``block``: the DSM's block maxima
    (:attr:`~matchplant.core.geometry.surface.Surface.block_max`)."""
    dz = hz - cam[2]
    dx, dy = (hx - cam[0]) / -dz, (hy - cam[1]) / -dz  # per metre of descent
    for k in range(1, samples + 1):
        u = (k / samples) * (canopy + skim)  # height above the hit
        x, y, z = hx - u * dx, hy - u * dy, hz + u
        if above_block_max(dsm_inv, bmax, block, x, y, z - skim):
            continue  # nothing around reaches within skim of the ray: the same answer as sampling, cheaper
        top = bilinear(dsm, dsm_inv, x, y)
        if z - top < skim and top - bilinear(gnd, gnd_inv, x, y) > hidden_height:  # the ground only if close
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _skimmed_kernel(dsm, dsm_inv, bmax, block, gnd, gnd_inv, hits, cam, hidden_height, skim, canopy, samples, out):
    for i in range(hits.shape[0]):
        out[i] = skimmed_one(dsm, dsm_inv, bmax, block, gnd, gnd_inv, hits[i, 0], hits[i, 1], hits[i, 2], cam,
                             hidden_height, skim, canopy, samples)


def skimmed(hits: np.ndarray, cam: np.ndarray, surface, ground, hidden_height: float, skim: float, canopy: float,
            samples: int = 16) -> np.ndarray:
    """Rays (camera to ``hits`` (N, 3) on the soil) that passed less than ``skim`` above a plant (the DSM
    standing ``hidden_height`` above the ground) on their way down, looked at in ``samples`` steps up to
    ``canopy + skim`` above the hit: they went over the plant's top without a ray grazing it, so where they
    landed is not the plant's edge."""
    out = np.zeros(len(hits), dtype=np.bool_)
    if len(hits):
        _skimmed_kernel(surface.data, surface.inverse, *surface.block_max, ground.data, ground.inverse,
                        np.ascontiguousarray(hits, dtype=np.float64), np.asarray(cam, dtype=np.float64),
                        float(hidden_height), float(skim), float(canopy), int(samples), out)
    return out


@numba.njit(cache=True, nogil=True)
def apex_one(dsm, inv, cx, cy, ax, ay, bx, by, lo_a, hi_a, lo_b, hi_b, grid, refine, work):
    """The highest DSM point of the parallelogram ``(cx, cy) + ga a + gb b`` (ga in [lo_a, hi_a], gb in [lo_b,
    hi_b]), as its (ga, gb): the best of a ``grid`` x ``grid`` lattice of cell centres, then ``refine`` times the
    best of its 3 x 3 neighbours a third of the step away (a plant's top is one smooth dome: 41 samples place
    it as finely as a 45 x 45 lattice would); the first lattice point when every sample is a hole. ``work``:
    scratch (>= grid x grid, 11), sampled a lattice at a time (:func:`~matchplant.core.geometry.raycast.bilinear_batch`)."""
    sa, sb = (hi_a - lo_a) / grid, (hi_b - lo_b) / grid  # lattice steps
    n = 0
    for jb in range(grid):
        for ja in range(grid):
            work[n, 6], work[n, 7] = lo_a + (ja + 0.5) * sa, lo_b + (jb + 0.5) * sb
            n += 1
    best = -math.inf
    ba, bb = work[0, 6], work[0, 7]
    for r in range(refine + 1):
        for k in range(n):  # map points of the lattice (ga, gb)
            work[k, 8], work[k, 9] = cx + work[k, 6] * ax + work[k, 7] * bx, cy + work[k, 6] * ay + work[k, 7] * by
        bilinear_batch(dsm, inv, work[:, 8], work[:, 9], n, work, work[:, 10])
        for k in range(n):
            if work[k, 10] > best:  # the first highest point; NaN never wins
                best, ba, bb = work[k, 10], work[k, 6], work[k, 7]
        if r == refine:
            break
        sa, sb = sa / 3.0, sb / 3.0  # a finer lattice around the best point, a third of the step
        n = 0
        for jb in range(-1, 2):
            for ja in range(-1, 2):
                if ja != 0 or jb != 0:
                    work[n, 6], work[n, 7] = ba + ja * sa, bb + jb * sb
                    n += 1
    return ba, bb
