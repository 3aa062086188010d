"""Whole-process runs for the comparisons: each side as a user starts it (``python -m matchplant.cli ...``,
the peer's command or a script calling it), so imports, reading and writing count as they do for a user.

The child inherits the benchmark's pinned core and single-thread environment (bench/runner.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def run_process(argv: list[str], cwd: Path | None = None) -> None:
    """Run ``argv`` to the end; a failure stops the benchmark with the command's last output."""
    proc = subprocess.run(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, argv))} failed ({proc.returncode}):\n"
                         f"{proc.stdout.decode(errors='replace')[-3000:]}")


def matchplant_command(step: str, config: Path) -> list[str]:
    """The command line a user runs for ``step`` with ``config``."""
    return [sys.executable, "-m", "matchplant.cli", step, "--config", str(config)]
