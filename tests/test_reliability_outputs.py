"""Issue 47, the outputs and the values: table-driven over every flag, key and writer the code holds
(tests/reliability_tables.py), so that a new one without the behaviour fails here:

- ``-`` has one meaning for every output: standard output for an output file (``--write-config``, ``inspect
  --report``, ``init --output``), a clear refusal for a folder or an input; never "must be a path, got [None]";
- every flag whose name says it is an output is declared as one (``path="out"`` or ``"out_file"``);
- every writer of ``core/runtime/io.py`` turns a write error (full disk, read-only file system, permission, a
  folder in the way) into an OutputError naming the file, and leaves no partial file; the command line too;
- every number key refuses ``inf``, ``-inf`` and ``nan`` (``max_minutes: inf`` made training_summary.json hold
  ``Infinity``, which is not JSON).
"""

from __future__ import annotations

import errno
import json
import os
import sys
from pathlib import Path

import pytest
import yaml
from demo_step import demo_spec
from reliability_tables import all_keys, config_classes, flags, holds, output_flags

import matchplant.cli as cli
from matchplant.cli import run_module
from matchplant.core.runtime import io
from matchplant.core.runtime.config import load_config, save_config
from matchplant.core.runtime.errors import ConfigError, OutputError

LINUX = sys.platform.startswith("linux")
OUTPUT_WORDS = ("output", "report", "write", "out", "save", "export")


def coco(tmp_path: Path) -> Path:
    path = tmp_path / "a.json"
    path.write_text(
        json.dumps(
            {
                "images": [{"id": 1, "file_name": "a.jpg", "width": 400, "height": 400}],
                "annotations": [
                    {"id": i, "image_id": 1, "category_id": 1, "bbox": [10 * i, 10, 20, 20]} for i in range(1, 6)
                ],
                "categories": [{"id": 1, "name": "plant"}],
            }
        )
    )
    return path


# --------------------------------------------------------------------------------------------------
# '-' for standard output


def test_every_flag_named_as_an_output_is_declared_as_one():
    named = [f for f in flags() if f.takes_value and any(w in f.option.lower() for w in OUTPUT_WORDS)]
    declared = {str(f) for f in output_flags()} | {"run --output"}  # NOT_DECLARED below
    assert named and not [str(f) for f in named if str(f) not in declared]


# outputs that are no file or folder a step writes into: the run log's folder of ``matchplant run`` is the season
# folder that holds the pipeline file itself (an "out" folder must hold no input)
NOT_DECLARED = {"run:output_dir"}


def test_every_path_key_named_as_an_output_is_declared_as_one():
    named = [
        str(k)
        for k in all_keys()
        if holds(k, Path)
        and k.path is None
        and any(w in k.name.split(".")[-1] for w in OUTPUT_WORDS)
        and str(k) not in NOT_DECLARED
    ]
    assert not named, f"outputs without path='out' or 'out_file' (so '-' and write errors are not checked): {named}"


@pytest.mark.parametrize("key", [k for k in all_keys() if k.path is not None], ids=str)
def test_dash_is_standard_output_for_an_output_file_and_refused_elsewhere(key):
    cls = config_classes()[key.step]
    if key.path == "out_file":
        cfg = load_config(cls, None, [f"{key.name}=-"], strict=False)
        value = cfg
        for part in key.name.split("."):
            value = getattr(value, part)
        assert str(value) == "-"
        return
    with pytest.raises(ConfigError) as info:
        load_config(cls, None, [f"{key.name}=-"], strict=False)
    text = str(info.value)
    assert key.name in text and "standard output" in text and "[None]" not in text, text


def gcp_rows(field: Path) -> list[str]:
    """The tiny field's surveyed points as 'id,x,y,z' lines."""
    lines = (field / "gcp" / "gcp_survey.csv").read_text().splitlines()
    return [",".join(ln.split(",")[:4]) for ln in lines[1:] if ln.strip()]


