"""The command line (matchplant.cli): one message without a traceback for a user's error, a short one for an
internal error, --write-config, --help, a GUI without a display."""

from __future__ import annotations

import subprocess
import sys

import pytest
from demo_step import demo_spec, write

import matchplant.cli as cli
from matchplant.cli import run_module


def test_cli_error_is_one_message_without_traceback(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(lambda cfg: None))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\ntile_sise: 1\n")
    assert run_module("demo", ["--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unknown config key 'tile_sise'") and "Traceback" not in err


def test_cli_internal_error_is_short_and_debug_shows_traceback(tmp_path, capsys, monkeypatch):
    def run(cfg):
        raise RuntimeError("boom")

    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, f"images: imgs\noutput_dir: {tmp_path / 'o'}\n")
    assert run_module("demo", [str(p)]) == 1
    assert "internal error: RuntimeError: boom" in capsys.readouterr().err
    with pytest.raises(RuntimeError):
        run_module("demo", [str(p), "--debug"])


def test_cli_write_config_and_unknown_module(tmp_path, capsys, monkeypatch):
    assert run_module("no_such_module", []) == 2
    assert "unknown module" in capsys.readouterr().err
    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(lambda cfg: None))
    assert run_module("demo", ["--write-config", str(tmp_path / "t.yaml")]) == 0
    assert "tile_size: 1024" in (tmp_path / "t.yaml").read_text()


def test_console_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "matchplant.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "project_boxes" in out.stdout


def test_gui_without_display_exits_2_with_the_headless_command(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("a display is always there on macOS and Windows")
    assert run_module("min_img_finder", ["--gui"]) == 2
    err = capsys.readouterr().err
    assert "needs a window" in err and "matchplant min_img_finder" in err and "without --gui" in err


def test_one_vocabulary_output_flag_and_help_examples():
    """Every step that writes an output folder takes --output (and the older --out of modules 0, 1 and 8) for
    the same key, and its --help example names one of its own keys."""
    import dataclasses

    from matchplant.steps import STEPS, resolve_step

    for name in STEPS:
        spec = resolve_step(name)
        keys = {f.name for f in dataclasses.fields(spec.config)}
        parser = cli.build_parser(spec)
        if spec.output_key in keys:
            for flag in ("--output", "--out"):
                args = parser.parse_args([flag, "somewhere"])
                assert getattr(args, f"flag__{spec.output_key}") == "somewhere", (name, flag)
        example = cli.help_example(spec)
        assert example == "KEY=VALUE" or example.split("=")[0] in keys, (name, example)
        assert example in parser.format_help().replace("\n", " ").replace("  ", " ") or len(example) > 30


def test_key_alias_reads_the_shared_name_with_a_note(tmp_path, caplog):
    """Module 8 calls its ODM folder 'project'; 'project_dir', its name in modules 2 and 3, is read as the
    same key (from YAML and --set), with a note; giving both is an error naming both."""
    from matchplant.core.runtime.config import load_config
    from matchplant.core.runtime.errors import ConfigError
    from matchplant.plant_projection.config import PlantProjectionConfig

    (tmp_path / "odm").mkdir()
    p = write(tmp_path, "project_dir: odm\n")
    with caplog.at_level("INFO", logger="matchplant"):
        cfg = load_config(PlantProjectionConfig, p, check_paths=False, strict=False)
    assert cfg.project == tmp_path / "odm"
    assert "read as 'project'" in caplog.text
    cfg = load_config(PlantProjectionConfig, None, [f"project_dir={tmp_path / 'odm'}"], check_paths=False, strict=False)
    assert cfg.project == tmp_path / "odm"
    with pytest.raises(ConfigError, match="'project_dir' and 'project'"):
        load_config(
            PlantProjectionConfig, write(tmp_path, "project_dir: odm\nproject: odm\n"), check_paths=False, strict=False
        )
