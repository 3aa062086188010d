"""One face for every photogrammetry project: ODM, Metashape or Pix4D (docs/DESIGN.md §2, §3).

    project = open_project("field", project_type="auto")   # ODMProject, or a PhotoProject for Metashape/Pix4D
    project.shot_ids(undistorted=False)                    # the posed photos
    project.nominal_shot("DJI_0001.JPG", undistorted=False)  # camera and pose of the original photo
    project.frame_of("DJI_0001.JPG").to_map(points)          # its frame -> the map CRS

A :class:`PhotoProject` answers the calls the steps make of an :class:`~matchplant.core.formats.odm.ODMProject`,
so the steps never ask which program made the project. Metashape and Pix4D pose the *original* photos: there are
no undistorted images (``shot_ids(undistorted=True)`` is empty), and projection goes through the distortion model.
The DSM and orthophoto are the user's GeoTIFF exports, in any CRS: the frame then maps to the DSM's CRS exactly
(pyproj), so nothing is resampled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from matchplant.core.formats.camera_set import CameraSet
from matchplant.core.formats.images import IMAGE_SUFFIXES, image_size, is_image_name
from matchplant.core.formats.metashape import read_metashape
from matchplant.core.formats.odm import OUTPUTS, ODMProject
from matchplant.core.formats.pix4d import SUFFIX, params_folder, read_pix4d
from matchplant.core.geometry.frames import Frame, parse_crs
from matchplant.core.geometry.geodetic import DatumTopocentricFrame, ReprojectedFrame, TangentFrame
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.units import metric_heights
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("cameras")

PROJECT_TYPES = ("auto", "odm", "metashape", "pix4d")
LOOKED_FOR = (
    "ODM: opensfm/reconstruction.json or opensfm/undistorted/reconstruction.json; Metashape: a camera export "
    "(.xml) or a project (.psx); Pix4D: 1_initial/params/<name>" + SUFFIX
)
# a Metashape export or Pix4D project's rasters: where each program puts them, else one file so named beside it
RASTERS = {
    "pix4d": {
        "dsm": ("3_dsm_ortho/1_dsm/*_dsm.tif",),
        "dtm": ("3_dsm_ortho/extras/dtm/*_dtm.tif",),
        "orthophoto": ("3_dsm_ortho/2_mosaic/*_mosaic*.tif",),
    },
    "metashape": {
        "dsm": ("*dsm*.tif", "*dem*.tif", "*DSM*.tif", "*DEM*.tif"),
        "dtm": ("*dtm*.tif", "*DTM*.tif"),
        "orthophoto": ("*ortho*.tif",),
    },
}


@dataclass(frozen=True)
class Found:
    """What :func:`detect_project` found: the program and the file(s) that say so."""

    program: str
    path: Path
    evidence: list[Path]


def detect_project(path: str | Path, project_type: str = "auto") -> Found:
    """Which program made the project at ``path`` (a folder or a file), from the files it holds."""
    path = Path(path)
    if project_type not in PROJECT_TYPES:
        raise InputError(
            f"project_type {project_type!r} is not one of {', '.join(PROJECT_TYPES)}", path=path, fix="use one of these"
        )
    if not path.exists():
        raise InputError("project not found", path=path, fix=f"give the project's folder or file ({LOOKED_FOR})")
    found = []
    if path.is_dir():
        odm = [path / OUTPUTS[k].relpath for k in ("reconstruction", "undistorted_reconstruction")]
        if any(p.is_file() for p in odm) or (path / "submodels").is_dir():
            found.append(Found("odm", path, [p for p in odm if p.is_file()] or [path / "submodels"]))
        meta = sorted(path.glob("*.psx")) + sorted(p for p in path.glob("*.xml") if _is_metashape_xml(p))
        if meta:
            found.append(Found("metashape", meta[0] if len(meta) == 1 else path, meta))
    elif path.suffix.lower() in (".psx", ".xml"):
        found.append(Found("metashape", path, [path]))
    params = params_folder(path)
    if params is not None:
        found.append(Found("pix4d", path, sorted(params.glob("*" + SUFFIX))))
    if project_type != "auto":
        found = [f for f in found if f.program == project_type]
    if not found:
        kind = "a project" if project_type == "auto" else f"a {project_type} project"
        raise InputError(f"this is not {kind}: looked for {LOOKED_FOR}", path=path, fix="point at the project")
    if len(found) > 1:
        raise InputError(
            f"this folder holds more than one project ({', '.join(f.program for f in found)})",
            path=path,
            fix="set project_type to the one to use (odm, metashape or pix4d)",
        )
    f = found[0]
    if f.program == "metashape" and len(f.evidence) > 1:
        raise InputError(
            f"{len(f.evidence)} Metashape files here ({', '.join(p.name for p in f.evidence)})",
            path=path,
            fix="point at the one to use",
        )
    log.info("%s project, from %s", f.program, ", ".join(str(p) for p in f.evidence))
    return f


def _is_metashape_xml(path: Path) -> bool:
    """True when an XML file's first kilobytes look like a Metashape document."""
    try:
        head = path.read_bytes()[:4096].decode("utf-8", "replace")
    except OSError:
        return False
    return "<document" in head and ("<chunk" in head or "<sensors" in head)


