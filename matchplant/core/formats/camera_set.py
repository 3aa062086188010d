"""The camera record every photogrammetry program's project reads into (docs/DESIGN.md §3, §8).

A :class:`CameraSet` is what the Metashape and Pix4D readers return: for each photo its file name, the size of
the original photo, its camera (intrinsics and distortion converted exactly to our conventions) and its pose
(a :class:`~matchplant.core.geometry.shot.Shot` in the set's :attr:`frame`, or None where the program did not
align it). Both programs pose the *original* photos, so projection goes through the distortion model.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np
from scipy.spatial.transform import Rotation

from matchplant.core.geometry.camera import Camera
from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.shot import Shot


@dataclass(frozen=True)
class Photo:
    """One photo: the program's label, its file name, its sensor, its camera and its pose (None: not aligned)."""

    label: str
    name: str
    sensor: str
    camera: Camera
    shot: Shot | None
    path: str | None = None  # the photo's path as the project stores it (Metashape's .psx), else None


@dataclass(frozen=True)
class Marker:
    """A ground control point: its reference coordinates (in ``crs``) and the pixels an operator marked.

    ``marks`` maps a photo label to (u, v) in our pixel convention (docs/DESIGN.md §3: pixel centres at integers).
    """

    label: str
    xyz: np.ndarray | None
    crs: object | None
    marks: dict[str, tuple[float, float]] = field(default_factory=dict)


@dataclass
class CameraSet:
    """Every photo of one project (one Metashape chunk, one Pix4D project) in one frame."""

    program: str  # "metashape" or "pix4d"
    source: Path  # the file or folder given
    files: list[Path]  # the files read, for "what was found where"
    frame: Frame
    photos: dict[str, Photo]  # by label (unique in the project)
    sensors: dict[str, Camera]
    markers: list[Marker] = field(default_factory=list)
    left_out: dict[str, list[str]] = field(default_factory=dict)  # why -> labels of photos not read (e.g. rig bands)

    @property
    def posed(self) -> dict[str, Photo]:
        """The photos the program aligned."""
        return {k: p for k, p in self.photos.items() if p.shot is not None}

    @property
    def unposed(self) -> list[str]:
        """Labels of the photos without a pose (not aligned)."""
        return [k for k, p in self.photos.items() if p.shot is None]

    def centres_map(self) -> np.ndarray:
        """Camera centres (N, 3) of the posed photos in the map CRS, in the order of :attr:`posed`."""
        shots = [p.shot for p in self.posed.values()]
        if not shots:
            return np.zeros((0, 3))
        return self.frame.to_map(np.array([s.center for s in shots]))


def stored_path(stored: str, base: Path) -> str:
    """A photo's path as a project file stores it, as this machine reads it: a relative one from ``base`` (the
    folder of the file that stores it), an absolute one as it is; another machine's (``C:\\...`` on Linux) cannot
    be reached here, and the photo is then looked for by its file name."""
    if PureWindowsPath(stored).is_absolute() or PurePosixPath(stored).is_absolute() or "\\" in stored:
        return stored
    return os.path.normpath(base / stored)


def only_camera(photos) -> Camera | None:
    """The camera of every photo where there is one, else None (a photo without a pose then has no camera)."""
    cams = {p.camera.id: p.camera for p in photos if p.camera is not None}
    return next(iter(cams.values())) if len(cams) == 1 else None


def file_name(path_or_label: str) -> str:
    """The last part of a path written on any platform (``C:\\a\\b.JPG`` and ``a/b.JPG`` give ``b.JPG``)."""
    name = PureWindowsPath(path_or_label).name if "\\" in path_or_label else PurePosixPath(path_or_label).name
    return name or path_or_label


def make_shots(ids: list[str], cameras: list[Camera], R: np.ndarray, centres: np.ndarray) -> list[Shot]:
    """Shots from world->camera rotations (N, 3, 3) and camera centres (N, 3), converted in one call."""
    if not ids:
        return []
    R = np.asarray(R, dtype=float)
    rotvecs = Rotation.from_matrix(R).as_rotvec()
    t = -np.einsum("nij,nj->ni", R, np.asarray(centres, dtype=float))
    return [Shot(id=i, camera=c, rotation=rv, translation=tt) for i, c, rv, tt in zip(ids, cameras, rotvecs, t)]


def check_rotation(R: np.ndarray, *, tol: float = 1e-6) -> bool:
    """True when ``R`` is a proper rotation (orthonormal, determinant +1) within ``tol``."""
    R = np.asarray(R, dtype=float)
    return (
        R.shape == (3, 3)
        and bool(np.all(np.isfinite(R)))
        and (np.abs(R @ R.T - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1.0) < tol)
    )
