"""``make demo``: MatchPlant end to end on a generated field, without a screen, with a report.

1. generates the ``small`` synthetic field (an ODM-shaped project with exact ground truth);
2. writes ``pipeline.yaml`` chaining modules 0 to 9 and runs it with ``matchplant run`` (ODM's outputs
   come from the generator; the ground-truth boxes stand in for hand annotation; a CPU-sized detector
   trains for a few minutes);
3. writes ``report.md`` with the coverage map, training curves, AP, the projected plants over the
   orthophoto, and per-plant height and NDVI against the truth.

Run ``python -m matchplant.demo --help`` for the options. Re-running skips the finished steps.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import geopandas as gpd
import numpy as np
import yaml
from scipy.spatial import cKDTree

from matchplant.core.config import load_config
from matchplant.core.errors import MatchPlantError
from matchplant.core.gui import figure
from matchplant.core.io import atomic_path, write_text
from matchplant.core.log import get_logger, setup_console
from matchplant.pipeline import PipelineConfig, read_pipeline, run_pipeline
from matchplant.simfield import generate_field
from matchplant.spatial_stat_extractor.config import StatsConfig
from matchplant.spatial_stat_extractor.run import run as run_stats

log = get_logger("demo")


def _step(name: str, module: str, **config) -> dict:
    return {"name": name, "module": module, "config": config}


def pipeline_spec(field: Path, crs: str, *, minutes: float, pretrained: str, tile: int) -> dict:
    """The demo's pipeline: every module, each reading the files the one before wrote."""
    net = int(round(tile * 2.5))
    # small plants (about 20 px) need the tiles enlarged 2.5x for MobileNet's coarse feature maps; anchors
    # are in the enlarged pixels. A 128 px tile holds at most ~40 plants: far fewer proposals than
    # torchvision's defaults (2000/1000) keep the box head cheap on a CPU
    model = {"architecture": "fasterrcnn_mobilenet_v3_large_fpn", "pretrained": pretrained,
             "min_size": net, "max_size": net, "anchor_sizes": [[net // 8, net // 4, net // 2]] * 3,
             "rpn": {"pre_nms_top_n_train": 1000, "post_nms_top_n_train": 400,
                     "pre_nms_top_n_test": 300, "post_nms_top_n_test": 100},
             "roi": {"batch_size_per_image": 64}}
    steps = [
        _step("0_gps", "gps_embeder", images="${field}/images_nogps", gnss_log="${field}/gnss/events.txt",
              log_crs="${crs}"),
        _step("1_gcp", "gcp_finder", images="${0_gps.output_dir}/images", survey="${field}/gcp/gcp_survey.csv",
              survey_crs="${crs}", auto=True),
        _step("2_odm", "odm_runner", project_dir="${field}", check_only=True),
        _step("3_select", "min_img_finder", project_dir="${field}"),
        _step("4_annotate", "bbox_drawer", images="${3_select.output_dir}/images",
              import_coco="${field}/truth/boxes_undistorted.json", min_score=0.0),
        _step("5_tiles", "img_splitter", images="${3_select.output_dir}/images",
              annotations="${4_annotate.output_dir}/annotations.json", tile_size=tile, overlap=tile // 4,
              negative_share=0.2, split=[0.55, 0.15, 0.3]),
        _step("6_train", "model_train", train_json="${5_tiles.output_dir}/train.json",
              val_json="${5_tiles.output_dir}/val.json", model=model, epochs=30, max_minutes=minutes, batch_size=4,
              num_workers=0, warmup_iters=20, step_size=20, save_every=0,
              lr={"backbone": 0.02, "fpn": 0.02, "rpn": 0.02, "roi_heads": 0.02}),
        _step("7_detect", "model_test", checkpoint="${6_train.output_dir}/checkpoints/best.pt",
              evaluate={"dataset_json": "${5_tiles.output_dir}/test.json"},
              detect={"images": "${3_select.output_dir}/images", "tile_size": tile, "overlap": tile // 4}),
        _step("8_plants", "plant_projection", project="${field}", predictions="${7_detect.output_dir}/predictions.json",
              mode="both", evaluate={"reference": "${field}/truth/map_boxes.csv"}),
        _step("9_stats", "spatial_stat_extractor", polygons="${8_plants.output_dir}/plants.gpkg",
              rasters={"dsm": "${field}/odm_dem/dsm.tif", "dtm": "${field}/odm_dem/dtm.tif",
                       "multispectral": "${field}/multispectral/multispectral.tif"}),
    ]
    return {"output_dir": ".", "field": str(field), "crs": crs, "steps": steps}


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def compare_with_truth(out: Path, field: Path) -> dict:
    """Per-plant height and NDVI of the projected plants against the truth, matched by position."""
    plants = gpd.read_file(out / "8_plants" / "plants.gpkg")
    stats = {}
    with open(out / "9_stats" / "stats.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            stats[str(row[next(iter(row))])] = row
    truth = {}
    with open(field / "truth" / "plants.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            truth[int(row["id"])] = row
    tid = np.array(list(truth))
    txy = np.array([[float(truth[i]["x"]), float(truth[i]["y"])] for i in tid])
    tree = cKDTree(txy)
    id_col = next(c for c in ("plant_id", "id") if c in plants.columns)
    cent = np.column_stack([plants.geometry.centroid.x, plants.geometry.centroid.y])
    dist, idx = tree.query(cent, distance_upper_bound=0.15)
    # truth NDVI: the same statistics over the true plant boxes (the generator's plant reflectance)
    truth_cfg = load_config(StatsConfig, None, [
        f"polygons={field / 'truth' / 'map_boxes.csv'}", f"output_dir={out / 'report' / 'truth_stats'}",
        f"polygons_crs={json.loads((field / 'truth' / 'field.json').read_text())['crs']}",
        f"rasters.multispectral={field / 'multispectral' / 'multispectral.tif'}", "write_polygons=false"])
    run_stats(truth_cfg)
    truth_ndvi = {}
    with open(out / "report" / "truth_stats" / "stats.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            key = next(iter(row))
            truth_ndvi[int(float(row[key]))] = float(row["ndvi_mean"])
    rows = []
    for k, pid in enumerate(plants[id_col]):
        if not np.isfinite(dist[k]):
            continue
        t = int(tid[idx[k]])
        s = stats.get(str(pid))
        if s is None or not s.get("chm_max"):
            continue
        rows.append((float(truth[t]["height"]), float(s["chm_max"]), truth_ndvi.get(t, np.nan), float(s["ndvi_mean"])))
    arr = np.array(rows, dtype=float).reshape(-1, 4)
    ok = np.isfinite(arr).all(axis=1)
    arr = arr[ok]
    result = {"plants_projected": int(len(plants)), "plants_true": int(len(truth)),
              "matched_to_truth": int(len(arr)),
              "height_r": _pearson(arr[:, 0], arr[:, 1]), "height_mae_m": float(np.mean(np.abs(arr[:, 1] - arr[:, 0]))),
              "height_bias_m": float(np.mean(arr[:, 1] - arr[:, 0])),
              "ndvi_r": _pearson(arr[:, 2], arr[:, 3]), "ndvi_mae": float(np.mean(np.abs(arr[:, 3] - arr[:, 2])))}
    _scatter(out / "report" / "traits_vs_truth.png", arr)
    return result


def _scatter(path: Path, arr: np.ndarray) -> None:
    fig = figure(headless=True, figsize=(10, 4.5))
    axes = fig.subplots(1, 2)
    for ax, (i, j), name in ((axes[0], (0, 1), "height (m): CHM max"), (axes[1], (2, 3), "NDVI mean")):
        ax.scatter(arr[:, i], arr[:, j], s=8, alpha=0.6)
        lo, hi = np.nanmin(arr[:, [i, j]]), np.nanmax(arr[:, [i, j]])
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_xlabel(f"truth {name}")
        ax.set_ylabel(f"MatchPlant {name}")
        ax.set_title(f"r = {_pearson(arr[:, i], arr[:, j]):.3f}, n = {len(arr)}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def write_report(out: Path, field: Path, timings: dict, compare: dict) -> Path:
    def load(p: Path) -> dict:
        return json.loads(p.read_text()) if p.is_file() else {}

    metrics = load(out / "7_detect" / "metrics.json")
    evaluation = load(out / "8_plants" / "evaluation.json")
    summary = load(out / "6_train" / "training_summary.json")
    selection = load(out / "3_select" / "selection.json")
    gps = load(out / "0_gps" / "match_summary.json")

    def fig(rel: str, caption: str) -> str:
        return f"![{caption}](../{rel})\n\n*{caption}*\n" if (out / rel).is_file() else f"*({caption}: not produced)*\n"

    def num(d: dict, *keys, fmt="{:.3f}") -> str:
        for k in keys:
            v = d.get(k) if isinstance(d, dict) else None
            if isinstance(v, dict):
                d = v
                continue
            if isinstance(v, (int, float)):
                return fmt.format(v)
        return "n/a"

    lines = [
        "# MatchPlant demo report", "",
        f"Generated {time.strftime('%Y-%m-%d %H:%M')} on the `small` synthetic field (`{field}`).", "",
        "## Steps", "", "| step | result | seconds |", "|---|---|---|",
    ]
    for name, (status, secs) in timings.items():
        lines.append(f"| {name} | {status} | {secs:.1f} |")
    lines += ["", "## Georeferencing (module 0)", "",
              f"Images matched to GNSS events: {gps.get('matched', 'n/a')} of {gps.get('images', 'n/a')}; "
              f"estimated clock offset {num(gps, 'clock_offset_s', fmt='{:.2f}')} s.", "",
              "## Coverage (module 3)", "",
              f"Selected images: {selection.get('images_selected', 'n/a')} of {selection.get('images_total', 'n/a')}, "
              f"covering {num(selection, 'coverage_pct', fmt='{:.1f}')} % of the field.", "",
              fig("3_select/coverage.png", "footprints of the selected undistorted images over the field"),
              "## Detector (modules 6 and 7)", "",
              f"Test AP50 = {num(metrics.get('coco', {}), 'AP50', fmt='{:.1%}')}, "
              f"AP = {num(metrics.get('coco', {}), 'AP', fmt='{:.1%}')} "
              f"(trained {summary.get('epochs_done', 'n/a')} epochs in {summary.get('train_time_s', 0) / 60:.1f} min "
              f"on {summary.get('device', 'the CPU')}).", "",
              fig("6_train/training_curves.png", "training loss and validation AP"),
              "## Plants on the map (module 8)", "",
              f"Reference plants matched: {num(evaluation, 'share_matched', fmt='{:.1%}')}; "
              f"with IoU > 0.5: {num(evaluation, 'share_iou_above_0.5', fmt='{:.1%}')}; "
              f"median IoU {num(evaluation, 'iou_median')}.", "",
              fig("8_plants/evaluation.png", "projected plants (red) and true plant boxes (green) over the orthophoto"),
              "## Per-plant traits against the truth (module 9)", "",
              f"Plants projected: {compare.get('plants_projected')}, true plants: {compare.get('plants_true')}, "
              f"matched by position: {compare.get('matched_to_truth')}.", "",
              "| trait | Pearson r | mean absolute error | bias |", "|---|---|---|---|",
              f"| height (CHM max vs true height) | {compare.get('height_r', float('nan')):.3f} | "
              f"{compare.get('height_mae_m', float('nan')):.3f} m | {compare.get('height_bias_m', float('nan')):+.3f} m |",
              f"| NDVI (mean over predicted vs true plant box) | {compare.get('ndvi_r', float('nan')):.3f} | "
              f"{compare.get('ndvi_mae', float('nan')):.3f} | |", "",
              fig("report/traits_vs_truth.png", "per-plant height and NDVI against the truth"), ""]
    path = out / "report" / "report.md"
    write_text(path, "\n".join(lines))
    write_text(out / "report" / "summary.json", json.dumps({"timings": timings, "traits": compare,
                                                              "detector": metrics, "projection": evaluation},
                                                             indent=1, default=str))
    return path


def run_demo(out: Path, *, preset: str = "small", seed: int = 0, minutes: float = 5.0, pretrained: str = "none",
             tile: int = 128, from_step: str = "") -> Path:
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    field = out / "field"
    t0 = time.time()
    meta = field / "truth" / "field.json"
    if not (meta.is_file() and json.loads(meta.read_text()).get("preset") == preset
            and json.loads(meta.read_text()).get("seed") == seed):
        log.info("generating the '%s' synthetic field (seed %d) ...", preset, seed)
        generate_field(preset=preset, seed=seed, out=field)
    t_field = time.time() - t0
    crs = json.loads(meta.read_text())["crs"]
    pipe = out / "pipeline.yaml"
    write_text(pipe, "# written by `make demo` (matchplant/demo.py); run again with: matchplant run pipeline.yaml\n"
               + yaml.safe_dump(pipeline_spec(field, crs, minutes=minutes, pretrained=pretrained, tile=tile),
                                sort_keys=False))
    results = run_pipeline(PipelineConfig(pipeline=pipe, from_step=from_step))
    timings = {"synthetic field": ("generated" if t_field > 1 else "reused", t_field)}
    for name in read_pipeline(pipe)[1]:
        stamp = out / ".pipeline" / f"{name.name}.json"
        secs = json.loads(stamp.read_text()).get("seconds", 0.0) if stamp.is_file() else 0.0
        timings[name.name] = (results.get(name.name, "?"), secs)
    compare = compare_with_truth(out, field)
    report = write_report(out, field, timings, compare)
    log.info("report: %s (%.1f min in all)", report, (time.time() - t0) / 60)
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m matchplant.demo", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("demo_output"), help="output folder (default demo_output)")
    p.add_argument("--preset", default="small", choices=("tiny", "small", "large"), help="synthetic field size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--minutes", type=float, default=5.0, help="time budget for training the detector")
    p.add_argument("--pretrained", default="none", choices=("none", "imagenet", "coco"),
                   help="starting weights (coco needs internet once; none trains from scratch)")
    p.add_argument("--from", dest="from_step", default="", help="re-run from this step on (e.g. 6_train)")
    p.add_argument("--debug", action="store_true")
    args = p.parse_args(argv)
    setup_console()
    try:
        run_demo(args.out, preset=args.preset, seed=args.seed, minutes=args.minutes, pretrained=args.pretrained,
                 from_step=args.from_step)
    except MatchPlantError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
