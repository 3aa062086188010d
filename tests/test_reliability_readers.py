"""Issue 47, the readers: one YAML reader for every config file, and one checked reader for every file the package
reads back. Table-driven over what the code holds (tests/reliability_tables.py), so that a new step, config or
reader without the behaviour fails here:

- every step's ``--config`` file (``init`` and ``run`` included), a pipeline file, a step's ``config:`` mapping and
  its ``config_file``, and a ``--set`` value refuse a key given twice, naming the file, both lines and the key;
- no YAML or JSON is parsed in the package outside ``core/runtime/readers.py``, and no ``.pt`` file outside the
  checkpoint reader: a damaged file is always named with a fix, never an internal error;
- every state file the package reads back (a pipeline's step records, a run's manifest, module 6's record of the
  checkpoints it may delete) is read by :func:`read_record`: a truncated one names the file and the way out.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from reliability_tables import calls, config_classes, config_fields

from matchplant.cli import run_module
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.readers import parse_value, read_record
from matchplant.pipeline.run import continue_interrupted

YAML_LOADS = {"load", "safe_load", "full_load", "unsafe_load", "load_all", "safe_load_all", "full_load_all"}
READERS = "core/runtime/readers.py"


def one_key(step: str) -> str:
    """A top-level key of the step's config that takes a plain value (the duplicate is found before its value)."""
    return next(k.name for k in config_fields(step, config_classes()[step]) if "." not in k.name)


