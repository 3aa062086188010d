"""Issue 47: ``matchplant init`` checks what it is given before it writes anything
(matchplant/pipeline/season_inputs.py, whose table decides error or warning for each problem): the project (what
was found and what is missing, for each photogrammetry program), its DSM and DTM, the annotations against the
project's photos, and the checkpoint's kind. An error writes nothing and exits 2; a warning names what the user
loses and the pipeline is written without it."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import sys
import types
from pathlib import Path

import pytest
import yaml
from small_detector import save_small, small_detector

from matchplant import cli
from matchplant.pipeline import season_inputs
from matchplant.pipeline.season_inputs import ERROR, Expected, ProjectKind, ProjectReport, read_project


def linked_copy(field: Path, dst: Path, without: tuple[str, ...] = ()) -> Path:
    """The field as a tree of links to its files (cheap), less the files ``without`` (relative paths)."""
    shutil.copytree(field, dst, copy_function=os.symlink)
    for rel in without:
        (dst / rel).unlink()
    return dst


def init(tmp_path: Path, project: Path, *args: str) -> tuple[int, Path]:
    out = tmp_path / "season" / "pipeline.yaml"
    return cli.main(["init", str(project), "--output", str(out), *args]), out


def test_a_folder_of_raw_photos_is_refused_with_what_is_missing(tiny_field, tmp_path, capsys):
    rc, out = init(tmp_path, tiny_field.root / "images")
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and not out.parent.exists()
    assert "photo(s) but no photogrammetry outputs" in err and "opensfm/reconstruction.json" in err, err
    assert "odm_runner" in err  # the fix: run the photogrammetry first


def test_the_report_says_what_was_found_and_what_is_missing(tiny_field, tmp_path, capsys):
    project = linked_copy(tiny_field.root, tmp_path / "p", without=("odm_dem/dtm.tif",))
    rc, out = init(tmp_path, project)
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "found:   dsm (odm_dem/dsm.tif)" in err and "missing: odm_dem/dtm.tif" in err, err


def test_no_dtm_is_a_warning_and_module_9_gets_no_heights(tiny_field, tmp_path, capsys):
    project = linked_copy(tiny_field.root, tmp_path / "p", without=("odm_dem/dtm.tif",))
    rc, out = init(tmp_path, project, "--annotations", str(tiny_field.boxes_undistorted), "--quiet")
    err = capsys.readouterr().err
    assert rc == 0, err
    warnings = [ln for ln in err.splitlines() if "dtm.tif" in ln]
    assert warnings and "plant height" in warnings[0] and "--dtm" in warnings[0], err
    rasters = {s["name"]: s["config"] for s in yaml.safe_load(out.read_text())["steps"]}["9_stats"]["rasters"]
    assert set(rasters) == {"rgb"}  # a DSM alone is refused by module 9 (CHM = DSM - DTM)


@pytest.mark.parametrize(
    "missing, named",
    [
        ("odm_dem/dsm.tif", "dsm.tif"),
        ("opensfm/reconstruction.json", "reconstruction.json"),
        ("opensfm/undistorted/reconstruction.json", "undistorted/reconstruction.json"),
    ],
)
def test_what_modules_3_and_8_need_is_an_error(missing, named, tiny_field, tmp_path, capsys):
    project = linked_copy(tiny_field.root, tmp_path / "p", without=(missing,))
    rc, out = init(tmp_path, project)
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and named in err and "nothing written" in err, err


def coco_of(tiny_field, tmp_path: Path, rename) -> Path:
    ds = json.loads(tiny_field.boxes_undistorted.read_text())
    for im in ds["images"]:
        im["file_name"] = rename(im["file_name"])
    path = tmp_path / "annotations.json"
    path.write_text(json.dumps(ds))
    return path


def test_annotations_of_another_flight_are_an_error(tiny_field, tmp_path, capsys):
    other = coco_of(tiny_field, tmp_path, lambda name: "FLIGHT2_" + name)
    rc, out = init(tmp_path, tiny_field.root, "--annotations", str(other))
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and "other photos" in err and "FLIGHT2_" in err, err


def test_some_annotated_photos_not_in_the_project_is_a_warning(tiny_field, tmp_path, capsys):
    first = []

    def rename(name):
        first.append(name)
        return "ELSEWHERE.JPG" if len(first) == 1 else name

    partly = coco_of(tiny_field, tmp_path, rename)
    rc, out = init(tmp_path, tiny_field.root, "--annotations", str(partly), "--quiet")
    err = capsys.readouterr().err
    assert rc == 0 and out.exists() and "ELSEWHERE.JPG" in err and "module 4 leaves their boxes out" in err, err


def yolo_best(path: Path) -> Path:
    """A file shaped like Ultralytics' best.pt: a pickled model of a module this environment does not have."""
    module = types.ModuleType("ultralytics_stub_for_test")
    sys.modules[module.__name__] = module

    class DetectionModel:
        pass

    DetectionModel.__module__, DetectionModel.__qualname__ = module.__name__, "DetectionModel"
    module.DetectionModel = DetectionModel
    import torch

    try:
        torch.save(
            {"model": DetectionModel(), "train_args": {"imgsz": 640}}, path, pickle_protocol=pickle.HIGHEST_PROTOCOL
        )
    finally:
        del sys.modules[module.__name__]
    return path


def test_a_yolo_checkpoint_is_an_error(tiny_field, tmp_path, capsys):
    best = yolo_best(tmp_path / "best.pt")
    rc, out = init(tmp_path, tiny_field.root, "--checkpoint", str(best))
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and "best.pt" in err and "another program" in err, err


def test_a_matchplant_checkpoint_is_taken(tiny_field, tmp_path, capsys):
    best = tmp_path / "best.pt"
    save_small(best, *small_detector())
    rc, out = init(tmp_path, tiny_field.root, "--checkpoint", str(best), "--quiet")
    assert rc == 0 and out.exists(), capsys.readouterr().err


def test_another_photogrammetry_program_plugs_in(tmp_path, monkeypatch):
    """A program's kind added to PROJECT_KINDS is read, and the kind that finds most is kept."""
    (tmp_path / "survey.other3d").write_text("cameras")

    def read_other(root: Path) -> ProjectReport:
        report = ProjectReport("Other3D", root)
        if (root / "survey.other3d").is_file():
            report.found["project"] = root / "survey.other3d"
        report.missing.append(Expected("dsm", "dem.tif", ERROR, "modules 3 and 8 need it", "export the DEM"))
        return report

    monkeypatch.setattr(
        season_inputs, "PROJECT_KINDS", [*season_inputs.PROJECT_KINDS, ProjectKind("other3d", read_other)]
    )
    report = read_project(tmp_path)
    assert report.program == "Other3D" and "project" in report.found
    assert any("missing: dem.tif" in line for line in report.lines())
