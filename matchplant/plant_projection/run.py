"""Step 8 from its config: project the predictions, merge, write; then, if asked, evaluate.

Library use::

    views, rejected = project_predictions(ODMProject("field"), read_predictions("predictions.json"))
    plants = merge_views(views)
    metrics = evaluate_boxes(reference_bounds, plant_bounds)

(from :mod:`~matchplant.plant_projection.views`, :mod:`~matchplant.plant_projection.merge` and
:mod:`~matchplant.plant_projection.evaluation`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from matchplant.core.coco import read_predictions
from matchplant.core.io import write_json
from matchplant.core.log import get_logger
from matchplant.core.odm import ODMProject
from matchplant.plant_projection.config import ProjectionConfig
from matchplant.plant_projection.evaluation import evaluate_boxes, evaluation_figure, read_boxes, read_plants_boxes
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.output import write_plants, write_table
from matchplant.plant_projection.views import project_predictions

log = get_logger("projection")


def run_projection(cfg: ProjectionConfig) -> dict:
    """Project, merge and write; the summary (also ``projection_summary.json``) counts every box, so none
    goes missing unnoticed."""
    out = Path(cfg.output_dir)
    project = ODMProject(cfg.project)
    preds = read_predictions(cfg.predictions, cfg.images_from)
    views, rejected = project_predictions(project, preds, image_type=cfg.image_type, dsm=cfg.dsm,
                                          min_score=cfg.min_score, edge_points=cfg.edge_points,
                                          map_box=cfg.map_box, border_pixels=cfg.border_pixels,
                                          clearance=cfg.silhouette_clearance, hidden_height=cfg.hidden_height,
                                          ground_window=cfg.ground_window)
    plants = merge_views(views, merge=cfg.merge, merge_iou=cfg.merge_iou)
    geometry = "box" if cfg.merge == "fuse" else cfg.geometry  # fused boxes have no single outline
    written = write_plants(plants, views, out, layer=cfg.layer, geometry=geometry, shapefile=cfg.write_shapefile)
    low = rejected["reason"] == "score below min_score"
    failed = rejected[~low]
    written["unprojected"] = write_table(failed, out / "unprojected_boxes.csv")
    if cfg.write_views:
        written["views"] = write_table(views.table, out / "views.csv")
    summary = {
        "detections": int(len(preds["predictions"])),
        "below_min_score": int(low.sum()),
        "projected_boxes": int(len(views.table)),
        "not_projected": int(len(failed)),
        "not_projected_by_reason": {str(k): int(v) for k, v in failed["reason"].value_counts().items()},
        "plants": int(len(plants)),
        "views_per_plant_median": float(plants["views"].median()) if len(plants) else 0.0,
        "spread_m_median": float(plants["spread_m"].median()) if len(plants) else 0.0,
        "crs": views.crs.to_string() if views.crs is not None else None,
        "outputs": {k: str(v) for k, v in written.items()},
    }
    write_json(out / "projection_summary.json", summary)
    log.info("%d of %d detections projected -> %d plants (median %.0f views each)", summary["projected_boxes"],
             summary["detections"], summary["plants"], summary["views_per_plant_median"])
    if len(failed):
        reasons = "; ".join(f"{v} x {k}" for k, v in summary["not_projected_by_reason"].items())
        log.warning("%d boxes could not be projected (%s); see %s", len(failed), reasons, written["unprojected"])
    if low.any():
        log.info("%d detections scored below min_score=%.2f and were left out", int(low.sum()), cfg.min_score)
    log.info("plants: %s and %s", written["gpkg"], written["csv"])
    return summary


def run_evaluation(cfg: ProjectionConfig) -> dict:
    """Score written plants against reference boxes; reads the plants from file so that a projection run
    earlier (or elsewhere) can be evaluated alone."""
    e = cfg.evaluate
    out = Path(cfg.output_dir)
    plants_path = e.plants or out / "plants.gpkg"
    ortho = e.orthophoto
    if ortho is None and cfg.project is not None:
        p = ODMProject(cfg.project)
        ortho = p.path("orthophoto") if p.has("orthophoto") else None
    predicted, crs = read_plants_boxes(plants_path)
    reference = read_boxes(e.reference, orthophoto=ortho, crs=crs)
    metrics = evaluate_boxes(reference, predicted, e.iou_threshold)
    match, iou = metrics.pop("_match"), metrics.pop("_iou")
    write_table(pd.DataFrame({"reference_index": np.arange(len(reference)), "xmin": reference[:, 0],
                              "ymin": reference[:, 1], "xmax": reference[:, 2], "ymax": reference[:, 3],
                              "plant_index": match, "iou": iou}), out / "evaluation_matches.csv")
    metrics.update(reference=str(e.reference), plants=str(plants_path))
    write_json(out / "evaluation.json", metrics)
    fig = evaluation_figure(out / "evaluation.png", reference, predicted, dict(metrics, _match=match, _iou=iou),
                            ortho, e.figure_pixels)
    thr = e.iou_threshold
    log.info("%d reference boxes: %.1f%% matched, %.1f%% with IoU > %g, median IoU %.3f; figure %s",
             metrics["reference_boxes"], 100 * metrics["share_matched"],
             100 * metrics[f"share_iou_above_{thr:g}"], thr, metrics["iou_median"], fig)
    return metrics


def run(cfg: ProjectionConfig) -> dict:
    """The step's entry point (``mode``: project, evaluate or both)."""
    result = {}
    if cfg.mode in ("project", "both"):
        result["projection"] = run_projection(cfg)
    if cfg.mode in ("evaluate", "both"):
        result["evaluation"] = run_evaluation(cfg)
    return result
