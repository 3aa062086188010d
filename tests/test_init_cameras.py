"""``matchplant init`` from Metashape and Pix4D projects (issue 45): the season's pipeline as from ODM, checked by
the pipeline's own checks; a folder of none of the three programs is refused, naming what was looked for."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from project_exports import write_exports
from small_detector import save_small, small_detector

from matchplant import cli
from matchplant.pipeline import read_pipeline
from matchplant.pipeline.plan import plan_pipeline


@pytest.fixture(scope="module")
def exports(tiny_field, tmp_path_factory) -> dict[str, Path]:
    """The tiny field as a Metashape export and a Pix4D project folder, with photos, DSM and orthophoto."""
    return write_exports(tiny_field.root, tmp_path_factory.mktemp("init_exports"))


@pytest.mark.parametrize("program", ["metashape", "pix4d"])
def test_init_writes_a_season_from_the_project(exports, tmp_path, program):
    """Module 3 and 8 read the project with its program named, module 8 the original photos; the rasters are the
    exports; every key, reference and path passes `matchplant run`'s checks."""
    checkpoint = tmp_path / "best.pt"
    save_small(checkpoint, *small_detector())  # init checks its kind (issue 47)
    out = tmp_path / "season" / "pipeline.yaml"
    out.parent.mkdir()
    rc = cli.main(["init", str(exports[program]), "--output", str(out), "--checkpoint", str(checkpoint)])
    assert rc == 0
    top, steps = read_pipeline(out)
    assert [s.name for s in steps] == ["3_select", "7_detect", "8_plants", "9_stats"]
    plan_pipeline(out, top, steps)
    spec = {s["name"]: s["config"] for s in yaml.safe_load(out.read_text())["steps"]}
    assert spec["3_select"]["project_type"] == program == spec["8_plants"]["project_type"]
    assert spec["8_plants"]["image_type"] == "original" and spec["7_detect"]["detect"]["images"].endswith("images")
    assert set(spec["9_stats"]["rasters"]) == {"dsm", "dtm", "rgb"}
    assert "from the project" in out.read_text()


def test_a_folder_of_no_program_is_refused_naming_what_was_looked_for(tmp_path, capsys):
    """Exit 2, no file, and the files of each program that were looked for."""
    (tmp_path / "photos").mkdir()
    out = tmp_path / "pipeline.yaml"
    assert cli.main(["init", str(tmp_path / "photos"), "--output", str(out)]) == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "opensfm/reconstruction.json" in err and ".psx" in err and "_calibrated_camera_parameters.txt" in err
