"""CPU training benchmark on real UAV/airborne data (issue 28.6): train module 6 from random weights with the
advice of ``matchplant inspect`` and otherwise default settings for N minutes of one core, report the test AP50.

Data: DeepForest's sample data (github weecology/DeepForest ``src/deepforest/data``, MIT licence, in
``../shared/data/deepforest-samples`` or ``--data``): NEON airborne RGB orthophoto tiles at 10 cm with
hand-drawn tree-crown boxes. It is the only real box-annotated aerial imagery among the project's sample data
(trees, not crops: small round crowns on an orthophoto are the closest thing to plants seen from a UAV).
OSBS_029 (400 x 400 px, 61 crowns) is cut into four 200 px quadrants (a box goes to the quadrant holding its
centre, clipped to it); quadrant 4 is the test set, quadrant 3 the validation set, quadrants 1-2 plus the
other sample tiles (SJER, BLAN and the two COCO-sample tiles, where their boxes exist) the training set.

Settings: ``model.min_size``/``max_size`` and ``anchor_sizes: auto`` as inspect advises for these boxes (the
tiles are small already: no tiling), ``model.architecture: auto``, ``model.pretrained: none`` (no download),
``max_minutes`` as given, ``threads: 1`` pinned to one core; everything else the default.

    python bench/bench_model_train_real.py --minutes 15      # the issue's run (one core, 15 min)
    python bench/bench_model_train_real.py --minutes 2       # a short check
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")  # NEON GeoTIFF tags OpenCV does not know: noise, not errors

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.core.formats.images import read_rgb8
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.log import setup_console
from matchplant.detection.data import CocoDetection
from matchplant.detection.evaluate import coco_evaluate, predict_dataset
from matchplant.detection.model import load_detector
from matchplant.detection.objects import recommend, size_stats
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

ROOT = Path(__file__).resolve().parents[1]
# ../shared/data beside the clone (a worktree may sit one level deeper)
DEFAULT_DATA = next((p / "shared" / "data" / "deepforest-samples" for p in ROOT.parents
                     if (p / "shared" / "data" / "deepforest-samples").is_dir()),
                    ROOT.parent / "shared" / "data" / "deepforest-samples")


def read_boxes(csv_path: Path) -> dict[str, list[list[float]]]:
    """DeepForest CSV (image_path, xmin, ymin, xmax, ymax, label) -> boxes per image file."""
    out: dict[str, list[list[float]]] = {}
    with open(csv_path, newline="") as fh:
        for row in csv.DictReader(fh):
            out.setdefault(row["image_path"], []).append([float(row[k]) for k in ("xmin", "ymin", "xmax", "ymax")])
    return out


def write_split(folder: Path, name: str, items: list[tuple[np.ndarray, list[list[float]]]]) -> Path:
    """A COCO split of (image, xyxy boxes) in module 5's layout (``name.json`` beside ``name/images``)."""
    import cv2

    images = folder / name / "images"
    images.mkdir(parents=True, exist_ok=True)
    data = new_dataset(["tree"])
    for i, (img, boxes) in enumerate(items, 1):
        file_name = f"{name}_{i:02d}.png"
        cv2.imwrite(str(images / file_name), img[:, :, ::-1])
        data["images"].append({"id": i, "file_name": file_name, "width": img.shape[1], "height": img.shape[0]})
        for b in boxes:
            data["annotations"].append(make_annotation(len(data["annotations"]) + 1, i,
                                                       [b[0], b[1], b[2] - b[0], b[3] - b[1]]))
    return write_dataset(folder / f"{name}.json", data)


