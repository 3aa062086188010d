"""Split-merge projects that are not whole (docs/DESIGN.md §6), for modules 2 (``check_only``), 3 and 8: a
submodel whose node failed (no ``opensfm/reconstruction.json``) and a submodel copied from another run (its
``reference_lla`` 1.1 km away) are named, never skipped (before: modules 3 and 8 ran on what was left, exit 0).
Must work: the whole split project, and a single project whose ``reconstruction.json`` is one object rather
than OpenSfM's list (accepted on purpose, said in the log).

The project is the tiny field rewritten by :func:`matchplant.simfield.split.split_field` (two submodels sharing a
flight line), made in the case's own inputs and broken in one way.
"""

from __future__ import annotations

import json
from pathlib import Path

from cases_odm_runner import RECON, UND_RECON, edit_json, project
from harness import Case, Work
from pyproj import Geod

from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.split import split_field

SUB = "submodels/submodel_0001"


def split_project(w: Work) -> Path:
    root = project(w)
    split_field(FieldPaths(root), submodels=2)
    return root


def failed_node(root: Path) -> None:
    for rel in (RECON, UND_RECON):
        (root / SUB / rel).unlink()


def from_another_run(root: Path) -> None:
    def move(data):
        for rec in data:
            ref = rec["reference_lla"]
            ref["longitude"], ref["latitude"], _ = Geod(ellps="WGS84").fwd(ref["longitude"], ref["latitude"], 30, 1100)

    for rel in (RECON, UND_RECON):
        edit_json(root / SUB / rel, move)


def step_args(step: str, w: Work, root: Path) -> list[str]:
    out = ["--set", f"output_dir={w.out}"]
    if step == "odm_runner":
        return ["--set", f"project_dir={root}", "--set", "check_only=true", *out]
    if step == "min_img_finder":
        return ["--set", f"project_dir={root}", *out]
    return ["--set", f"project={root}", "--set", f"predictions={w.copy('predictions.json')}", *out]


def broken_split(step: str, change):
    def prepare(w: Work) -> list[str]:
        root = split_project(w)
        if change is not None:
            change(root)
        return step_args(step, w, root)

    return prepare


def dict_reconstruction(w: Work) -> list[str]:
    root = project(w)
    for rel in (RECON, UND_RECON):
        data = json.loads((root / rel).read_text())
        (root / rel).write_text(json.dumps(data[0]))  # one object, not a list of one
    return step_args("odm_runner", w, root)


def manifest_ok(w: Work) -> None:
    manifest = json.loads((w.out / "odm_manifest.json").read_text())
    assert manifest["ok"] and not manifest["problems"], manifest["problems"]


STEPS = {"odm_runner": "m2", "min_img_finder": "m3", "plant_projection": "m8"}
CASES = [Case(f"{m}-split-whole", step, broken_split(step, None), expect="ok") for step, m in STEPS.items()]
CASES += [
    Case(
        f"{m}-split-failed-node",
        step,
        broken_split(step, failed_node),
        mentions=("submodel_0001", "opensfm/reconstruction.json", "node"),
        outputs_allowed=("odm_manifest.json",),
    )
    for step, m in STEPS.items()
]
CASES += [
    Case(
        f"{m}-split-submodel-from-another-run",
        step,
        broken_split(step, from_another_run),
        mentions=("submodel_0001", "reference_lla", "1.1 km", "another run"),
        outputs_allowed=("odm_manifest.json",),
    )
    for step, m in STEPS.items()
]
CASES += [Case("m2-reconstruction-one-object", "odm_runner", dict_reconstruction, expect="ok", check=manifest_ok)]
