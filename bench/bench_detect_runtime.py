"""Is ONNX Runtime faster than PyTorch on a CPU for module 7's light detector, with the same boxes? (issue 40)

    taskset -c 1 python bench/bench_detect_runtime.py              # one pinned core, one thread each
    taskset -c 1 python bench/bench_detect_runtime.py --rounds 9 --tiles 4

The light model (``fasterrcnn_resnet18_fpn_lite``, random weights, eval mode, score threshold 0 so that every
image gives its 100 boxes to compare) detects on ``--tiles`` tiles of 1024 px cut from a synthetic photo (resized
by the model to 800 px), once as PyTorch runs it (``inference_mode``) and once with its backbone, feature pyramid
and RPN head in ONNX Runtime (:func:`matchplant.model_test.runtime_onnx.onnx_detector`; the rest PyTorch's).
The two alternate tile by tile in the same process, ``--rounds`` times over the tiles; the median time per tile
and the range of each are printed. Same boxes: every PyTorch box has an ONNX box of its class with IoU > 0.99
and a score within 1e-3 (and the counts are equal).
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torchvision.ops import box_iou

from matchplant.core.formats.images import read_rgb8
from matchplant.detection.model import ModelConfig, build_detector, set_score_threshold
from matchplant.detection.synth import make_photo
from matchplant.model_test.runtime_onnx import onnx_detector

ARCH = "fasterrcnn_resnet18_fpn_lite"


def same_boxes(a: dict, b: dict) -> tuple[bool, float, float]:
    """Every box of ``a`` matched in ``b`` (same class, IoU > 0.99, score within 1e-3); worst IoU, score diff."""
    if len(a["boxes"]) != len(b["boxes"]):
        return False, 0.0, float("inf")
    if not len(a["boxes"]):
        return True, 1.0, 0.0
    iou = box_iou(a["boxes"], b["boxes"]) * (a["labels"][:, None] == b["labels"][None, :])
    best, j = iou.max(dim=1)
    ds = (a["scores"] - b["scores"][j]).abs().max().item()
    worst = best.min().item()
    return worst > 0.99 and ds < 1e-3, worst, ds


def main(argv: list[str] | None = None) -> None:
    """Parse the options, time the light detector in PyTorch and ONNX Runtime on one thread, compare the boxes."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tiles", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)
    import onnxruntime as ort

    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = build_detector(ModelConfig(architecture=ARCH, pretrained="none"), 2, load_weights=False).eval()
    set_score_threshold(model, 0.0)
    t0 = time.perf_counter()
    onnx = onnx_detector(copy.deepcopy(model), threads=1)
    export_s = time.perf_counter() - t0
    path = Path(tempfile.mkdtemp()) / "photo.png"
    make_photo(path, 1024 * args.tiles, 1024, n_plants=40 * args.tiles, radius=(15, 40), seed=1)
    photo = torch.from_numpy(read_rgb8(path)).permute(2, 0, 1).float() / 255
    tiles = [photo[:, :, 1024 * i : 1024 * (i + 1)].contiguous() for i in range(args.tiles)]
    runs = {"torch": model, "onnxruntime": onnx}
    times: dict[str, list[float]] = {k: [] for k in runs}
    ok, worst, ds = True, 1.0, 0.0
    with torch.inference_mode():
        for m in runs.values():
            m([tiles[0]])  # warm-up
        for _ in range(args.rounds):
            for tile in tiles:
                out = {}
                for k, m in runs.items():
                    t0 = time.perf_counter()
                    out[k] = m([tile])[0]
                    times[k].append(time.perf_counter() - t0)
                same, w, d = same_boxes(out["torch"], out["onnxruntime"])
                ok, worst, ds = ok and same, min(worst, w), max(ds, d)
    print(
        f"{ARCH}, {args.tiles} tiles of 1024 px (800 px network input), {args.rounds} rounds alternating, "
        f"torch {torch.__version__} ({torch.get_num_threads()} thread), onnxruntime {ort.__version__} (1 thread); "
        f"export {export_s:.1f} s"
    )
    base = np.median(times["torch"])
    for k, t in times.items():
        print(
            f"  {k:<12} median {np.median(t):.3f} s per tile (range {min(t):.3f}-{max(t):.3f}); "
            f"speed vs torch {base / np.median(t):.2f}x"
        )
    pair = np.asarray(times["torch"]) / np.asarray(times["onnxruntime"])  # each tile's two runs, back to back
    print(
        f"  per tile, torch time / onnxruntime time: median {np.median(pair):.2f}x "
        f"(quartiles {np.quantile(pair, 0.25):.2f}-{np.quantile(pair, 0.75):.2f}, "
        f"range {pair.min():.2f}-{pair.max():.2f}, {pair.size} pairs)"
    )
    print(f"  same boxes: {ok} (worst IoU {worst:.4f}, largest score difference {ds:.1e})")


if __name__ == "__main__":
    main(sys.argv[1:])
