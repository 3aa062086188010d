"""Which photo sees which plant whole, from where: the views, found before any photo is decoded.

For each camera, every plant near it is projected at once (its draped rings, :mod:`.outlines`); a plant is
seen whole when every ring point falls inside the photo in front of the camera. Each view keeps the plant's
pixel box in the photo and how it is seen: the off-nadir angle of the line of sight, the distance, and the
ground sampling distance at the plant (from the projection's Jacobian on the ground, distortion included).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from matchplant.core.geometry.ground import ground_to_pixels
from matchplant.views.cameras import CameraView
from matchplant.views.outlines import Outlines

GSD_STEP = 0.01  # metres: the ground step of the Jacobian behind the sampling distance


@dataclass
class Views:
    """One row per (camera, plant) seen whole: ``box`` is (u0, v0, u1, v1) in the photo's pixels."""

    camera: np.ndarray  # (V,) index into the camera list
    plant: np.ndarray  # (V,) index into the outlines
    box: np.ndarray  # (V, 4)
    off_nadir: np.ndarray  # (V,) degrees
    distance: np.ndarray  # (V,) metres
    gsd: np.ndarray  # (V,) metres per pixel

    def take(self, keep: np.ndarray) -> Views:
        """The views selected by ``keep`` (a mask or indices)."""
        return Views(*(getattr(self, f)[keep] for f in self.__dataclass_fields__))


def camera_views(k: int, cam: CameraView, outlines: Outlines) -> Views:
    """The plants camera ``k`` sees whole."""
    shot, frame = cam.shot, cam.frame
    uv = ground_to_pixels(shot, outlines.centre, frame)
    # a first cut on the centre alone (a plant seen whole has its centre inside too)
    near = np.flatnonzero(np.isfinite(uv).all(axis=1) & shot.camera.in_image(uv))
    if near.size == 0:
        return _empty()
    pts, offsets = outlines.plant_points(near)
    puv = ground_to_pixels(shot, pts, frame)
    inside = shot.camera.in_image(puv) & np.isfinite(puv).all(axis=1)
    starts = 2 * offsets[:-1]  # each point with its prism's bottom
    whole = np.logical_and.reduceat(inside, starts)
    safe = np.where(np.isfinite(puv), puv, 0.0)
    lo = np.minimum.reduceat(safe, starts, axis=0)
    hi = np.maximum.reduceat(safe, starts, axis=0)
    plants = near[whole]
    if plants.size == 0:
        return _empty()
    centre = outlines.centre[plants]
    eye = frame.to_map(shot.center[None, :])[0]
    sight = eye - centre
    distance = np.linalg.norm(sight, axis=1)
    off_nadir = np.degrees(np.arccos(np.clip(sight[:, 2] / distance, -1.0, 1.0)))
    du = ground_to_pixels(shot, centre + [GSD_STEP, 0.0, 0.0], frame) - uv[plants]
    dv = ground_to_pixels(shot, centre + [0.0, GSD_STEP, 0.0], frame) - uv[plants]
    area = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0])  # pixels covered by a GSD_STEP square
    gsd = GSD_STEP / np.sqrt(area)
    box = np.concatenate([lo[whole], hi[whole]], axis=1)
    return Views(np.full(plants.size, k), plants, box, off_nadir, distance, gsd)


def all_views(cameras: list[CameraView], outlines: Outlines) -> Views:
    """:func:`camera_views` of every camera, concatenated."""
    parts = [camera_views(k, cam, outlines) for k, cam in enumerate(cameras)]
    return Views(*(np.concatenate([getattr(p, f) for p in parts]) for f in Views.__dataclass_fields__))


def best_views(views: Views, best: int) -> Views:
    """Each plant's ``best`` views by off-nadir angle (then distance); all of them when ``best`` is 0."""
    order = np.lexsort((views.distance, views.off_nadir, views.plant))
    v = views.take(order)
    if best <= 0:
        return v
    first = np.r_[True, v.plant[1:] != v.plant[:-1]]
    group_start = np.maximum.accumulate(np.where(first, np.arange(len(v.plant)), 0))
    rank = np.arange(len(v.plant)) - group_start
    return v.take(rank < best)


def _empty() -> Views:
    z = np.zeros(0)
    return Views(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4)), z, z, z)
