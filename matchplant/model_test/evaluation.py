"""Module 7's COCO evaluation of test tiles (the ``evaluate`` section).

Every box the model finds (no score threshold) is scored by pycocotools' COCOeval with ``maxDets`` raised for
dense tiles; AP, AP50, AP75, AP by size (from the ground-truth area), precision, recall and F1 at the operating
threshold, the plants found (a plant in two overlapping tiles counts once), a precision-recall curve, a confidence
histogram, images with drawn boxes, ``test_predictions.json`` and ``metrics.json``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from matchplant.core.formats.images import read_rgb8
from matchplant.core.formats.predictions import write_predictions
from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.data import CocoDetection
from matchplant.detection.evaluate import (
    coco_evaluate,
    draw_boxes,
    matches_at_iou50,
    operating_point,
    plot_pr_curve,
    plot_score_histogram,
    predict_dataset,
    summarise_stats,
    write_image,
)
from matchplant.detection.gpu import Runtime
from matchplant.detection.model import set_score_threshold
from matchplant.detection.tile_objects import distinct_objects, found_objects
from matchplant.model_test.config import EvalConfig, ModelTestConfig
from matchplant.model_test.inputs import nothing_in_test
from matchplant.model_test.scale import check_test_scale

log = get_logger("model_test")

METRIC_UNITS = (
    "fractions 0..1 for every AP, AR, precision, recall, F1 and threshold (no percents); 'images' "
    "counts test tiles, 'tile_boxes' annotated boxes in them, 'plants' distinct plants (one seen in two "
    "overlapping tiles counts once); 'coco' and 'at_threshold' score tile boxes, 'plants_found' "
    "distinct plants (found when any of their tile boxes is matched at IoU 0.5)"
)


def test_tiles(cfg: ModelTestConfig, ck: dict) -> CocoDetection:
    """The test tiles, checked against their files and the checkpoint's classes."""
    return CocoDetection(
        cfg.evaluate.dataset_json,
        cfg.evaluate.images,
        class_names=ck["class_names"],
        classes_from=f"the checkpoint {cfg.checkpoint}",
    )


def evaluate(cfg: ModelTestConfig, runtime: Runtime, out: Path, *, ck: dict, ds: CocoDetection) -> dict:
    """COCO evaluation of the checkpoint ``ck`` on the test tiles ``ds``; writes metrics, figures and predictions
    into ``out`` (:func:`~matchplant.model_test.run.run` gives a staging folder moved into place at the end)."""
    ecfg = cfg.evaluate
    # no score threshold before COCOeval, and as many boxes as maxDets
    model, ck = load_detector(
        ck, runtime.device, overrides={"roi": {"detections_per_img": ecfg.max_detections}}, source=cfg.checkpoint
    )
    set_score_threshold(model, 0.0)
    results = predict_dataset(
        model,
        ds,
        runtime,
        batch_size=cfg.batch_size,
        num_workers=cfg.num_workers,
        desc="evaluating",
    )
    if not results:
        raise nothing_in_test(len(ds), Path(ecfg.dataset_json), Path(cfg.checkpoint))
    metrics, ev, scores, hits = _metrics(cfg, ck, ds, results)
    plot_pr_curve(ev, out / "pr_curve.png", metrics["at_threshold"], ck["class_names"])
    plot_score_histogram(scores, hits, out / "score_histogram.png", ecfg.operating_threshold)
    _write_test_predictions(cfg, ds, results, out / "test_predictions.json")
    _draw_eval_images(ds, results, ecfg, out / "drawn")
    metrics["config"] = to_dict(cfg)
    write_json(out / "metrics.json", metrics)
    op = metrics["at_threshold"]
    log.info(
        "test: %s; at score >= %.2f: precision %.1f%%, recall %.1f%%, F1 %.1f%% (%s)",
        summarise_stats(metrics["coco"]),
        op["threshold"],
        100 * op["precision"],
        100 * op["recall"],
        100 * op["f1"],
        Path(cfg.output_dir) / "metrics.json",
    )
    return metrics


def _metrics(cfg: ModelTestConfig, ck: dict, ds: CocoDetection, results: list[dict]):
    """``(metrics, the COCOeval, scores, hits at IoU 0.5)`` of ``results`` on the test tiles."""
    ecfg = cfg.evaluate
    stats, ev = coco_evaluate(ds.data, results, max_dets=ecfg.max_detections)
    object_of, n_plants = distinct_objects(ds.data)  # a plant in two overlapping tiles is one plant
    metrics = {
        "checkpoint": str(cfg.checkpoint),
        "dataset": str(ecfg.dataset_json),
        "units": METRIC_UNITS,
        "images": len(ds),
        "plants": n_plants,
        "tile_boxes": len(ds.data["annotations"]),
        "detections": len(results),
        "max_detections": ecfg.max_detections,
        "coco": stats,
        "plant_scale_vs_training": check_test_scale(ds.data, ck),
    }
    scores, hits, n_gt = matches_at_iou50(ev)
    metrics["at_threshold"] = operating_point(scores, hits, n_gt, ecfg.operating_threshold)
    found = found_objects(ev, object_of, ecfg.operating_threshold)
    metrics["plants_found"] = {
        "threshold": ecfg.operating_threshold,
        "plants": n_plants,
        "found": found,
        "recall": found / n_plants if n_plants else 0.0,
    }
    return metrics, ev, scores, hits


def _write_test_predictions(cfg: ModelTestConfig, ds: CocoDetection, results: list[dict], path: Path) -> None:
    """Every box found on the test tiles (no threshold), as COCO results."""
    write_predictions(
        path,
        [dict(im) for im in ds.images],
        ds.data["categories"],
        [dict(r, id=i + 1) for i, r in enumerate(results)],
        info={
            "description": "MatchPlant module 7 predictions on test tiles (no threshold)",
            "checkpoint": str(cfg.checkpoint),
        },
    )


def _draw_eval_images(ds: CocoDetection, results: list[dict], ecfg: EvalConfig, folder: Path) -> None:
    """A few test tiles with their true boxes (green) and the boxes found at the operating threshold (red)."""
    if ecfg.drawn_images == 0:
        return
    picks = np.unique(np.linspace(0, len(ds) - 1, min(ecfg.drawn_images, len(ds))).round().astype(int))
    for i in picks:
        im = ds.images[i]
        img = read_rgb8(ds.paths[i])
        gt = ds.target(i)["boxes"].numpy()
        dets = [r for r in results if r["image_id"] == im["id"] and r["score"] >= ecfg.operating_threshold]
        b = np.asarray([r["bbox"] for r in dets], dtype=float).reshape(-1, 4)
        b[:, 2:] += b[:, :2]
        drawn = draw_boxes(draw_boxes(img, gt, (0, 200, 0)), b, (230, 30, 30), np.asarray([r["score"] for r in dets]))
        write_image(folder / (Path(im["file_name"]).stem + ".png"), drawn)
