"""``matchplant init``'s checks of what it is given, before it writes anything: the project (what was found and what
is missing, for each photogrammetry program a project can come from), its DTM, the annotations against the project's
photos, and the checkpoint's kind. A mistake is said now, not hours later at the step that needs the file.

Each problem is an error (``init`` writes nothing and exits 2) or a named warning (the pipeline is written without
what the missing file would give), decided per case:

===========================================  ========  ==========================================================
problem                                      kind      why
===========================================  ========  ==========================================================
no photogrammetry outputs (raw photos)       error     modules 3, 7 and 8 need the cameras: run ODM first
no camera reconstruction / undistorted       error     modules 3, 7 and 8 place every photo and plant with them
photos and their cameras
no DSM                                       error     modules 3 and 8 meet the cameras' rays on it
no DTM                                       warning   module 9 gives no plant height (CHM = DSM - DTM); the
                                                       pipeline's module 9 is written without the DSM
no orthophoto                                warning   module 9 gives no colour statistics from it
neither DTM nor orthophoto (when detecting)  error     module 9 has no raster to measure the plants on
no georeferencing (coords.txt)               warning   positions stay in the reconstruction's local frame
annotations unreadable / not COCO            error     modules 4 to 6 read them
annotations naming none of the project's     error     another flight's boxes: nothing to train on
photos
some annotated photos not in the project     warning   those photos' boxes are left out by module 4
checkpoint not a detector MatchPlant reads   error     module 7 (or 6, to fine-tune) loads it (a YOLO best.pt,
                                                       another program's file)
===========================================  ========  ==========================================================

A photogrammetry program is a :class:`ProjectKind`: the files its project holds (:class:`Expected`), and how it lists
the project's photos. :data:`PROJECT_KINDS` holds OpenDroneMap, Metashape and Pix4D (read through
:mod:`matchplant.core.formats.projects`); another program plugs in by adding its kind there. :func:`read_project`
reports on the project as each kind and keeps the kind that finds most.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.images import is_image_name
from matchplant.core.formats.odm import OUTPUTS, ODMProject
from matchplant.core.formats.pix4d import SUFFIX
from matchplant.core.formats.projects import detect_project, open_project
from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import match_names

log = get_logger("init")

ERROR, WARNING = "error", "warning"


@dataclass(frozen=True)
class Expected:
    """One file (or folder) a project of some program holds, and what missing it means."""

    key: str  # the name the pipeline uses: reconstruction, undistorted_images, dsm, dtm, orthophoto, coords
    what: str
    level: str  # ERROR or WARNING when missing
    consequence: str  # what a missing one costs, in the user's terms
    how: str  # how to get it


@dataclass
class ProjectReport:
    """A folder read as one program's project: what was found (key -> path), what is missing, and its photos."""

    program: str
    root: Path
    found: dict[str, Path] = field(default_factory=dict)
    missing: list[Expected] = field(default_factory=list)
    photos: list[str] = field(default_factory=list)  # the project's photos (shot ids: original file names)

    def problems(self, level: str) -> list[Expected]:
        """The missing files of one level (ERROR or WARNING)."""
        return [m for m in self.missing if m.level == level]

    def lines(self) -> list[str]:
        """What was found and what is missing, one line each, for the log and the error."""
        out = [f"{self.program} project {self.root}:"]
        out += [f"  found:   {key} ({_rel(p, self.root)})" for key, p in self.found.items()]
        out += [f"  missing: {m.what} ({m.level}: {m.consequence}; {m.how})" for m in self.missing]
        return out


@dataclass(frozen=True)
class ProjectKind:
    """A photogrammetry program (its ``project_type`` name): ``read(root)`` reports on a folder as its project."""

    program: str
    read: Callable[[Path], ProjectReport]


def _rel(path: Path, root: Path) -> str:
    try:
        return Path(path).relative_to(root).as_posix()
    except ValueError:
        return str(path)


# --------------------------------------------------------------------------------------------------
# OpenDroneMap

