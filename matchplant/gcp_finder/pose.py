"""Where each GCP appears in an image: the camera's position, heading, pitch and height, and a pinhole.

Without a reconstruction (ODM has not run yet) the pose comes from the image's own metadata: GPS for the
position, DJI's XMP or the flight line for the heading, and one of several height sources, because EXIF
altitudes are often in another height datum than the survey.
"""

from __future__ import annotations

import math

import numpy as np
from pyproj import CRS, Transformer

from matchplant.core.geometry.camera import PinholeCamera
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.metadata import ImageInfo


def camera_rotation(yaw_deg: float, pitch_deg: float = -90.0) -> np.ndarray:
    """World (east, north, up) -> camera (x right, y down, z forward) rotation for a gimbal camera.

    ``yaw`` is the heading of the image's top edge (clockwise from north); ``pitch`` the gimbal pitch
    (-90 straight down, 0 horizontal). Roll is taken as zero (a gimbal keeps it small).
    """
    psi, p = math.radians(yaw_deg), math.radians(pitch_deg)
    h = np.array([math.sin(psi), math.cos(psi), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    z = math.cos(p) * h + math.sin(p) * up
    y = math.sin(p) * h - math.cos(p) * up
    x = np.cross(y, z)
    return np.stack([x, y, z])


def track_yaw(positions: np.ndarray) -> np.ndarray:
    """Heading (degrees from north) of the flight line each image was taken on.

    Consecutive steps in about the same direction (within 30°) form a flight line; a line's heading is
    from its first to its last image, which averages out the GPS noise of single steps. A turn between
    lines is a lone step; images at the ends of a line take that line's heading.
    """
    p = np.asarray(positions, dtype=float)[:, :2]
    n = len(p)
    if n < 2:
        return np.zeros(n)
    seg = np.diff(p, axis=0)
    unit = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    agree = np.einsum("ij,ij->i", unit[1:], unit[:-1]) > math.cos(math.radians(30))
    run = np.r_[0, np.cumsum(~agree)]  # run id of each step
    heading, is_line = {}, {}
    for r in np.unique(run):
        k = np.flatnonzero(run == r)
        d = p[k[-1] + 1] - p[k[0]]
        heading[r], is_line[r] = d, len(k) >= 2
    if not any(is_line.values()):
        is_line = dict.fromkeys(is_line, True)
    out = np.zeros((n, 2))
    for i in range(n):
        arriving = run[i - 1] if i > 0 else None
        leaving = run[i] if i < n - 1 else None
        use = [r for r in (arriving, leaving) if r is not None and is_line[r]] or [
            r for r in (arriving, leaving) if r is not None
        ]
        out[i] = heading[use[0]] / max(np.linalg.norm(heading[use[0]]), 1e-9)
    return np.degrees(np.arctan2(out[:, 0], out[:, 1])) % 360.0


def pinhole(info: ImageInfo, ratio: float) -> PinholeCamera:
    """The image's camera as a distortion-free pinhole (good enough to find a GCP within a zoomed view)."""
    return PinholeCamera(
        id=info.model or "camera",
        projection_type="perspective",
        width=info.width,
        height=info.height,
        focal_x=ratio,
        focal_y=ratio,
    )


def predict_pixels(
    info: ImageInfo, ratio: float, yaw: float, pitch: float, camera_z: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Predicted pixels (N, 2) of map points (N, 3) in one image; ``camera_z`` (N,) is the camera height
    used for each point (so each point's own height above ground can be applied)."""
    R = camera_rotation(yaw, pitch)
    centre = np.broadcast_to(np.r_[info.xyz[:2], 0.0], points.shape).copy()
    centre[:, 2] = camera_z
    return pinhole(info, ratio).project((points - centre) @ R.T)


def footprint(info: ImageInfo, ratio: float, yaw: float, pitch: float, height: float) -> np.ndarray:
    """The image's four corners on a level ground ``height`` metres below the camera (map x, y)."""
    cam = pinhole(info, ratio)
    corners = np.array(
        [[-0.5, -0.5], [info.width - 0.5, -0.5], [info.width - 0.5, info.height - 0.5], [-0.5, info.height - 0.5]]
    )
    rays = cam.bearings(corners) @ camera_rotation(yaw, pitch)
    s = height / np.maximum(-rays[:, 2], 1e-6)
    return info.xyz[:2] + rays[:, :2] * s[:, None]


def camera_positions(infos: list[ImageInfo], crs) -> None:
    """Set each image's ``xyz``: its GPS position in ``crs`` (z: the EXIF altitude or NaN)."""
    t = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True)
    for info in infos:
        x, y = t.transform(info.lon, info.lat)
        info.xyz = np.array([x, y, info.alt if info.alt is not None else np.nan])


def image_yaw(info: ImageInfo, cfg: GcpFinderConfig, track: float) -> float:
    """The heading of the image top: DJI XMP, the flight line's direction, or the configured value."""
    src = cfg.yaw_source
    if src == "auto":
        src = "xmp" if info.yaw is not None else "track"
    if src == "xmp":
        if info.yaw is None:
            raise InputError(
                "the image has no DJI yaw in its XMP", path=info.path, fix="set 'yaw_source' to 'track' or 'fixed'"
            )
        return info.yaw
    if src == "track":
        return (track + cfg.yaw_deg) % 360.0
    return cfg.yaw_deg


def camera_heights(info: ImageInfo, cfg: GcpFinderConfig, pts: np.ndarray, ground: float) -> tuple[np.ndarray, str]:
    """The camera's height (z in the survey's datum) used for each GCP, and which source gave it."""
    hs = cfg.height_source
    if hs == "auto":
        # DJI's relative altitude is robust; EXIF altitudes are often in another height datum than the survey
        hs = "relative" if info.relative_alt is not None else "gps" if info.alt is not None else "fixed"
    if hs == "gps":
        if info.alt is None:
            raise InputError(
                "the image has no GPS altitude",
                path=info.path,
                fix="set 'height_source' to 'relative' or 'fixed' (with flight_height_m)",
            )
        return np.full(len(pts), info.alt + cfg.altitude_offset_m), hs
    if hs == "relative":
        if info.relative_alt is None:
            raise InputError(
                "the image has no DJI relative altitude",
                path=info.path,
                fix="set 'height_source' to 'gps' or 'fixed' (with flight_height_m)",
            )
        return np.full(len(pts), ground + info.relative_alt), hs  # take-off taken at the GCPs' median height
    if cfg.flight_height_m is None:
        raise ConfigError(
            "the images have no altitude; set the flight height", fix="set 'flight_height_m' (metres above ground)"
        )
    return pts[:, 2] + cfg.flight_height_m, hs
