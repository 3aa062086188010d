"""``matchplant inspect``: object sizes in pixels and the settings they call for (issue 16)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from matchplant.cli import main as cli_main
from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.detection.objects import recommend, size_stats


def _dataset(path, sizes_wh, image=(5472, 3648)):
    ds = new_dataset(["plant"])
    ds["images"].append({"id": 1, "file_name": "a.jpg", "width": image[0], "height": image[1]})
    for i, (w, h) in enumerate(sizes_wh):
        ds["annotations"].append(make_annotation(i + 1, 1, [10, 10, w, h]))
    return write_dataset(path, ds)


def test_inspect_reports_sizes_and_advice(tmp_path, capsys):
    rng = np.random.default_rng(0)
    w, h = rng.normal(46, 8, 500), rng.normal(40, 6, 500)
    coco = _dataset(tmp_path / "a.json", zip(w, h))
    report = tmp_path / "report.json"
    assert cli_main(["inspect", str(coco), "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "recommended" in printed and "tile_size: 576    overlap: 72" in printed
    r = json.loads(report.read_text())
    s = r["objects_px"]
    assert s["boxes"] == 500
    assert s["width"]["p50"] == pytest.approx(np.percentile(w, 50), abs=0.01)       # independent numpy check
    assert s["sqrt_area"]["p5"] == pytest.approx(np.percentile(np.sqrt(w * h), 5), abs=0.01)
    a = r["recommended"]
    # ~40-46 px plants (longest 1 %: 63 px): overlap above the largest plants, tile 8x it, no enlargement
    assert np.percentile(np.maximum(w, h), 99) <= a["overlap"] == 72 and a["tile_size"] == 576
    assert a["min_size"] == 576 and a["min_size_floor"] <= 352
    first = a["anchor_sizes"]["fasterrcnn_resnet50_fpn"][0][0]
    assert 20 <= first <= 35 and a["anchor_sizes"]["fasterrcnn_resnet50_fpn"][1][0] == pytest.approx(2 * first, abs=1)


def test_small_objects_are_enlarged_and_tiles_fit_the_photos():
    stats = size_stats(np.full(100, 12.0), np.full(100, 12.0))
    a = recommend(stats, [(400, 300)])
    assert a["min_size"] >= 2 * a["tile_size"] and a["median_object_px_in_detector"] >= 24
    assert a["tile_size"] <= 300


def test_inspect_without_boxes_is_a_clear_error(tmp_path, capsys):
    coco = _dataset(tmp_path / "empty.json", [])
    assert cli_main(["inspect", str(coco)]) == 2
    assert "no boxes" in capsys.readouterr().err
