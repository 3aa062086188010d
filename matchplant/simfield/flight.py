"""The camera, the lawn-mower flight, and the rendering of images by ray casting into the field.

Poses are :class:`~matchplant.core.formats.reconstruction.Shot` objects in the local frame (map CRS minus the
``coords.txt`` offset), the frame ODM's ``reconstruction.json`` is in. Rays come from
``Shot.ray_directions`` (the foundation's camera conventions) and are intersected with the field's
surface: terrain (analytic) plus the canopy-height raster, marched in steps finer than a pixel's
footprint and refined by bisection, so relief displacement and occlusion are real.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from matchplant.core.geometry.camera import PinholeCamera
from matchplant.core.geometry.shot import Shot
from matchplant.simfield.config import Settings
from matchplant.simfield.scene import Rasters, Terrain

START_UTC = dt.datetime(2024, 6, 5, 15, 30, 0, tzinfo=dt.timezone.utc)  # early-season maize flight
SHOT_INTERVAL_S = 2.0
TURN_S = 6.0
GPS_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.timezone.utc)
GPS_LEAP_S = 18  # GPS time = UTC + 18 s
SENSOR_WIDTH_MM = 13.2  # 1-inch sensor


def make_camera(s: Settings) -> PinholeCamera:
    """A ``brown`` camera with small, realistic distortion (monotonic over the whole image)."""
    w, h = s.image_width, s.image_height
    return PinholeCamera(
        id=f"v2 matchplant simcam {w} {h} brown {s.focal:.4f}",
        projection_type="brown",
        width=w,
        height=h,
        focal_x=s.focal,
        focal_y=s.focal * 1.002,
        c_x=0.004,
        c_y=-0.003,
        k1=-0.045,
        k2=0.018,
        k3=0.0,
        p1=0.0006,
        p2=-0.0004,
    )


def nadir_rotation(heading: np.ndarray, tilt_deg: float) -> np.ndarray:
    """World->camera rotation for a camera flying along ``heading`` (unit, horizontal), pitched forward
    by ``tilt_deg`` off nadir: image top points forward, x right, y down, z along the optical axis."""
    f = np.array([heading[0], heading[1], 0.0])
    down = np.array([0.0, 0.0, -1.0])
    t = np.radians(tilt_deg)
    z = np.cos(t) * down + np.sin(t) * f
    y = -np.cos(t) * f + np.sin(t) * down
    x = np.cross(y, z)
    return np.stack([x, y, z])


@dataclass
class Exposure:
    """One photo of the flight: image name, raw camera pose, flight line and true UTC time."""

    name: str
    shot: Shot  # raw camera, local frame
    line: int
    utc: dt.datetime  # true time of the exposure


def plan_flight(s: Settings, terrain: Terrain, camera: PinholeCamera, rng: np.random.Generator) -> list[Exposure]:
    """Serpentine lines along the rows (north-south) with the requested front and side overlap."""
    scale = max(camera.width, camera.height)
    foot_w = s.altitude * camera.width / (s.focal * scale)  # across track (image x)
    foot_h = s.altitude * camera.height / (s.focal * scale)  # along track (image y)
    step_x = (1 - s.overlap_side) * foot_w
    step_y = (1 - s.overlap_front) * foot_h

    def stations(length: float, foot: float, step: float) -> np.ndarray:
        n = 1 if length <= foot else int(np.ceil((length - foot) / step - 1e-9)) + 1
        return length / 2 + (np.arange(n) - (n - 1) / 2) * step

    xs = stations(s.field_width, foot_w, step_x)
    ys = stations(s.field_length, foot_h, step_y)
    z_fly = terrain.height(s.field_width / 2, s.field_length / 2) + s.altitude
    lead = s.altitude * np.tan(np.radians(s.tilt_deg))  # a forward-tilted camera looks ahead of itself
    out: list[Exposure] = []
    t = START_UTC
    for line, x in enumerate(xs):
        north = line % 2 == 0
        heading = np.array([0.0, 1.0 if north else -1.0])
        R0 = nadir_rotation(heading, s.tilt_deg)
        for y in ys if north else ys[::-1]:
            noise = Rotation.from_rotvec(rng.normal(0, np.radians(s.attitude_noise_deg), 3)).as_matrix()
            centre = np.array(
                [x + rng.normal(0, 0.02), y - heading[1] * lead + rng.normal(0, 0.02), z_fly + rng.normal(0, 0.03)]
            )
            name = f"SIM_{len(out) + 1:04d}.JPG"
            out.append(Exposure(name=name, shot=Shot.from_center(name, camera, noise @ R0, centre), line=line, utc=t))
            t += dt.timedelta(seconds=SHOT_INTERVAL_S)
        t += dt.timedelta(seconds=TURN_S)
    return out


def gps_time_of_week(utc: dt.datetime) -> tuple[int, float]:
    """GPS week and seconds of week of a UTC time (GPS runs ahead of UTC by the leap seconds)."""
    sec = (utc - GPS_EPOCH).total_seconds() + GPS_LEAP_S
    week = int(sec // 604800)
    return week, sec - week * 604800


# -- rendering ---------------------------------------------------------------------------------------


def ground_hit(origin: np.ndarray, dirs: np.ndarray, terrain: Terrain) -> np.ndarray:
    """Ray parameter where each ray meets the bare terrain."""
    # start on the terrain's tangent plane below the camera, then Newton steps on
    # f(s) = z(s) - T(x(s), y(s)), f'(s) = d_z - grad T . d_xy (robust on steep slopes and oblique rays)
    z0 = terrain.height(origin[0], origin[1])
    gx, gy = terrain.gradient(origin[0], origin[1])
    s = (origin[2] - z0) / (gx * dirs[:, 0] + gy * dirs[:, 1] - dirs[:, 2])
    for _ in range(2):
        x, y = origin[0] + s * dirs[:, 0], origin[1] + s * dirs[:, 1]
        gx, gy = terrain.gradient(x, y)
        f = origin[2] + s * dirs[:, 2] - terrain.height(x, y)
        s = s - f / (dirs[:, 2] - gx * dirs[:, 0] - gy * dirs[:, 1])
    return s


def cast(
    origin: np.ndarray,
    dirs: np.ndarray,
    terrain: Terrain,
    rasters: Rasters,
    top: float,
    step: float,
    s_g: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Where rays first meet terrain + canopy: (row, col) of the raster cell hit by each ray.

    Between the height ``top`` above the terrain and the terrain itself, each ray is sampled every
    ``step`` metres horizontally; the first sample below the canopy is refined by bisection. ``s_g``,
    the ray parameter of each ray's ground hit, is computed when not given.
    """
    g = rasters.grid
    canopy = rasters.canopy.ravel()
    if s_g is None:
        s_g = ground_hit(origin, dirs, terrain)
    p_g = origin[None, :] + s_g[:, None] * dirs
    # go back up the ray until it is ``top`` above the local terrain (which may rise towards the camera)
    gx, gy = terrain.gradient(p_g[:, 0], p_g[:, 1])
    climb = np.maximum(gx * dirs[:, 0] + gy * dirs[:, 1] - dirs[:, 2], 0.05)  # height gained per unit of s
    s_top = np.maximum(0.0, s_g - 1.1 * top / climb)
    p_top = origin[None, :] + s_top[:, None] * dirs
    h_top = p_top[:, 2] - terrain.height(p_top[:, 0], p_top[:, 1])  # height above ground at s_top (>= top)
    seg = np.maximum(np.hypot(*(p_g - p_top)[:, :2].T), 1e-9)  # horizontal length of the segment
    # segment ends in raster cell units (both inside the grid, so every point between is too)
    lim_c, lim_r = g.width - 1e-3, g.height - 1e-3
    c0 = np.clip((p_top[:, 0] - g.x0) / g.res, 0, lim_c)
    r0 = np.clip((g.y1 - p_top[:, 1]) / g.res, 0, lim_r)
    dc = np.clip((p_g[:, 0] - g.x0) / g.res, 0, lim_c) - c0
    dr = np.clip((g.y1 - p_g[:, 1]) / g.res, 0, lim_r) - r0
    width = g.width
    block, coarse = rasters.block_max()
    bwidth, bmax = coarse.shape[1], coarse.ravel()
    # float32 state halves the memory traffic; cell positions stay exact to 1e-3 cell
    state = [a.astype(np.float32) for a in (r0, dr, c0, dc, h_top)]

    def below(r0, dr, c0, dc, h, t):
        # terrain taken as linear along the short segment: height above ground h_top (1 - t)
        flat = (r0 + t * dr).astype(np.intp) * width + (c0 + t * dc).astype(np.intp)
        return h * (1.0 - t) <= canopy[flat]

    # 1. coarse: skip the stretch [t - dt, t] where the ray stays above the highest canopy within a
    #    block of its start (dt spans under one block, so the whole stretch is covered)
    coarse_dt = 0.9 * block * g.res / seg

    def may_hit(r0, dr, c0, dc, h, dt, t):
        ts = np.maximum(t - dt, 0)
        flat = ((r0 + ts * dr).astype(np.intp) // block) * bwidth + (c0 + ts * dc).astype(np.intp) // block
        return h * (1.0 - t) <= bmax[flat]

    start, _ = _first(may_hit, state, np.zeros(len(dirs), np.float32), coarse_dt.astype(np.float32))
    # 2. fine: every ``step`` metres from there, then bisection between the last sample above and the first below
    lo, hi = _first(below, state, start.astype(np.float32), (step / seg).astype(np.float32))
    for _ in range(4):
        mid = 0.5 * (lo + hi)
        b = below(r0, dr, c0, dc, h_top, mid)
        hi = np.where(b, mid, hi)
        lo = np.where(b, lo, mid)
    return (r0 + hi * dr).astype(np.intp), (c0 + hi * dc).astype(np.intp)


def _first(test, state: list, t0: np.ndarray, dt_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each ray, the first ``t = t0 + i dt`` (i >= 1, capped at 1) where ``test`` holds (always at 1):
    returns (previous t, that t)."""
    n = len(t0)
    t_hit = np.ones(n)
    t_prev = t0.astype(float)
    ix = np.arange(n)
    state = list(state) + [t0, dt_]
    takes_dt = test.__code__.co_argcount == 7
    finished = np.zeros(n, bool)
    i = 1
    while ix.size:
        a, d = state[-2], state[-1]
        t = np.minimum(a + np.float32(i) * d, np.float32(1.0))
        args = state[:5] + ([d] if takes_dt else [])
        new = (test(*args, t) | (t >= 1.0)) & ~finished
        if new.any():
            t_hit[ix[new]] = t[new]
            t_prev[ix[new]] = a[new] + np.float32(i - 1) * d[new]
            finished |= new
        if finished.mean() > 0.3:  # drop finished rays now and then, not every step
            keep = ~finished
            state = [x[keep] for x in state]
            ix = ix[keep]
            finished = finished[keep]
        i += 1
    return t_prev, t_hit


_BEARINGS: dict = {}


def pixel_bearings(camera) -> np.ndarray:
    """Camera-frame unit bearings of every pixel centre, row by row (cached: the same for every shot)."""
    key = camera  # frozen dataclass: every parameter is part of the key
    if key not in _BEARINGS:
        if len(_BEARINGS) > 3:
            _BEARINGS.clear()
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        _BEARINGS[key] = camera.bearings(np.stack([u.ravel(), v.ravel()], axis=1).astype(float))
    return _BEARINGS[key]


def render(
    shot: Shot, terrain: Terrain, rasters: Rasters, top: float, step: float, chunk: int = 250_000
) -> tuple[np.ndarray, np.ndarray]:
    """RGB image (h, w, 3) uint8 and plant-id image (h, w) int32 (0 where no plant) seen by ``shot``."""
    cam = shot.camera
    w, h = cam.width, cam.height
    rgb = np.empty((h * w, 3), np.uint8)
    ids = np.empty(h * w, np.int32)
    origin = shot.center
    bearings = pixel_bearings(cam)
    s_ground = _ground_hits_interpolated(shot, terrain)
    for start in range(0, h * w, chunk):
        k = slice(start, min(start + chunk, h * w))
        # the world directions of Shot.ray_directions(uv) = camera.bearings(uv) @ R, bearings computed once
        r, c = cast(origin, np.einsum("ni,ij->nj", bearings[k], shot.R), terrain, rasters, top, step, s_ground[k])
        rgb[k] = rasters.albedo[r, c]
        lab = rasters.label[r, c]
        ids[k] = np.where(lab > 0, lab, 0)
    return rgb.reshape(h, w, 3), ids.reshape(h, w)


def _ground_hits_interpolated(shot: Shot, terrain: Terrain, every: int = 8) -> np.ndarray:
    """Ground-hit ray parameter of every pixel (row by row), exact on a grid of every ``every``-th pixel
    and bilinear in between: the terrain is smooth, so the error is far below a raster cell."""
    cam = shot.camera
    us = np.unique(np.r_[np.arange(0, cam.width, every), cam.width - 1]).astype(float)
    vs = np.unique(np.r_[np.arange(0, cam.height, every), cam.height - 1]).astype(float)
    uu, vv = np.meshgrid(us, vs)
    coarse = ground_hit(shot.center, shot.ray_directions(np.stack([uu.ravel(), vv.ravel()], 1)), terrain)
    coarse = coarse.reshape(len(vs), len(us))

    def weights(knots: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        x = np.arange(n, dtype=float)
        i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
        return i, (x - knots[i]) / (knots[i + 1] - knots[i])

    iu, fu = weights(us, cam.width)
    iv, fv = weights(vs, cam.height)
    top = coarse[iv][:, iu] * (1 - fu) + coarse[iv][:, iu + 1] * fu
    bottom = coarse[iv + 1][:, iu] * (1 - fu) + coarse[iv + 1][:, iu + 1] * fu
    return (top * (1 - fv)[:, None] + bottom * fv[:, None]).ravel()


def footprint(shot: Shot, terrain: Terrain, n: int = 16) -> np.ndarray:
    """(xmin, ymin, xmax, ymax) of the image's border rays on the terrain (local frame)."""
    cam = shot.camera
    us = np.linspace(-0.5, cam.width - 0.5, n)
    vs = np.linspace(-0.5, cam.height - 0.5, n)
    border = np.concatenate(
        [
            np.stack([us, np.full(n, vs[0])], 1),
            np.stack([us, np.full(n, vs[-1])], 1),
            np.stack([np.full(n, us[0]), vs], 1),
            np.stack([np.full(n, us[-1]), vs], 1),
        ]
    )
    d = shot.ray_directions(border)
    s = ground_hit(shot.center, d, terrain)
    p = shot.center[None, :] + s[:, None] * d
    return np.array([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])