ODM_EXPECTED = (
    Expected(
        "reconstruction",
        f"{OUTPUTS['reconstruction'].relpath} (camera poses)",
        ERROR,
        "modules 3, 7 and 8 place every photo and plant with the cameras",
        f"run ODM on the photos ({OUTPUTS['reconstruction'].produced_by}; module 2 does this)",
    ),
    Expected(
        "undistorted_images",
        f"{OUTPUTS['undistorted_images'].relpath} (undistorted photos)",
        ERROR,
        "modules 3 to 8 read the undistorted photos",
        f"re-run ODM with {OUTPUTS['undistorted_images'].produced_by}",
    ),
    Expected(
        "undistorted_reconstruction",
        f"{OUTPUTS['undistorted_reconstruction'].relpath} (cameras of the undistorted photos)",
        ERROR,
        "modules 3 and 8 place the undistorted photos with them",
        f"re-run ODM with {OUTPUTS['undistorted_reconstruction'].produced_by}",
    ),
    Expected(
        "dsm",
        f"{OUTPUTS['dsm'].relpath} (surface model)",
        ERROR,
        "modules 3 and 8 meet the cameras' rays on it",
        "re-run ODM with --dsm (module 2's odm.dsm: true)",
    ),
    Expected(
        "dtm",
        f"{OUTPUTS['dtm'].relpath} (terrain model)",
        WARNING,
        "module 9 gives no plant height (CHM = DSM - DTM)",
        "re-run ODM with --dtm (module 2's odm.dtm: true)",
    ),
    Expected(
        "orthophoto",
        f"{OUTPUTS['orthophoto'].relpath} (orthophoto)",
        WARNING,
        "module 9 gives no colour statistics from it",
        f"re-run ODM with {OUTPUTS['orthophoto'].produced_by}",
    ),
    Expected(
        "coords",
        f"{OUTPUTS['coords'].relpath} (georeferencing)",
        WARNING,
        "plant positions stay in the reconstruction's local frame, not map coordinates",
        f"give ODM {OUTPUTS['coords'].produced_by}",
    ),
)


def read_odm(root: Path) -> ProjectReport:
    """The folder read as an OpenDroneMap project (a split-merge one included)."""
    report = ProjectReport("OpenDroneMap", Path(root))
    if not Path(root).is_dir():
        report.missing += ODM_EXPECTED
        return report
    project = ODMProject(root)
    for item in ODM_EXPECTED:
        if project.has(item.key):
            report.found[item.key] = project.path(item.key)
        else:
            report.missing.append(item)
    if project.has("undistorted_images"):
        report.photos = list(project.undistorted_images())
    return report


# Metashape and Pix4D pose the original photos (no undistorted ones); the rasters are the user's exports
PHOTO_EXPECTED = (
    Expected(
        "dsm",
        "the DSM export (a GeoTIFF beside the project)",
        ERROR,
        "modules 3 and 8 meet the cameras' rays on it",
        "export the DEM/DSM as a GeoTIFF beside the project",
    ),
    Expected(
        "dtm",
        "the DTM export (a GeoTIFF beside the project)",
        WARNING,
        "module 9 gives no plant height (CHM = DSM - DTM)",
        "export the terrain model (DTM) as a GeoTIFF beside the project",
    ),
    Expected(
        "orthophoto",
        "the orthophoto export",
        WARNING,
        "module 9 gives no colour statistics from it",
        "export the orthomosaic as a GeoTIFF beside the project",
    ),
)


CAMERA_FILES = {"metashape": "a camera export (.xml) or a project (.psx)", "pix4d": f"1_initial/params/<name>{SUFFIX}"}


def photo_project_reader(program: str, name: str) -> Callable[[Path], ProjectReport]:
    """The reader of a ``program`` (metashape, pix4d) project: its cameras, rasters and original photos."""

    def read(root: Path) -> ProjectReport:
        report = ProjectReport(name, Path(root))
        try:
            found = detect_project(root, program)
        except InputError:  # not this program's project: nothing found
            cameras = Expected("cameras", CAMERA_FILES[program], ERROR, "every module places photos with them", "")
            report.missing.append(cameras)
            return report
        project = open_project(root, program)
        report.found["cameras"] = found.evidence[0] if found.evidence else found.path
        for item in PHOTO_EXPECTED:
            if project.has(item.key):
                report.found[item.key] = project.path(item.key)
            else:
                report.missing.append(item)
        report.photos = sorted(project.shot_ids(undistorted=False))
        return report

    return read


PROJECT_KINDS: list[ProjectKind] = [
    ProjectKind("odm", read_odm),
    ProjectKind("metashape", photo_project_reader("metashape", "Metashape")),
    ProjectKind("pix4d", photo_project_reader("pix4d", "Pix4D")),
]


