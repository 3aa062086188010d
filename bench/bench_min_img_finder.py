"""Benchmark of module 3 (min_images): footprints per second and selection time on a large flight.

    python bench/bench_min_img_finder.py            # 1,000-image flight (40 x 25 lawn-mower grid)
    python bench/bench_min_img_finder.py --quick    # 200 images (20 x 10), plus the integer-program optimum

The flight is the hand-built ODM project of tests/test_min_img_finder.py (nadir cameras over a sloped, bumpy
DSM), so the numbers measure module 3 alone, not the synthetic-field renderer.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_min_img_finder import make_project  # noqa: E402

from matchplant.core.runtime.config import load_config  # noqa: E402
from matchplant.min_img_finder.config import MinImgFinderConfig  # noqa: E402
from matchplant.min_img_finder.run import MinImageFinder  # noqa: E402
from matchplant.min_img_finder.setcover import select_milp  # noqa: E402


def main() -> None:
    """Parse the options, time module 3's footprints and selection on a generated flight and print them."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="200 images instead of 1,000")
    ap.add_argument("--milp", action="store_true", help="also solve the integer program (60 s limit)")
    args = ap.parse_args()
    nx, ny = (20, 10) if args.quick else (40, 25)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        project = make_project(Path(tmp) / "flight", nx=nx, ny=ny, spacing=(1.0, 0.8), size=(40, 30))
        print(f"flight: {nx * ny} images, built in {time.perf_counter() - t:.1f} s")
        cfg = load_config(
            MinImgFinderConfig,
            None,
            [f"project_dir={project}", f"output_dir={Path(tmp) / 'out'}", "uncovered_threshold=2"],
        )
        t = time.perf_counter()
        finder = MinImageFinder(cfg)
        load = time.perf_counter() - t
        n = len(finder.footprints)
        print(
            f"footprints: {n} in {finder.footprint_seconds:.2f} s = {n / finder.footprint_seconds:.0f} footprints/s "
            f"(with DSM and orthophoto reading); grid {finder.grid.A.shape[1]} cells; set-up total {load:.2f} s"
        )
        for label, overlap in (("no overlap cap", 100.0), ("max_overlap 30 %", 30.0)):
            cfg.max_overlap = overlap
            t = time.perf_counter()
            sel = finder.select()
            print(
                f"greedy ({label}): {len(sel.indices)} images, "
                f"coverage {100 * finder.exact_coverage(sel.indices):.2f} %, "
                f"selection {sel.seconds:.3f} s (with exact polygon check {time.perf_counter() - t:.3f} s)"
                + (", cap relaxed" if sel.relaxed else "")
            )
        if args.quick or args.milp:
            best = select_milp(finder.grid, 0.98, 1.0, time_limit=60)
            print(
                f"milp (no cap): {len(best.indices)} images, {'optimal' if best.optimal else 'time limit'}, "
                f"{best.seconds:.2f} s"
            )
        t = time.perf_counter()
        finder.evaluate(sel)
        print(f"owned areas + pixel outlines for {len(sel.indices)} images: {time.perf_counter() - t:.2f} s")


if __name__ == "__main__":
    main()
