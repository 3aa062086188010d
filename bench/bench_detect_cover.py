"""What ``detect.cover`` (module 7 on the photos that see every point k times) costs module 8, and what it saves.

    python bench/bench_detect_cover.py                 # the demo's field (simfield 'small', seed 0), k = 1, 2, 3
    python bench/bench_detect_cover.py --field DIR     # an existing synthetic field
    python bench/bench_detect_cover.py --survey-only   # only the 1,000-photo 20 MP survey's estimates
    python bench/bench_detect_cover.py --field demo_output/field --predictions demo_output/7_detect/predictions.json

1. **Multi-view cost, on the demo's field.** The detector is replaced by the field's true boxes (every plant
   visible in every undistorted photo, score 1), so what is measured is the geometry's cost of fewer views, not
   a detector's misses. For each k the photos are chosen by module 7's own cover
   (:func:`matchplant.model_test.cover.choose`, from the footprints on the DSM), their boxes projected and merged
   by module 8 (``project_predictions`` + ``merge_views``, module 8's defaults), and the plants compared with the
   all-photo run's: the share of its plants that the k run holds at IoU > 0.5 (one-to-one), and each run's
   share of the true plants at IoU > 0.5.
2. **Estimate on a survey-like flight.** simfield's flight planner lays out a survey of 5472 x 3648 px photos
   (its 'realistic' camera: 20 m, 85 % front and side overlap) over a field sized for about 1,000 photos; their
   footprints are traced on the terrain (no image rendered), the cover chosen for each k, and module 7's plan
   (:func:`matchplant.model_test.estimate.plan`: tiles and network input) gives the cover's estimate against all
   photos'. The seconds use the light model's measured CPU rate (``architectures.py``); the ratio does not
   depend on it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import shapely

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.footprints import border_pixels
from matchplant.core.formats.odm import ODMProject
from matchplant.detection.architectures import get_architecture
from matchplant.model_test.cover import choose, incidence, multi_cover
from matchplant.model_test.estimate import input_pixels, plan
from matchplant.plant_projection.config import PlantProjectionConfig
from matchplant.plant_projection.evaluation import evaluate_boxes
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.views import project_predictions
from matchplant.simfield.config import PRESETS
from matchplant.simfield.flight import ground_hit, make_camera, plan_flight
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.scene import Terrain

BOX = ["xmin", "ymin", "xmax", "ymax"]
LITE = "fasterrcnn_resnet18_fpn_lite"


def demo_field(given: str | None) -> FieldPaths:
    """The given field, else the demo's small field (generated once in the temp folder)."""
    if given:
        return FieldPaths(Path(given))
    root = Path(tempfile.gettempdir()) / "matchplant_bench_fields" / "small_seed0"
    if not (root / "truth" / "map_boxes.csv").is_file():
        from matchplant.simfield import generate_field

        print(f"generating the small synthetic field in {root} (once) ...", flush=True)
        generate_field(preset="small", seed=0, out=root)
    return FieldPaths(root)


def true_boxes(f: FieldPaths) -> dict:
    """The field's true boxes in every undistorted photo as module 7's predictions (score 1)."""
    ds = read_dataset(f.boxes_undistorted, validate=False)
    return {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }


def plants_from(project: ODMProject, preds: dict, names: set[str] | None) -> pd.DataFrame:
    """Module 8's plants (its defaults) from the boxes of the photos ``names`` (None: every photo)."""
    images = [im for im in preds["images"] if names is None or im["file_name"] in names]
    ids = {im["id"] for im in images}
    subset = dict(preds, images=images, predictions=[a for a in preds["predictions"] if a["image_id"] in ids])
    views, _ = project_predictions(project, subset, ProjectionSettings.from_config(PlantProjectionConfig()))
    return merge_views(views)


def multi_view_cost(f: FieldPaths, ks: list[int], predictions: Path | None = None) -> None:
    """``predictions``: a module 7 ``predictions.json`` on some of the field's undistorted photos (a trained
    detector's boxes, scores and misses included) in place of the true boxes; the cover is chosen among its
    photos."""
    preds = true_boxes(f) if predictions is None else json.loads(Path(predictions).read_text())
    project = ODMProject(f.root)
    truth = pd.read_csv(f.map_boxes)[BOX].to_numpy()
    names = {im["file_name"] for im in preds["images"]}
    files = sorted(p for p in f.undistorted_images.glob("*.tif") if p.name in names)
    t0 = time.perf_counter()
    every = plants_from(project, preds, None)
    print(
        f"field: {f.root} ({len(files)} photos, {len(truth)} true plants; "
        f"{'true boxes' if predictions is None else predictions}; module 8 in {time.perf_counter() - t0:.1f} s)"
    )
    ref = evaluate_boxes(truth, every[BOX].to_numpy())
    print(
        f"{'photos':>14} {'n':>4} {'plants':>7} {'views':>6} {'kept of all-photo plants (IoU>0.5)':>36} "
        f"{'true plants IoU>0.5':>20}"
    )
    print(
        f"{'all':>14} {len(files):4d} {len(every):7d} {np.median(every['views']):6.0f} {'100.0 %':>36} "
        f"{100 * ref['share_iou_above_0.5']:19.1f} %"
    )
    for k in ks:
        cover = choose(files, k, f.root)
        plants = plants_from(project, preds, {p.name for p in cover.files})
        kept = evaluate_boxes(every[BOX].to_numpy(), plants[BOX].to_numpy())
        true = evaluate_boxes(truth, plants[BOX].to_numpy())
        print(
            f"{'cover k=' + str(k):>14} {len(cover.files):4d} {len(plants):7d} {np.median(plants['views']):6.0f} "
            f"{100 * kept['share_iou_above_0.5']:34.1f} % {100 * true['share_iou_above_0.5']:19.1f} %",
            flush=True,
        )


