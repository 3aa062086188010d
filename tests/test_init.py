"""``matchplant init`` (issue 40, point 2): a season's pipeline.yaml written from an ODM project folder, so a breeder
writes none by hand. Checked: every step it writes passes the pipeline's own checks (modules, keys, references,
paths) as written; plain YAML, paths relative to the file, a comment above each step; the steps follow what was
given (annotations: train; a checkpoint: detect; neither: the photos to annotate); a file in the way is kept; and
(slow) ``matchplant run`` completes the written pipeline unchanged on the tiny field."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml
from small_detector import save_small, small_detector

from matchplant import cli
from matchplant.pipeline import read_pipeline
from matchplant.pipeline.plan import plan_pipeline


def _init(tmp_path: Path, field: Path, *args: str) -> tuple[int, Path]:
    out = tmp_path / "season" / "pipeline.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    return cli.main(["init", str(field), "--output", str(out), *args]), out


def _names(path: Path) -> list[str]:
    return [s.name for s in read_pipeline(path)[1]]


def test_with_annotations_every_step_is_written_and_checks(tiny_field, tmp_path):
    rc, path = _init(tmp_path, tiny_field.root, "--annotations", str(tiny_field.boxes_undistorted))
    assert rc == 0
    text = path.read_text()
    assert "&id" not in text and "*id" not in text
    assert str(tmp_path) not in text and str(tiny_field.root) not in text  # relative to the file
    assert _names(path) == ["2_odm", "3_select", "4_annotate", "5_tiles", "6_train", "7_detect", "8_plants", "9_stats"]
    lines = text.splitlines()
    for name in _names(path):
        assert lines[lines.index(f"  - name: {name}") - 1].startswith("  # "), name
    top, steps = read_pipeline(path)
    plan_pipeline(path, top, steps)  # every module, key, value range, reference and input path, as `run` checks
    spec = {s["name"]: s["config"] for s in yaml.safe_load(text)["steps"]}
    assert spec["6_train"]["model"]["architecture"] == "auto" and spec["6_train"]["model"]["pretrained"] == "auto"
    # the tiling the plants call for (matchplant inspect): the tiny field's 400x300 photos are each one tile
    assert spec["5_tiles"]["tile_size"] == 400 == spec["7_detect"]["detect"]["tile_size"]
    rasters = spec["9_stats"]["rasters"]
    assert set(rasters) == {"dsm", "dtm", "rgb"}  # what the project holds


def test_with_a_checkpoint_it_detects_and_with_nothing_it_selects_the_photos_to_annotate(tiny_field, tmp_path):
    checkpoint = tmp_path / "best.pt"
    save_small(checkpoint, *small_detector())  # init checks its kind (issue 47); module 7 reads it when it runs
    rc, path = _init(tmp_path / "a", tiny_field.root, "--checkpoint", str(checkpoint))
    assert rc == 0 and _names(path) == ["2_odm", "3_select", "7_detect", "8_plants", "9_stats"]
    assert yaml.safe_load(path.read_text())["checkpoint"] == "../../best.pt"
    rc, path = _init(tmp_path / "b", tiny_field.root)
    assert rc == 0 and _names(path) == ["2_odm", "3_select"]
    assert "matchplant bbox_drawer --gui" in path.read_text() and "--set annotations=" in path.read_text()


def test_a_file_in_the_way_is_kept(tiny_field, tmp_path, capsys):
    rc, path = _init(tmp_path, tiny_field.root)
    path.write_text("# my edits\n")
    rc, path = _init(tmp_path, tiny_field.root)
    assert rc == 2 and path.read_text() == "# my edits\n"
    assert "force" in capsys.readouterr().err
    rc, path = _init(tmp_path, tiny_field.root, "--set", "force=true")
    assert rc == 0 and path.read_text() != "# my edits\n"


def test_a_folder_that_is_no_odm_project_is_refused(tmp_path, capsys):
    rc, path = _init(tmp_path, tmp_path / "nowhere")
    assert rc == 2 and not path.exists()
    assert "fix:" in capsys.readouterr().err


@pytest.mark.slow
def test_run_completes_the_written_pipeline_unchanged(tiny_field, tmp_path):
    """The acceptance: init on the demo's (tiny) field, then `matchplant run` on the file as written. Training by
    module 6's 30 epochs, not a time budget (max_minutes 0, an init option), so the detector is the same on a busy
    machine (60 iterations, about 3 of the ~6 minutes this test takes on a busy 2-core machine)."""
    field = tmp_path / "field"
    shutil.copytree(tiny_field.root, field)
    rc, path = _init(
        tmp_path, field, "--annotations", str(field / "truth" / "boxes_undistorted.json"), "--set", "max_minutes=0"
    )
    assert rc == 0
    assert cli.main(["run", str(path)]) == 0  # the file as init wrote it
    assert path.parent.joinpath("9_stats", "stats.csv").is_file()
    summary = json.loads(path.parent.joinpath("6_train", "training_summary.json").read_text())
    assert summary["status"] in ("finished", "stopped_by_max_minutes")
