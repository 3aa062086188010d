"""An OpenDroneMap project folder: its files (docs/DESIGN.md §2), which are missing, and how to get them.

    project = ODMProject("path/to/project")
    project.require("reconstruction", "undistorted_images", "dsm")   # clear error naming the ODM option
    shot = project.shot("DJI_0001.JPG", undistorted=True)           # camera sized to the real image
    frame = project.frame_of("DJI_0001.JPG")                         # that shot's frame -> map CRS
    frame = project.frame()                                          # the project's map frame (its CRS)

A split-merge project (ODM's ``--split``, docs/DESIGN.md §6) reads as one project: the shots of every
``submodels/submodel_NNNN/`` (each in its own frame: its reconstruction's ``reference_lla`` and its
``coords.txt``), the undistorted images of every submodel, and the merged DSM, DTM and orthophoto at the
top (a submodel's when the merged one is missing, said in the log). An image in two submodels (the split
overlap) is used once, from the submodel whose cameras are centred nearest to it. Code that places a
shot must use :meth:`ODMProject.frame_of`, which is the project's frame in a single project.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from matchplant.core.formats.images import TIFF_SUFFIXES, image_size, is_image_name
from matchplant.core.formats.reconstruction import Reconstruction, read_reconstruction
from matchplant.core.geometry.frames import Frame, OffsetFrame, detect_frame, read_coords_txt
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import match_names

log = get_logger("odm")


@dataclass(frozen=True)
class Output:
    """One ODM output: its path in the project, what it holds and which ODM option or step writes it."""

    relpath: str
    what: str
    produced_by: str  # the ODM option or step that writes it


OUTPUTS: dict[str, Output] = {
    "reconstruction": Output(
        "opensfm/reconstruction.json", "camera poses of the original images", "any completed ODM run (the OpenSfM step)"
    ),
    "topocentric_reconstruction": Output(
        "opensfm/reconstruction.topocentric.json",
        "the reconstruction in its local frame",
        "georeferenced ODM runs (>= 2.0)",
    ),
    "undistorted_reconstruction": Output(
        "opensfm/undistorted/reconstruction.json",
        "camera poses of the undistorted images",
        "the OpenSfM undistort step (do not use --optimize-disk-space)",
    ),
    "undistorted_images": Output(
        "opensfm/undistorted/images",
        "undistorted images",
        "the OpenSfM undistort step (do not use --optimize-disk-space)",
    ),
    "dsm": Output("odm_dem/dsm.tif", "digital surface model", "--dsm"),
    "dtm": Output("odm_dem/dtm.tif", "digital terrain model", "--dtm"),
    "orthophoto": Output(
        "odm_orthophoto/odm_orthophoto.tif", "orthophoto", "the orthophoto step (do not use --skip-orthophoto)"
    ),
    "coords": Output(
        "odm_georeferencing/coords.txt",
        "map CRS and offset",
        "georeferencing: GPS in the images' EXIF or a gcp_list.txt",
    ),
}
# in a split-merge project these are per submodel; the others (rasters, coords.txt) are merged at the top
PER_SUBMODEL = ("reconstruction", "topocentric_reconstruction", "undistorted_reconstruction", "undistorted_images")
SUBMODELS_DIR = "submodels"


def submodel_dirs(root: Path) -> list[Path]:
    """``submodels/submodel_NNNN`` folders holding an OpenSfM reconstruction, in order."""
    folder = Path(root) / SUBMODELS_DIR
    if not folder.is_dir():
        return []
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_dir()
        and p.name.startswith("submodel_")
        and (
            (p / OUTPUTS["reconstruction"].relpath).is_file()
            or (p / OUTPUTS["undistorted_reconstruction"].relpath).is_file()
        )
    )


class ODMProject:
    """An ODM project folder (single or split-merge): which outputs it has, and its shots, frames and rasters.

    Parameters
    ----------
    root : str or Path
        The project folder (the one that holds opensfm/, odm_dem/ and odm_orthophoto/, or submodels/).
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(
                "ODM project folder not found",
                path=self.root,
                fix="point the config at the folder that holds opensfm/, odm_dem/ and odm_orthophoto/",
            )
        subs = submodel_dirs(self.root)
        self.submodels: list[ODMProject] = [ODMProject(p) for p in subs]
        self._warned: set[str] = set()
        if self.submodels:
            log.info("split-merge project: %d submodels (%s)", len(subs), ", ".join(p.name for p in subs))

    @property
    def is_split(self) -> bool:
        """True for a split-merge project (it has submodels)."""
        return bool(self.submodels)

    @property
    def name(self) -> str:
        """The project folder's name."""
        return self.root.name

    def _raster_source(self, name: str) -> ODMProject:
        """Where a merged output comes from: the top, else the first submodel that has it (logged once)."""
        if not self.is_split or (self.root / OUTPUTS[name].relpath).is_file():
            return self
        for sub in self.submodels:
            if (sub.root / OUTPUTS[name].relpath).is_file():
                if name not in self._warned:
                    self._warned.add(name)
                    log.warning(
                        "merged %s missing (%s); using %s's, which covers only that submodel's part of the field",
                        OUTPUTS[name].what,
                        self.root / OUTPUTS[name].relpath,
                        sub.name,
                    )
                return sub
        return self

    def path(self, name: str) -> Path:
        """Path of an output by name (of the first submodel for a per-submodel output)."""
        if self.is_split and name in PER_SUBMODEL:
            return self.submodels[0].path(name)  # one of them (messages); see sub_paths()
        return self._raster_source(name).root / OUTPUTS[name].relpath

    def has(self, name: str) -> bool:
        """True when the output exists (in every submodel for a per-submodel output)."""
        if self.is_split and name in PER_SUBMODEL:
            return all(sub.has(name) for sub in self.submodels)
        p = self.path(name)
        if name == "undistorted_images":
            return p.is_dir() and any(p.iterdir())
        return p.is_file()

    def missing(self, *names: str) -> list[str]:
        """Names of the outputs (all by default) that are missing."""
        return [n for n in (names or OUTPUTS) if not self.has(n)]

    def missing_paths(self, names) -> list[tuple[str, str]]:
        """(path relative to the project, output name) of each missing output among ``names``, per submodel."""
        out = []
        for n in names:
            if self.is_split and n in PER_SUBMODEL:
                out += [(f"{SUBMODELS_DIR}/{s.name}/{OUTPUTS[n].relpath}", n) for s in self.submodels if not s.has(n)]
            elif not self.has(n):
                out.append((OUTPUTS[n].relpath, n))
        return out

    def require(self, *names: str) -> None:
        """Raise one error listing every missing output and the ODM option that produces it."""
        missing = self.missing_paths(self.missing(*names))
        if missing:
            lines = [f"  - {rel} ({OUTPUTS[n].what}): produced by {OUTPUTS[n].produced_by}" for rel, n in missing]
            raise InputError(
                "the ODM project lacks outputs this step needs:\n" + "\n".join(lines),
                path=self.root,
                fix="re-run ODM with the options named above (module 2 does this)",
            )

    def check(self) -> dict[str, bool]:
        """Which outputs exist (for module 2's manifest and for reports)."""
        return {name: self.has(name) for name in OUTPUTS}

    # -- reading --------------------------------------------------------------------------------
    @cached_property
    def coords(self):
        """The CRS and integer offset of odm_georeferencing/coords.txt; None when the file is missing."""
        return read_coords_txt(self.path("coords")) if self.has("coords") else None

    def reconstruction(self, undistorted: bool = False) -> Reconstruction:
        """One folder's reconstruction; a split project has one per submodel (:attr:`submodels`), each in its
        own frame: use :meth:`shot_ids`, :meth:`shot` and :meth:`frame_of` instead."""
        if self.is_split:
            raise InputError(
                "a split-merge project has one reconstruction per submodel, each in its own frame",
                path=self.root / SUBMODELS_DIR,
                fix="read it through shot_ids(), shot() and frame_of() (or one submodel's folder)",
            )
        name = "undistorted_reconstruction" if undistorted else "reconstruction"
        self.require(name)
        return self._read(name)

    def _read(self, name: str) -> Reconstruction:
        cache = self.__dict__.setdefault("_recon_cache", {})
        if name not in cache:
            cache[name] = read_reconstruction(self.path(name))
        return cache[name]

    def frame(self, crs=None) -> Frame:
        """The reconstruction's frame (both reconstruction files share it) with its map CRS. In a split project:
        the map frame of the merged outputs (top-level coords.txt), for its CRS; shots use :meth:`frame_of`."""
        if self.is_split:
            if self.coords is not None and self._raster_source("coords") is self:
                return OffsetFrame(crs=crs or self.coords[0], offset=self.coords[1])
            return self.submodels[0].frame(crs)
        cache = self.__dict__.setdefault("_frame_cache", {})
        key = None if crs is None else crs.to_string()
        if key not in cache:
            name = "reconstruction" if self.has("reconstruction") else "undistorted_reconstruction"
            self.require(name)
            rec = self._read(name)
            cache[key] = detect_frame(
                rec.reference_lla, self.coords, self.has("topocentric_reconstruction"), crs, source=self.path(name)
            )
        return cache[key]

    # -- shots, over the submodels of a split project ---------------------------------------------
    def shot_ids(self, undistorted: bool = True) -> set[str]:
        """Every shot id of the project (the reconstruction's; empty when that file is missing)."""
        name = "undistorted_reconstruction" if undistorted else "reconstruction"
        if self.is_split:
            return {sid for sid, sub in self._owners.items() if sub.has(name) and sid in sub.shot_ids(undistorted)}
        return set(self._read(name).shots) if self.has(name) else set()

    def owner(self, shot_id: str) -> ODMProject:
        """The folder whose reconstruction places ``shot_id``: the project itself, or one submodel."""
        if not self.is_split:
            return self
        try:
            return self._owners[shot_id]
        except KeyError:
            raise InputError(
                f"image '{shot_id}' is in none of the {len(self.submodels)} submodels' reconstructions",
                path=self.root / SUBMODELS_DIR,
                fix="ODM could not place this image; use another image, or check the name",
            ) from None

    def own_raster(self, shot_id: str, name: str = "dsm") -> Path | None:
        """The raster ``name`` of the submodel that places ``shot_id`` (ODM leaves each submodel's own DSM, DTM and
        orthophoto in its folder; they agree with its poses, the merged one only near its centre); None when
        that submodel has none. In a single project: the project's raster, or None."""
        p = self.owner(shot_id).root / OUTPUTS[name].relpath
        return p if p.is_file() else None

    def frame_of(self, shot_id: str) -> Frame:
        """The frame ``shot_id``'s pose is in (its submodel's, in the project's map CRS)."""
        if not self.is_split:
            return self.frame()
        return self.owner(shot_id).frame(self.frame().crs)

    @cached_property
    def _owners(self) -> dict[str, ODMProject]:
        """Shot id -> the submodel it is used from. An image in several submodels (the split overlap) is used
        from the one whose cameras' centroid (map CRS) is nearest to it, where it lies least near an edge."""
        crs = self.frame().crs
        placed: dict[str, list[tuple[ODMProject, np.ndarray]]] = {}
        centroids = []
        for sub in self.submodels:
            shots = {}
            for und in (False, True):
                name = "undistorted_reconstruction" if und else "reconstruction"
                if sub.has(name):
                    shots.update(sub._read(name).shots)
            if not shots:
                centroids.append(np.full(2, np.nan))
                continue
            ids = sorted(shots)
            frame = sub.frame(crs)
            if not frame.crs.equals(crs):
                raise InputError(
                    f"submodel {sub.name} is in {frame.crs.name}, the merged outputs in {crs.name}",
                    path=sub.path("coords"),
                    fix="re-run ODM's split-merge so that every submodel "
                    "shares the map CRS of odm_georeferencing/coords.txt",
                )
            centres = frame.to_map(np.array([shots[i].center for i in ids]))
            centroids.append(centres[:, :2].mean(axis=0))
            for sid, c in zip(ids, centres):
                placed.setdefault(sid, []).append((sub, c[:2]))
        owners, shared = {}, []
        index = {id(s): k for k, s in enumerate(self.submodels)}
        for sid, cands in placed.items():
            if len(cands) == 1:
                owners[sid] = cands[0][0]
                continue
            dist = [float(np.hypot(*(c - centroids[index[id(sub)]]))) for sub, c in cands]
            owners[sid] = cands[int(np.argmin(dist))][0]
            shared.append(f"{sid} -> {owners[sid].name} (of {', '.join(s.name for s, _ in cands)})")
        if shared:
            log.info(
                "%d images appear in more than one submodel (the split overlap); each is used once, from the "
                "submodel whose cameras are centred nearest to it, e.g. %s",
                len(shared),
                "; ".join(shared[:3]),
            )
            for line in shared:
                log.debug("split overlap: %s", line)
        return owners

    def undistorted_image_path(self, shot_id: str) -> Path:
        """ODM names undistorted images as the original name plus ``.tif``."""
        if self.is_split:
            return self.owner(shot_id).undistorted_image_path(shot_id)
        folder = self.path("undistorted_images")
        for candidate in (folder / f"{shot_id}.tif", folder / shot_id):
            if candidate.is_file():
                return candidate
        loose = self.undistorted_images().get(shot_id)
        if loose is not None:
            return loose
        raise InputError(
            f"undistorted image of '{shot_id}' not found",
            path=folder / f"{shot_id}.tif",
            fix="the undistort step did not finish; re-run ODM without --optimize-disk-space",
        )

    def undistorted_images(self) -> dict[str, Path]:
        """Shot id -> undistorted image path, for every undistorted image present (in a split project, each
        image once, from the submodel it is used from; images no reconstruction places are kept too)."""
        if self.is_split:
            out: dict[str, Path] = {}
            for sub in self.submodels:
                for sid, p in sub.undistorted_images().items():
                    if self._owners.get(sid, sub) is sub or sid not in out:
                        out[sid] = p
            return dict(sorted(out.items()))
        cache = self.__dict__.setdefault("_undistorted_cache", {})
        if "images" not in cache:
            cache["images"] = self._list_undistorted()
        return dict(cache["images"])

    def _list_undistorted(self) -> dict[str, Path]:
        """The undistorted images by shot id: ``<shot id>.tif``, or a name that differs from a shot id only by
        case or extension (``IMG_1.jpg.tif`` or ``IMG_1.tif`` for shot ``IMG_1.JPG``: matched, said once)."""
        folder = self.path("undistorted_images")
        out = {}
        if folder.is_dir():
            for p in sorted(folder.iterdir()):
                if is_image_name(p, TIFF_SUFFIXES) and p.is_file():
                    out[p.name[:-4] if p.name.lower().endswith(".tif") else p.stem] = p
        ids = self.shot_ids(undistorted=True) if self.has("undistorted_reconstruction") else set()
        stray = [k for k in out if k not in ids]
        if stray and ids:
            matched, _ = match_names(stray, ids - set(out))
            taken = Counter(matched.values())  # two files for one shot: neither is taken
            matched = {k: t for k, t in matched.items() if taken[t] == 1}
            for name, sid in matched.items():
                out[sid] = out.pop(name)
            if matched:
                first = next(iter(matched.items()))
                log.warning(
                    "%d undistorted image name(s) differ from their shot ids by case or extension and were "
                    "matched (e.g. %s -> shot %s) in %s",
                    len(matched),
                    out[first[1]].name,
                    first[1],
                    folder,
                )
        return out

    def shot(self, shot_id: str, undistorted: bool = True) -> Shot:
        """A shot whose camera has the real size of the image on disk (undistorted images may be smaller); in
        its own frame (:meth:`frame_of`)."""
        if self.is_split:
            return self.owner(shot_id).shot(shot_id, undistorted)
        rec = self.reconstruction(undistorted=undistorted)
        shot = rec.shot(shot_id)
        if undistorted:
            w, h = image_size(self.undistorted_image_path(shot_id))
            if (w, h) != (shot.camera.width, shot.camera.height):
                shot = shot.with_camera(shot.camera.resized(w, h))
        return shot

    def nominal_shot(self, shot_id: str, undistorted: bool = True) -> Shot:
        """The shot as the reconstruction stores it (nominal camera size; no image file needed)."""
        owner = self.owner(shot_id)
        name = "undistorted_reconstruction" if undistorted else "reconstruction"
        owner.require(name)
        return owner._read(name).shot(shot_id)
