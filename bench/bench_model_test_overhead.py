"""Module 7's tiled detection against its own model passes, in one run (issue 30 point 5).

    taskset -c 1 python bench/bench_model_test_overhead.py 0.0    # every box kept: ~10,000 tile boxes to merge
    taskset -c 1 python bench/bench_model_test_overhead.py 0.5    # the default score threshold

A 640 x 512 synthetic photo in 42 tiles of 128 px (overlap 32) seen at 320 px by an untrained MobileNetV3-FPN,
batch 4, one thread. The predictor is timed inside ``detect_image``, so both sides of the ratio come from the same
run on the same load: ``model / total`` is the speed of the tiled detection relative to the model's passes
alone (tiling, cut detection, the merge across tiles and the nested-duplicate pass are the difference). Round 0
is a warm-up; the median, min and max of the other rounds are printed. ``python -m bench --only detect`` is the
alternating comparison against the bare model (minutes per pair on one core).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from matchplant.core.formats.images import read_rgb8
from matchplant.detection.model import ModelConfig, build_detector, set_score_threshold
from matchplant.detection.synth import make_photo
from matchplant.model_test.tiles import detect_image, model_predictor


def main(threshold: float, rounds: int = 3) -> None:
    """Print module 7's tiled detection time against its model passes alone, per round, at a score threshold."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = build_detector(
        ModelConfig(architecture="fasterrcnn_mobilenet_v3_large_fpn", pretrained="none", min_size=320, max_size=320),
        2,
        load_weights=False,
    ).eval()
    set_score_threshold(model, threshold)
    photo = Path(tempfile.mkdtemp()) / "photo.png"
    make_photo(photo, 640, 512, n_plants=60, radius=(8, 16), seed=2)
    img = read_rgb8(photo)
    predict = model_predictor(model, torch.device("cpu"))
    spent = [0.0, 0]

    def timed(tiles):
        t = time.perf_counter()
        out = predict(tiles)
        spent[0] += time.perf_counter() - t
        spent[1] += sum(len(o[0]) for o in out)
        return out

    ratios = []
    for r in range(rounds):
        spent[:] = [0.0, 0]
        t = time.perf_counter()
        boxes, _, _ = detect_image(img, timed, tile_size=128, overlap=32, batch_size=4, score_threshold=threshold)
        total = time.perf_counter() - t
        if r:
            ratios.append(spent[0] / total)
        print(
            f"round {r}: total {total:.2f} s, model {spent[0]:.2f} s, tile boxes {spent[1]}, final {len(boxes)}, "
            f"model/total {spent[0] / total:.3f}",
            flush=True,
        )
    print(
        f"tiled detection / model passes: median {np.median(ratios):.3f} (min {min(ratios):.3f}, max {max(ratios):.3f})"
    )


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 0.5)
