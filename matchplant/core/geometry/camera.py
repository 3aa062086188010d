"""Camera models with OpenSfM's conventions (docs/DESIGN.md §3), vectorised over many points.

Camera frame: x right, y down, z forward. Normalised image coordinates are scaled by
``S = max(width, height)`` and centred: ``u = x_n * S + (w - 1) / 2``, ``v = y_n * S + (h - 1) / 2``.

Two families cover OpenSfM's frame cameras:

* :class:`PinholeCamera` - ``perspective`` (focal, k1, k2), ``simple_radial``, ``radial`` and ``brown``
  (focal_x, focal_y, c_x, c_y, k1, k2, k3, p1, p2): ``x = X/Z`` then radial and tangential distortion.
* :class:`FisheyeCamera` - ``fisheye`` (focal, k1, k2) and ``fisheye_opencv`` (focal_x, focal_y, c_x,
  c_y, k1..k4): angle ``theta = atan2(sqrt(X^2 + Y^2), Z)`` then ``theta_d = theta (1 + k1 theta^2 + ...)``.

Each maps camera-frame points to pixels (:meth:`project`) and pixels to unit bearing vectors
(:meth:`bearings`); the inverse of the distortion is solved with Newton's method to machine precision.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from matchplant.core.runtime.errors import GeometryError

PINHOLE_TYPES = ("perspective", "brown", "radial", "simple_radial")
FISHEYE_TYPES = ("fisheye", "fisheye_opencv")
_NEWTON_ITERATIONS = 30


@dataclass(frozen=True)
class Camera:
    """Common part: image size, focal lengths and principal point in normalised units."""

    id: str
    projection_type: str
    width: int
    height: int
    focal_x: float
    focal_y: float
    c_x: float = 0.0
    c_y: float = 0.0

    @property
    def scale(self) -> float:
        """Pixels per normalised unit: the larger image side."""
        return float(max(self.width, self.height))

    # -- normalised <-> pixel -------------------------------------------------------------------
    def normalized_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Normalised image coordinates to pixels (pixel centres at integers, origin top-left)."""
        xy = np.asarray(xy, dtype=float)
        s = self.scale
        return np.stack([xy[..., 0] * s + (self.width - 1) / 2.0, xy[..., 1] * s + (self.height - 1) / 2.0], axis=-1)

    def pixel_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Pixels to normalised image coordinates (centred, divided by the larger side)."""
        uv = np.asarray(uv, dtype=float)
        s = self.scale
        return np.stack(
            [(uv[..., 0] - (self.width - 1) / 2.0) / s, (uv[..., 1] - (self.height - 1) / 2.0) / s], axis=-1
        )

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image stored at another size (normalised parameters are unchanged).

        ODM may write undistorted images smaller than the camera's nominal size; the aspect ratio must
        match, otherwise the file is not an image of this camera.
        """
        if abs(width / height - self.width / self.height) > 0.01:
            raise GeometryError(
                f"image size {width}x{height} does not have the aspect ratio of camera '{self.id}' "
                f"({self.width}x{self.height})",
                fix="check that the image belongs to this reconstruction",
            )
        return replace(self, width=int(width), height=int(height))

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True for pixels inside the image (its outer pixel edges), widened by ``margin`` pixels."""
        uv = np.asarray(uv, dtype=float)
        return (
            (uv[..., 0] >= -0.5 - margin)
            & (uv[..., 0] <= self.width - 0.5 + margin)
            & (uv[..., 1] >= -0.5 - margin)
            & (uv[..., 1] <= self.height - 0.5 + margin)
        )

    # -- to be provided by each family ----------------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Camera-frame points (N, 3) to pixels (N, 2)."""
        raise NotImplementedError

    def bearings(self, uv: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Pixels (N, 2) to unit bearing vectors (N, 3) in the camera frame."""
        raise NotImplementedError

    def to_opensfm(self) -> dict:  # pragma: no cover - abstract
        """The camera as an OpenSfM reconstruction's camera entry."""
        raise NotImplementedError


@dataclass(frozen=True)
class PinholeCamera(Camera):
    """Rectilinear camera with Brown-Conrady distortion (covers perspective, radial, brown)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def _radial(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The radial factor 1 + k1 r² + k2 r⁴ + k3 r⁶ and its derivative with respect to r²."""
        k1, k2, k3 = self.k1, self.k2, self.k3
        return 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)), k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)

    def _coefficients(self) -> tuple[float, ...]:
        """Every distortion coefficient (all zero: no distortion)."""
        return (self.k1, self.k2, self.k3, self.p1, self.p2)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = x * x + y * y
        radial, _ = self._radial(r2)
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def _undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert :meth:`_distort` with Newton's method on the 2x2 Jacobian."""
        if not any(self._coefficients()):
            return xd, yd
        x, y = xd.copy(), yd.copy()
        p1, p2 = self.p1, self.p2
        for _ in range(_NEWTON_ITERATIONS):
            r2 = x * x + y * y
            radial, d_radial = self._radial(r2)
            fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
            fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
            j11 = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j12
            dx = (j22 * fx - j12 * fy) / det
            dy = (j11 * fy - j12 * fx) / det
            x = x - dx
            y = y - dy
            if np.nanmax(np.abs(dx) + np.abs(dy), initial=0.0) < 1e-15:
                break
        return x, y

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) to pixels (N, 2); points at or behind the camera give NaN."""
        p = np.asarray(points_cam, dtype=float)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(z > 0, p[..., 0] / z, np.nan)
            y = np.where(z > 0, p[..., 1] / z, np.nan)
        xd, yd = self._distort(x, y)
        return self.normalized_to_pixel(self._affine(xd, yd))

    def _affine(self, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
        """Distorted coordinates to normalised image coordinates: the focal lengths and the principal point."""
        return np.stack([self.focal_x * xd + self.c_x, self.focal_y * yd + self.c_y], axis=-1)

    def _affine_inverse(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image coordinates back to distorted coordinates (the inverse of :meth:`_affine`)."""
        return (n[..., 0] - self.c_x) / self.focal_x, (n[..., 1] - self.c_y) / self.focal_y

    def bearings(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) to unit bearing vectors (N, 3) in the camera frame."""
        xd, yd = self._affine_inverse(self.pixel_to_normalized(uv))
        x, y = self._undistort(xd, yd)
        inv = 1.0 / np.sqrt(x * x + y * y + 1.0)  # (x, y, 1) scaled to unit length, without temporaries
        b = np.empty(x.shape + (3,))
        b[..., 0], b[..., 1], b[..., 2] = x * inv, y * inv, inv
        return b

    def to_opensfm(self) -> dict:
        """The camera as an OpenSfM reconstruction's camera entry (the parameters of its projection type)."""
        d = {"projection_type": self.projection_type, "width": self.width, "height": self.height}
        if self.projection_type == "perspective":
            d.update(focal=self.focal_x, k1=self.k1, k2=self.k2)
        elif self.projection_type == "simple_radial":
            d.update(focal_x=self.focal_x, focal_y=self.focal_y, c_x=self.c_x, c_y=self.c_y, k1=self.k1)
        elif self.projection_type == "radial":
            d.update(focal_x=self.focal_x, focal_y=self.focal_y, c_x=self.c_x, c_y=self.c_y, k1=self.k1, k2=self.k2)
        else:
            d.update(
                focal_x=self.focal_x,
                focal_y=self.focal_y,
                c_x=self.c_x,
                c_y=self.c_y,
                k1=self.k1,
                k2=self.k2,
                k3=self.k3,
                p1=self.p1,
                p2=self.p2,
            )
        return d

    def undistorted(self) -> PinholeCamera:
        """A ``perspective`` camera without distortion, as OpenSfM writes for undistorted images."""
        f = (self.focal_x + self.focal_y) / 2.0
        return PinholeCamera(
            id=self.id, projection_type="perspective", width=self.width, height=self.height, focal_x=f, focal_y=f
        )