# --------------------------------------------------------------------------------------------------
# the checks


def _photos_in(root: Path) -> int:
    """Photos at the top of the folder or in its images/ (a folder of raw photos, not a project)."""
    return sum(1 for folder in (root, root / "images") if folder.is_dir() for p in folder.iterdir() if is_image_name(p))


def read_project(root: Path, project_type: str = "auto") -> ProjectReport:
    """The folder read as the project of the program whose files it holds most of (or of ``project_type``); an error
    when it holds none."""
    kinds = [k for k in PROJECT_KINDS if project_type in ("auto", k.program)]
    reports = [kind.read(Path(root)) for kind in kinds]
    best = max(reports, key=lambda r: len(r.found))
    if best.found:
        return best
    photos = _photos_in(Path(root))
    held = f"{photos} photo(s) but " if photos else ""
    expected = "; ".join(f"{r.program}: {', '.join(m.what for m in r.missing if m.level == ERROR)}" for r in reports)
    raise InputError(
        f"this folder holds {held}no photogrammetry outputs (looked for {expected})",
        path=root,
        fix="run the photogrammetry first (module 2 runs OpenDroneMap: matchplant odm_runner --set "
        "images=PHOTOS), then give init the project folder it writes",
    )


def check_annotations(annotations: Path, report: ProjectReport) -> list[str]:
    """Errors (raised) and warnings (returned) of the annotations against the project's photos."""
    ds = read_dataset(annotations, validate=False)
    names = [Path(str(im.get("file_name", ""))).name for im in ds["images"]]
    if not names:
        raise InputError(
            "the annotations list no photos", path=annotations, fix="give module 4's annotations.json (COCO)"
        )
    if not report.photos:
        return []
    # an annotation names the original photo (IMG_1.JPG) or its undistorted copy (IMG_1.JPG.tif)
    files = {f"{p}.tif": p for p in report.photos}
    matched, unmatched = match_names([files.get(n, n) for n in names], report.photos)
    if not matched:
        raise InputError(
            f"the annotations are of other photos: none of their {len(names)} photo(s) (e.g. {names[0]}) is among "
            f"the project's {len(report.photos)} (e.g. {report.photos[0]}): another flight's annotations?",
            path=annotations,
            fix="give the annotations drawn on this project's photos (module 3 lists the ones to annotate)",
        )
    if unmatched:
        return [
            f"{len(unmatched)} of the {len(names)} annotated photos are not in the project (e.g. {unmatched[0]}): "
            f"module 4 leaves their boxes out ({annotations})"
        ]
    return []


def check_season_inputs(
    project: Path,
    annotations: Path | None = None,
    checkpoint: Path | None = None,
    check_checkpoint: Callable[[Path], None] | None = None,
    project_type: str = "auto",
) -> ProjectReport:
    """Every check of ``init``'s inputs; raises one error listing every problem found, logs each warning, and
    returns the project's report (what the pipeline may use). ``check_checkpoint(path)`` raises a
    MatchPlantError when the file is not a detector MatchPlant reads."""
    report = read_project(project, project_type)
    for line in report.lines():
        log.info(line)
    errors = [f"{m.what} is missing: {m.consequence} ({m.how})" for m in report.problems(ERROR)]
    warnings = [f"no {m.what}: {m.consequence}; {m.how}" for m in report.problems(WARNING)]
    if "dtm" not in report.found and "orthophoto" not in report.found and (annotations or checkpoint):
        errors.append(
            "neither a DTM nor an orthophoto: module 9 has no raster to measure the plants on (re-run ODM "
            "with --dtm, or with its orthophoto step)"
        )
    if annotations is not None:
        try:
            warnings += check_annotations(Path(annotations), report)
        except MatchPlantError as exc:
            errors.append(f"annotations {annotations}: {exc.problem}")
    if checkpoint is not None and check_checkpoint is not None:
        try:
            check_checkpoint(Path(checkpoint))
        except MatchPlantError as exc:
            errors.append(f"checkpoint {checkpoint}: {exc.problem}")
    for text in warnings:
        log.warning(text)
    if errors:
        lines = "\n".join(f"  - {e}" for e in errors)
        raise ConfigError(
            f"init found {len(errors)} problem(s) with what it was given (nothing written):\n{lines}",
            path=project,
            fix="correct them (each says how), then run matchplant init again",
        )
    return report
