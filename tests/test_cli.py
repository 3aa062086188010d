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