def inputs(flag, tmp_path, request) -> list[str]:
    """What a step needs besides the output flag to run (the steps whose output can be standard output)."""
    if flag.step == "inspect":
        return [str(coco(tmp_path))]
    if flag.step == "init":
        return [str(request.getfixturevalue("tiny_field").root)]
    if flag.step == "cameras":  # the photo pixels of the field's ground control points
        field = request.getfixturevalue("tiny_field").root
        points = tmp_path / "points.csv"
        points.write_text("x,y,z\n" + "".join(ln.split(",", 1)[1] + "\n" for ln in gcp_rows(field)))
        return [str(field), "--points", str(points)]
    return []


@pytest.mark.parametrize("flag", output_flags(), ids=str)
def test_every_output_flag_takes_dash(flag, tmp_path, capsys, request):
    """Each output flag with ``-``: a run that writes to standard output, or a refusal that says why."""
    args = inputs(flag, tmp_path, request) if flag.dest != "write_config" else []
    code = run_module(flag.step, [*args, flag.option, "-", "--quiet"])
    out, err = capsys.readouterr()
    assert code in (0, 2) and "[None]" not in err and "internal error" not in err, err
    if flag.dest == "write_config":
        assert code == 0 and yaml.safe_load(out) is not None and "wrote" not in out, out
    elif flag.key is not None and "out_file" == _kind(flag):
        assert code == 0 and out.strip(), err
    else:
        assert code == 2 and "standard output" in err, err


def _kind(flag) -> str | None:
    from reliability_tables import key_of

    key = key_of(flag.step, flag.key)
    return key.path if key else None


def test_inspect_report_dash_is_json_on_standard_output(tmp_path, capsys):
    assert run_module("inspect", [str(coco(tmp_path)), "--report", "-", "--quiet"]) == 0
    out = capsys.readouterr().out
    report = json.loads(out)  # the JSON alone on standard output (the text goes to standard error)
    assert report["recommended"]["tile_size"] > 0 and report["recommended"]["max_minutes"] > 0