def survey_footprints(photos: int, seed: int = 0) -> tuple[list, tuple[int, int]]:
    """Footprints of a survey-like flight of about ``photos`` 20 MP photos (simfield's planner, no rendering)."""
    s = PRESETS["realistic"]
    cam = make_camera(s)
    scale = max(cam.width, cam.height)
    foot_w, foot_h = s.altitude * cam.width / (s.focal * scale), s.altitude * cam.height / (s.focal * scale)
    step_w, step_h = (1 - s.overlap_side) * foot_w, (1 - s.overlap_front) * foot_h
    # as many flight lines as stations per line, in area: lines x stations ~ photos
    lines = max(1, round(np.sqrt(photos * step_h / step_w)))
    per_line = max(1, round(photos / lines))
    s = dataclasses.replace(
        s, field_width=foot_w + (lines - 1) * step_w - 1e-6, field_length=foot_h + (per_line - 1) * step_h - 1e-6
    )
    rng = np.random.default_rng(seed)
    terrain = Terrain.random(s, rng)
    polygons = []
    uv = border_pixels(cam.width, cam.height, 16)
    for e in plan_flight(s, terrain, cam, rng):
        d = e.shot.ray_directions(uv)
        p = e.shot.center[None, :] + ground_hit(e.shot.center, d, terrain)[:, None] * d
        polygons.append(shapely.Polygon(p[:, :2]))
    return polygons, (cam.width, cam.height)


def survey_estimate(photos: int, ks: list[int], tile: int = 1024, overlap: int = 128) -> None:
    """Print the tiles, network input and estimated CPU hours of detecting on every photo and on each k-cover."""
    polygons, size = survey_footprints(photos)
    model = {"min_size": 800, "max_size": 1333}
    # the light model's CPU rate is per photo megapixel on a 1024 px tile: per network input megapixel here
    rate = get_architecture(LITE).cpu_seconds_per_megapixel
    per_input = rate * 1024 * 1024 / input_pixels(1024, 1024, 800, 1333) if rate else None
    whole = plan([size] * len(polygons), tile, overlap, model)
    hours = lambda p: f"{per_input * p['input_megapixels'] / 3600:.1f} h" if per_input else "-"  # noqa: E731
    print(
        f"\nsurvey: {len(polygons)} photos of {size[0]}x{size[1]} px ({size[0] * size[1] / 1e6:.1f} MP), "
        f"85 % overlap; tiles of {tile} px ({overlap} overlap), network input {model['min_size']} px; "
        f"{LITE} at {rate} s per photo megapixel (one core)"
    )
    print(f"{'photos':>14} {'n':>5} {'tiles':>7} {'input MP':>9} {'estimate':>9} {'of all':>7}")
    print(
        f"{'all':>14} {len(polygons):5d} {whole['tiles']:7d} {whole['input_megapixels']:9.0f} {hours(whole):>9} "
        f"{'100 %':>7}"
    )
    t0 = time.perf_counter()
    A = incidence(polygons)
    print(f"  ({A.shape[1]} field points, {time.perf_counter() - t0:.1f} s)")
    for k in ks:
        t0 = time.perf_counter()
        chosen = multi_cover(A, k)
        p = plan([size] * len(chosen), tile, overlap, model)
        share = p["input_megapixels"] / whole["input_megapixels"]
        print(
            f"{'cover k=' + str(k):>14} {len(chosen):5d} {p['tiles']:7d} {p['input_megapixels']:9.0f} "
            f"{hours(p):>9} {100 * share:6.1f} % (chosen in {time.perf_counter() - t0:.1f} s)",
            flush=True,
        )


def main(argv: list[str] | None = None) -> None:
    """Parse the options, measure the multi-view cost on the field and print the survey's estimates."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--field", help="an existing synthetic field folder (default: the demo's, generated once)")
    ap.add_argument("--k", type=int, nargs="+", default=[1, 2, 3], help="cover multiplicities to measure")
    ap.add_argument("--photos", type=int, default=1000, help="photos of the survey-like flight")
    ap.add_argument("--survey-only", action="store_true", help="skip the demo field's module 8 runs")
    ap.add_argument(
        "--predictions",
        type=Path,
        help="module 7's predictions.json on the field's photos (a trained detector) in place of the true boxes",
    )
    args = ap.parse_args(argv)
    if not args.survey_only:
        multi_view_cost(demo_field(args.field), args.k, args.predictions)
    survey_estimate(args.photos, args.k)


if __name__ == "__main__":
    main(sys.argv[1:])
