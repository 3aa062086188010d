"""Split-merge projects that are not whole (docs/DESIGN.md §6): a submodel whose node failed (no
reconstruction) or one copied from another run (its frame 1.1 km away) is named by modules 2, 3 and 8, never
skipped; the whole project passes. The project is the tiny field rewritten by :mod:`matchplant.simfield.split`."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest
from pyproj import Geod

from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.reconstruction import read_reconstruction
from matchplant.core.formats.split_check import check_split, split_problems
from matchplant.core.runtime.errors import InputError
from matchplant.odm_runner.outputs import check_outputs
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.split import split_field


@pytest.fixture(scope="module")
def split(tiny_field, tmp_path_factory) -> FieldPaths:
    dst = tmp_path_factory.mktemp("split_check") / "field"
    shutil.copytree(tiny_field.root, dst)
    return split_field(FieldPaths(dst), submodels=2)


def _copy(split: FieldPaths, tmp_path):
    root = tmp_path / "p"
    shutil.copytree(split.root, root)
    return root


def test_a_whole_split_project_passes(split):
    assert split_problems(ODMProject(split.root)) == []
    check_split(ODMProject(split.root))
    assert check_outputs(split.root).ok


def test_a_failed_node_is_named(split, tmp_path):
    root = _copy(split, tmp_path)
    sub = root / "submodels" / "submodel_0001"
    for rel in ("opensfm/reconstruction.json", "opensfm/undistorted/reconstruction.json"):
        (sub / rel).unlink()
    with pytest.raises(InputError, match="submodels/submodel_0001 has no opensfm/reconstruction.json"):
        check_split(ODMProject(root))
    report = check_outputs(root)
    assert not report.ok and any("submodel_0001 has no" in p for p in report.problems)


def test_a_submodel_from_another_run_is_named(split, tmp_path):
    """Its reference_lla 1.1 km north (a reconstruction copied from another flight): both its frame and the
    images it shares with submodel_0000 are 1.1 km off."""
    root = _copy(split, tmp_path)
    sub = root / "submodels" / "submodel_0001"
    for rel in ("opensfm/reconstruction.json", "opensfm/undistorted/reconstruction.json"):
        path = sub / rel
        data = json.loads(path.read_text())
        for rec in data:
            ref = rec["reference_lla"]
            ref["longitude"], ref["latitude"], _ = Geod(ellps="WGS84").fwd(ref["longitude"], ref["latitude"], 0, 1100)
        path.write_text(json.dumps(data))
    problems = split_problems(ODMProject(root))
    assert len(problems) == 1 and "submodel_0001: its reference_lla" in problems[0] and "1.1 km" in problems[0]
    with pytest.raises(InputError, match="not whole.*submodel_0001"):
        check_split(ODMProject(root))
    assert any("submodel_0001: its reference_lla" in p for p in check_outputs(root).problems)


def test_shared_images_placed_apart_are_named(split, tmp_path):
    """A reference only 300 m off (under the 1 km rule): the images both submodels hold disagree by 300 m."""
    root = _copy(split, tmp_path)
    path = root / "submodels" / "submodel_0001" / "opensfm" / "undistorted" / "reconstruction.json"
    data = json.loads(path.read_text())
    for rec in data:
        ref = rec["reference_lla"]
        ref["longitude"], ref["latitude"], _ = Geod(ellps="WGS84").fwd(ref["longitude"], ref["latitude"], 90, 300)
    path.write_text(json.dumps(data))
    (root / "submodels" / "submodel_0001" / "opensfm" / "reconstruction.json").write_text(json.dumps(data))
    problems = split_problems(ODMProject(root))
    assert len(problems) == 1 and "place the 3 images they share" in problems[0]
    gap = float(problems[0].split(") ")[1].split(" m apart")[0])
    assert np.isclose(gap, 300, atol=5)


def test_a_reconstruction_that_is_one_object_is_read_and_said(tiny_field, tmp_path, caplog):
    """Module 2's decision: a reconstruction.json holding one object, not OpenSfM's list, is accepted on purpose."""
    src = tiny_field.root / "opensfm" / "reconstruction.json"
    data = json.loads(src.read_text())
    one = tmp_path / "reconstruction.json"
    one.write_text(json.dumps(data[0]))
    with caplog.at_level(logging.INFO, logger="matchplant"):
        rec = read_reconstruction(one)
    assert "holds one reconstruction object, not OpenSfM's list" in caplog.text
    assert sorted(rec.shots) == sorted(read_reconstruction(src).shots)
