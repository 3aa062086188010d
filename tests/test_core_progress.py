"""Progress (matchplant.core.runtime.progress): log lines at an interval when not on a terminal (issue 17)."""

from __future__ import annotations

import logging
import sys

from log_records import log_records, messages

from matchplant.core.runtime import progress as progress_module
from matchplant.core.runtime.progress import progress_line


def _progress_records(monkeypatch, interval: str, body):
    monkeypatch.delenv("MATCHPLANT_QUIET", raising=False)
    monkeypatch.delenv("MATCHPLANT_PROGRESS", raising=False)
    monkeypatch.setenv("MATCHPLANT_PROGRESS_INTERVAL", interval)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    with log_records("matchplant.progress", logging.INFO) as records:
        body(progress_module.progress)
    return messages(records)


def test_progress_logs_lines_when_not_on_a_terminal(monkeypatch):
    clock = {"t": 1000.0}
    monkeypatch.setattr("tqdm.std.time", lambda: clock["t"])  # tqdm's clock: one simulated second per image

    def body(progress):
        for _ in progress(range(40), desc="detecting", unit="image"):
            clock["t"] += 1.0  # one image per second: a line at about every 10 images

    lines = _progress_records(monkeypatch, "10", body)
    assert 3 <= len(lines) <= 5, lines
    assert lines[0].startswith("detecting: 1") and "/40 image" in lines[0]
    # rate 1.00 image/s and the ETA from it: after n images, 40 - n seconds left
    n = int(lines[1].split(":")[1].split("/")[0])
    assert "1.00 image/s" in lines[1] and f"ETA 0:{40 - n:02d}" in lines[1], lines[1]
    assert lines[-1].startswith("detecting: 40/40 image 100%")


def test_progress_postfix_updates_do_not_add_lines(monkeypatch):
    """Training sets the loss as a postfix on every batch: still one line per interval, not one per batch."""
    clock = {"t": 1000.0}
    monkeypatch.setattr("tqdm.std.time", lambda: clock["t"])

    def body(progress):
        bar = progress(range(60), desc="epoch 1/2", unit="batch")
        for k in bar:
            clock["t"] += 2.0  # a batch every 2 s
            bar.set_postfix(loss=1.0 / (k + 1))

    lines = _progress_records(monkeypatch, "10", body)
    assert 10 <= len(lines) <= 14, lines  # 120 s at one line per 10 s (and the last)


def test_progress_is_silent_for_short_loops_and_when_quiet(monkeypatch):
    def body(progress):
        assert list(progress([1, 2, 3], desc="quick")) == [1, 2, 3]
        bar = progress(None, desc="tiles", total=5)
        bar.update(5)
        bar.close()

    assert _progress_records(monkeypatch, "10", body) == []
    monkeypatch.setenv("MATCHPLANT_QUIET", "1")
    assert list(progress_module.progress([1, 2])) == [1, 2]


def test_progress_line_format():
    assert (
        progress_line("tiles", 30, 120, 60.0, "tile") == "tiles: 30/120 tile 25% (1:00 elapsed, 2.0 s/tile, ETA 3:00)"
    )
    assert progress_line("x", 5, None, 2.0) == "x: 5 it (0:02 elapsed, 2.50 it/s)"
