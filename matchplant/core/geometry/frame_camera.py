"""The frame camera of Agisoft Metashape and Pix4D: Brown's model with k4, affinity and skew (docs/DESIGN.md §3).

In our normalised units (docs/DESIGN.md §3) a camera-frame point ``(X, Y, Z)`` goes to

    x = X / Z,  y = Y / Z,  r² = x² + y²
    x' = x (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) + 2 p1 x y + p2 (r² + 2 x²)
    y' = y (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) + p1 (r² + 2 y²) + 2 p2 x y
    x_n = focal_x x' + skew y' + c_x,   y_n = focal_y y' + c_y

which is :class:`~matchplant.core.geometry.camera.PinholeCamera` (OpenCV's order of p1 and p2) plus ``k4`` and
``skew``. The readers convert each program's parameters to these exactly (Metashape's P1 is our p2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from matchplant.core.geometry.camera import PinholeCamera
from matchplant.core.runtime.errors import GeometryError


@dataclass(frozen=True)
class FrameCamera(PinholeCamera):
    """A pinhole camera with radial k1..k4, tangential p1/p2 (OpenCV order) and skew, all normalised."""

    k4: float = 0.0
    skew: float = 0.0

    def _radial(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The radial factor and its derivative with respect to r²."""
        k1, k2, k3, k4 = self.k1, self.k2, self.k3, self.k4
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        d_radial = k1 + r2 * (2.0 * k2 + r2 * (3.0 * k3 + r2 * 4.0 * k4))
        return radial, d_radial

    def _coefficients(self) -> tuple[float, ...]:
        """Every distortion coefficient, k4 included."""
        return (self.k1, self.k2, self.k3, self.k4, self.p1, self.p2)

    def _affine(self, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
        """Distorted coordinates to normalised image coordinates, with the skew."""
        return np.stack([self.focal_x * xd + self.skew * yd + self.c_x, self.focal_y * yd + self.c_y], axis=-1)

    def _affine_inverse(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image coordinates back to distorted coordinates."""
        yd = (n[..., 1] - self.c_y) / self.focal_y
        return (n[..., 0] - self.c_x - self.skew * yd) / self.focal_x, yd

    def undistorted_project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points to pixels of the same camera without distortion (a pure pinhole: K·X/Z)."""
        p = np.asarray(points_cam, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(p[..., 2] > 0, p[..., 0] / p[..., 2], np.nan)
            y = np.where(p[..., 2] > 0, p[..., 1] / p[..., 2], np.nan)
        return self.normalized_to_pixel(self._affine(x, y))

    def to_opensfm(self) -> dict:
        """OpenSfM's ``brown`` camera, which has no k4 or skew: refused when either is used."""
        if self.k4 or self.skew:
            raise GeometryError(
                f"camera '{self.id}' uses k4 or skew, which an OpenSfM reconstruction cannot hold",
                fix="keep this camera in its Metashape or Pix4D project; it is read from there",
            )
        return super().to_opensfm()  # projection_type "brown": every parameter OpenSfM has