def quadrants(img: np.ndarray, boxes: list[list[float]]) -> list[tuple[np.ndarray, list[list[float]]]]:
    h, w = img.shape[:2]
    out = []
    for y0, x0 in ((0, 0), (0, w // 2), (h // 2, 0), (h // 2, w // 2)):
        y1, x1 = y0 + h // 2, x0 + w // 2
        kept = []
        for b in boxes:
            cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
            if x0 <= cx < x1 and y0 <= cy < y1:
                kept.append([max(b[0], x0) - x0, max(b[1], y0) - y0, min(b[2], x1) - x0, min(b[3], y1) - y0])
        out.append((img[y0:y1, x0:x1], kept))
    return out


def build_dataset(data: Path, work: Path) -> tuple[Path, Path, Path]:
    osbs = read_boxes(data / "OSBS_029.csv")["OSBS_029.tif"]
    q = quadrants(read_rgb8(data / "OSBS_029.tif"), osbs)
    train_items = [q[0], q[1]]
    for image, table in (("2018_SJER_3_252000_4107000_image_477.tif", "2018_SJER_3_252000_4107000_image_477.csv"),
                         ("2019_BLAN_3_751000_4330000_image_crop.jpg", "2019_BLAN_3_751000_4330000_image_crop_bbox.csv")):
        if (data / image).is_file() and (data / table).is_file():
            boxes = next(iter(read_boxes(data / table).values()))
            train_items.append((read_rgb8(data / image), boxes))
    coco = data / "coco_sample_file.json"
    if coco.is_file():
        sample = json.loads(coco.read_text())
        for im in sample["images"]:
            if (data / im["file_name"]).is_file():
                boxes = [[a["bbox"][0], a["bbox"][1], a["bbox"][0] + a["bbox"][2], a["bbox"][1] + a["bbox"][3]]
                         for a in sample["annotations"] if a["image_id"] == im["id"]]
                train_items.append((read_rgb8(data / im["file_name"]), boxes))
    return (write_split(work, "train", train_items), write_split(work, "val", [q[2]]),
            write_split(work, "test", [q[3]]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=15.0, help="max_minutes of the training run")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="DeepForest's sample data folder")
    ap.add_argument("--out", type=Path, default=None, help="keep the run here (default: a temporary folder)")
    ap.add_argument("--no-pin", action="store_true", help="do not pin to one core")
    args = ap.parse_args()
    if not (args.data / "OSBS_029.csv").is_file():
        raise SystemExit(f"DeepForest's sample data not found in {args.data} (give --data)")
    if not args.no_pin and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
    setup_console()
    work = args.out or Path(tempfile.mkdtemp())
    shutil.rmtree(work / "run", ignore_errors=True)
    train_json, val_json, test_json = build_dataset(args.data, work)
    tdata = json.loads(train_json.read_text())
    wh = np.array([a["bbox"][2:] for a in tdata["annotations"]], float)
    advice = recommend(size_stats(wh[:, 0], wh[:, 1]), [(im["width"], im["height"]) for im in tdata["images"]])
    settings = [f"train_json={train_json}", f"val_json={val_json}", f"output_dir={work / 'run'}",
                "model.architecture=auto", "model.pretrained=none", f"model.min_size={advice['min_size']}",
                f"model.max_size={advice['max_size']}", "model.anchor_sizes=auto",
                f"model.aspect_ratios={json.dumps(advice['aspect_ratios'])}", f"max_minutes={args.minutes:g}",
                "threads=1", "num_workers=0", "device=cpu"]
    cfg = load_config(ModelTrainConfig, None, settings)
    t0 = time.perf_counter()
    summary = train(cfg)
    wall = time.perf_counter() - t0
    model, _ = load_detector(work / "run" / "checkpoints" / "best.pt")
    model.roi_heads.score_thresh = 0.05
    test = CocoDetection(test_json)
    import torch

    stats, _ = coco_evaluate(test.data, predict_dataset(model, test, torch.device("cpu")))
    command = "python bench/bench_model_train_real.py " + " ".join(
        f"--minutes {args.minutes:g}".split() + (["--no-pin"] if args.no_pin else []))
    print(json.dumps({
        "command": command, "data": str(args.data), "licence": "MIT (DeepForest)",
        "train": {"images": len(tdata["images"]), "boxes": len(tdata["annotations"])},
        "test": {"images": len(test.images), "boxes": len(test.data["annotations"])},
        "inspect_advice": {k: advice[k] for k in ("min_size", "max_size", "aspect_ratios")},
        "architecture": summary.get("architecture"), "status": summary["status"], "message": summary["message"],
        "estimate_s": summary["estimate"]["run_as_configured_s"], "planned_iterations": summary["iterations_planned"],
        "iterations_done": summary["iterations_done"], "wall_s": round(wall, 1),
        "over_budget_s": round(wall - 60 * args.minutes, 1),
        "test_AP50": stats["AP50"], "test_AP": stats["AP"], "best_val": summary["best"],
    }, indent=1))


if __name__ == "__main__":
    main()
