"""Size and time of the synthetic field presets (issue 3): images, plants, boxes, disk, wall and CPU time.

    python bench/bench_simfield.py            # tiny, small and large (large takes many minutes)
    python bench/bench_simfield.py --quick    # tiny and small only
    python bench/bench_simfield.py --quick --noise exact realistic   # each also with noise: realistic
    python bench/bench_simfield.py --presets large --workers 0 --keep /data/large_field

Each preset runs in its own process so that its peak memory is measured alone. Prints a Markdown table
for the README.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import json, resource, sys, time
from matchplant.simfield import generate_field
from matchplant.core.runtime.io import read_json
def cpu():  # this process and its finished worker processes
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + kids.ru_utime + kids.ru_stime
t, c = time.perf_counter(), cpu()
p = generate_field(preset=sys.argv[1], seed=0, out=sys.argv[2], workers=int(sys.argv[3]), noise=sys.argv[4])
wall, cpu = time.perf_counter() - t, cpu() - c
field = read_json(p.field_json)
raw = read_json(p.boxes_raw)
und = read_json(p.boxes_undistorted)
size = sum(f.stat().st_size for f in p.root.rglob('*') if f.is_file())
print(json.dumps({"preset": sys.argv[1], "images": field["flight"]["images"], "plants": field["n_plants"],
                  "width": field["camera"]["opensfm"]["width"], "height": field["camera"]["opensfm"]["height"],
                  "gsd_cm": 100 * field["gsd"], "raw_boxes": len(raw["annotations"]),
                  "undistorted_boxes": len(und["annotations"]), "disk_mb": size / 1e6, "wall_s": wall,
                  "cpu_s": cpu, "workers": int(sys.argv[3]), "noise": sys.argv[4],
                  "peak_mb": max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                                 resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024}))
"""


def run(preset: str, out: Path, workers: int, noise: str = "exact") -> dict:
    """Generate one preset in a child process; its sizes, wall and CPU time and peak memory."""
    env = dict(os.environ, MATCHPLANT_QUIET="1")
    res = subprocess.run(
        [sys.executable, "-c", CHILD, preset, str(out), str(workers), noise], capture_output=True, text=True, env=env
    )
    if res.returncode != 0:
        raise SystemExit(f"{preset} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    """Parse the options, generate each preset and print its size and time."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny and small only")
    ap.add_argument("--presets", nargs="+", default=None, help="presets to run (default: all)")
    ap.add_argument(
        "--workers", type=int, default=1, help="rendering processes (0: one per core); CPU s is summed over them"
    )
    ap.add_argument(
        "--noise",
        nargs="+",
        default=["exact"],
        choices=("exact", "realistic"),
        help="noise models to generate each preset with (realistic: simfield/noise.py)",
    )
    ap.add_argument("--keep", type=Path, default=None, help="write the fields under this folder and keep them")
    args = ap.parse_args()
    presets = args.presets or (["tiny", "small"] if args.quick else ["tiny", "small", "large"])
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench_simfield_"))
    rows = []
    try:
        for preset in presets:
            for noise in args.noise:
                t = time.perf_counter()
                print(f"generating {preset} ({noise}) ...", file=sys.stderr, flush=True)
                rows.append(run(preset, base / f"{preset}_{noise}", args.workers, noise))
                print(f"  done in {time.perf_counter() - t:.1f} s", file=sys.stderr, flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)
    print(f"\nmachine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; python {sys.version.split()[0]}")
    print(
        "| preset | noise | images | size px | GSD cm | plants | boxes raw / undist. | disk MB | workers "
        "| wall s | CPU s | peak MB |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['preset']} | {r['noise']} | {r['images']} | {r['width']}x{r['height']} | {r['gsd_cm']:.2f} "
            f"| {r['plants']} | {r['raw_boxes']} / {r['undistorted_boxes']} | {r['disk_mb']:.0f} | {r['workers']} "
            f"| {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['peak_mb']:.0f} |"
        )


if __name__ == "__main__":
    main()
