"""Whole-process runs for the comparisons: each side as a user starts it (``python -m matchplant.cli ...``,
the peer's command or a script calling it), so imports, reading and writing count as they do for a user.

The child inherits the benchmark's pinned core and single-thread environment (bench/runner.py). With
``BENCH_CLOCK=cpu`` in the environment a run counts the CPU time of the process and its children (user +
system, ``os.wait4``) instead of the wall time: on a shared, busy machine the wall time of a whole process
swings threefold from run to run, its CPU time far less; time spent waiting for the disk is then not counted."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path


def run_process(argv: list[str], cwd: Path | None = None) -> float | None:
    """Run ``argv`` to the end; a failure stops the benchmark with the command's last output. Returns the CPU
    seconds of the process with ``BENCH_CLOCK=cpu`` (the harness then times with them), else None (wall)."""
    with tempfile.TemporaryFile() as out:
        proc = subprocess.Popen(argv, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            out.seek(0)
            raise SystemExit(
                f"{' '.join(map(str, argv))} failed ({proc.returncode}):\n{out.read().decode(errors='replace')[-3000:]}"
            )
    return usage.ru_utime + usage.ru_stime if os.environ.get("BENCH_CLOCK") == "cpu" else None


def matchplant_command(step: str, config: Path) -> list[str]:
    """The command line a user runs for ``step`` with ``config``."""
    return [sys.executable, "-m", "matchplant.cli", step, "--config", str(config)]