def open_project(
    path: str | Path,
    project_type: str = "auto",
    *,
    dsm: str | Path | None = None,
    orthophoto: str | Path | None = None,
    images: str | Path | None = None,
) -> ODMProject | PhotoProject:
    """The project at ``path`` behind one face (module docstring); ``dsm``, ``orthophoto`` and ``images`` (the
    folder of the original photos) override where a Metashape or Pix4D project's files are looked for."""
    found = detect_project(path, project_type)
    if found.program == "odm":
        return ODMProject(found.path)
    cameras = read_metashape(found.evidence[0]) if found.program == "metashape" else read_pix4d(found.path)
    return PhotoProject(cameras, dsm=dsm, orthophoto=orthophoto, images=images)


class PhotoProject:
    """A Metashape or Pix4D project with the calls of an :class:`ODMProject` (original photos only)."""

    is_split = False
    submodels: list = []

    def __init__(self, cameras: CameraSet, *, dsm=None, orthophoto=None, images=None, dtm=None):
        self.cameras = cameras
        self.program = cameras.program
        src = Path(cameras.source)
        self.root = src if src.is_dir() else src.parent
        self._rasters = {"dsm": dsm, "orthophoto": orthophoto, "dtm": dtm}
        self.images_dir = Path(images) if images is not None else None
        # shot id: the photo's file name where every name is unique, else the program's label (subfolders)
        self._disk_names = {label: self._disk_name(p.name) for label, p in cameras.photos.items()}
        names = list(self._disk_names.values())
        unique = len(set(names)) == len(names)
        self._by_id = {(self._disk_names[p.label] if unique else p.label): p for p in cameras.photos.values()}
        self._shots = {k: replace(p.shot, id=k) for k, p in self._by_id.items() if p.shot is not None}

    @cached_property
    def _files(self) -> dict[str, Path]:
        """File name -> file of the photos at hand: in ``images``, the project folder and its images/."""
        folders = [f for f in (self.images_dir, self.root, self.root / "images") if f is not None and f.is_dir()]
        index = {}
        for folder in reversed(folders):
            index.update({p.name: p for p in folder.iterdir() if p.is_file()})
        return index

    @cached_property
    def _stems(self) -> dict[str, list[str]]:
        """Photo file name without its extension -> the photos at hand of that name."""
        stems: dict[str, list[str]] = {}
        for name, path in self._files.items():
            if is_image_name(path):
                stems.setdefault(path.stem, []).append(name)
        return stems

    def _disk_name(self, name: str) -> str:
        """The photo's file name: Metashape labels a camera by its file name without the extension by default
        (``DJI_0001`` for ``DJI_0001.JPG``); such a label is the one photo at hand of that name."""
        if is_image_name(Path(name)):
            return name
        hits = sorted(self._stems.get(name, []), key=lambda n: (IMAGE_SUFFIXES.index(Path(n).suffix.lower()), n))
        if len(hits) > 1:  # a camera's JPEG beside a PNG or TIFF made from it: the JPEG, said
            log.warning("photo %r: %s at hand; using %s", name, ", ".join(hits), hits[0])
        return hits[0] if hits else name

    @property
    def name(self) -> str:
        """The project's name (its folder)."""
        return self.root.name

    def _find(self, what: str) -> Path | None:
        """A raster given, else the one file the program's layout names (docs above); None if none or several."""
        given = self._rasters.get(what)
        if given is not None:
            return Path(given)
        hits = sorted({p for pattern in RASTERS[self.program].get(what, ()) for p in self.root.glob(pattern)})
        if len(hits) > 1:
            log.warning("several %s files in %s (%s): set it in the config", what, self.root, ", ".join(map(str, hits)))
        return hits[0] if len(hits) == 1 else None

    def path(self, name: str) -> Path:
        """Where output ``name`` is (the DSM, the orthophoto; the camera file for the poses)."""
        if name in ("dsm", "dtm", "orthophoto"):
            return self._find(name) or self.root / f"<{name}.tif>"
        if name in ("reconstruction", "coords"):
            return self.cameras.files[0]
        return self.root / f"<{OUTPUTS[name].relpath} (none in a {self.program} project)>"

    def has(self, name: str) -> bool:
        """Whether output ``name`` is at hand."""
        if name in ("reconstruction", "coords"):
            return True
        if name in ("dsm", "dtm", "orthophoto"):
            p = self._find(name)
            return p is not None and p.is_file()
        return False

    def missing(self, *names: str) -> list[str]:
        """The outputs among ``names`` not at hand."""
        return [n for n in names if not self.has(n)]

    def require(self, *names: str) -> None:
        """Raise one error naming what is missing and how to make it in this program."""
        missing = self.missing(*names)
        if not missing:
            return
        undistorted = [n for n in missing if n.startswith("undistorted")]
        if undistorted:
            raise InputError(
                f"a {self.program} project has no undistorted images: MatchPlant uses the original photos",
                path=self.cameras.source,
                fix="detect on the original photos (module 8: image_type: original)",
            )
        how = {
            "metashape": "in Metashape: File > Export > Export DEM / Export Orthomosaic (GeoTIFF), then set its path",
            "pix4d": "run Pix4D's step 3 (DSM, Orthomosaic), or set the GeoTIFF's path",
        }[self.program]
        raise InputError(
            f"the {self.program} project lacks: {', '.join(missing)} (looked for "
            + "; ".join(RASTERS[self.program].get(n, ("-",))[0] for n in missing)
            + f" in {self.root})",
            path=self.root,
            fix=how + " (config keys dsm / orthophoto)",
        )

    def check(self) -> dict[str, bool]:
        """Which outputs exist."""
        return {name: self.has(name) for name in ("reconstruction", "dsm", "orthophoto")}

    # -- poses ----------------------------------------------------------------------------------------------
    def shot_ids(self, undistorted: bool = True) -> set[str]:
        """The posed photos (there are no undistorted images: empty for ``undistorted=True``)."""
        return set() if undistorted else set(self._shots)

    def owner(self, shot_id: str) -> PhotoProject:
        """The project itself (no submodels)."""
        return self

    def own_raster(self, shot_id: str, name: str = "dsm") -> Path | None:
        """The project's raster ``name``, or None."""
        return self._find(name) if self.has(name) else None

    def nominal_shot(self, shot_id: str, undistorted: bool = False) -> Shot:
        """The photo's camera and pose, as the project stores them."""
        if undistorted:
            self.require("undistorted_reconstruction")
        shot = self._shots.get(shot_id)
        if shot is None:
            why = "is not aligned" if shot_id in self._by_id else "is not in the project"
            raise InputError(
                f"photo '{shot_id}' {why} ({len(self.shot_ids(False))} photos have a pose)",
                path=self.cameras.source,
                fix=f"align it in {self.program} and export again, or use another photo",
            )
        return shot

    def shot(self, shot_id: str, undistorted: bool = False) -> Shot:
        """The photo's shot, its camera checked against the photo on disk where the photo is at hand."""
        shot = self.nominal_shot(shot_id, undistorted)
        p = self.image_paths(missing_ok=True).get(shot_id)
        if p is not None:
            w, h = image_size(p)
            if (w, h) != (shot.camera.width, shot.camera.height):
                raise InputError(
                    f"photo '{shot_id}' is {w}x{h} on disk but {shot.camera.width}x{shot.camera.height} in the project",
                    path=p,
                    fix="use the original photos the project was made from (not resized or rotated copies)",
                )
        return shot

    @cached_property
    def _frame(self) -> Frame:
        """The cameras' frame, mapped to the DSM's CRS when a DSM in another CRS is given."""
        frame = self.cameras.frame
        dsm = self._find("dsm")
        if dsm is None or not dsm.is_file():
            return frame
        import rasterio  # lazy: GIS only where a raster is read (training runs without it)

        with rasterio.open(dsm) as src:
            crs = parse_crs(src.crs, source=dsm) if src.crs else None
            bounds = src.bounds
        if crs is None:
            raise InputError(
                "the DSM has no CRS, so it cannot be placed under the cameras",
                path=dsm,
                fix="export the DSM as a GeoTIFF with its coordinate system",
            )
        frame = self.frame(crs)
        centres = np.vstack([frame.to_map(s.center[None, :]) for s in self._shots.values()])
        reach = max(50.0, float(np.ptp(centres[:, 2])) + 100.0)  # a camera sees about its height around it
        lo, hi = centres[:, :2].min(axis=0) - reach, centres[:, :2].max(axis=0) + reach
        if bounds.left > hi[0] or bounds.right < lo[0] or bounds.bottom > hi[1] or bounds.top < lo[1]:
            raise InputError(
                f"the DSM ({bounds.left:.1f}..{bounds.right:.1f}, {bounds.bottom:.1f}..{bounds.top:.1f} in "
                f"{crs.name}) does not overlap the cameras ({lo[0] + reach:.1f}..{hi[0] - reach:.1f}, "
                f"{lo[1] + reach:.1f}..{hi[1] - reach:.1f})",
                path=dsm,
                fix="give the DSM exported from this project (config key dsm)",
            )
        return frame

    def frame(self, crs=None) -> Frame:
        """The frame of every shot, converted to ``crs`` (default: the DSM's CRS, else the project's)."""
        base = self.cameras.frame
        if crs is None:
            return self._frame
        crs = metric_heights(crs)  # a DSM's heights in feet are read as metres (Surface.open): so are the rays'
        if base.crs.equals(crs):
            return base
        log.info("the %s cameras are in %s; the map is %s (converted exactly)", self.program, base.crs.name, crs.name)
        if isinstance(base, DatumTopocentricFrame):
            return DatumTopocentricFrame(base.lat, base.lon, base.alt, base.geodetic_crs, crs)
        return ReprojectedFrame(base, crs)

    def frame_of(self, shot_id: str) -> Frame:
        """The frame ``shot_id``'s rays are walked in: the project's when it is a shift of the map (Pix4D), else
        its tangent frame at the camera (Metashape: straight rays, within 0.33 mm of the exact curve for 60 m
        rays; docs/DESIGN.md §8)."""
        frame = self.frame()
        if frame.is_affine:
            return frame
        cache = self.__dict__.setdefault("_tangent", {})
        if shot_id not in cache:
            cache[shot_id] = TangentFrame(frame, self.nominal_shot(shot_id).center)
        return cache[shot_id]

    # -- photos on disk -------------------------------------------------------------------------------------
    def image_paths(self, missing_ok: bool = False) -> dict[str, Path]:
        """Shot id -> the original photo's file, looked for in ``images``, the project folder and its images/."""
        cache = self.__dict__.setdefault("_paths", None)
        if cache is None:
            cache = self.__dict__["_paths"] = {}
            for sid, photo in self._by_id.items():
                stored = Path(photo.path) if photo.path else None
                if stored is not None and not stored.is_absolute():
                    stored = self.root / stored
                on_disk = self._files.get(self._disk_names[photo.label])
                hit = stored if stored is not None and stored.is_file() else on_disk
                if hit is not None:
                    cache[sid] = hit
        if not missing_ok:
            lost = sorted(s for s in self.shot_ids(False) if s not in cache)
            if lost:
                raise InputError(
                    f"{len(lost)} photo(s) named in the {self.program} project are not on disk (e.g. {lost[0]})",
                    path=self.images_dir or self.root,
                    fix="set 'images' to the folder of the original photos the project was made from",
                )
        return dict(cache)

    def undistorted_images(self) -> dict[str, Path]:
        """None: the programs pose the originals (see :meth:`image_paths`)."""
        return {}
