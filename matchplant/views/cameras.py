"""A project's cameras, as the crops need them: each original photo, its pose and its frame.

:func:`survey_cameras` is the one place that turns "a project" into camera records: any project
:func:`~matchplant.core.formats.projects.open_project` reads (ODM, Metashape, Pix4D), always its original photos
posed with their distortion model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.formats.images import image_size, list_images, match_name
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.projects import open_project
from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("views")

DSM_HOW = {
    "odm": "run ODM with --dsm (module 2 does), or set 'dsm'",
    "metashape": "in Metashape: File > Export > Export DEM (GeoTIFF) beside the camera export, or set 'dsm'",
    "pix4d": "run Pix4D's step 3 (DSM, Orthomosaic), or set 'dsm'",
}


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


def survey_cameras(
    project: str | Path,
    photos: str | Path | None = None,
    dsm: str | Path | None = None,
    project_type: str = "auto",
) -> Survey:
    """The cameras of a project's original photos: an ODM project (its ``opensfm/reconstruction.json``), a
    Metashape camera export or project, or a Pix4D project (``project_type``: ``auto`` tells them apart).

    ``photos``: the folder of the original photos (default: ODM's ``images/``; for Metashape and Pix4D, the
    paths they store, else the project's folder); ``dsm``: a DSM other than the project's. Photos the project
    poses but that are not on disk are left out (logged)."""
    proj = open_project(project, project_type, dsm=dsm, images=photos)
    program = getattr(proj, "program", "odm")
    proj.require("reconstruction")
    files, folder = _photo_files(proj, photos)
    cameras, missing = [], []
    for sid in sorted(proj.shot_ids(undistorted=False)):
        path = files.get(sid)
        if path is None:
            missing.append(sid)
            continue
        shot = proj.nominal_shot(sid, undistorted=False)
        w, h = image_size(path)
        if (w, h) != (shot.camera.width, shot.camera.height):
            shot = shot.with_camera(shot.camera.resized(w, h))
        cameras.append(CameraView(sid, path, shot, proj.frame_of(sid)))
    if missing:
        log.warning("%d photo(s) of the project not found in %s (e.g. %s)", len(missing), folder, missing[0])
    if not cameras:
        raise InputError(
            f"none of the {program} project's photos is in the photo folder",
            path=folder,
            fix="set 'photos' to the folder of the original photos the project was made from",
        )
    dsm_path = Path(dsm) if dsm else proj.path("dsm")
    if not dsm_path.is_file():
        raise InputError("DSM not found", path=dsm_path, fix=DSM_HOW[program])
    return Survey(cameras, proj.frame().crs, dsm_path, program)


def _photo_files(proj, photos) -> tuple[dict[str, Path], Path]:
    """Shot id -> original photo on disk, and the folder looked in (for messages)."""
    if isinstance(proj, ODMProject):
        folder = Path(photos) if photos else proj.root / "images"
        on_disk = {p.name: p for p in list_images(folder, key="photos")}
        ids = proj.shot_ids(undistorted=False)
        names = {sid: sid if sid in on_disk else match_name(sid, on_disk) for sid in ids}
        return {sid: on_disk[n] for sid, n in names.items() if n is not None}, folder
    return proj.image_paths(missing_ok=True), Path(photos) if photos else proj.root
