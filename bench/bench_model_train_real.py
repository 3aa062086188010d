"""CPU training benchmark on real aerial data (issue 28): train module 6 from random weights with the advice of
``matchplant inspect`` and otherwise default settings for N minutes of one core; report the estimate printed
before training against the actual time, where the run stopped against its budget, and the test AP50.

Data (:mod:`bench.deepforest_photos`): 47 photos of about 400 px with 947 tree-crown boxes of 15-75 px, cut from the
annotated NEON orthophotos that DeepForest's PyPI package ships (MIT). Get the wheel once with the ordinary
client (nothing is downloaded at run time)::

    pip download deepforest==2.1.0 --no-deps -d ~/deepforest-wheel

Settings: ``model.min_size``/``max_size`` and ``model.aspect_ratios`` as ``matchplant inspect`` advises for the
training boxes, ``model.anchor_sizes: auto``, ``model.architecture: auto``, ``model.pretrained: none`` (no
download), ``max_minutes`` as given, ``device: cpu`` (``--device``); everything else the default (``num_workers``
among them: 0 on one core, where it is sized to the cores). ``--set KEY=VALUE`` adds settings (to explore; the
issue's run uses none). ``python -m bench`` runs it as the row ``train-real`` (15 minutes; ``--quick``: 2).

    taskset -c 1 nice -n -5 python -m bench.bench_model_train_real --data ~/deepforest-wheel --minutes 15
    python -m bench.bench_model_train_real --data ~/deepforest-wheel --minutes 2      # a short check
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench import deepforest_photos
from bench.gpu_figures import figures_of
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.log import setup_console
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.data import CocoDetection
from matchplant.detection.evaluate import coco_evaluate, predict_dataset
from matchplant.detection.objects import recommend, size_stats
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

GPU_KIT_DATA = Path(__file__).resolve().parents[1] / ".gpu" / "deepforest"  # bench/gpu_kit.sh puts the photos there
DEFAULT_DATA = (
    Path(os.environ.get("MATCHPLANT_DEEPFOREST", ""))
    if os.environ.get("MATCHPLANT_DEEPFOREST")
    else (GPU_KIT_DATA if GPU_KIT_DATA.is_dir() else Path.home() / "deepforest-wheel")
)
GPU_MINUTES = 3.0  # issue 38: the GPU's budget (its AP50 against the CPU's 15 minutes)


def find_wheel(folder: Path) -> Path:
    """The DeepForest wheel in ``folder`` (or ``folder`` itself: a wheel, or a folder of its data files)."""
    if folder.is_file() or (folder / "deepforest").is_dir() or (folder / "OSBS_029.xml").is_file():
        return folder
    wheels = sorted(folder.glob("deepforest-*.whl"))
    if not wheels:
        raise SystemExit(
            f"no deepforest-*.whl in {folder}: get it with "
            f"'pip download deepforest==2.1.0 --no-deps -d {folder}' (or give --data)"
        )
    return wheels[-1]


def inspect_settings(train_json: Path) -> tuple[dict, list[str]]:
    """``matchplant inspect``'s advice for the training boxes, and the settings a user copies from it."""
    data = json.loads(train_json.read_text())
    wh = np.array([a["bbox"][2:] for a in data["annotations"]], float)
    advice = recommend(size_stats(wh[:, 0], wh[:, 1]), [(im["width"], im["height"]) for im in data["images"]])
    return advice, [
        f"model.min_size={advice['min_size']}",
        f"model.max_size={advice['max_size']}",
        "model.anchor_sizes=auto",
        f"model.aspect_ratios={json.dumps(advice['aspect_ratios'])}",
    ]


def test_ap(checkpoint: Path, test_json: Path) -> dict:
    """COCO AP figures of a checkpoint on the test photos (score threshold 0.05)."""
    model, _ = load_detector(checkpoint)
    model.roi_heads.score_thresh = 0.05
    test = CocoDetection(test_json)
    stats, _ = coco_evaluate(test.data, predict_dataset(model, test, torch.device("cpu")))
    return stats


def run(wheel: Path, minutes: float, work: Path, device: str = "cpu", extra: list[str] = ()) -> dict:
    """Build the photos, train as the issue says, score the test photos; the result as a dict."""
    shutil.rmtree(work / "run", ignore_errors=True)
    return {
        **run_on(*deepforest_photos.build(wheel, work), minutes, work, device, extra),
        "data": deepforest_photos.LICENCE,
    }


