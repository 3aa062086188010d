"""Logging (matchplant.core.runtime.log): each run's log file holds its config, the versions and every
message; --quiet keeps info off the console, not out of the file."""

from __future__ import annotations

from demo_step import demo_spec, write

import matchplant.cli as cli
from matchplant.cli import run_module
from matchplant.core.runtime.log import get_logger


def test_cli_runs_logs_config_and_versions(tmp_path, capsys, monkeypatch):
    seen = {}

    def run(cfg):
        seen["cfg"] = cfg
        get_logger("demo").info("working")

    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\n")
    assert run_module("demo", [str(p), "--set", "tile_size=256", "--set", f"output_dir={tmp_path / 'o'}"]) == 0
    assert seen["cfg"].tile_size == 256
    logs = list((tmp_path / "o" / "logs").glob("demo_*.log"))
    assert len(logs) == 1
    text = logs[0].read_text()
    assert "tile_size: 256" in text and "numpy" in text and "working" in text


def test_quiet_keeps_info_off_the_console(tmp_path, capsys, monkeypatch):
    def run(cfg):
        get_logger("demo").info("chatter")
        get_logger("demo").warning("important")

    monkeypatch.setattr(cli, "resolve_module", lambda name: demo_spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, f"images: imgs\noutput_dir: {tmp_path / 'o'}\n")
    assert run_module("demo", [str(p), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "important" in err and "chatter" not in err
    assert "chatter" in next((tmp_path / "o" / "logs").glob("*.log")).read_text()  # the log file has it all