@dataclass(frozen=True)
class FisheyeCamera(Camera):
    """Equidistant-type fisheye: ``fisheye`` (k1, k2) and ``fisheye_opencv`` (k1..k4)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    def _theta_d(self, th: np.ndarray) -> np.ndarray:
        t2 = th * th
        return th * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) to pixels (N, 2) through the fisheye model."""
        p = np.asarray(points_cam, dtype=float)
        r = np.hypot(p[..., 0], p[..., 1])
        theta = np.arctan2(r, p[..., 2])
        td = self._theta_d(theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(r > 0, td / r, 1.0 / np.where(p[..., 2] > 0, p[..., 2], np.nan))
        x = s * p[..., 0]
        y = s * p[..., 1]
        return self.normalized_to_pixel(np.stack([self.focal_x * x + self.c_x, self.focal_y * y + self.c_y], axis=-1))

    def bearings(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) to unit bearing vectors (N, 3) in the camera frame (Newton inversion of the fisheye model)."""
        n = self.pixel_to_normalized(uv)
        xd = (n[..., 0] - self.c_x) / self.focal_x
        yd = (n[..., 1] - self.c_y) / self.focal_y
        td = np.hypot(xd, yd)
        th = td.copy()
        for _ in range(_NEWTON_ITERATIONS):
            t2 = th * th
            f = self._theta_d(th) - td
            df = 1.0 + t2 * (3 * self.k1 + t2 * (5 * self.k2 + t2 * (7 * self.k3 + t2 * 9 * self.k4)))
            step = f / df
            th = th - step
            if np.nanmax(np.abs(step), initial=0.0) < 1e-15:
                break
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(td > 0, np.sin(th) / td, 0.0)
        return np.stack([xd * scale, yd * scale, np.cos(th)], axis=-1)

    def to_opensfm(self) -> dict:
        """The camera as an OpenSfM reconstruction's camera entry (the parameters of its projection type)."""
        d = {"projection_type": self.projection_type, "width": self.width, "height": self.height}
        if self.projection_type == "fisheye":
            d.update(focal=self.focal_x, k1=self.k1, k2=self.k2)
        else:
            d.update(
                focal_x=self.focal_x,
                focal_y=self.focal_y,
                c_x=self.c_x,
                c_y=self.c_y,
                k1=self.k1,
                k2=self.k2,
                k3=self.k3,
                k4=self.k4,
            )
        return d


def camera_from_opensfm(camera_id: str, d: dict) -> Camera:
    """Build a camera from an entry of ``reconstruction.json``'s ``cameras``."""
    t = d.get("projection_type", "perspective")
    if t not in PINHOLE_TYPES + FISHEYE_TYPES:
        raise GeometryError(
            f"camera '{camera_id}' has projection type '{t}', which MatchPlant does not support",
            fix=f"supported: {', '.join(PINHOLE_TYPES + FISHEYE_TYPES)}; re-run ODM with --camera-lens brown",
        )
    try:
        w, h = int(d["width"]), int(d["height"])
        if t in ("perspective", "fisheye"):
            f = float(d["focal"])
            common = dict(id=camera_id, projection_type=t, width=w, height=h, focal_x=f, focal_y=f)
            if t == "perspective":
                return PinholeCamera(**common, k1=float(d.get("k1", 0)), k2=float(d.get("k2", 0)))
            return FisheyeCamera(**common, k1=float(d.get("k1", 0)), k2=float(d.get("k2", 0)))
        fx = float(d["focal_x"])
        fy = float(d.get("focal_y", fx))
        common = dict(
            id=camera_id,
            projection_type=t,
            width=w,
            height=h,
            focal_x=fx,
            focal_y=fy,
            c_x=float(d.get("c_x", 0)),
            c_y=float(d.get("c_y", 0)),
        )
        k = {name: float(d.get(name, 0.0)) for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
        if t in ("brown", "radial", "simple_radial"):
            return PinholeCamera(**common, k1=k["k1"], k2=k["k2"], k3=k["k3"], p1=k["p1"], p2=k["p2"])
        if t == "fisheye_opencv":
            return FisheyeCamera(**common, k1=k["k1"], k2=k["k2"], k3=k["k3"], k4=k["k4"])
    except KeyError as exc:
        raise GeometryError(
            f"camera '{camera_id}' ({t}) lacks the parameter {exc}",
            fix="the reconstruction file is incomplete; re-run the reconstruction",
        ) from exc
    raise AssertionError(t)  # pragma: no cover - every supported type returned above