def run_on(
    train_json: Path,
    val_json: Path,
    test_json: Path,
    minutes: float,
    work: Path,
    device: str = "cpu",
    extra: list[str] = (),
) -> dict:
    """Train on these splits as the issue says (``inspect``'s advice, defaults, ``minutes`` of budget), score the
    test split; the result as a dict."""
    advice, advised = inspect_settings(train_json)
    settings = [
        f"train_json={train_json}",
        f"val_json={val_json}",
        f"output_dir={work / 'run'}",
        "model.architecture=auto",
        "model.pretrained=none",
        *advised,
        f"max_minutes={minutes:g}",
        f"device={device}",
        *extra,
    ]
    cfg = load_config(ModelTrainConfig, None, settings)
    load = os.getloadavg()
    t0, cpu0 = time.perf_counter(), time.process_time()
    summary = train(cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    stats = test_ap(work / "run" / "checkpoints" / "best.pt", test_json)
    counts = {
        p.stem: [len(d["images"]), len(d["annotations"])]
        for p, d in ((p, json.loads(p.read_text())) for p in (train_json, val_json, test_json))
    }
    estimate = summary["estimate"]["planned_s"]
    kept = sorted((work / "run" / "checkpoints").glob("*.pt"))  # issue 39: a budget run once kept 741 MB of them
    return {
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_before": [round(v, 2) for v in load],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "photos_boxes": counts,
        "settings": settings,
        "inspect_advice": {k: advice[k] for k in ("min_size", "max_size", "aspect_ratios")},
        "architecture": summary.get("architecture"),
        "status": summary["status"],
        "message": summary["message"],
        "estimate_s": estimate,
        "wall_s": round(wall, 1),
        "estimate_error": round(estimate / wall - 1, 3),
        "over_budget_s": round(wall - 60 * minutes, 1) if minutes else None,
        "planned_iterations": summary["iterations_planned"],
        "iterations_done": summary["iterations_done"],
        "cpu_s": round(cpu, 1),
        "cpu_s_per_iteration": round(cpu / max(summary["iterations_done"], 1), 3),
        "best_val": summary["best"],
        "test_AP50": round(stats["AP50"], 4),
        "test_AP": round(stats["AP"], 4),
        "checkpoints": [p.name for p in kept],
        "checkpoints_MB": round(sum(p.stat().st_size for p in kept) / 1e6, 1),
    }


def run_row(name: str, work: Path, quick: bool, device: str) -> dict:
    """``python -m bench``'s row (bench/runner.py): 15 minutes (--quick: 2) on its pinned core; on a GPU 3 minutes,
    with the acceptance figures of issue 38."""
    minutes = GPU_MINUTES if device == "cuda" else 2.0 if quick else 15.0
    command = f"python -m bench.bench_model_train_real --minutes {minutes:g} --device {device}"
    try:
        wheel = find_wheel(DEFAULT_DATA)
    except SystemExit as exc:
        return {"name": name, "skipped": str(exc), "command": command}
    r = run(wheel, minutes, work, device)
    row = (
        f"test AP50 {100 * r['test_AP50']:.1f} % after {r['iterations_done']} iterations of "
        f"{r['architecture']['chosen']} in {r['wall_s'] / 60:.1f} min (max_minutes {minutes:g}); estimate "
        f"{r['estimate_s']:.0f} s vs {r['wall_s']:.0f} s ({100 * r['estimate_error']:+.0f} %) | load "
        f"{r['load_before'][0]:.1f} | {command}"
    )
    out = {"name": name, "row": row, "command": command, "result": r}
    if device == "cuda":
        out["acceptance"] = figures_of(name, [r["test_AP50"], abs(r["estimate_error"])])
    return out


def main() -> None:
    """Parse the options, train on the DeepForest photos for the time asked and print the result."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=15.0, help="max_minutes of the training run (0 = none)")
    ap.add_argument(
        "--data",
        type=Path,
        default=DEFAULT_DATA,
        help="folder holding deepforest-*.whl (or the wheel, or a folder of its data files)",
    )
    ap.add_argument("--device", default="cpu", help="cpu (the issue's run) or cuda")
    ap.add_argument("--out", type=Path, default=None, help="keep the run here (default: a temporary folder)")
    ap.add_argument(
        "--set",
        dest="extra",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an extra module 6 setting (exploration; the issue's run has none)",
    )
    args = ap.parse_args()
    setup_console()
    work = args.out or Path(tempfile.mkdtemp(prefix="bench_train_real_"))
    result = run(find_wheel(args.data), args.minutes, work, args.device, args.extra)
    print(
        json.dumps(
            {"command": " ".join(["python", "-m", "bench.bench_model_train_real", *sys.argv[1:]]), **result},
            indent=1,
            default=str,
        )
    )


if __name__ == "__main__":
    main()
