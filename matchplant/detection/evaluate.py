"""Running a detector over a COCO dataset and scoring it with pycocotools' COCOeval (modules 6 and 7).

The rules that keep the numbers honest (docs/DESIGN.md §3): every box goes to COCOeval (no score threshold
before it), ``maxDets`` is raised above COCO's 100 for dense plant tiles, and the size classes come from
the ground truth ``area``. Precision, recall and F1 at an operating threshold reuse COCOeval's own
matching at IoU 0.5, so they agree with AP by construction of the same matches.
"""

from __future__ import annotations

import contextlib
import copy
import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path
from matchplant.core.runtime.progress import progress
from matchplant.detection.data import collate
from matchplant.detection.gpu import as_runtime

STAT_NAMES = (
    "AP",
    "AP50",
    "AP75",
    "AP_small",
    "AP_medium",
    "AP_large",
    "AR_1",
    "AR_10",
    "AR_max",
    "AR_small",
    "AR_medium",
    "AR_large",
)


def predict_dataset(
    model, dataset, device, *, batch_size: int = 4, num_workers: int = 0, amp: bool = False, desc: str = "detecting"
) -> list[dict]:
    """COCO results (``image_id, category_id, bbox [x,y,w,h], score``) of ``model`` on every image. ``device``: the
    run's :class:`~matchplant.detection.gpu.Runtime` (its ``amp``), or a bare device with ``amp``."""
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torch.utils.data import DataLoader

    runtime = as_runtime(device, amp)
    model.eval()
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers, collate_fn=collate)
    results: list[dict] = []
    cat_of_label = np.asarray([0] + list(dataset.category_ids))
    with torch.inference_mode():
        for images, targets in progress(loader, desc=desc, unit="batch"):
            images = [im.to(runtime.device, non_blocking=True) for im in images]
            with torch.autocast(device_type=runtime.kind, enabled=runtime.amp):
                outputs = model(images)
            for out, target in zip(outputs, targets):
                boxes = out["boxes"].float().cpu().numpy()
                scores = out["scores"].float().cpu().numpy()
                cats = cat_of_label[out["labels"].cpu().numpy()]
                xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
                results.extend(
                    {
                        "image_id": int(target["image_id"]),
                        "category_id": int(c),
                        "bbox": [round(float(v), 2) for v in b],
                        "score": round(float(s), 5),
                    }
                    for b, s, c in zip(xywh, scores, cats)
                )
    return results


def _quiet():
    return contextlib.redirect_stdout(io.StringIO())


def coco_gt(dataset: dict):
    """A pycocotools COCO object from a dataset dict (``area`` filled in where missing)."""
    data = copy.deepcopy(dataset)
    data.setdefault("info", {})
    for a in data.get("annotations", []):
        a.setdefault("area", float(a["bbox"][2]) * float(a["bbox"][3]))
        a.setdefault("iscrowd", 0)
    with _quiet():
        gt = COCO()
        gt.dataset = data
        gt.createIndex()
    return gt


def coco_evaluate(dataset: dict, results: list[dict], *, max_dets: int = 300):
    """COCOeval of ``results`` against ``dataset``; returns ``(stats dict, COCOeval or None)``.

    Stats: AP (IoU .50:.95), AP50, AP75, AP by size (from GT area), AR; ``None`` where COCOeval has no
    value (e.g. no large plants). ``maxDets`` is ``[1, 10, max_dets]``; every stat uses ``max_dets``
    boxes except AR_1 and AR_10.
    """
    if not results:
        n_gt = len(dataset.get("annotations", []))
        return {name: (0.0 if n_gt else None) for name in STAT_NAMES}, None
    gt = coco_gt(dataset)
    with _quiet():
        dt = gt.loadRes(copy.deepcopy(results))
        ev = COCOeval(gt, dt, "bbox")
        ev.params.maxDets = [1, 10, int(max_dets)]
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    values = list(ev.stats)
    # pycocotools' summarize() computes AP (IoU .50:.95) at a fixed maxDets=100 and reports -1 when 100 is
    # not in maxDets; average its precision at our maxDets instead (the same number when max_dets is 100)
    precision = ev.eval["precision"][:, :, :, 0, -1]
    values[0] = float(precision[precision > -1].mean()) if (precision > -1).any() else -1.0
    stats = {name: (float(v) if v >= 0 else None) for name, v in zip(STAT_NAMES, values)}
    return stats, ev


