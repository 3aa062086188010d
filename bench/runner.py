"""Running the comparisons: one child process per comparison, pinned to one core with one thread.

The parent (``python -m bench``) starts ``python -m bench --child NAME`` with every thread pool set to
one thread in its environment; the child pins itself to one core, builds the data in a temporary folder,
times ours and the peer in turn and writes its result as JSON for the parent, which prints the table
and records everything (machine, versions, each time) in ``bench/results/``.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.gpu_figures import TARGETS, acceptance_line, figures_of
from bench.harness import (
    Comparison,
    across_runs,
    alternate,
    machine_info,
    overhead,
    pin_one_core,
    ratio_text,
    single_thread_env,
    summarise,
    versions,
)

HERE = Path(__file__).parent
RESULTS = HERE / "results"

# name -> (module in bench/, what it compares); each module has comparison(name, work, quick, device)
REGISTRY = {
    "zonal-center": ("bench.bench_spatial_stat_extractor", "module 9, pixel-centre rule vs rasterstats"),
    "zonal-coverage": ("bench.bench_spatial_stat_extractor", "module 9, coverage-weighted vs exactextract"),
    "zonal-coverage-process": (
        "bench.bench_spatial_stat_extractor",
        "module 9's command, coverage-weighted vs a script calling exactextract",
    ),
    "gps-embed": ("bench.bench_gps_embeder", "module 0, GPS into EXIF copies vs exiftool -geotag"),
    "gps-embed-process": ("bench.bench_gps_embeder", "module 0's command vs exiftool -geotag, 1.1 MB JPEGs"),
    "train": ("bench.bench_model_train", "module 6, training loop vs a bare torchvision loop"),
    "detect": ("bench.bench_model_train", "module 7, tiled detection vs the bare model on the same tiles"),
    "tiling": ("bench.bench_img_splitter", "module 5, tiling vs SAHI slice_coco"),
    "box-pairs": ("bench.bench_core_boxes", "module 8, overlapping box pairs vs shapely STRtree"),
    # a whole run with its result, not a comparison (the module has run_row(name, work, quick, device))
    "train-real": (
        "bench.bench_model_train_real",
        (
            "module 6 from random weights on real aerial photos, inspect's "
            "advice, max_minutes 15 (--quick: 2) on one core: estimate vs "
            "actual time, test AP50"
        ),
    ),
}
REGISTRY.update(
    {
        "train-ceiling": (
            "bench.bench_gpu",
            "module 6 at 1024 px on files vs ResNet-50 FPN alone on tensors on the GPU (its ceiling); GPU options",
        ),
        "detect-photos": ("bench.bench_gpu", "module 7 on a folder of 20 MP JPEG photos: photos/s from disk"),
    }
)
# what --device cuda measures, in this order (about 8 minutes on an H200: ../shared/gpu/README.md)
GPU_NAMES = ("train", "detect", "train-ceiling", "detect-photos", "train-real")

PACKAGES = [
    "matchplant",
    "numpy",
    "numba",
    "shapely",
    "rasterio",
    "exactextract",
    "rasterstats",
    "piexif",
    "pillow",
    "torch",
    "torchvision",
    "opencv-python-headless",
    "opencv-python",
    "sahi",
]


def run_child(name: str, quick: bool, device: str, pairs: int, out: Path) -> int:
    """In the child: pin (on a CPU: a GPU run needs its loader's cores), set up, alternate, write the result JSON to
    ``out``."""
    core = pin_one_core() if device == "cpu" else None
    module = importlib.import_module(REGISTRY[name][0])
    if hasattr(module, "run_row"):
        with tempfile.TemporaryDirectory(prefix=f"bench_{name}_") as tmp:
            result = module.run_row(name, Path(tmp), quick, device)
        out.write_text(json.dumps({**result, "pinned_core": core}, indent=1, default=str))
        return 0
    with tempfile.TemporaryDirectory(prefix=f"bench_{name}_") as tmp:
        t0 = time.perf_counter()
        cmp: Comparison = module.comparison(name, Path(tmp), quick, device)
        setup_s = time.perf_counter() - t0
        result = {
            "name": name,
            "what": cmp.what,
            "ours": cmp.ours_label,
            "peer": cmp.peer_label,
            "pinned_core": core,
            "threads": {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")},
            "items": cmp.items,
            "unit": cmp.unit,
            "setup_s": round(setup_s, 2),
            "notes": cmp.notes,
        }
        if cmp.peer is None:
            result["skipped"] = cmp.skip or "peer not available"
        else:

            def show(i, a, b):
                print(
                    f"  pair {i + 1}: {cmp.ours_label} {a:.3f} s, {cmp.peer_label} {b:.3f} s, ratio {b / a:.2f}",
                    flush=True,
                )

            a, b = alternate(cmp.ours, cmp.peer, pairs=pairs, warmup=1, reset=cmp.reset, on_pair=show)
            result["summary"] = summarise(a, b)
            result["overhead"] = overhead(result["summary"])
            if cmp.check is not None:
                result["check"] = cmp.check()
    out.write_text(json.dumps(result, indent=1, default=str))
    return 0


def acceptance(r: dict, device: str) -> list[dict]:
    """A row's acceptance figures on a GPU: its own (whole runs), the speed ratio's (comparisons), or the figures it
    should have given marked not measured when it failed."""
    if device != "cuda":
        return []
    if "acceptance" in r:
        return r["acceptance"]
    if r["name"] == "train" and "summary" in r:  # a comparison: its median speed ratio
        return figures_of("train", [round(r["summary"]["ratio_median"], 3)])
    return figures_of(r["name"]) if r["name"] in TARGETS else []


def describe(r: dict) -> str:
    """One comparison's result as a line: both timings and the speed ratio, its row, or why it was skipped."""
    if "row" in r:
        return f"{r['name']:<15} {r['row']}"
    if "summary" not in r:
        return f"{r['name']:<15} SKIPPED: {r.get('skipped') or r.get('error')}"
    s = r["summary"]
    line = (
        f"{r['name']:<15} {r['ours']} {s['ours_median_s']:.3f} s | {r['peer']} {s['peer_median_s']:.3f} s"
        f" | speed ratio {ratio_text(s)}"
    )
    if r["items"]:
        line += f" | {r['items'] / s['ours_median_s']:.1f} vs {r['items'] / s['peer_median_s']:.1f} {r['unit']}/s"
    if "check" in r:
        line += " | check: " + ", ".join(
            f"{k} {v:.2g}" if isinstance(v, float) else f"{k} {v}" for k, v in r["check"].items()
        )
    return line


def combine(results: list[dict]) -> dict:
    """The runs of one comparison as one result: the first run's record with the summary over all runs."""
    ok = [r for r in results if "summary" in r]
    if not ok:
        return results[0]
    first = dict(ok[0])
    first["summary"] = across_runs([r["summary"] for r in ok])
    first["overhead"] = overhead(first["summary"])
    first["checks"] = [r.get("check") for r in ok]
    return first


def run_all(names: list[str], quick: bool, device: str, pairs: int, save: bool = True, runs: int = 3) -> int:
    """In the parent: each comparison ``runs`` times, each run in its own single-threaded child; print and
    record (a row's spread is over the runs: see ``across_runs``)."""
    env = single_thread_env() if device == "cpu" else dict(os.environ)  # a GPU run uses the machine's cores
    env.setdefault("MATCHPLANT_QUIET", "1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE.parent), env.get("PYTHONPATH")]))
    record = {
        "command": " ".join(["python -m bench", *sys.argv[1:]]),
        "quick": quick,
        "device": device,
        "pairs": pairs,
        "machine": machine_info(),
        "versions": versions(PACKAGES),
        "results": [],
    }
    failed = 0
    for name in names:
        print(f"\n=== {name}: {REGISTRY[name][1]}{' (quick)' if quick else ''}", flush=True)
        results = []
        for run in range(runs):
            if runs > 1:
                print(f"  run {run + 1} of {runs} (load average {os.getloadavg()[0]:.1f})", flush=True)
            r = _run_once(name, quick, device, pairs, env)
            failed += "error" in r
            results.append(r)
            if "summary" not in r:  # a failure, or a row of its own (run_row: a long single run)
                break
        r = combine(results)
        r["load_average"] = os.getloadavg()
        record["results"].append(r)
        print(describe(r), flush=True)
    print("\nsummary (speed ratio = peer time / our time: the median of the runs' medians, and their range)")
    for r in record["results"]:
        print("  " + describe(r))
    figures = [a for r in record["results"] for a in acceptance(r, device)]
    if figures:
        print("\nacceptance (issue 38, on this GPU)")
        for a in figures:
            print("  " + acceptance_line(a))
        record["acceptance"] = figures
    if save:
        RESULTS.mkdir(exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        path = RESULTS / f"bench-{stamp}{'-quick' if quick else ''}.json"
        path.write_text(json.dumps(record, indent=1, default=str))
        print(f"recorded in {path}")
    return 1 if failed else 0


def _run_once(name: str, quick: bool, device: str, pairs: int, env: dict) -> dict:
    """One run of a comparison in a fresh child process."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        cmd = [
            sys.executable,
            "-m",
            "bench",
            "--child",
            name,
            "--device",
            device,
            "--pairs",
            str(pairs),
            "--result",
            str(out),
        ]
        rc = subprocess.call(cmd + (["--quick"] if quick else []), env=env, cwd=HERE.parent)
        if rc == 0 and out.exists():
            return json.loads(out.read_text())
        return {"name": name, "error": f"the benchmark process exited with status {rc}"}
