"""A project's cameras, as the crops need them: each original photo, its pose and its frame.

:func:`survey_cameras` is the one place that turns "a project" into camera records; ODM (and plain OpenSfM)
projects are read here, and other photogrammetry projects plug in beside them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.formats.images import image_size, list_images, match_name
from matchplant.core.formats.odm import ODMProject
from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("views")


@dataclass(frozen=True)
class CameraView:
    """One original photo: its file, its pose with the original (distorted) camera at the file's size, and the
    frame its pose is in."""

    name: str
    photo: Path
    shot: Shot
    frame: Frame


@dataclass(frozen=True)
class Survey:
    """What the crops need of a project: its cameras, the map CRS and the DSM."""

    cameras: list[CameraView]
    crs: object
    dsm: Path
    source: str


def survey_cameras(project: str | Path, photos: str | Path | None = None, dsm: str | Path | None = None) -> Survey:
    """The cameras of an ODM project (its ``opensfm/reconstruction.json``: the original photos' poses).

    ``photos``: the folder of the original photos (default: the project's ``images/``); ``dsm``: a DSM other
    than the project's ``odm_dem/dsm.tif``. Photos the reconstruction does not place are left out (logged)."""
    odm = ODMProject(project)
    odm.require("reconstruction")
    folder = Path(photos) if photos else odm.root / "images"
    files = {p.name: p for p in list_images(folder, key="photos")}
    ids = sorted(odm.shot_ids(undistorted=False))
    cameras, missing = [], []
    for sid in ids:
        name = sid if sid in files else match_name(sid, files)
        if name is None:
            missing.append(sid)
            continue
        shot = odm.nominal_shot(sid, undistorted=False)
        w, h = image_size(files[name])
        if (w, h) != (shot.camera.width, shot.camera.height):
            shot = shot.with_camera(shot.camera.resized(w, h))
        cameras.append(CameraView(sid, files[name], shot, odm.frame_of(sid)))
    if missing:
        log.warning("%d photo(s) of the reconstruction not found in %s (e.g. %s)", len(missing), folder, missing[0])
    if not cameras:
        raise InputError(
            "none of the reconstruction's photos is in the photo folder",
            path=folder,
            fix="set 'photos' to the folder of the original photos the project was made from",
        )
    dsm_path = Path(dsm) if dsm else odm.path("dsm")
    if not dsm_path.is_file():
        raise InputError("DSM not found", path=dsm_path, fix="run ODM with --dsm (module 2 does), or set 'dsm'")
    return Survey(cameras, odm.frame().crs, dsm_path, "odm")
