"""Geocentric coordinates of any datum to a local east-north-up frame and on to a map CRS (docs/DESIGN.md §3).

Metashape places its cameras in the geocentric (earth-centred) frame of the chunk's datum. A
:class:`DatumTopocentricFrame` is the east-north-up frame around a point on that datum's ellipsoid: a rigid
motion of the geocentric frame (so camera poses move into it exactly and rays stay straight), converted to the
map CRS with PROJ (``topocentric`` then ``cart`` on the datum's own ellipsoid, then the datum's geographic 3D CRS to
the map CRS; a vertical datum needs its geoid grid, refused by name when PROJ lacks it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from matchplant.core.geometry.frames import Frame, TopocentricFrame, _proj
from matchplant.core.runtime.errors import GeometryError

if TYPE_CHECKING:
    from pyproj import CRS


def ellipsoid_params(crs: CRS) -> tuple[float, float]:
    """Semi-major axis (m) and squared eccentricity of ``crs``'s ellipsoid."""
    ell = crs.ellipsoid
    if ell is None:
        raise GeometryError(f"the CRS {crs.name!r} has no ellipsoid", fix="use a geographic or projected CRS")
    a = float(ell.semi_major_metre)
    b = float(ell.semi_minor_metre)
    return a, 1.0 - (b * b) / (a * a)


def enu_rotation(lat: float, lon: float) -> np.ndarray:
    """The rotation (3, 3) from geocentric axes to east-north-up axes at geodetic ``lat``, ``lon`` (degrees)."""
    phi, lam = np.radians(lat), np.radians(lon)
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def geodetic_to_geocentric(lat: float, lon: float, h: float, a: float, e2: float) -> np.ndarray:
    """Geocentric (x, y, z) of a geodetic point on the ellipsoid (a, e²)."""
    phi, lam = np.radians(lat), np.radians(lon)
    n = a / np.sqrt(1.0 - e2 * np.sin(phi) ** 2)
    return np.array(
        [(n + h) * np.cos(phi) * np.cos(lam), (n + h) * np.cos(phi) * np.sin(lam), (n * (1.0 - e2) + h) * np.sin(phi)]
    )


