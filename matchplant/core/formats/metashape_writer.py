"""Our writer of Metashape camera exports (Agisoft XML), for tests and benchmarks: a field's poses in Metashape's
convention, read back by :func:`~matchplant.core.formats.metashape.read_metashape` (docs/DESIGN.md §8)."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from matchplant.core.geometry.frame_camera import FrameCamera
from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.geodetic import DatumTopocentricFrame, TangentFrame, map_transformer
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_text


def write_metashape(path: str | Path, shots: dict[str, Shot], frame: Frame) -> Path:
    """Write shots (any of our cameras without fisheye; poses in ``frame``) as a Metashape camera export.

    The chunk is an east-north-up frame around the cameras on ``frame``'s datum (chunk transform to geocentric:
    rotation Qᵀ, the origin, scale 1) with ``frame``'s CRS as reference. A Metashape chunk is rigid in geocentric
    space and a map projection is not (docs/DESIGN.md §3): ``frame``'s directions reach the chunk through the
    Jacobian G (frame <- east-north-up) at each camera, whose scale across differs from its scale along the
    vertical by the projection's scale (about 1e-4). No rotation carries that, so each photo gets its own sensor
    (Metashape's "split groups"): the pose takes the rotation of an RQ factorisation of R·G and the sensor its
    triangular part (:func:`_sensor_for`), which gives back the rays of ``frame`` through the reader's tangent
    frame at the camera (:class:`~matchplant.core.geometry.geodetic.TangentFrame`)."""
    crs = frame.crs
    ids = sorted(shots)
    centres = frame.to_map(np.array([shots[k].center for k in ids]))
    lon, lat, _ = geocentric_to_geodetic_from_map(centres.mean(axis=0), crs)
    enu = DatumTopocentricFrame(lat, lon, 0.0, crs.geodetic_crs or crs, crs)
    local = enu.from_map(centres)
    cams, sensor_xml = [], []
    for k, c in zip(ids, local):
        shot = shots[k]
        G = np.linalg.solve(TangentFrame(frame, shot.center).J, TangentFrame(enu, c).J)  # frame <- ENU
        triangle, R = _rq(shot.R @ G)  # R: ENU -> camera
        sensor_xml.append(_sensor_xml(len(cams), _sensor_for(shot.camera, triangle, k)))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T, c
        cams.append(
            f'<camera id="{len(cams)}" sensor_id="{len(cams)}" label="{escape(k)}"><transform>'
            + " ".join(repr(float(v)) for v in T.ravel())
            + "</transform></camera>"
        )
    chunk_tf = (
        "<transform><rotation>" + " ".join(repr(float(v)) for v in enu.Q.T.ravel()) + "</rotation><translation>"
        + " ".join(repr(float(v)) for v in enu.origin) + "</translation><scale>1</scale></transform>"
    )  # fmt: skip
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n<document version="1.5.0">\n<chunk label="MatchPlant" enabled="true">'
        f'<sensors next_id="{len(cams)}">{"".join(sensor_xml)}</sensors><cameras next_id="{len(cams)}">'
        + "\n".join(cams)
        + f"</cameras>{chunk_tf}<reference>{escape(crs.to_wkt('WKT1_GDAL'))}</reference></chunk>\n</document>\n"
    )
    return write_text(path, text)


def _rq(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``m = A @ R``: A upper triangular with a positive diagonal, R a rotation (where det(m) > 0)."""
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ m).T)
    a, rot = flip @ r.T @ flip, flip @ q.T
    signs = np.diag(np.sign(np.diag(a)))
    return a @ signs, signs @ rot


def _sensor_for(cam, triangle: np.ndarray, label: str) -> FrameCamera:
    """``cam`` behind the camera-frame map ``triangle`` (upper triangular, within ~1e-4 of a multiple of I).

    A normalised point n becomes L n + e (L, e: ``triangle`` over its corner), seen as K D(L n + e). With
    s² = det L, Brown's distortion D obeys D(s n) = s D_s(n) for the coefficients k_i s^2i and p_i s, so the new
    sensor is K (L D_s(n) + e): L / s - I and e (the projection's scale, ~1e-4, times the camera's tilt) act
    after the distortion instead of before, which moves a ray by that times the distortion's slope."""
    L, e = triangle[:2, :2] / triangle[2, 2], triangle[:2, 2] / triangle[2, 2]
    s = float(np.sqrt(np.linalg.det(L)))
    fx, fy, skew = cam.focal_x, cam.focal_y, getattr(cam, "skew", 0.0)
    return FrameCamera(
        id=f"{cam.id} {label}", projection_type="brown", width=cam.width, height=cam.height,
        focal_x=fx * L[0, 0], focal_y=fy * L[1, 1], skew=fx * L[0, 1] + skew * L[1, 1],
        c_x=fx * e[0] + skew * e[1] + cam.c_x, c_y=fy * e[1] + cam.c_y,
        k1=cam.k1 * s**2, k2=cam.k2 * s**4, k3=cam.k3 * s**6, k4=getattr(cam, "k4", 0.0) * s**8,
        p1=cam.p1 * s, p2=cam.p2 * s,
    )  # fmt: skip


def geocentric_to_geodetic_from_map(point: np.ndarray, crs) -> tuple[float, float, float]:
    """(lon, lat, h) on ``crs``'s datum of a map point."""
    geo = (crs.geodetic_crs or crs).to_3d()
    lon, lat, h = map_transformer(crs, geo, what="the cameras' CRS").transform(*np.asarray(point, dtype=float))
    return float(lon), float(lat), float(h)


def _sensor_xml(sid: int, cam) -> str:
    """A ``<sensor>`` with its calibration in Metashape's convention (the reader's conversion, inverted)."""
    if cam.projection_type not in ("perspective", "brown", "radial", "simple_radial"):
        raise InputError(
            f"camera '{cam.id}' is a {cam.projection_type} camera, which Metashape's frame model cannot hold",
            fix="export frame (pinhole) cameras only",
        )
    s = float(max(cam.width, cam.height))
    cal = {
        "f": cam.focal_y * s, "cx": cam.c_x * s, "cy": cam.c_y * s, "b1": (cam.focal_x - cam.focal_y) * s,
        "b2": getattr(cam, "skew", 0.0) * s, "k1": cam.k1, "k2": cam.k2, "k3": cam.k3,
        "k4": getattr(cam, "k4", 0.0), "p1": cam.p2, "p2": cam.p1,
    }  # fmt: skip
    res = f'<resolution width="{cam.width}" height="{cam.height}"/>'
    return (
        f'<sensor id="{sid}" label="{escape(cam.id)}" type="frame">{res}<calibration type="frame" class="adjusted">'
        + res
        + "".join(f"<{k}>{float(v)!r}</{k}>" for k, v in cal.items())
        + "</calibration></sensor>"
    )
