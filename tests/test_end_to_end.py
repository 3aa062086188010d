"""``matchplant run`` over modules 0-9 on the tiny synthetic field, checked against its truth; then resume
after a failed step.

The detector is trained for one short epoch only (its accuracy is tested in test_model_train.py); module 8
projects the ground-truth image boxes written as a plain COCO results list, so that the map positions
and module 9's heights can be checked against the truth exactly.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from matchplant.cli import run_module
from matchplant.core.runtime.errors import MatchPlantError
from matchplant.pipeline import PipelineConfig, run_pipeline

# every test shares the season's run of all ten steps (over a minute)
pytestmark = pytest.mark.slow


def pipeline(field, crs: str) -> dict:
    return {
        "output_dir": "run",
        "field": str(field),
        "crs": crs,
        "steps": [
            {
                "name": "gps",
                "module": "gps_embed",
                "config": {
                    "images": "${field}/images_nogps",
                    "gnss_log": "${field}/gnss/events.txt",
                    "log_crs": "${crs}",
                },
            },
            {
                "name": "gcp",
                "module": "gcp_finder",
                "config": {
                    "images": "${gps.output_dir}/images",
                    "survey": "${field}/gcp/gcp_survey.csv",
                    "survey_crs": "${crs}",
                    "auto": True,
                },
            },
            {"name": "odm", "module": "odm_runner", "config": {"project_dir": "${field}", "check_only": True}},
            {"name": "select", "module": "min_img_finder", "config": {"project_dir": "${field}"}},
            {
                "name": "annotate",
                "module": "bbox_drawer",
                "config": {
                    "images": "${select.output_dir}/images",
                    "import_coco": "${field}/truth/boxes_undistorted.json",
                    "min_score": 0.0,
                },
            },
            {
                "name": "tiles",
                "module": "img_splitter",
                "config": {
                    "images": "${select.output_dir}/images",
                    "annotations": "${annotate.output_dir}/annotations.json",
                    "tile_size": 128,
                    "overlap": 32,
                    "split": [0.5, 0.25, 0.25],
                    "workers": 1,
                },
            },
            {
                "name": "train",
                "module": "train",
                "config": {
                    "train_json": "${tiles.output_dir}/train.json",
                    "val_json": "${tiles.output_dir}/val.json",
                    "model": {
                        "architecture": "fasterrcnn_mobilenet_v3_large_fpn",
                        "pretrained": "none",
                        "min_size": 128,
                        "max_size": 128,
                        "rpn": {
                            "pre_nms_top_n_train": 200,
                            "post_nms_top_n_train": 100,
                            "pre_nms_top_n_test": 100,
                            "post_nms_top_n_test": 100,
                        },
                        "roi": {"batch_size_per_image": 32},
                    },
                    "epochs": 1,
                    "batch_size": 4,
                    "num_workers": 0,
                    "warmup_iters": 2,
                    "save_every": 0,
                },
            },
            {
                "name": "detect",
                "module": "model_test",
                "config": {
                    "checkpoint": "${train.output_dir}/checkpoints/last.pt",
                    "evaluate": {"dataset_json": "${tiles.output_dir}/test.json", "drawn_images": 1},
                    "detect": {
                        "images": "${select.output_dir}/images",
                        "tile_size": 128,
                        "overlap": 32,
                        "score_threshold": 0.0,
                        "drawn_images": 1,
                    },
                },
            },
            {
                "name": "plants",
                "module": "project_boxes",
                "config": {
                    "project": "${field}",
                    "predictions": "${truth_predictions}",
                    "images_from": "${field}/truth/boxes_undistorted.json",
                    "mode": "both",
                    "evaluate": {"reference": "${field}/truth/map_boxes.csv"},
                },
            },
            {
                "name": "stats",
                "module": "stat_extractor",
                "config": {
                    "polygons": "${plants.output_dir}/plants.gpkg",
                    "rasters": {
                        "dsm": "${field}/odm_dem/dsm.tif",
                        "dtm": "${field}/odm_dem/dtm.tif",
                        "multispectral": "${field}/multispectral/multispectral.tif",
                    },
                },
            },
        ],
    }


@pytest.fixture(scope="module")
def season(tiny_field, tmp_path_factory):
    import torch

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("season")
    truth = json.loads(tiny_field.boxes_undistorted.read_text())
    results = [
        {"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"], "score": 1.0}
        for a in truth["annotations"]
    ]
    (root / "truth_predictions.json").write_text(json.dumps(results))
    crs = json.loads(tiny_field.field_json.read_text())["crs"]
    spec = pipeline(tiny_field.root, crs)
    spec["truth_predictions"] = str(root / "truth_predictions.json")
    pipe = root / "pipeline.yaml"
    pipe.write_text(yaml.safe_dump(spec, sort_keys=False))
    first = run_pipeline(PipelineConfig(pipeline=pipe))
    return root, pipe, first, tiny_field


def test_every_step_runs_and_chains(season):
    root, pipe, first, field = season
    assert list(first.values()) == ["ran"] * 10
    run = root / "run"
    for f in (
        "gps/match_report.csv",
        "gcp/gcp_list.txt",
        "odm/odm_manifest.json",
        "select/selected_images.csv",
        "annotate/annotations.json",
        "tiles/train.json",
        "train/checkpoints/last.pt",
        "detect/predictions.json",
        "plants/plants.gpkg",
        "stats/stats.csv",
    ):
        assert (run / f).is_file(), f


def test_outputs_agree_with_the_truth(season):
    root, pipe, first, field = season
    run = root / "run"
    # module 0: every image matched, at the position the generator wrote into the raw image's EXIF
    with open(run / "gps" / "match_report.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(list(field.images.glob("*.JPG"))) and all(r["status"] == "matched" for r in rows)
    for r in rows:
        lat, lon = _exif_latlon(field.images / r["image"])
        assert abs(float(r["latitude"]) - lat) < 1e-7 and abs(float(r["longitude"]) - lon) < 1e-7
    # module 8 (from the true image boxes): plants on the map where the truth has them
    ev = json.loads((run / "plants" / "evaluation.json").read_text())
    assert ev["share_matched"] >= 0.99 and ev["share_iou_above_0.5"] >= 0.95 and ev["iou_median"] >= 0.85
    # module 9: each plant's CHM maximum is close to a true plant height
    heights = {}
    with open(field.plants_csv, newline="") as fh:
        for r in csv.DictReader(fh):
            heights[int(r["id"])] = float(r["height"])
    with open(run / "stats" / "stats.csv", newline="") as fh:
        chm = np.array([float(r["chm_max"]) for r in csv.DictReader(fh) if r.get("chm_max")])
    assert len(chm) >= 0.9 * len(heights)
    true = np.array(sorted(heights.values()))
    assert abs(np.median(chm) - np.median(true)) < 0.05
    # module 9's canopy: every plant outlined on the CHM; over the canopy, NDVI is the leaves' own 0.8
    # (the generator's leaf reflectance), with no soil mixed in as in a box mean
    assert (run / "stats" / "outlines.gpkg").is_file()
    with open(run / "stats" / "stats.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("outline_flag") == ""]
    assert len(rows) >= 0.9 * len(heights)
    canopy = np.array([float(r["ndvi_canopy_mean"]) for r in rows])
    box = np.array([float(r["ndvi_mean"]) for r in rows])
    assert np.median(canopy) > 0.79 and np.median(box) < 0.7


def _exif_latlon(path) -> tuple[float, float]:
    import piexif

    gps = piexif.load(str(path))["GPS"]

    def deg(v, ref):
        d = sum(n / q / 60**i for i, (n, q) in enumerate(v))
        return -d if ref in (b"S", b"W") else d

    return (
        deg(gps[piexif.GPSIFD.GPSLatitude], gps[piexif.GPSIFD.GPSLatitudeRef]),
        deg(gps[piexif.GPSIFD.GPSLongitude], gps[piexif.GPSIFD.GPSLongitudeRef]),
    )


def test_rerun_skips_and_a_failed_step_resumes(season, tmp_path):
    root, pipe, first, field = season
    again = run_pipeline(PipelineConfig(pipeline=pipe))
    assert set(again.values()) == {"up to date"}
    # break the detection step: the steps before it stay up to date and their files untouched
    broken = yaml.safe_load(pipe.read_text())
    broken["steps"][7]["config"]["checkpoint"] = "${train.output_dir}/checkpoints/missing.pt"
    bad = root / "broken.yaml"
    bad.write_text(yaml.safe_dump(broken, sort_keys=False))
    before = (root / "run" / "train" / "checkpoints" / "last.pt").stat().st_mtime_ns
    with pytest.raises(MatchPlantError, match="step 'detect'"):
        run_pipeline(PipelineConfig(pipeline=bad))
    assert (root / "run" / "train" / "checkpoints" / "last.pt").stat().st_mtime_ns == before
    # from the command line: one message, exit code 2, then --from re-runs the last two steps only
    assert run_module("run", [str(bad)]) == 2
    assert run_module("run", [str(pipe), "--from", "plants"]) == 0
    summary = json.loads((root / "run" / ".pipeline" / "plants.json").read_text())
    assert summary["module"] == "project_boxes"