@pytest.mark.parametrize("step", list(config_classes()))
def test_every_steps_config_file_refuses_a_duplicate_key(step, tmp_path, capsys):
    key = one_key(step)
    path = tmp_path / f"{step}.yaml"
    path.write_text(f"# {step}\n{key}: 1\n\n{key}: 2\n", encoding="utf-8")
    assert run_module(step, ["--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err, err
    assert str(path) in err and f"'{key}'" in err and "twice" in err and "lines 2 and 4" in err, err


@pytest.mark.parametrize("step", list(config_classes()))
def test_a_duplicate_key_in_a_section_is_refused_too(step):
    sections = {k.name.split(".")[0] for k in config_fields(step, config_classes()[step]) if "." in k.name}
    if not sections:
        pytest.skip(f"{step}'s config has no section")
    name = sorted(sections)[0]
    inner = next(
        k.name.split(".", 1)[1] for k in config_fields(step, config_classes()[step]) if k.name.startswith(name)
    )
    inner = inner.split(".")[0]
    with pytest.raises(ConfigError, match=f"'{inner}' is given twice, at lines 2 and 3"):
        load_config(config_classes()[step], _write(f"{name}:\n  {inner}: 1\n  {inner}: 2\n"), strict=False)


def _write(text: str) -> Path:
    import tempfile

    path = Path(tempfile.mkdtemp()) / "c.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_a_set_value_with_a_duplicate_key_is_refused():
    with pytest.raises(ConfigError, match="'a' is given twice"):
        parse_value("{a: 1, a: 2}")


@pytest.mark.parametrize(
    "where",
    ["top", "step", "config"],
)
def test_a_pipeline_refuses_a_duplicate_key_wherever_it_is(where, tmp_path, capsys):
    steps = "steps:\n  - module: inspect\n    config: {annotations: a.json}\n"
    if where == "top":
        text = f"output_dir: out\noutput_dir: out2\n{steps}"
    elif where == "step":
        text = "steps:\n  - module: inspect\n    module: inspect\n"
    else:
        text = "steps:\n  - module: inspect\n    config:\n      annotations: a.json\n      annotations: b.json\n"
    path = tmp_path / "pipeline.yaml"
    path.write_text(text, encoding="utf-8")
    assert run_module("run", [str(path)]) == 2
    err = capsys.readouterr().err
    assert "twice" in err and str(path) in err and "Traceback" not in err, err


def test_a_steps_config_file_in_a_pipeline_refuses_a_duplicate_key(tmp_path, capsys):
    (tmp_path / "step.yaml").write_text("annotations: a.json\nannotations: b.json\n", encoding="utf-8")
    path = tmp_path / "pipeline.yaml"
    path.write_text("steps:\n  - module: inspect\n    config_file: step.yaml\n", encoding="utf-8")
    assert run_module("run", [str(path)]) == 2
    err = capsys.readouterr().err
    assert "twice" in err and "step.yaml" in err and "'annotations'" in err, err


# --------------------------------------------------------------------------------------------------
# one reader of each kind


def test_yaml_is_parsed_only_by_the_one_reader():
    stray = [c for c in calls("yaml", YAML_LOADS) if c[0] != READERS]
    assert not stray, f"YAML parsed outside {READERS} (a duplicate key would be taken silently): {stray}"


def test_json_is_parsed_only_by_the_one_reader():
    stray = [c for c in calls("json", {"load", "loads"}) if c[0] != READERS]
    assert not stray, f"JSON parsed outside {READERS} (a damaged file would be an internal error): {stray}"


def test_checkpoints_are_loaded_only_by_the_checkpoint_reader():
    stray = [c for c in calls("torch", {"load"}) if c[0] != "detection/checkpoint.py"]
    stray += calls("pickle", {"load", "loads"}) + calls("np", {"load"}) + calls("numpy", {"load"})
    assert not stray, f"a file loaded outside the checked readers: {stray}"


# --------------------------------------------------------------------------------------------------
# state files


@pytest.mark.parametrize("damage", ["truncated", "empty", "a list", "binary", "a folder"])
def test_a_damaged_record_is_named_with_the_way_out(damage, tmp_path):
    path = tmp_path / "rec.json"
    good = json.dumps({"fingerprint": "abc", "started": 1.0})
    if damage == "a folder":
        path.mkdir()
    else:
        data = {"truncated": good[:-7], "empty": "", "a list": "[1, 2]"}.get(damage)
        path.write_bytes(data.encode() if data is not None else b"\x00\x01\xff" * 10)
    with pytest.raises(InputError) as info:
        read_record(path, what="the step's record", fix="delete it, or re-run with --set force=true")
    text = str(info.value)
    assert str(path) in text and "damaged" in text and "delete it" in text, text


def test_a_missing_record_is_the_default(tmp_path):
    assert read_record(tmp_path / "none.json", what="x", fix="y", default={}) == {}


STATE_READERS = {
    # state file -> the module that reads it back through read_record
    ".pipeline/<step>.json": "pipeline/run.py",
    ".pipeline/<step>.started.json": "pipeline/run.py",
    "manifest.json": "core/runtime/manifest.py",
    "checkpoints/auto_checkpoints.json": "model_train/checkpoint.py",
    "the demo's records (training_summary.json, metrics, stamps)": "demo_pipeline.py",
}


@pytest.mark.parametrize("state, module", list(STATE_READERS.items()))
def test_each_state_file_is_read_with_the_checked_reader(state, module):
    source = (Path(__file__).resolve().parents[1] / "matchplant" / module).read_text(encoding="utf-8")
    assert "read_record(" in source, f"{state} is read in {module} without read_record"


def test_a_truncated_start_record_of_a_resumable_step_is_named(tmp_path):
    started = tmp_path / "6_train.started.json"
    started.write_text('{"fingerprint": "0123')
    spec = SimpleNamespace(resume_key="resume", resume_file=lambda cfg: tmp_path / "last.pt")
    step = SimpleNamespace(name="6_train")
    with pytest.raises(InputError) as info:
        continue_interrupted(step, spec, SimpleNamespace(resume=False), started, "0123")
    assert str(started) in str(info.value) and "delete" in str(info.value)


@pytest.mark.parametrize("record", ["<step>.json"])
def test_a_truncated_pipeline_record_is_named_not_an_internal_error(record, tmp_path, capsys):
    annotations = tmp_path / "a.json"
    annotations.write_text(
        json.dumps(
            {
                "images": [{"id": 1, "file_name": "a.jpg", "width": 100, "height": 100}],
                "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20]}],
                "categories": [{"id": 1, "name": "plant"}],
            }
        )
    )
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(
        "output_dir: out\nsteps:\n  - name: sizes\n    module: inspect\n    config: {annotations: a.json}\n"
    )
    state = tmp_path / "out" / ".pipeline" / record.replace("<step>", "sizes")
    state.parent.mkdir(parents=True)
    state.write_text('{"fingerprint": "0123')
    assert run_module("run", [str(pipeline)]) == 2
    err = capsys.readouterr().err
    assert "internal error" not in err and str(state) in err and "delete" in err, err
