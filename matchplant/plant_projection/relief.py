"""Compiled pieces of the silhouette (:mod:`~matchplant.plant_projection.silhouette`) that sample
the DSM many times per box: the plant's top inside a box, and rays that skimmed a plant on their way down.

Both are loops with an early exit or a running maximum over a few dozen samples per box; numpy would build
(boxes x samples) temporaries for them, numba walks them once (:func:`matchplant.core.geometry.raycast.bilinear`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from matchplant.core.geometry.raycast import Raster, above_block_max, bilinear, bilinear_batch
from matchplant.core.geometry.surface import Surface
from matchplant.plant_projection.dsm_noise import HIDDEN_SIGMAS, ground_noise
from matchplant.plant_projection.settings import ProjectionSettings

SKIM = 0.1  # metres: a ray that passed this close over a plant before landing on the soil missed the plant's top
SKIM_SAMPLES = 16  # samples along a soil ray looking for a plant it skimmed (skimmed_one)
APEX_GRID, APEX_REFINE = 5, 2  # the plant's top: a 5 x 5 lattice, refined twice (apex_one)
# apex_one's scratch columns, after bilinear_batch's six: a lattice point (ga, gb), its map (x, y), its height
GA, GB, MAP_X, MAP_Y, HEIGHT = 6, 7, 8, 9, 10
APEX_WORK = (APEX_GRID * APEX_GRID, HEIGHT + 1)  # the scratch's shape


class Scene(NamedTuple):
    """What the compiled silhouette judges one image's box rays against (:meth:`of`)."""

    dsm: Raster
    ground: Raster  # the ground under the plants (Surface.ground)
    cam: np.ndarray  # the camera centre on the map (3,)
    hidden_height: float  # metres above the ground at which a hit lay behind a plant's top (plus the soil's noise)
    skim: float  # metres: how close over a plant a ray that skimmed it passed
    canopy: float  # metres: the tallest plant above the ground

    @classmethod
    def of(cls, surface: Surface, cam: np.ndarray, settings: ProjectionSettings) -> Scene:
        """The scene of one image: the DSM, its ground, the camera centre and the heights the rays are judged by."""
        window = settings.ground_window
        # soil hits scatter about the ground by the DSM's noise: only a hit standing out of it lay behind a plant
        hidden = settings.hidden_height + HIDDEN_SIGMAS * ground_noise(surface, window).spread
        return cls(
            surface.raster,
            surface.ground(window).raster,
            np.ascontiguousarray(cam, dtype=np.float64),
            float(hidden),
            SKIM,
            float(surface.canopy_height(window)),
        )


@numba.njit(cache=True, nogil=True)
def skimmed_one(scene, hx, hy, hz):
    """:func:`skimmed` for one hit (compiled callers)."""
    dsm, gnd, cam, skim = scene.dsm, scene.ground, scene.cam, scene.skim
    dz = hz - cam[2]
    dx, dy = (hx - cam[0]) / -dz, (hy - cam[1]) / -dz  # per metre of descent
    for k in range(1, SKIM_SAMPLES + 1):
        u = (k / SKIM_SAMPLES) * (scene.canopy + skim)  # height above the hit
        x, y, z = hx - u * dx, hy - u * dy, hz + u
        if above_block_max(dsm, x, y, z - skim):
            continue  # nothing around reaches within skim of the ray: the same answer as sampling, cheaper
        top = bilinear(dsm.data, dsm.inv, x, y)
        if z - top < skim and top - bilinear(gnd.data, gnd.inv, x, y) > scene.hidden_height:  # ground only if close
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _skimmed_kernel(scene, hits, out):
    for i in range(hits.shape[0]):
        out[i] = skimmed_one(scene, hits[i, 0], hits[i, 1], hits[i, 2])


def skimmed(hits: np.ndarray, scene: Scene) -> np.ndarray:
    """Rays (camera to ``hits`` (N, 3) on the soil) that passed less than ``scene.skim`` above a plant (the DSM
    standing ``scene.hidden_height`` above the ground) on their way down, looked at in :data:`SKIM_SAMPLES` steps
    up to ``canopy + skim`` above the hit: they went over the plant's top without a ray grazing it, so where they
    landed is not the plant's edge."""
    out = np.zeros(len(hits), dtype=np.bool_)
    if len(hits):
        _skimmed_kernel(scene, np.ascontiguousarray(hits, dtype=np.float64), out)
    return out


@numba.njit(cache=True, nogil=True)
def apex_one(dsm, frame, window, work):
    """The highest point of :class:`Raster` ``dsm`` in the parallelogram ``(cx, cy) + ga a + gb b`` (``frame`` =
    (cx, cy, ax, ay, bx, by); ga in [lo_a, hi_a], gb in [lo_b, hi_b], ``window`` = (lo_a, hi_a, lo_b, hi_b)), as
    its (ga, gb): the best of an :data:`APEX_GRID` x :data:`APEX_GRID` lattice of cell centres, then
    :data:`APEX_REFINE` times the best of its 3 x 3 neighbours a third of the step away (a plant's top is one
    smooth dome: 41 samples place it as finely as a 45 x 45 lattice would); the first lattice point when every
    sample is a hole. ``work``: scratch (:data:`APEX_WORK`), sampled a lattice at a time
    (:func:`~matchplant.core.geometry.raycast.bilinear_batch`)."""
    cx, cy, ax, ay, bx, by = frame
    lo_a, hi_a, lo_b, hi_b = window
    sa, sb = (hi_a - lo_a) / APEX_GRID, (hi_b - lo_b) / APEX_GRID  # lattice steps
    n = 0
    for jb in range(APEX_GRID):
        for ja in range(APEX_GRID):
            work[n, GA], work[n, GB] = lo_a + (ja + 0.5) * sa, lo_b + (jb + 0.5) * sb
            n += 1
    best = -math.inf
    ba, bb = work[0, GA], work[0, GB]
    for r in range(APEX_REFINE + 1):
        for k in range(n):  # map points of the lattice (ga, gb)
            work[k, MAP_X] = cx + work[k, GA] * ax + work[k, GB] * bx
            work[k, MAP_Y] = cy + work[k, GA] * ay + work[k, GB] * by
        bilinear_batch(dsm.data, dsm.inv, work[:, MAP_X], work[:, MAP_Y], n, work, work[:, HEIGHT])
        for k in range(n):
            if work[k, HEIGHT] > best:  # the first highest point; NaN never wins
                best, ba, bb = work[k, HEIGHT], work[k, GA], work[k, GB]
        if r == APEX_REFINE:
            break
        sa, sb = sa / 3.0, sb / 3.0  # a finer lattice around the best point, a third of the step
        n = 0
        for jb in range(-1, 2):
            for ja in range(-1, 2):
                if ja != 0 or jb != 0:
                    work[n, GA], work[n, GB] = ba + ja * sa, bb + jb * sb
                    n += 1
    return ba, bb
