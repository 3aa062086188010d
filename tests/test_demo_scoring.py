"""The demo scores the map only on photos the detector never saw (issue 29, point 7): modules 8 and 9 run as
the demo runs them, on detections of the held-out photos only, and the record says which photos were
projected, checked against module 8's own views."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml

from matchplant.core.formats.coco import annotations_by_image, read_dataset
from matchplant.core.formats.predictions import write_predictions
from matchplant.core.runtime.io import read_json
from matchplant.demo import (
    compare_with_truth,
    environment,
    held_out_photos,
    held_out_record,
)
from matchplant.demo_pipeline import map_steps
from matchplant.pipeline import PipelineConfig, run_pipeline


@pytest.mark.slow
def test_scoring_on_a_split_that_excludes_the_training_photos(tiny_field, tmp_path):
    photos = sorted(p.name for p in tiny_field.undistorted_images.glob("*.tif"))
    train, val = photos[::3], photos[1:2]
    summary = {"splits": {"train": {"source_images": train}, "val": {"source_images": val}}}
    held, splits = held_out_photos(summary, photos)
    assert held and not set(held) & set(train + val)
    # stand-in detections: the true boxes of the held-out photos only (as module 7 writes them)
    ds = read_dataset(tiny_field.boxes_undistorted)
    by_image = annotations_by_image(ds)
    images, preds = [], []
    for im in ds["images"]:
        if im["file_name"] in held:
            images.append(
                {
                    "id": im["id"],
                    "file_name": im["file_name"],
                    "width": im["width"],
                    "height": im["height"],
                    "source_image": im["file_name"],
                    "x0": 0,
                    "y0": 0,
                }
            )
            preds += [
                {"id": len(preds) + 1, "image_id": im["id"], "category_id": 1, "bbox": a["bbox"], "score": 0.9}
                for a in by_image[im["id"]]
            ]
    predictions = write_predictions(
        tmp_path / "7_detect" / "predictions.json",
        images,
        [{"id": 1, "name": "plant", "supercategory": "plant"}],
        preds,
    )
    crs = read_json(tiny_field.field_json)["crs"]
    spec = {
        "output_dir": ".",
        "field": str(tiny_field.root),
        "crs": crs,
        "predictions": str(predictions),
        "steps": map_steps(tiny_field.root, "${predictions}"),
    }
    pipe = tmp_path / "pipeline.yaml"
    pipe.write_text(yaml.safe_dump(spec, sort_keys=False))
    run_pipeline(PipelineConfig(pipeline=pipe))
    record = held_out_record(tmp_path, held, splits)
    views = pd.read_csv(tmp_path / "8_plants" / "views.csv")
    assert set(views["image"]) <= set(held)  # module 8 projected no training photo
    assert record["training_photos_projected"] == 0 and record["photos_projected"] == views["image"].nunique()
    assert record["photos"] == held and record["splits"]["train"] == sorted(train)
    scores = compare_with_truth(tmp_path, tiny_field.root)
    evaluation = read_json(tmp_path / "8_plants" / "evaluation.json")
    # every true plant seen by a held-out photo is scored; with true boxes nearly all of them are found
    assert evaluation["share_matched"] > 0.8 and scores["traits"]["matched"] > 0.8 * scores["traits"]["true_plants"]


def test_the_report_names_the_threads_training_used_not_its_own(tmp_path):
    """A demo re-run from module 8 trains nothing: the thread count it reports is the one the training ran with."""
    (tmp_path / "6_train").mkdir()
    (tmp_path / "6_train" / "training_summary.json").write_text(json.dumps({"threads": 3, "device": "cpu"}))
    env = environment(tmp_path)
    assert env["torch_threads"] == 3 and env["device"] == "cpu"
    assert environment(tmp_path / "none")["torch_threads"] is None  # no training: said, not guessed
