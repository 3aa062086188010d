"""Run every benchmark script in bench/ (or those named), passing the remaining flags (e.g. --quick)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    here = Path(__file__).parent
    names = [a for a in argv if not a.startswith("-")]
    flags = [a for a in argv if a.startswith("-")]
    scripts = sorted(here.glob("bench_*.py"))
    if names:
        scripts = [s for s in scripts if any(n in s.stem for n in names)]
    failed = 0
    for script in scripts:
        print(f"\n=== {script.stem} {' '.join(flags)}", flush=True)
        t0 = time.time()
        rc = subprocess.call([sys.executable, str(script), *flags])
        print(f"=== {script.stem}: exit {rc}, {time.time() - t0:.1f} s", flush=True)
        failed += rc != 0
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