def matches_at_iou50(ev) -> tuple[np.ndarray, np.ndarray, int]:
    """From a COCOeval: every detection's score and whether it matched a plant at IoU 0.5, and the number
    of (non-ignored) plants. Detections ignored by COCOeval (matched to crowd boxes) are left out."""
    all_area = list(ev.params.areaRng[0])
    max_det = ev.params.maxDets[-1]
    scores, hits, n_gt = [], [], 0
    for e in ev.evalImgs:
        if e is None or list(e["aRng"]) != all_area or e["maxDet"] != max_det:
            continue
        keep = ~np.asarray(e["dtIgnore"][0], dtype=bool)
        scores.append(np.asarray(e["dtScores"], dtype=float)[keep])
        hits.append((np.asarray(e["dtMatches"][0]) > 0)[keep])
        n_gt += int((~np.asarray(e["gtIgnore"], dtype=bool)).sum())
    if not scores:
        return np.zeros(0), np.zeros(0, dtype=bool), n_gt
    return np.concatenate(scores), np.concatenate(hits), n_gt


def operating_point(scores: np.ndarray, hits: np.ndarray, n_gt: int, threshold: float) -> dict:
    """Precision, recall and F1 of the detections scoring at least ``threshold``."""
    sel = scores >= threshold
    tp = int(hits[sel].sum())
    fp = int(sel.sum()) - tp
    fn = n_gt - tp
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / n_gt if n_gt else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {
        "threshold": float(threshold),
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "precision": precision,
        "recall": recall,
        "f1": f1,
    }


# --------------------------------------------------------------------------------------------------
# figures


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def plot_pr_curve(ev, path: Path, operating: dict | None = None, class_names: list[str] | None = None) -> Path:
    """Precision against recall at IoU 0.5 and 0.75 (COCOeval's interpolated curve), per class."""
    fig = figure(headless=True, figsize=(5.5, 4.5))
    ax = fig.add_subplot()
    rec = ev.params.recThrs
    for k in range(ev.eval["precision"].shape[2]):
        name = class_names[k] if class_names and k < len(class_names) else f"class {k + 1}"
        for t, iou, style in ((0, 0.5, "-"), (5, 0.75, "--")):
            p = ev.eval["precision"][t, :, k, 0, -1]
            ax.plot(rec[p > -1], p[p > -1], style, label=f"{name}, IoU {iou}")
    if operating:
        ax.plot([operating["recall"]], [operating["precision"]], "ko", label=f"score >= {operating['threshold']:.2f}")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.01), title="precision-recall")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return _save(fig, path)


def plot_score_histogram(scores: np.ndarray, hits: np.ndarray, path: Path, threshold: float | None = None) -> Path:
    """How confident the detector is on true and on false detections (IoU 0.5)."""
    fig = figure(headless=True, figsize=(5.5, 4))
    ax = fig.add_subplot()
    bins = np.linspace(0, 1, 41)
    ax.hist(
        [scores[hits], scores[~hits]],
        bins=bins,
        stacked=True,
        label=["true positive", "false positive"],
        color=["tab:green", "tab:red"],
    )
    if threshold is not None:
        ax.axvline(threshold, color="k", ls="--", label=f"threshold {threshold:.2f}")
    ax.set(xlabel="score", ylabel="detections", title="confidence of the detections")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def draw_boxes(
    image: np.ndarray, boxes_xyxy: np.ndarray, color: tuple[int, int, int], scores: np.ndarray | None = None
) -> np.ndarray:
    """A copy of an RGB image with boxes (and their scores) drawn on it."""
    out = np.ascontiguousarray(image.copy())
    thick = max(1, int(round(max(image.shape[:2]) / 500)))
    for i, b in enumerate(np.asarray(boxes_xyxy, dtype=float).reshape(-1, 4)):
        x1, y1, x2, y2 = (int(round(v)) for v in b)
        cv2.rectangle(out, (x1, y1), (x2, y2), color, thick)
        if scores is not None:
            cv2.putText(
                out,
                f"{scores[i]:.2f}",
                (x1, max(y1 - 3, 10)),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35 * thick,
                color,
                1,
                cv2.LINE_AA,
            )
    return out


def write_image(path: Path, rgb: np.ndarray) -> Path:
    """Write an RGB image atomically, its format from the suffix (PNG by default); the path."""
    ok, buf = cv2.imencode(Path(path).suffix or ".png", rgb[:, :, ::-1])
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    with atomic_path(path) as tmp:
        buf.tofile(tmp)
    return Path(path)


def summarise_stats(stats: dict[str, Any]) -> str:
    """AP, AP50 and AP75 of COCOeval's stats as percentages on one line for the log ("n/a" when missing)."""

    def fmt(v):
        return "n/a" if v is None else f"{100 * v:.1f}%"

    return ", ".join(f"{k} {fmt(stats.get(k))}" for k in ("AP", "AP50", "AP75"))
