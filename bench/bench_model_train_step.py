"""CPU cost of one training step of module 6 on the real photos of :mod:`bench.deepforest_photos`, for several
settings (issue 28): what the box head's samples, the proposal counts and the input size cost on a CPU.

Each setting builds MobileNetV3-FPN from random weights with ``anchor_sizes: auto``, trains 4 steps on the same
batch of 4 training photos and prints the CPU seconds (``time.process_time``: what the process used, whatever the
other load) of each step and the wall seconds of one inference pass per photo. One torch thread.

    python -m bench.bench_model_train_step                       # the settings below
    python -m bench.bench_model_train_step "model.min_size=320,model.max_size=320"
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from bench import deepforest_photos
from bench.bench_model_train_real import DEFAULT_DATA, find_wheel
from matchplant.core.runtime.config import load_config
from matchplant.detection.data import CocoDetection, collate
from matchplant.detection.model import build_detector, resolve_auto_anchors
from matchplant.model_train.config import ModelTrainConfig

CPU_HEADS = (
    "model.roi.batch_size_per_image=192,model.rpn.pre_nms_top_n_train=1000,"
    "model.rpn.post_nms_top_n_train=500,model.rpn.pre_nms_top_n_test=600,model.rpn.post_nms_top_n_test=300"
)
SETTINGS = (
    "model.min_size=448,model.max_size=448",  # torchvision's counts (512 samples, 2000)
    f"model.min_size=448,model.max_size=448,{CPU_HEADS}",  # what auto sets on a CPU for these photos
    f"model.min_size=320,model.max_size=320,{CPU_HEADS}",
)  # a smaller input


def step_seconds(train_json: Path, setting: str, steps: int = 4) -> tuple[list[float], float]:
    """CPU seconds of each training step at one setting, and the inference seconds per image."""
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            f"train_json={train_json}",
            "model.pretrained=none",
            "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
            "model.anchor_sizes=auto",
            *setting.split(","),
        ],
    )
    model = build_detector(resolve_auto_anchors(cfg.model, train_json), 2, load_weights=False).train()
    ds = CocoDetection(train_json)
    images, targets = collate([ds[i] for i in range(4)])
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.0, momentum=0.9)
    cpu = []
    for _ in range(steps):
        t = time.process_time()
        loss = sum(model(images, targets).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        cpu.append(time.process_time() - t)
    model.eval()
    t = time.perf_counter()
    with torch.inference_mode():
        model(images)
    return cpu, (time.perf_counter() - t) / len(images)


def main() -> None:
    """Parse the settings and print each one's training-step and inference cost on the DeepForest photos."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("settings", nargs="*", default=list(SETTINGS), help="comma-separated KEY=VALUE settings")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="as bench_model_train_real's --data")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        train_json, _, _ = deepforest_photos.build(find_wheel(args.data), Path(tmp))
        for setting in args.settings:
            cpu, inference = step_seconds(train_json, setting)
            print(
                f"{setting}: training step CPU s {[round(c, 2) for c in cpu]}, inference {inference:.2f} s per "
                "photo (wall)",
                flush=True,
            )


if __name__ == "__main__":
    main()