def test_a_bare_dash_in_a_yaml_file_says_to_quote_it(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"annotations: {coco(tmp_path)}\nreport: -\n")
    assert run_module("inspect", ["--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "line 2" in err and 'key: "-"' in err and str(cfg) in err, err
    cfg.write_text(f'annotations: {coco(tmp_path)}\nreport: "-"\n')
    assert run_module("inspect", ["--config", str(cfg), "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["images"] == 1


def test_a_pipelines_output_folder_is_no_standard_output(tmp_path, capsys):
    path = tmp_path / "pipeline.yaml"
    path.write_text(f'output_dir: "-"\nsteps:\n  - module: inspect\n    config: {{annotations: {coco(tmp_path)}}}\n')
    assert run_module("run", [str(path)]) == 2
    err = capsys.readouterr().err
    assert "output_dir" in err and "standard output" in err and not (tmp_path / "-").exists(), err


# --------------------------------------------------------------------------------------------------
# write errors


def _write_text(path):
    return io.write_text(path, "x" * 100)


def _write_json(path):
    return io.write_json(path, {"a": list(range(100))})


def _atomic_path(path):
    with io.atomic_path(path) as tmp:
        Path(tmp).write_text("x" * 100)


def _batched(path):
    with io.BatchedWrites(path.parent) as batch:
        batch.write(path.name, b"x" * 100)


def _save_config(path):
    save_config(config_classes()["inspect"](), path)


WRITERS = {
    "write_text": _write_text,
    "write_json": _write_json,
    "atomic_path": _atomic_path,
    "BatchedWrites": _batched,
    "save_config": _save_config,
}


def _full_disk(monkeypatch, tmp_path):
    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(io.os, "fsync", no_space)
    monkeypatch.setattr(io, "_datasync", no_space)
    monkeypatch.setattr(io.os, "replace", no_space)
    return tmp_path / "out.txt"


def _read_only(monkeypatch, tmp_path):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(io.tempfile, "mkstemp", read_only)
    return tmp_path / "out.txt"


def _a_folder(monkeypatch, tmp_path):
    (tmp_path / "out.txt").mkdir()
    return tmp_path / "out.txt"


def _dev_full(monkeypatch, tmp_path):
    if not LINUX:
        pytest.skip("/dev/full is Linux's")
    return Path("/dev/full")


def _no_permission(monkeypatch, tmp_path):
    if os.name != "posix" or os.geteuid() == 0:
        pytest.skip("permissions do not stop root (or are not POSIX here)")
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    return folder / "out.txt"


TARGETS = {
    "full disk": _full_disk,
    "read-only file system": _read_only,
    "a folder in the way": _a_folder,
    "/dev/full": _dev_full,
    "no permission": _no_permission,
}


@pytest.mark.parametrize("target", list(TARGETS))
@pytest.mark.parametrize("writer", list(WRITERS))
def test_every_writer_names_the_file_of_a_write_error_and_leaves_nothing(writer, target, tmp_path, monkeypatch):
    path = TARGETS[target](monkeypatch, tmp_path)
    before = sorted(p.name for p in path.parent.iterdir()) if path.parent != Path("/dev") else []
    with pytest.raises(OutputError) as info:
        WRITERS[writer](path)
    assert str(path.name) in str(info.value) and "fix:" in str(info.value), str(info.value)
    if path.parent != Path("/dev"):
        monkeypatch.undo()
        assert sorted(p.name for p in path.parent.iterdir()) == before, "a partial output was left"


@pytest.mark.skipif(not LINUX, reason="/dev/full is Linux's")
@pytest.mark.parametrize("flag", output_flags(), ids=str)
def test_every_output_flag_on_a_full_disk_is_a_clear_error(flag, tmp_path, capsys, request):
    args = inputs(flag, tmp_path, request) if flag.dest != "write_config" else []
    if _kind(flag) == "out":
        pytest.skip("a folder: /dev/full is refused as not a folder")
    force = ["--set", "force=true"] if flag.step == "init" and flag.dest != "write_config" else []
    code = run_module(flag.step, [*args, flag.option, "/dev/full", *force, "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "/dev/full" in err and "internal error" not in err, err


@pytest.mark.skipif(not LINUX, reason="/dev/full is Linux's")
def test_init_through_a_link_to_a_full_disk_is_a_clear_error(tiny_field, tmp_path, capsys):
    link = tmp_path / "pipeline.yaml"
    link.symlink_to("/dev/full")
    code = run_module("init", [str(tiny_field.root), "--output", str(link), "--set", "force=true", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "internal error" not in err and ("pipeline.yaml" in err or "/dev/full" in err), err


@pytest.mark.parametrize(
    "code, filename, words",
    [
        (errno.ENOSPC, "/data/out/plants.gpkg", ("cannot write /data/out/plants.gpkg", "disk is full")),
        (errno.ENOSPC, None, ("cannot write an output", "disk is full")),
        (errno.EROFS, "/mnt/ro/x.tif", ("/mnt/ro/x.tif", "read-only")),
        (errno.EACCES, "/data/in/photo.jpg", ("cannot use /data/in/photo.jpg", "permission denied")),
    ],
)
def test_a_file_error_inside_a_step_is_named_not_internal(code, filename, words, tmp_path, capsys, monkeypatch):
    """A file a library opened itself (GDAL, OpenCV): the command line's last net still names it."""

    def run(cfg):
        raise OSError(code, os.strerror(code), *([filename] if filename else []))

    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(run))
    (tmp_path / "imgs").mkdir()
    assert run_module("demo", ["--set", f"images={tmp_path / 'imgs'}", "--set", f"output_dir={tmp_path / 'o'}"]) == 2
    err = capsys.readouterr().err
    assert "internal error" not in err and "fix:" in err and all(w in err for w in words), err


# --------------------------------------------------------------------------------------------------
# non-finite numbers


@pytest.mark.parametrize("key", [k for k in all_keys() if holds(k, float)], ids=str)
@pytest.mark.parametrize("value", ["inf", ".inf", "-inf", "nan"])
def test_every_number_key_refuses_a_non_finite_value(key, value):
    with pytest.raises(ConfigError) as info:
        load_config(config_classes()[key.step], None, [f"{key.name}={value}"], strict=False)
    assert key.name in str(info.value) and "finite" in str(info.value), str(info.value)