def geocentric_to_geodetic(xyz: np.ndarray, crs: CRS) -> np.ndarray:
    """Geocentric points (N, 3) of ``crs``'s datum to (lon, lat, ellipsoidal height), exactly (PROJ ``cart``)."""
    a, e2 = ellipsoid_params(crs)
    cart = _proj().Transformer.from_pipeline(
        f"+proj=pipeline +step +inv +proj=cart +a={a!r} +es={e2!r} +step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    p = np.asarray(xyz, dtype=float).reshape(-1, 3)
    lon, lat, h = cart.transform(p[:, 0], p[:, 1], p[:, 2])
    return np.stack([lon, lat, h], axis=-1)


def map_transformer(source: CRS, target: CRS, *, what: str):
    """A pyproj transformer from ``source`` to ``target`` (3D where they are), refusing a ballpark one: a
    datum or geoid shift whose grid PROJ lacks is an error naming both CRSs, never a silent metre."""
    pyproj = _proj()
    src = source if source.is_compound or len(source.axis_info) == 3 else source.to_3d()
    dst = target if target.is_compound or len(target.axis_info) == 3 else target.to_3d()
    try:
        return pyproj.Transformer.from_crs(src, dst, always_xy=True, only_best=True)
    except pyproj.exceptions.ProjError as exc:
        raise GeometryError(
            f"{what}: PROJ cannot convert {source.name!r} to {target.name!r} exactly here ({exc})",
            fix="install the PROJ grid it names (projsync --file <grid>, or PROJ_NETWORK=ON), "
            "or export the project in a CRS without that datum or geoid",
        ) from exc


class DatumTopocentricFrame(TopocentricFrame):
    """East-north-up around (lat, lon, h) on the ellipsoid of ``geodetic_crs`` (any datum), to the map ``crs``."""

    kind = "topocentric"

    def __init__(self, lat: float, lon: float, alt: float, geodetic_crs: CRS, crs: CRS):
        self.lat, self.lon, self.alt = float(lat), float(lon), float(alt)
        self.crs = crs
        self.geodetic_crs = geodetic_crs.geodetic_crs or geodetic_crs
        self.a, self.e2 = ellipsoid_params(self.geodetic_crs)
        self.origin = geodetic_to_geocentric(self.lat, self.lon, self.alt, self.a, self.e2)
        self.Q = enu_rotation(self.lat, self.lon)
        ellps = f"+a={self.a!r} +es={self.e2!r}"
        self._enu_to_lla = _proj().Transformer.from_pipeline(
            f"+proj=pipeline +step +inv +proj=topocentric {ellps} +lat_0={self.lat!r} +lon_0={self.lon!r} "
            f"+h_0={self.alt!r} +step +inv +proj=cart {ellps} +step +proj=unitconvert +xy_in=rad +xy_out=deg"
        )
        self._lla_to_map = map_transformer(self.geodetic_crs, crs, what="the cameras' frame")

    def from_geocentric(self, xyz: np.ndarray) -> np.ndarray:
        """Geocentric points (N, 3) of the datum to this frame (a rotation and a shift: exact)."""
        return (np.asarray(xyz, dtype=float) - self.origin) @ self.Q.T

    def describe(self) -> str:
        """One line for the log."""
        return (
            f"east-north-up around lat {self.lat:.7f}, lon {self.lon:.7f} on {self.geodetic_crs.name} "
            f"-> {self.crs.name}"
        )


class ReprojectedFrame(Frame):
    """Another frame whose map coordinates are converted to ``crs`` with PROJ (exact; rays become slightly
    curved in the new map, which the ray walk follows: not affine)."""

    kind = "reprojected"

    def __init__(self, base: Frame, crs: CRS):
        self.base, self.crs = base, crs
        self._to = map_transformer(base.crs, crs, what="the cameras' map CRS to the DSM's")

    def to_map(self, points: np.ndarray) -> np.ndarray:
        """Frame points (N, 3) to ``crs``."""
        shape = np.shape(points)
        p = self.base.to_map(np.asarray(points, dtype=float).reshape(-1, 3))
        return np.stack(self._to.transform(p[:, 0], p[:, 1], p[:, 2]), axis=-1).reshape(shape)

    def from_map(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in ``crs`` to the frame."""
        shape = np.shape(points)
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        q = np.stack(self._to.transform(p[:, 0], p[:, 1], p[:, 2], direction="INVERSE"), axis=-1)
        return self.base.from_map(q).reshape(shape)

    def describe(self) -> str:
        """One line for the log."""
        return f"{getattr(self.base, 'describe', lambda: self.base.kind)()} -> {self.crs.name}"


class TangentFrame(Frame):
    """The tangent (first-order) map of another frame at one point: ``map = m0 + J (p - p0)``.

    Module 8 walks straight map rays (docs/DESIGN.md §3); through a photo's tangent frame at its camera centre a
    ray of a geocentric-rigid project (Metashape) stays straight, and departs from the exact conversion by the
    earth's curvature over the ray's horizontal run r (r²/2R) and the turn of the map's grid: 0.06 mm for 30 m
    rays, at most 0.33 mm for 60 m rays within 60° of nadir (tests/test_core_cameras.py). ``J`` maps frame
    directions to map directions (:meth:`map_directions`)."""

    kind = "tangent"

    def __init__(self, base: Frame, point: np.ndarray, h: float = 1.0):
        self.base, self.crs = base, base.crs
        self.p0 = np.asarray(point, dtype=float)
        pts = self.p0[None, :] + np.concatenate([np.eye(3) * h, -np.eye(3) * h, np.zeros((1, 3))])
        m = base.to_map(pts)
        self.m0 = m[6]
        self.J = ((m[:3] - m[3:6]) / (2 * h)).T  # central differences: F is smooth, the error is ~h² F'''
        self.J_inv = np.linalg.inv(self.J)

    @property
    def is_affine(self) -> bool:
        """Straight lines stay straight (with :meth:`map_directions` for their directions)."""
        return True

    def to_map(self, points: np.ndarray) -> np.ndarray:
        """Frame points (..., 3) to the map."""
        return (np.asarray(points, dtype=float) - self.p0) @ self.J.T + self.m0

    def from_map(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) to the frame."""
        return (np.asarray(points, dtype=float) - self.m0) @ self.J_inv.T + self.p0

    def map_directions(self, dirs: np.ndarray) -> np.ndarray:
        """Unit frame directions (N, 3) as unit map directions."""
        d = np.asarray(dirs, dtype=float) @ self.J.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def describe(self) -> str:
        """One line for the log."""
        return f"tangent map of ({getattr(self.base, 'describe', lambda: self.base.kind)()}) at a camera"
