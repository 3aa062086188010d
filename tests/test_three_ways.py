"""One behaviour for the three ways of every module (issue 40): a numbered folder's script is the command with
the folder's config file, so that config may only name what the command needs the user to give (its required
inputs, chained from the module before) and where outputs go; every other key holds the command's default. Then
``python N_x/x.py`` and ``matchplant x`` on the same inputs run the same settings (module 9's folder config once
preset a DSM and DTM under odm_project/, and its script failed on an orthophoto alone where the command worked).
The GUIs open on the same config classes (tests/test_core_gui_setup.py)."""

from __future__ import annotations

import dataclasses
import re
import runpy
import sys
from pathlib import Path

import pyogrio
import pytest
import yaml

from matchplant import cli
from matchplant.core.runtime.config import load_config, to_dict
from matchplant.steps import STEPS, resolve_step

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = [folder for folder, _ in STEPS.values() if folder]
CONFIG_NAMES = {"6_model_train": "train_config.yaml", "7_model_test": "test_config.yaml"}
# inputs a folder config names although the command has no default for them, and why the script cannot fail on
# them where the command works: the module before writes them with the required input, or the mode needs them
CHAINED = {
    ("6_model_train", "val_json"): "module 5 writes val.json beside train.json (the required input)",
    ("7_model_test", "evaluate.dataset_json"): "module 5's test.json, evaluated by default; detect.images unset",
    ("8_plant_projection", "project"): "required by the default mode 'project'",
    ("8_plant_projection", "predictions"): "required by the default mode 'project'",
}


def _given_by_user(folder: str, key: str, f: dataclasses.Field | None) -> bool:
    """A key the folder config may set: a required input, an output, or a CHAINED input."""
    if f is None:
        return False
    return bool(f.metadata.get("required") or f.metadata.get("path") == "out" or (folder, key) in CHAINED)


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v and all(isinstance(x, str) for x in v) and not k.endswith("map"):
            out.update(_flat(v, f"{prefix}{k}."))
        out[prefix + k] = v
    return out


@pytest.mark.parametrize("folder", FOLDERS)
def test_a_folder_config_holds_the_commands_defaults(folder):
    spec = resolve_step(folder.split("_", 1)[1])
    path = ROOT / folder / CONFIG_NAMES.get(folder, "config.yaml")
    folder_cfg = load_config(spec.config, path, check_paths=False, strict=False)
    given = _flat(to_dict(folder_cfg))
    default = _flat(to_dict(spec.config()))
    written = _flat(yaml.safe_load(path.read_text()) or {})
    required = {k for k in written if _given_by_user(folder, k, _field(spec.config, k))}
    differ = sorted(
        k for k in written if k in default and k not in required and not _parent(k, required) and given[k] != default[k]
    )
    assert not differ, {k: (given[k], default[k]) for k in differ}


def _parent(key: str, keys: set[str]) -> bool:
    """``key`` is a section holding one of ``keys`` (its whole value differs through that key)."""
    return any(k.startswith(key + ".") for k in keys)


def _field(cls: type, dotted: str) -> dataclasses.Field | None:
    head, _, rest = dotted.partition(".")
    for f in dataclasses.fields(cls):
        if f.name == head:
            if not rest:
                return f
            sub = f.default_factory if f.default is dataclasses.MISSING else f.default
            return _field(sub if isinstance(sub, type) else type(sub), rest) if dataclasses.is_dataclass(sub) else None
    return None


@pytest.mark.parametrize("folder", FOLDERS)
def test_the_folder_script_and_the_command_run_the_same_settings(folder, tmp_path, monkeypatch):
    """Both ways write the config they would run (--write-config) with the folder config's required inputs
    given to both: the files are the same."""
    name = folder.split("_", 1)[1]
    spec = resolve_step(name)
    path = ROOT / folder / CONFIG_NAMES.get(folder, "config.yaml")
    written = yaml.safe_load(path.read_text()) or {}
    sets = []
    for key, value in _flat(written).items():
        f = _field(spec.config, key)
        if _given_by_user(folder, key, f) and value is not None:
            sets += ["--set", f"{key}={(path.parent / str(value)).resolve() if f.metadata.get('path') else value}"]
    script = next((ROOT / folder).glob("*.py"))
    monkeypatch.setattr(sys, "argv", [str(script), *sets, "--write-config", str(tmp_path / "script.yaml")])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(script), run_name="__main__")
    assert done.value.code == 0
    assert cli.run_module(name, [*sets, "--write-config", str(tmp_path / "command.yaml")]) == 0
    script_cfg = yaml.safe_load((tmp_path / "script.yaml").read_text())
    command_cfg = yaml.safe_load((tmp_path / "command.yaml").read_text())
    assert script_cfg == command_cfg


def test_a_module_without_a_window_says_so_for_gui(capsys):
    assert cli.run_module("plant_projection", ["--gui"]) == 2
    err = capsys.readouterr().err
    assert "plant_projection has no window" in err and "fix:" in err and "without --gui" in err, err


def test_every_gui_example_names_a_module_with_a_window():
    """The README examples with --gui are not run (they open windows): each must at least name a module that has
    one (module 8's example once gave an argparse error)."""
    docs = [ROOT / "README.md", *sorted(ROOT.glob("[0-9]_*/README.md")), *sorted(ROOT.glob("docs/**/*.md"))]
    named = re.compile(r"(?:python [0-9]_\w+/(\w+)\.py|matchplant (\w+))[^`\n]*--gui")
    found = [(doc.name, m.group(1) or m.group(2)) for doc in docs for m in named.finditer(doc.read_text())]
    assert found
    assert [(doc, name) for doc, name in found if resolve_step(name).gui is None] == []


def _outputs(folder: Path) -> dict[str, object]:
    """Every output file's content: GeoPackages as their tables (the file stamps the time it was written), the
    run report without its timings and memory, the log's name only (it is the run's console, times included)."""
    out: dict[str, object] = {}
    for p in sorted(folder.rglob("*")):
        if not p.is_file() or p.parent.name == "logs":
            continue
        if p.suffix == ".gpkg":
            data = pyogrio.read_dataframe(p).to_wkt().to_csv()
        else:
            data = p.read_bytes()
        if p.suffix == ".json":
            data = re.sub(rb'"(\w*(seconds|_s|time|memory|peak)\w*)": [0-9.e+-]+', rb'"\1": 0', data)
        out[str(p.relative_to(folder))] = data
    return out


def test_module_9_folder_script_and_command_write_the_same_files_from_an_orthophoto_alone(
    tiny_field, tmp_path, monkeypatch
):
    """The case the issue saw: an orthophoto without a DSM or DTM, through module 9's folder script (its config
    file) and through the command: both run, and their output files are the same (run timings aside)."""
    inputs = ["--set", f"polygons={tiny_field.map_boxes}", "--set", f"rasters.rgb={tiny_field.orthophoto}"]
    script = ROOT / "9_spatial_stat_extractor" / "spatial_stat_extractor.py"
    monkeypatch.setattr(sys, "argv", [str(script), *inputs, "--set", f"output_dir={tmp_path / 'script'}"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(script), run_name="__main__")
    assert done.value.code == 0
    assert cli.run_module("spatial_stat_extractor", [*inputs, "--set", f"output_dir={tmp_path / 'command'}"]) == 0
    script_files, command_files = _outputs(tmp_path / "script"), _outputs(tmp_path / "command")
    assert any(name.endswith(".csv") for name in script_files), sorted(script_files)
    assert sorted(script_files) == sorted(command_files)
    differ = [name for name in script_files if script_files[name] != command_files[name]]
    assert differ == []
