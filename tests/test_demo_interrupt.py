"""Ctrl-C anywhere in the demo: one line, exit 130, no traceback (issue 29, point 3), while the libraries load
and while a step runs; and ``make demo`` adds no line of its own."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _terminal_sigint() -> None:
    """In the child, before exec: Ctrl-C's default disposition, as a terminal gives it. A disposition 'ignore'
    left in the test process by an earlier test is inherited through exec, and then the Ctrl-C these tests send
    is ignored (make exits 0, the demo runs on): seen in two full-suite runs, never alone."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(out: Path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg", MATCHPLANT_QUIET="0")
    return subprocess.Popen(
        [sys.executable, "-m", "matchplant.demo", "--preset", "tiny", "--out", str(out), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        cwd=REPO,
        start_new_session=True,
        preexec_fn=_terminal_sigint,
    )


def _interrupt_when(proc: subprocess.Popen, seen, timeout: float = 240) -> tuple[int, list[str]]:
    """Send SIGINT to the process group (as a terminal's Ctrl-C does) once ``seen(lines)`` holds."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    t0 = time.time()
    while not seen(lines) and proc.poll() is None and time.time() - t0 < timeout:
        time.sleep(0.05)
    assert proc.poll() is None, "".join(lines)
    before = len(lines)
    os.killpg(proc.pid, signal.SIGINT)
    rc = proc.wait(timeout=120)
    reader.join(timeout=10)
    return rc, [ln.rstrip("\n") for ln in lines[before:] if ln.strip()]


def _one_line(rc: int, after: list[str]) -> None:
    assert rc == 130, after
    assert not any("Traceback" in ln or "KeyboardInterrupt" in ln for ln in after), after
    assert after[-1].startswith("interrupted (Ctrl-C)"), after
    assert len([ln for ln in after if ln.startswith("interrupted")]) == 1


@pytest.mark.slow
def test_ctrl_c_while_starting_gives_one_line_and_130(tmp_path):
    rc, after = _interrupt_when(_start(tmp_path / "demo"), lambda lines: True)  # at once: during the imports
    if rc == 130:
        _one_line(rc, after)
    assert not (tmp_path / "demo").exists() or rc == 130


@pytest.mark.slow
def test_ctrl_c_during_a_step_gives_one_line_and_130(tmp_path):
    rc, after = _interrupt_when(
        _start(tmp_path / "demo"), lambda lines: any("rendering images" in ln or "running" in ln for ln in lines)
    )
    _one_line(rc, after)
    # ours is the only line the interrupt causes: what else is read after the signal is the step's ordinary output
    # written just before it arrived (progress, a step's info line such as "GNSS log: 9 events"), never an error,
    # a warning or a second message
    others = [ln for ln in after[:-1] if not ln.startswith(("rendering", "generating", "["))]
    assert not [ln for ln in others if ln.lower().startswith(("error", "warning")) or "interrupt" in ln.lower()], after


def _make_demo(tmp_path: Path, preexec) -> subprocess.Popen:
    """The Makefile's demo recipe, run by make with a stand-in for the venv's python."""
    bin_dir = tmp_path / "venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "python").write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    (bin_dir / "python").chmod(0o755)
    (tmp_path / "venv" / ".installed").touch()  # newer than the requirements: make installs nothing
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen(
        [
            "make",
            "-s",
            "-C",
            str(REPO),
            "demo",
            f"VENV={tmp_path / 'venv'}",
            f"DEMO_ARGS=--preset tiny --out {tmp_path / 'demo'}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
        preexec_fn=preexec,
    )


def _step_running(lines: list[str]) -> bool:
    return any("rendering images" in ln or "running" in ln for ln in lines)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_make_demo_adds_no_line_of_its_own(tmp_path):
    rc, after = _interrupt_when(_make_demo(tmp_path, _terminal_sigint), _step_running)
    assert rc in (-signal.SIGINT, 130), after  # make ends by the signal: the shell reports 130
    assert not any(ln.startswith("make") for ln in after), after
    assert after[-1].startswith("interrupted (Ctrl-C)") and not any("Traceback" in ln for ln in after), after


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None or not Path("/proc/self/status").is_file(), reason="no make/proc")
def test_make_demo_started_with_sigint_ignored_does_not_exit_0(tmp_path):
    """`make demo &` from a script: make (and the shell) ignore SIGINT, the demo does not (it re-enables it). make
    cannot end by the signal, so the demo's 130 is passed on: make exits 2 after its line naming the 130."""
    rc, after = _interrupt_when(
        _make_demo(tmp_path, lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)), _step_running
    )
    assert rc == 2, after
    assert any(ln.startswith("interrupted (Ctrl-C)") for ln in after), after
    assert "Error 130" in after[-1] and not any("Traceback" in ln for ln in after), after


def _training_summary(out: Path) -> dict:
    import json

    return json.loads((out / "6_train" / "training_summary.json").read_text())


@pytest.mark.slow
def test_ctrl_c_during_training_then_the_demo_again_continues_the_training(tmp_path):
    """Issue 40: Ctrl-C in [6_train] keeps a mid-epoch checkpoint and says so in its one line; running the demo
    again continues that training from the interrupted iteration instead of starting at iteration 1."""
    out = tmp_path / "demo"
    # six epochs (about 10 s each on an idle machine): the tiny demo's two can end before a progress line shows.
    # Interrupted once training's first line is out (a progress line, or the end of epoch 1): iterations done
    epochs = ("--epochs", "6")
    rc, after = _interrupt_when(
        _start(out, *epochs), lambda lines: any(ln.startswith("epoch 1/") for ln in lines), timeout=600
    )
    _one_line(rc, after)
    assert [ln for ln in after if not ln.startswith(("epoch ", "["))] == [after[-1]], after
    first = _training_summary(out)
    assert first["status"] == "interrupted", first
    assert "training's checkpoint (interrupted (Ctrl-C) after" in after[-1], after
    done = int(first["message"].split(" after ")[1].split()[0])
    assert done >= 1
    # the re-run: interrupt it again once training has resumed (one of its own batches done)
    before: list[str] = []

    def resumed(lines: list[str]) -> bool:
        before[:] = lines
        at = next((i for i, ln in enumerate(lines) if "resuming" in ln), None)
        return at is not None and any(ln.startswith("epoch ") for ln in lines[at + 1 :])

    rc, _ = _interrupt_when(_start(out, *epochs), resumed, timeout=600)
    assert rc == 130
    text = "".join(before)
    assert "[6_train] continuing its interrupted run" in text, text
    assert f"after {done} iteration(s)" in text and "replaces them" not in text, text
    second = _training_summary(out)
    assert int(second["message"].split(" after ")[1].split()[0]) > done, (first, second)
