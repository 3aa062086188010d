"""OpenSfM ``reconstruction.json``: cameras, shots (poses) and points.

A shot's ``rotation`` is the angle-axis vector of the world->camera rotation ``R`` and its
``translation`` is ``t`` with ``X_cam = R X_world + t``; the camera centre is ``C = -R^T t``
(not ``translation``, and never ``gps_position``, which ODM leaves unconverted).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from matchplant.core.camera import Camera, camera_from_opensfm
from matchplant.core.errors import InputError
from matchplant.core.io import read_json, write_json


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix()


def rotation_vector(matrix: np.ndarray) -> np.ndarray:
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
        return rotation_matrix(self.rotation)

    @cached_property
    def center(self) -> np.ndarray:
        return -self.R.T @ np.asarray(self.translation, dtype=float)

    @classmethod
    def from_center(cls, id: str, camera: Camera, R: np.ndarray, center: np.ndarray, **kw) -> "Shot":
        R = np.asarray(R, dtype=float)
        t = -R @ np.asarray(center, dtype=float)
        return cls(id=id, camera=camera, rotation=rotation_vector(R), translation=t, **kw)

    def with_camera(self, camera: Camera) -> "Shot":
        return replace(self, camera=camera)

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        # einsum, not ``@``: a multi-threaded BLAS spends ~30x the CPU on (N, 3) x (3, 3) products
        return np.einsum("...j,ij->...i", np.asarray(points, dtype=float), self.R) + \
            np.asarray(self.translation, dtype=float)

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the reconstruction frame to pixels (N, 2); NaN behind the camera."""
        return self.camera.project(self.world_to_camera(points))

    def ray_directions(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions (N, 3) in the reconstruction frame through pixels ``uv``."""
        return np.einsum("...i,ij->...j", self.camera.bearings(uv), self.R)  # = bearings @ R

    def viewing_direction(self) -> np.ndarray:
        """The optical axis in the world frame."""
        return self.R[2]

    def to_opensfm(self) -> dict:
        d = {"rotation": [float(v) for v in self.rotation], "translation": [float(v) for v in self.translation],
             "camera": self.camera.id}
        if self.capture_time is not None:
            d["capture_time"] = float(self.capture_time)
        if self.gps_position is not None:
            d["gps_position"] = [float(v) for v in self.gps_position]
        d.update(self.extra)
        return d


@dataclass
class Reconstruction:
    cameras: dict[str, Camera]
    shots: dict[str, Shot]
    point_ids: list[str] = field(default_factory=list)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    reference_lla: dict | None = None
    path: Path | None = None

    def shot(self, shot_id: str) -> Shot:
        try:
            return self.shots[shot_id]
        except KeyError:
            raise InputError(f"image '{shot_id}' is not in the reconstruction ({len(self.shots)} images are)",
                             path=self.path, fix="ODM could not place this image; use another image, "
                                                 "or check the image name") from None

    def to_opensfm(self) -> list:
        rec = {"cameras": {cid: cam.to_opensfm() for cid, cam in self.cameras.items()},
               "shots": {sid: shot.to_opensfm() for sid, shot in self.shots.items()},
               "points": {pid: {"coordinates": [float(c) for c in xyz], "color": [128.0, 128.0, 128.0]}
                          for pid, xyz in zip(self.point_ids, self.points)}}
        if self.reference_lla is not None:
            rec["reference_lla"] = dict(self.reference_lla)
        return [rec]


def read_reconstruction(path: str | Path) -> Reconstruction:
    """Read every partial reconstruction of the file into one (ODM shares one frame between them)."""
    path = Path(path)
    data = read_json(path)
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data or not all(isinstance(r, dict) for r in data):
        raise InputError("not an OpenSfM reconstruction (expected a list of reconstructions)", path=path,
                         fix="point to opensfm/reconstruction.json of an ODM project")
    cameras: dict[str, Camera] = {}
    shots: dict[str, Shot] = {}
    pids: list[str] = []
    pts: list = []
    reference = None
    try:
        for rec in data:
            for cid, cd in rec.get("cameras", {}).items():
                cameras[cid] = camera_from_opensfm(cid, cd)
            reference = reference or rec.get("reference_lla")
            for sid, sd in rec.get("shots", {}).items():
                known = {"rotation", "translation", "camera", "capture_time", "gps_position"}
                shots[sid] = Shot(id=sid, camera=cameras[sd["camera"]],
                                  rotation=np.asarray(sd["rotation"], dtype=float),
                                  translation=np.asarray(sd["translation"], dtype=float),
                                  capture_time=sd.get("capture_time"),
                                  gps_position=tuple(sd["gps_position"]) if "gps_position" in sd else None,
                                  extra={k: v for k, v in sd.items() if k not in known})
            for pid, pd in rec.get("points", {}).items():
                pids.append(pid)
                pts.append(pd["coordinates"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"reconstruction file is incomplete or malformed ({type(exc).__name__}: {exc})",
                         path=path, fix="re-run the reconstruction, or restore the file from ODM's output") from exc
    if not shots:
        raise InputError("the reconstruction holds no images", path=path,
                         fix="ODM did not reconstruct anything; check its log and the image overlap")
    points = np.asarray(pts, dtype=float).reshape(-1, 3)
    return Reconstruction(cameras=cameras, shots=shots, point_ids=pids, points=points,
                          reference_lla=reference, path=path)


def write_reconstruction(path: str | Path, recon: Reconstruction) -> Path:
    return write_json(path, recon.to_opensfm(), indent=None)
