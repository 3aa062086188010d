"""``anchor_sizes: auto`` against the demo's hand-set anchors: AP50 on held-out tiles, same training budget.

    python bench/bench_detection_anchors.py                        # 120 training tiles, input 320 px, 8 epochs per run
    python bench/bench_detection_anchors.py --quick                # 48 training tiles, 4 epochs per run
    python bench/bench_detection_anchors.py --tiles 48 --net 192 --epochs 6 --seeds 0 1   # the README's CPU setting

Synthetic 128 px tiles with plants of ~15-30 px (the demo's scale), MobileNetV3 Faster R-CNN from random
weights with the demo's settings (the tile enlarged to ``--net`` px, 2.5x = 320 in the demo, its RPN
sizes), trained twice per seed with the same data, seed and number of epochs: once with the demo's
anchors (its rule ``[net/8, net/4, net/2]`` at each level, derived from the tile size: ``[[40, 80, 160]]
* 3`` at 320), once with ``anchor_sizes: auto`` (from the training boxes). Both are evaluated on the
same held-out tiles (never seen in training). Also prints the auto anchors for ~40 px objects on 512 px
tiles, and checks that every object size there has an anchor with IoU >= 0.5.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from matchplant.core.runtime.config import load_config
from matchplant.detection.architectures import get_architecture
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.data import CocoDetection
from matchplant.detection.evaluate import coco_evaluate, predict_dataset
from matchplant.detection.model import set_score_threshold
from matchplant.detection.objects import auto_anchor_sizes
from matchplant.detection.synth import make_tiles
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

os.environ.setdefault("MATCHPLANT_QUIET", "1")


def demo_settings(net: int, seed: int) -> list[str]:
    """The demo's model and optimisation settings (matchplant/demo.py) at input size ``net``."""
    return [
        "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
        "model.pretrained=none",
        f"model.min_size={net}",
        f"model.max_size={net}",
        "model.rpn.pre_nms_top_n_train=1000",
        "model.rpn.post_nms_top_n_train=400",
        "model.rpn.pre_nms_top_n_test=300",
        "model.rpn.post_nms_top_n_test=100",
        "model.roi.batch_size_per_image=64",
        "batch_size=4",
        "num_workers=0",
        "warmup_iters=20",
        "save_every=0",
        f"seed={seed}",
        "lr.backbone=0.02",
        "lr.fpn=0.02",
        "lr.rpn=0.02",
        "lr.roi_heads=0.02",
    ]


def run_one(name: str, anchors: str, data: Path, epochs: int, net: int, seed: int, out: Path) -> dict:
    """Train one detector with the given anchors and score it on the test tiles: anchors, AP50, AP, training time."""
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            f"train_json={data / 'train.json'}",
            f"output_dir={out / name}",
            f"epochs={epochs}",
            f"step_size={max(1, epochs - 1)}",
            f"model.anchor_sizes={anchors}",
            *demo_settings(net, seed),
        ],
    )
    t0 = time.perf_counter()
    train(cfg)
    seconds = time.perf_counter() - t0
    import torch  # lazy: only the evaluation needs it here

    model, ck = load_detector(out / name / "checkpoints" / "last.pt")
    set_score_threshold(model, 0.0)
    test = CocoDetection(data / "test.json")
    stats, _ = coco_evaluate(test.data, predict_dataset(model, test, torch.device("cpu")))
    return {
        "anchors": ck["model_config"]["anchor_sizes"],
        "AP50": stats["AP50"],
        "AP": stats["AP"],
        "train_s": round(seconds, 1),
    }


def anchors_for_40px_on_512px() -> dict:
    """Auto anchors for ~40 px objects on 512 px tiles (min_size 512), and whether each object size
    between the 1st and 99th percentile has a square anchor with IoU >= 0.5."""
    rng = np.random.default_rng(0)
    w, h = rng.normal(40, 6, 2000), rng.normal(40, 6, 2000)
    lo, hi = np.percentile(np.sqrt(w * h), [1, 99])
    out = {}
    for arch in ("fasterrcnn_resnet50_fpn", "fasterrcnn_mobilenet_v3_large_fpn", "retinanet_resnet50_fpn"):
        sizes = auto_anchor_sizes(w, h, get_architecture(arch).anchors)
        flat = np.array(sorted({s for level in sizes for s in level}), float)
        worst = min((np.minimum(s, flat) ** 2 / np.maximum(s, flat) ** 2).max() for s in np.linspace(lo, hi, 50))
        out[arch] = {
            "anchor_sizes": sizes,
            "objects_p1_p99_px": [round(lo, 1), round(hi, 1)],
            "worst_best_iou": round(float(worst), 3),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    """Parse the options, train with auto and with the demo's anchors per seed, and print both APs."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="48 training tiles, 4 epochs")
    ap.add_argument("--tiles", type=int, default=None, help="training tiles (120; --quick 48)")
    ap.add_argument("--epochs", type=int, default=None, help="epochs per run (8; --quick 4)")
    ap.add_argument("--net", type=int, default=320, help="detector input size (min_size = max_size; demo 320)")
    ap.add_argument("--test-tiles", type=int, default=40, help="held-out tiles scored")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="one pair of runs per seed")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    args = ap.parse_args(argv)
    n_train = args.tiles or (48 if args.quick else 120)
    epochs = args.epochs or (4 if args.quick else 8)
    if args.threads:
        import torch  # lazy: only to set the thread count

        torch.set_num_threads(args.threads)
    demo_anchors = json.dumps([[args.net // 8, args.net // 4, args.net // 2]] * 3)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        for name, n, seed in (("train", n_train, 0), ("test", args.test_tiles, 2)):
            make_tiles(
                data, n_images=n, size=128, plants=(2, 6), radius=(7, 14), negatives=2, seed=seed, name=f"{name}.json"
            )
        for seed in args.seeds:
            runs.append(
                {
                    "seed": seed,
                    "demo_hand_set": run_one(f"demo{seed}", demo_anchors, data, epochs, args.net, seed, Path(tmp)),
                    "auto": run_one(f"auto{seed}", "auto", data, epochs, args.net, seed, Path(tmp)),
                }
            )
    results = {
        "settings": {
            "train_tiles": n_train,
            "test_tiles": args.test_tiles,
            "epochs": epochs,
            "tile": 128,
            "input": args.net,
            "seeds": args.seeds,
            "threads": args.threads or "default",
        },
        "runs": runs,
        "mean_AP50": {k: float(np.mean([r[k]["AP50"] for r in runs])) for k in ("demo_hand_set", "auto")},
        "auto_for_40px_on_512px_tiles": anchors_for_40px_on_512px(),
    }
    print(json.dumps(results, indent=1))
    a, d = results["mean_AP50"]["auto"], results["mean_AP50"]["demo_hand_set"]
    print(
        f"AP50 on held-out tiles, mean of {len(runs)} seed(s): auto {a:.3f} vs demo {d:.3f}: "
        f"{'auto matches or beats the demo' if a >= d else 'auto is worse'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
