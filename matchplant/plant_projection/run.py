"""Step 8 from its config: project the predictions, merge, write; then, if asked, evaluate.

Library use::

    views, rejected = project_predictions(ODMProject("field"), read_predictions("predictions.json", every_box=True))
    plants = merge_views(views)
    metrics = evaluate_boxes(reference_bounds, plant_bounds)

(from :mod:`~matchplant.core.formats.predictions`, :mod:`~matchplant.plant_projection.views`,
:mod:`~matchplant.plant_projection.merge` and :mod:`~matchplant.plant_projection.evaluation`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.formats.projects import PhotoProject, open_project
from matchplant.core.formats.split_check import check_split
from matchplant.core.geometry.surface import NODATA, STATUS_TEXT
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.guard import staged_outputs
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.plant_projection.config import PlantProjectionConfig
from matchplant.plant_projection.evaluation import evaluate_boxes, evaluation_figure, read_boxes, read_plants_boxes
from matchplant.plant_projection.inputs import check_dsm
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.output import write_plants, write_table
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.views import (
    BOX_OUTSIDE_IMAGE,
    EMPTY_BOX,
    NOT_IN_RECONSTRUCTION,
    dsm_files,
    project_predictions,
)

log = get_logger("plant_projection")


def run_projection(cfg: PlantProjectionConfig, dest: Path | None = None) -> dict:
    """Project, merge and write (into ``dest``, the staging folder; default ``output_dir``); the summary (also
    ``projection_summary.json``) counts every box, so none goes missing unnoticed. Nothing projected, or
    nothing scoring ``min_score``, is an error (with ``unprojected_boxes.csv`` saying why for each box)."""
    out = Path(cfg.output_dir)
    dest = Path(dest or out)
    project = open_project(cfg.project, cfg.project_type, dsm=cfg.dsm)
    check_split(project)  # a failed or foreign submodel: named, not skipped
    preds = read_predictions(cfg.predictions, cfg.images_from, every_box=True)
    for path in dsm_files(project, cfg.dsm):
        check_dsm(path, "dsm" if cfg.dsm is not None else None)
    scores = np.array([float(p.get("score", 1.0)) for p in preds["predictions"]])
    if not (scores >= cfg.min_score).any():
        raise ConfigError(
            f"0 of {len(scores)} detections score at least min_score={cfg.min_score:g} (the highest "
            f"scores {scores.max():.3f}), so no box would be projected",
            path=cfg.predictions,
            fix=f"lower 'min_score' (e.g. to {np.floor(scores.max() * 100) / 100:.2f}), or check that "
            "these are the model's predictions",
        )
    views, rejected = project_predictions(project, preds, ProjectionSettings.from_config(cfg))
    low = rejected["reason"] == "score below min_score"
    failed = rejected[~low]
    lost_in_holes(failed, len(preds["predictions"]) - int(low.sum()), views.dsm_holes, cfg, out)
    if not len(views.table):
        out.mkdir(parents=True, exist_ok=True)
        report = write_table(failed, out / "unprojected_boxes.csv")  # the why, kept although the run fails
        raise nothing_projected(failed, cfg, project, report)
    plants = merge_views(views, merge=cfg.merge, merge_iou=cfg.merge_iou)
    geometry = "box" if cfg.merge == "fuse" else cfg.geometry  # fused boxes have no single outline
    written = write_plants(plants, views, dest, layer=cfg.layer, geometry=geometry, vector_formats=cfg.vector_formats)
    written["unprojected"] = write_table(failed, dest / "unprojected_boxes.csv")
    if cfg.write_views:
        written["views"] = write_table(views.table, dest / "views.csv")
    written = {k: out / Path(v).name for k, v in written.items()}  # where they will be once moved into place
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
    write_json(dest / "projection_summary.json", summary)
    log.info(
        "%d of %d detections projected -> %d plants (median %.0f views each)",
        summary["projected_boxes"],
        summary["detections"],
        summary["plants"],
        summary["views_per_plant_median"],
    )
    if len(failed):
        reasons = "; ".join(f"{v} x {k}" for k, v in summary["not_projected_by_reason"].items())
        log.warning(
            "%d of %d boxes could not be projected (%s)%s; see %s",
            len(failed),
            len(preds["predictions"]) - int(low.sum()),
            reasons,
            unknown_images(failed),
            written["unprojected"],
        )
    if low.any():
        log.info("%d detections scored below min_score=%.2f and were left out", int(low.sum()), cfg.min_score)
    log.info("plants: %s", " and ".join(str(written[k]) for k in (*cfg.vector_formats, "csv")))
    return summary


MOST_LOST = 0.5  # more than this share of the boxes lost in DSM holes is an error, not a warning


def lost_in_holes(failed: pd.DataFrame, boxes: int, holes: dict, cfg: PlantProjectionConfig, out: Path) -> None:
    """Boxes lost because their rays meet the ground in DSM holes larger than ``fill_holes``: a warning naming the
    DSM, the key, the largest hole and the fix; an error (with ``unprojected_boxes.csv``) when they are most of
    the boxes."""
    lost = int((failed["reason"] == STATUS_TEXT[NODATA]).sum())
    if not lost:
        return
    with_holes = {Path(p): h for p, h in holes.items() if h.count}
    largest = max((h.largest for h in with_holes.values()), default=0.0)
    where = ", ".join(f"{p} ({h.count} hole(s), the largest {h.largest:.2f} m across)" for p, h in with_holes.items())
    problem = (
        f"{lost} of {boxes} boxes lost: their rays meet the ground in DSM holes (nodata) larger than fill_holes = "
        f"{cfg.fill_holes:g} m, which are left unfilled: {where or 'the DSM'}"
    )
    fix = (
        f"set fill_holes: {np.ceil(largest * 10) / 10:g} (metres) to fill holes up to the largest from their rims "
        "(right where the ground under them is like the rim's), or fill the DSM's holes in ODM (a denser point "
        "cloud, --dem-gapfill-steps) and re-run"
    )
    dsm = next(iter(with_holes), Path(cfg.dsm) if cfg.dsm is not None else None)
    if lost > MOST_LOST * boxes:
        out.mkdir(parents=True, exist_ok=True)
        report = write_table(failed, out / "unprojected_boxes.csv")  # the why, kept although the run fails
        raise InputError(f"{problem}; each box's reason is in {report}", path=dsm, fix=fix)
    log.warning("%s; %s", problem, fix)


def unknown_images(failed: pd.DataFrame) -> str:
    """``; images not in the reconstruction: a.tif (did you mean 'b'?), ...`` or ``""``."""
    miss = failed[failed["reason"] == NOT_IN_RECONSTRUCTION].drop_duplicates("source_image")
    if not len(miss):
        return ""
    names = [f"{r.source_image}{' (' + r.hint + ')' if r.hint else ''}" for r in miss.head(5).itertuples()]
    return f"; {len(miss)} image(s) not in the reconstruction: {', '.join(names)}{' ...' if len(miss) > 5 else ''}"


def nothing_projected(
    failed: pd.DataFrame, cfg: PlantProjectionConfig, project: ODMProject | PhotoProject, report: Path
) -> InputError:
    """Why no box at all could be projected, and what to change, by the most common reason."""
    counts = failed["reason"].value_counts()
    top = str(counts.index[0])
    why = "; ".join(f"{v} x {k}" for k, v in counts.items())
    problem = f"none of the {len(failed)} boxes could be projected ({why}); each box's reason is in {report}"
    if top == NOT_IN_RECONSTRUCTION:
        some = sorted(project.shot_ids(undistorted=True) or project.shot_ids(undistorted=False))[:3]
        kind = f" or set image_type to auto (it is '{cfg.image_type}');" if cfg.image_type != "auto" else ";"
        return InputError(
            problem + unknown_images(failed),
            path=cfg.predictions,
            fix=f"the image names in the predictions must be the project's (e.g. {', '.join(some)}, "
            f"or their undistorted '<name>.tif'){kind} check that predictions and project are "
            "of the same flight",
        )
    if top == BOX_OUTSIDE_IMAGE:
        return InputError(
            problem,
            path=cfg.predictions,
            fix="check 'image_type' (undistorted or original photos) and that the boxes are in pixels of these images",
        )
    if top == EMPTY_BOX:
        return InputError(problem, path=cfg.predictions, fix="the boxes have no width or height; regenerate them")
    dsm = Path(cfg.dsm) if cfg.dsm is not None else project.path("dsm")
    return InputError(
        problem,
        path=dsm,
        fix="the rays miss the DSM: use the DSM of this ODM project"
        + (" (or leave 'dsm' empty)" if cfg.dsm is not None else "")
        + ", or fill its holes",
    )


def run_evaluation(cfg: PlantProjectionConfig, dest: Path | None = None) -> dict:
    """Score written plants against reference boxes; reads the plants from file so that a projection run
    earlier (or elsewhere) can be evaluated alone (``dest``: the staging folder, where a projection of this
    run wrote its plants)."""
    e = cfg.evaluate
    out = Path(dest or cfg.output_dir)
    plants_path = e.plants or next(
        (p for p in (out / "plants.gpkg", Path(cfg.output_dir) / "plants.gpkg") if p.is_file()), out / "plants.gpkg"
    )
    ortho = e.orthophoto
    if ortho is None and cfg.project is not None:
        p = open_project(cfg.project, cfg.project_type, dsm=cfg.dsm)
        ortho = p.path("orthophoto") if p.has("orthophoto") else None
    predicted, crs = read_plants_boxes(plants_path)
    reference = read_boxes(e.reference, orthophoto=ortho, crs=crs)
    if not len(reference):
        raise InputError(
            "the reference holds no boxes",
            path=e.reference,
            fix="point evaluate.reference at the boxes drawn on the orthophoto",
        )
    metrics = evaluate_boxes(reference, predicted, e.iou_threshold)
    if metrics["share_matched"] == 0:
        r, p = reference, predicted
        raise InputError(
            f"none of the {len(r)} reference boxes overlaps any of the {len(p)} plants (reference "
            f"{r[:, 0].min():.1f}..{r[:, 2].max():.1f} E, {r[:, 1].min():.1f}..{r[:, 3].max():.1f} N; "
            f"plants {p[:, 0].min():.1f}..{p[:, 2].max():.1f} E, {p[:, 1].min():.1f}..{p[:, 3].max():.1f}"
            " N)",
            path=e.reference,
            fix="check that the reference is of this field and in the plants' CRS (a CSV must be in the map CRS)",
        )
    match, iou = metrics.pop("_match"), metrics.pop("_iou")
    write_table(
        pd.DataFrame(
            {
                "reference_index": np.arange(len(reference)),
                "xmin": reference[:, 0],
                "ymin": reference[:, 1],
                "xmax": reference[:, 2],
                "ymax": reference[:, 3],
                "plant_index": match,
                "iou": iou,
            }
        ),
        out / "evaluation_matches.csv",
    )
    metrics.update(reference=str(e.reference), plants=str(e.plants or Path(cfg.output_dir) / "plants.gpkg"))
    write_json(out / "evaluation.json", metrics)
    fig = evaluation_figure(
        out / "evaluation.png", reference, predicted, dict(metrics, _match=match, _iou=iou), ortho, e.figure_pixels
    )
    thr = e.iou_threshold
    log.info(
        "%d reference boxes: %.1f%% matched, %.1f%% with IoU > %g, median IoU %.3f; figure %s",
        metrics["reference_boxes"],
        100 * metrics["share_matched"],
        100 * metrics[f"share_iou_above_{thr:g}"],
        thr,
        metrics["iou_median"],
        fig,
    )
    return metrics


def run(cfg: PlantProjectionConfig) -> dict:
    """Module 8's entry point: project the detections to plants on the map, evaluate them, or both (``mode``).

    All or nothing: a failed run leaves ``output_dir`` as it was (apart from its log and, when no box could be
    projected, the report why).

    Parameters
    ----------
    cfg : PlantProjectionConfig
        The step's settings, as loaded from its YAML config (``8_plant_projection/config.yaml``) or built in Python.

    Returns
    -------
    dict
        ``"projection"`` -> the projection summary (projection_summary.json) and/or ``"evaluation"`` -> the
        scores against the reference boxes (evaluation.json), as ``mode`` asks.
    """
    result = {}
    with staged_outputs(cfg.output_dir) as stage:
        if cfg.mode in ("project", "both"):
            result["projection"] = run_projection(cfg, stage)
        if cfg.mode in ("evaluate", "both"):
            result["evaluation"] = run_evaluation(cfg, stage)
    return result
