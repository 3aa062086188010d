"""After a run: are the outputs later steps need there (docs/DESIGN.md §2), and what was run.

:func:`check_outputs` names, for each missing output, the ODM option that produces it;
:func:`write_manifest` records the run, its options and every output in ``odm_manifest.json``.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rasterio

from matchplant.core.formats.odm import OUTPUTS, ODMProject
from matchplant.core.formats.reconstruction import read_reconstruction
from matchplant.core.formats.split_check import split_problems
from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import MatchPlantError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import package_versions
from matchplant.core.runtime.validate_gis import check_raster
from matchplant.odm_runner.config import OdmRunnerConfig
from matchplant.odm_runner.inputs import odm_option_dict

# outputs modules 3, 8 and 9 read (docs/DESIGN.md §2); the topocentric copy is optional
REQUIRED_OUTPUTS = (
    "reconstruction",
    "undistorted_reconstruction",
    "undistorted_images",
    "dsm",
    "dtm",
    "orthophoto",
    "coords",
)


@dataclass
class OutputReport:
    """What an ODM project holds, and every reason later steps could not use it (empty: ok)."""

    project: Path
    present: dict[str, bool]
    problems: list[str] = field(default_factory=list)  # missing outputs, each with the option producing it
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Whether later steps can use the project (no problems)."""
        return not self.problems


def check_outputs(project_dir: str | Path, required: Sequence[str] = REQUIRED_OUTPUTS) -> OutputReport:
    """Check the outputs modules 3, 8 and 9 need; each problem names the ODM option that fixes it."""
    project = ODMProject(project_dir)
    present = project.check()
    problems = [
        f"{rel} ({OUTPUTS[n].what}) is missing: produced by {OUTPUTS[n].produced_by}"
        for rel, n in project.missing_paths([n for n in required if not present[n]])
    ]
    details: dict[str, Any] = {}
    problems += split_problems(project)  # submodels that failed or come from another run
    readable = True
    for sub in project.submodels or [project]:
        where = f"submodels/{sub.name}/" if project.is_split else ""
        readable &= _check_reconstructions(sub, where, problems)
    if readable:  # the checks below read the reconstructions again; their problems are said once
        for sub in project.submodels or [project]:
            where = f"submodels/{sub.name}: " if project.is_split else ""
            _check_undistorted(sub, where, sub.has("undistorted_images"), problems, details)
        if project.is_split:
            _check_split(project, problems, details)
    for name in ("dsm", "dtm", "orthophoto"):
        if present[name]:
            info = _raster_info(project.path(name))
            details[name] = info
            if "error" in info:
                problems.append(
                    f"{OUTPUTS[name].relpath} is unreadable ({info['error']}): re-run ODM ({OUTPUTS[name].produced_by})"
                )
                continue
            try:
                check_raster(project.path(name), bands=1, what=OUTPUTS[name].what)
            except MatchPlantError as exc:
                problems.append(f"{OUTPUTS[name].relpath}: {exc.problem}: {exc.fix}")
    if present["coords"]:
        try:
            crs, offset = project.coords
            details["crs"] = crs.to_string()
            details["offset"] = [float(offset[0]), float(offset[1])]
        except MatchPlantError as exc:
            problems.append(f"odm_georeferencing/coords.txt is unreadable: {exc.problem} ({exc.fix})")
    return OutputReport(project=Path(project_dir), present=present, problems=problems, details=details)


def _check_reconstructions(project: ODMProject, where: str, problems: list[str]) -> bool:
    """Each reconstruction file present is read whole (truncated, malformed, no images, unknown camera
    model); False when one cannot be used."""
    ok = True
    for name in ("reconstruction", "topocentric_reconstruction", "undistorted_reconstruction"):
        if not project.has(name):
            continue
        try:
            read_reconstruction(project.path(name))
        except MatchPlantError as exc:
            ok = False
            problems.append(f"{where}{OUTPUTS[name].relpath} cannot be used: {exc.problem} ({exc.fix})")
    return ok


def _check_undistorted(
    project: ODMProject, where: str, images_present: bool, problems: list[str], details: dict
) -> None:
    """Every reconstructed image has its undistorted image (one folder: the project or a submodel)."""
    if not project.has("undistorted_reconstruction"):
        return
    try:
        shots = project.shot_ids(undistorted=True)
        images = set(project.undistorted_images())
    except MatchPlantError as exc:
        problems.append(f"{where}opensfm/undistorted/reconstruction.json is unreadable: {exc.problem}")
        return
    details["undistorted_shots"] = details.get("undistorted_shots", 0) + len(shots)
    details["undistorted_images"] = details.get("undistorted_images", 0) + len(images)
    lacking = sorted(shots - images)
    if lacking and images_present:
        problems.append(
            f"{where}{len(lacking)} of {len(shots)} reconstructed images have no undistorted image "
            f"(e.g. {lacking[0]}.tif): produced by the OpenSfM undistort step "
            "(do not use --optimize-disk-space)"
        )


def _check_split(project: ODMProject, problems: list[str], details: dict) -> None:
    """A split-merge run: the merged outputs at the top, and each submodel's frame and images."""
    for name in ("dsm", "dtm", "orthophoto", "coords"):
        if not (project.root / OUTPUTS[name].relpath).is_file():
            problems.append(
                f"{OUTPUTS[name].relpath} (the merged {OUTPUTS[name].what}) is missing at the top of "
                f"the split-merge project: produced by ODM's merge stage (--merge all) from each "
                f"submodel's ({OUTPUTS[name].produced_by})"
            )
    subs = {}
    try:
        ids = project.shot_ids(undistorted=True)
        for sub in project.submodels:
            frame = sub.frame(project.frame().crs)
            own = sum(1 for sid in ids if project.owner(sid) is sub)
            subs[sub.name] = {
                "frame": frame.describe(),
                "shots": len(sub.shot_ids(undistorted=True)),
                "used_shots": own,
            }
        details["split"] = {
            "submodels": subs,
            "images": len(ids),
            "images_in_several_submodels": sum(s["shots"] for s in subs.values()) - len(ids),
        }
    except MatchPlantError as exc:
        problems.append(f"the submodels cannot be read as one project: {exc.problem}")


def _raster_info(path: Path) -> dict:
    try:
        with rasterio.open(path) as src:
            return {
                "width": src.width,
                "height": src.height,
                "bands": src.count,
                "crs": src.crs.to_string() if src.crs else None,
                "resolution_m": [abs(src.transform.a), abs(src.transform.e)],
            }
    except Exception as exc:  # noqa: BLE001 - any GDAL failure means the file is unusable
        return {"error": str(exc)}


def write_manifest(path: str | Path, cfg: OdmRunnerConfig, report: OutputReport, run_info: dict | None) -> Path:
    """What was run, with which options, and every output with its size and whether it is there."""
    project = ODMProject(report.project)
    outputs = {}
    for name, out in OUTPUTS.items():
        p = project.path(name)
        entry: dict[str, Any] = {"path": out.relpath, "exists": report.present[name], "produced_by": out.produced_by}
        if report.present[name] and p.is_file():
            entry["bytes"] = p.stat().st_size
        outputs[name] = entry
    data = {
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
        "project_dir": str(report.project),
        "run": run_info,
        "odm_options": odm_option_dict(cfg.odm),
        "outputs": outputs,
        "details": report.details,
        "problems": report.problems,
        "ok": report.ok,
        "config": to_dict(cfg),
        "versions": package_versions(),
    }
    return write_json(path, data)
