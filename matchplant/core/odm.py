"""An OpenDroneMap project folder: its files (docs/DESIGN.md §2), which are missing, and how to get them.

    project = ODMProject("path/to/project")
    project.require("reconstruction", "undistorted_images", "dsm")   # clear error naming the ODM option
    rec = project.reconstruction(undistorted=True)
    shot = project.shot("DJI_0001.JPG", undistorted=True)           # camera sized to the real image
    frame = project.frame()                                          # reconstruction frame -> map CRS
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import rasterio
from PIL import Image

from matchplant.core.errors import InputError
from matchplant.core.frames import Frame, detect_frame, read_coords_txt
from matchplant.core.reconstruction import Reconstruction, Shot, read_reconstruction


@dataclass(frozen=True)
class Output:
    relpath: str
    what: str
    produced_by: str  # the ODM option or step that writes it


OUTPUTS: dict[str, Output] = {
    "reconstruction": Output("opensfm/reconstruction.json", "camera poses of the original images",
                             "any completed ODM run (the OpenSfM step)"),
    "topocentric_reconstruction": Output("opensfm/reconstruction.topocentric.json",
                                         "the reconstruction in its local frame", "georeferenced ODM runs (>= 2.0)"),
    "undistorted_reconstruction": Output("opensfm/undistorted/reconstruction.json",
                                         "camera poses of the undistorted images",
                                         "the OpenSfM undistort step (do not use --optimize-disk-space)"),
    "undistorted_images": Output("opensfm/undistorted/images", "undistorted images",
                                 "the OpenSfM undistort step (do not use --optimize-disk-space)"),
    "dsm": Output("odm_dem/dsm.tif", "digital surface model", "--dsm"),
    "dtm": Output("odm_dem/dtm.tif", "digital terrain model", "--dtm"),
    "orthophoto": Output("odm_orthophoto/odm_orthophoto.tif", "orthophoto",
                         "the orthophoto step (do not use --skip-orthophoto)"),
    "coords": Output("odm_georeferencing/coords.txt", "map CRS and offset",
                     "georeferencing: GPS in the images' EXIF or a gcp_list.txt"),
}


class ODMProject:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("ODM project folder not found", path=self.root,
                             fix="point the config at the folder that holds opensfm/, odm_dem/ and odm_orthophoto/")

    def path(self, name: str) -> Path:
        return self.root / OUTPUTS[name].relpath

    def has(self, name: str) -> bool:
        p = self.path(name)
        if name == "undistorted_images":
            return p.is_dir() and any(p.iterdir())
        return p.is_file()

    def missing(self, *names: str) -> list[str]:
        return [n for n in (names or OUTPUTS) if not self.has(n)]

    def require(self, *names: str) -> None:
        """Raise one error listing every missing output and the ODM option that produces it."""
        missing = self.missing(*names)
        if missing:
            lines = [f"  - {OUTPUTS[n].relpath} ({OUTPUTS[n].what}): produced by {OUTPUTS[n].produced_by}"
                     for n in missing]
            raise InputError("the ODM project lacks outputs this step needs:\n" + "\n".join(lines),
                             path=self.root, fix="re-run ODM with the options named above (module 2 does this)")

    def check(self) -> dict[str, bool]:
        """Which outputs exist (for module 2's manifest and for reports)."""
        return {name: self.has(name) for name in OUTPUTS}

    # -- reading --------------------------------------------------------------------------------
    @cached_property
    def coords(self):
        return read_coords_txt(self.path("coords")) if self.has("coords") else None

    def reconstruction(self, undistorted: bool = False) -> Reconstruction:
        name = "undistorted_reconstruction" if undistorted else "reconstruction"
        self.require(name)
        return self._read(name)

    def _read(self, name: str) -> Reconstruction:
        cache = self.__dict__.setdefault("_recon_cache", {})
        if name not in cache:
            cache[name] = read_reconstruction(self.path(name))
        return cache[name]

    def frame(self, crs=None) -> Frame:
        """The reconstruction's frame (both reconstruction files share it) with its map CRS."""
        name = "reconstruction" if self.has("reconstruction") else "undistorted_reconstruction"
        self.require(name)
        rec = self._read(name)
        return detect_frame(rec.reference_lla, self.coords, self.has("topocentric_reconstruction"), crs,
                            source=self.path(name))

    def undistorted_image_path(self, shot_id: str) -> Path:
        """ODM names undistorted images as the original name plus ``.tif``."""
        folder = self.path("undistorted_images")
        for candidate in (folder / f"{shot_id}.tif", folder / shot_id):
            if candidate.is_file():
                return candidate
        raise InputError(f"undistorted image of '{shot_id}' not found", path=folder / f"{shot_id}.tif",
                         fix="the undistort step did not finish; re-run ODM without --optimize-disk-space")

    def undistorted_images(self) -> dict[str, Path]:
        """Shot id -> undistorted image path, for every undistorted image present."""
        folder = self.path("undistorted_images")
        out = {}
        if folder.is_dir():
            for p in sorted(folder.iterdir()):
                if p.suffix.lower() in (".tif", ".tiff") and not p.name.startswith("."):
                    out[p.name[:-4] if p.name.lower().endswith(".tif") else p.stem] = p
        return out

    def shot(self, shot_id: str, undistorted: bool = True) -> Shot:
        """A shot whose camera has the real size of the image on disk (undistorted images may be smaller)."""
        rec = self.reconstruction(undistorted=undistorted)
        shot = rec.shot(shot_id)
        if undistorted:
            w, h = image_size(self.undistorted_image_path(shot_id))
            if (w, h) != (shot.camera.width, shot.camera.height):
                shot = shot.with_camera(shot.camera.resized(w, h))
        return shot


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) read from the file header only."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except Exception:  # noqa: BLE001 - PIL cannot read every GeoTIFF layout; GDAL can
        try:
            with rasterio.open(path) as src:
                return int(src.width), int(src.height)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"cannot read the image size: {exc}", path=path,
                             fix="check that the file is a complete image") from exc
