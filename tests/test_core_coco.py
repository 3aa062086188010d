"""COCO files (matchplant.core.formats.coco): datasets and predictions round-trip, validation names each problem."""

from __future__ import annotations

import json

import numpy as np
import pytest

from matchplant.core.formats import coco, predictions
from matchplant.core.runtime.errors import InputError


def _dataset():
    ds = coco.new_dataset(["maize", "weed"])
    ds["images"] = [
        {"id": 1, "file_name": "t.png", "width": 100, "height": 80, "source_image": "a.JPG", "x0": 900, "y0": 100}
    ]
    ds["annotations"] = [coco.make_annotation(1, 1, [10, 10, 20, 30]), coco.make_annotation(2, 1, [50, 5, 5, 5], 2)]
    return ds


def test_coco_roundtrip_and_provenance(tmp_path):
    ds = _dataset()
    assert coco.validate_dataset(ds) == []
    p = coco.write_dataset(tmp_path / "d.json", ds)
    again = coco.read_dataset(p)
    assert again["annotations"][0]["area"] == 600
    assert coco.to_source_pixels(again["annotations"][0]["bbox"], again["images"][0]) == [910, 110, 20, 30]
    np.testing.assert_array_equal(coco.boxes_xyxy(again["annotations"]), [[10, 10, 30, 40], [50, 5, 55, 10]])


@pytest.mark.parametrize(
    "mutate, words",
    [
        (lambda d: d["annotations"].append(coco.make_annotation(1, 1, [0, 0, 1, 1])), "duplicate annotation ids"),
        (lambda d: d["annotations"].append(coco.make_annotation(9, 7, [0, 0, 1, 1])), "missing image 7"),
        (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [0, 0, 1, 1], 5)), "unknown category 5"),
        (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [0, 0, 0, 4])), "size 0.0x4.0"),
        (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [90, 70, 30, 30])), "outside t.png"),
    ],
)
def test_coco_validation(tmp_path, mutate, words):
    ds = _dataset()
    mutate(ds)
    problems = coco.validate_dataset(ds)
    assert any(words in p for p in problems)
    p = coco.write_dataset(tmp_path / "d.json", ds)
    with pytest.raises(InputError, match="problem"):
        coco.read_dataset(p)


def test_predictions_roundtrip_and_plain_results(tmp_path):
    ds = _dataset()
    preds = [{"image_id": 1, "category_id": 1, "bbox": [1, 2, 3, 4], "score": 0.9}]
    p = predictions.write_predictions(tmp_path / "p.json", ds["images"], ds["categories"], preds)
    got = predictions.read_predictions(p)
    assert got["images"][0]["source_image"] == "a.JPG" and got["predictions"] == preds
    plain = tmp_path / "r.json"
    plain.write_text(json.dumps(preds))
    with pytest.raises(InputError, match="no image names"):
        predictions.read_predictions(plain)
    d = coco.write_dataset(tmp_path / "d.json", ds)
    assert predictions.read_predictions(plain, images_from=d)["images"][0]["id"] == 1
