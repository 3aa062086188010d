"""A camera's pose (an OpenSfM shot): ``X_cam = R X_world + t`` with ``R`` from the angle-axis ``rotation``;
the camera centre is ``C = -R^T t`` (docs/DESIGN.md §3)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from matchplant.core.geometry.camera import Camera


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of an angle-axis vector."""
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix()


def rotation_vector(matrix: np.ndarray) -> np.ndarray:
    """Angle-axis vector of a rotation matrix (3, 3)."""
    return Rotation.from_matrix(np.asarray(matrix, dtype=float)).as_rotvec()


@dataclass(frozen=True)
class Shot:
    """One image's pose and camera."""

    id: str
    camera: Camera
    rotation: np.ndarray  # angle-axis, world -> camera
    translation: np.ndarray
    capture_time: float | None = None
    gps_position: tuple | None = None  # as stored; not converted by ODM - do not use for placement
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    @cached_property
    def R(self) -> np.ndarray:
        """World -> camera rotation matrix (3, 3)."""
        return rotation_matrix(self.rotation)

    @cached_property
    def center(self) -> np.ndarray:
        """Camera centre in the reconstruction frame."""
        return -self.R.T @ np.asarray(self.translation, dtype=float)

    @classmethod
    def from_center(cls, id: str, camera: Camera, R: np.ndarray, center: np.ndarray, **kw) -> Shot:
        """A shot from a world -> camera rotation matrix and the camera centre."""
        R = np.asarray(R, dtype=float)
        t = -R @ np.asarray(center, dtype=float)
        return cls(id=id, camera=camera, rotation=rotation_vector(R), translation=t, **kw)

    def with_camera(self, camera: Camera) -> Shot:
        """The same pose with another camera (e.g. the undistorted one)."""
        return replace(self, camera=camera)

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the reconstruction frame to camera-frame points (N, 3)."""
        # einsum, not ``@``: a multi-threaded BLAS spends ~30x the CPU on (N, 3) x (3, 3) products
        return np.einsum("...j,ij->...i", np.asarray(points, dtype=float), self.R) + np.asarray(
            self.translation, dtype=float
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the reconstruction frame to pixels (N, 2); NaN behind the camera."""
        return self.camera.project(self.world_to_camera(points))

    def ray_directions(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions (N, 3) in the reconstruction frame through pixels ``uv``."""
        return self.camera.bearings(uv) @ self.R  # rows are R^T b: camera to world

    def to_opensfm(self) -> dict:
        """The shot as an OpenSfM reconstruction's shot entry."""
        d = {
            "rotation": [float(v) for v in self.rotation],
            "translation": [float(v) for v in self.translation],
            "camera": self.camera.id,
        }
        if self.capture_time is not None:
            d["capture_time"] = float(self.capture_time)
        if self.gps_position is not None:
            d["gps_position"] = [float(v) for v in self.gps_position]
        d.update(self.extra)
        return d
