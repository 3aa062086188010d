"""Pixels to the ground and back: a shot's pose, the reconstruction frame and the DSM together.

``pixels_to_ground`` casts rays through pixels and intersects them with the DSM in the map CRS;
``ground_to_pixels`` projects map points into an image. For an :class:`~matchplant.core.geometry.frames.OffsetFrame`
rays stay straight in map space and the intersection is exact; for a topocentric frame the straight
map-space ray is a sub-millimetre approximation, which a few secant steps on the exact mapping remove.
"""

from __future__ import annotations

import numpy as np

from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import HIT, Surface

# a topocentric frame: the straight map-space ray through the camera and the point where the reconstruction-frame
# ray has come down this far (at least REACH_MIN metres; a ray's descent per unit at least DESCENT_MIN)
REACH_MIN = 1.0
DESCENT_MIN = 1e-3
SECANT_STEP = 1e-3  # the secant steps on the exact curve start this far (ray parameter) from the straight hit
SECANT_ITERATIONS = 6  # secant steps at most
SECANT_TOLERANCE = 1e-7  # metres: the largest height error above the target at which they stop
SECANT_FLAT = 1e-15  # two heights closer than this: no secant through them (the step keeps its point)
SETTLED = 0.5  # a hit below this share of the clearance above the surface had settled onto it


def pixels_to_ground(
    shot: Shot, uv: np.ndarray, frame: Frame, surface: Surface, *, clearance: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Map points (N, 3) where the rays through pixels ``uv`` (N, 2) meet the DSM, and a status per ray.

    ``clearance`` > 0: a ray stops where it first comes within that many metres above the surface
    (:meth:`Surface.intersect`), so a ray grazing a plant's top stays on the plant.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    return rays_to_ground(shot, shot.ray_directions(uv), frame, surface, clearance=clearance)


def rays_to_ground(
    shot: Shot,
    dirs: np.ndarray,
    frame: Frame,
    surface: Surface,
    *,
    clearance: float = 0.0,
    settle: float = 0.0,
    heights: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pixels_to_ground` for ray directions (N, 3) in the reconstruction frame, already computed
    (:meth:`Shot.ray_directions`); the same rays can then meet several surfaces. ``settle`` and ``heights`` (the
    range of map heights to search per ray, when known): :meth:`Surface.intersect`."""
    c = shot.center
    if frame.is_affine:
        origin = frame.to_map(c[None, :])
        map_dirs = frame.map_directions(dirs)  # a shift keeps them; a photo's tangent frame turns them
        points, _, status = surface.intersect(origin, map_dirs, clearance=clearance, settle=settle, heights=heights)
        return points, status
    # Non-affine frame: a straight map-space ray through the centre and a point near the ground...
    c_map = frame.to_map(c[None, :])[0]
    reach = max(c_map[2] - surface.zmin, REACH_MIN) / np.maximum(-dirs[:, 2], DESCENT_MIN)
    far_map = frame.to_map(c[None, :] + reach[:, None] * dirs)
    map_dirs = (far_map - c_map) / reach[:, None]
    points, s, status = surface.intersect(c_map[None, :], map_dirs, clearance=clearance, settle=settle, heights=heights)
    # ...then secant steps on the exact curve s -> frame.to_map(c + s * dir).
    ok = status == HIT
    if ok.any():
        d = dirs[ok]
        # each ray's height above the surface: the clearance, or 0 where it settled onto the surface
        target = np.full(int(ok.sum()), clearance)
        if settle > 0 and clearance > 0:
            p = points[ok]
            target[p[:, 2] - surface.sample(p[:, 0], p[:, 1]) < SETTLED * clearance] = 0.0

        def g(sv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            p = frame.to_map(c[None, :] + sv[:, None] * d)
            return p, p[:, 2] - surface.sample(p[:, 0], p[:, 1]) - target

        s0 = s[ok]
        s1 = s0 + SECANT_STEP
        _, f0 = g(s0)
        p1, f1 = g(s1)
        for _ in range(SECANT_ITERATIONS):
            denom = np.where(np.abs(f1 - f0) > SECANT_FLAT, f1 - f0, np.nan)
            s2 = np.where(np.isfinite(denom), s1 - f1 * (s1 - s0) / denom, s1)
            s0, f0 = s1, f1
            s1 = s2
            p1, f1 = g(s1)
            if np.nanmax(np.abs(f1), initial=0.0) < SECANT_TOLERANCE:
                break
        points[ok] = p1
    return points, status


def ground_to_pixels(shot: Shot, points_map: np.ndarray, frame: Frame) -> np.ndarray:
    """Pixels (N, 2) of map points (N, 3) in ``shot``'s image; NaN behind the camera."""
    return shot.project(frame.from_map(np.asarray(points_map, dtype=float).reshape(-1, 3)))
