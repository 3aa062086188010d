"""Which box of a nested pair should module 7 keep? The score-aware rule against "keep the larger", on real photos
with a trained detector (issue 39: on sorghum photos the dropped inner box was the correct panicle in 5 of 12 pairs).

    python bench/bench_nested_merge.py --checkpoint RUN/checkpoints/best.pt --dataset test.json --images test/images

A module 6 checkpoint detects on every photo of a COCO dataset as module 7 does (:func:`detect_image`, its default
score threshold and tiles), with the nested merge switched off; the photo's boxes are then merged three ways:
none, module 7's rule (:func:`merge_nested`: of two boxes of a class, one at least ``merge_containment`` inside
the other, the lower-scoring one goes) and the old rule (the inner box always goes). Each is scored against the
dataset's boxes (one-to-one matches at IoU >= 0.5, best score first): boxes, true positives, precision, recall.
For every nested pair the two rules decide differently, it says which box matched a true box. With
``bench_model_train_real`` (DeepForest's MIT photos of tree crowns, 15 minutes of CPU training)::

    python -m bench.bench_model_train_real --minutes 15 --out /tmp/df
    python bench/bench_nested_merge.py --checkpoint /tmp/df/run/checkpoints/best.pt \\
        --dataset /tmp/df/test.json --images /tmp/df/test/images
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torchvision.ops import box_iou

from matchplant.core.formats.images import read_rgb8
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.model import set_score_threshold
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.merge import _inside_pairs, merge_nested
from matchplant.model_test.tiles import detect_image, model_predictor


def matched(truth: np.ndarray, boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Per box, whether it is a true positive: one-to-one at IoU >= 0.5, the best-scoring boxes first."""
    hit = np.zeros(len(boxes), bool)
    if not len(truth) or not len(boxes):
        return hit
    iou = box_iou(torch.from_numpy(boxes).float(), torch.from_numpy(truth).float()).numpy()
    free = np.ones(len(truth), bool)
    for i in np.argsort(-scores, kind="stable"):
        j = np.flatnonzero(free & (iou[i] >= 0.5))
        if j.size:
            best = j[np.argmax(iou[i, j])]
            free[best], hit[i] = False, True
    return hit


def larger_kept(boxes: np.ndarray, labels: np.ndarray, containment: float) -> np.ndarray:
    """The old rule: the inner box of every nested pair goes, whatever the scores."""
    area = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    inner, _ = _inside_pairs(boxes, labels, area, containment)
    return np.setdiff1d(np.arange(len(boxes)), inner)


def main(argv: list[str] | None = None) -> dict:
    """Parse the options, detect on the photos and score no merge, score-aware and keep-the-larger against the truth."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--dataset", type=Path, required=True, help="COCO json of the photos and their true boxes")
    ap.add_argument("--images", type=Path, required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    defaults = ModelTestConfig()
    containment, threshold = defaults.detect.merge_containment, defaults.detect.score_threshold
    model, ck = load_detector(args.checkpoint, torch.device("cpu"))
    set_score_threshold(model, threshold)
    predictor = model_predictor(model, torch.device("cpu"))
    tile = int(ck["model_config"].get("min_size", 800))
    ds = json.loads(args.dataset.read_text())
    totals = {rule: {"boxes": 0, "true_positives": 0} for rule in ("none", "score_aware", "larger_kept")}
    differ = {"pairs_decided_differently": 0, "inner_correct": 0, "outer_correct": 0, "neither": 0, "both": 0}
    n_truth = 0
    for im in ds["images"]:
        truth = np.array(
            [[x, y, x + w, y + h] for x, y, w, h in (a["bbox"] for a in ds["annotations"] if a["image_id"] == im["id"])]
        ).reshape(-1, 4)
        n_truth += len(truth)
        image = read_rgb8(args.images / im["file_name"])
        boxes, scores, labels = detect_image(
            image, predictor, tile_size=tile, overlap=0, score_threshold=threshold, merge_containment=2.0
        )
        hit = matched(truth, boxes, scores)
        area = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
        inner, outer = _inside_pairs(boxes, labels, area, containment)
        for i, o in zip(inner, outer):
            if scores[i] > scores[o]:  # module 7 keeps the inner box, the old rule the outer one
                differ["pairs_decided_differently"] += 1
                key = "both" if hit[i] and hit[o] else "inner_correct" if hit[i] else "outer_correct" if hit[o] else ""
                differ[key or "neither"] += 1
        for rule, keep in (
            ("none", np.arange(len(boxes))),
            ("score_aware", merge_nested(boxes, scores, labels, containment)),
            ("larger_kept", larger_kept(boxes, labels, containment)),
        ):
            totals[rule]["boxes"] += len(keep)
            totals[rule]["true_positives"] += int(matched(truth, boxes[keep], scores[keep]).sum())
    for t in totals.values():
        t["precision"] = round(t["true_positives"] / max(t["boxes"], 1), 4)
        t["recall"] = round(t["true_positives"] / max(n_truth, 1), 4)
    result = {
        "photos": len(ds["images"]),
        "true_boxes": n_truth,
        "score_threshold": threshold,
        "containment": containment,
        "rules": totals,
        "nested_pairs": differ,
    }
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
