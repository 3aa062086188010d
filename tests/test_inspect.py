"""``matchplant inspect``: object sizes in pixels and the settings they call for (issue 16)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from matchplant.cli import main as cli_main
from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.detection.objects import recommend, size_stats, tiling_note


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
    assert s["width"]["p50"] == pytest.approx(np.percentile(w, 50), abs=0.01)  # independent numpy check
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


def test_photos_smaller_than_the_tile_are_not_tiled():
    """Issue 28: 40 px objects call for ~768 px tiles; photos of about 400 px are then kept whole (one tile each),
    not cut into four overlapping 320 px tiles that repeat their pixels."""
    stats = size_stats(np.full(100, 40.0), np.full(100, 40.0))
    sizes = [(383, 412), (416, 345), (400, 400)]
    a = recommend(stats, sizes)
    assert 8 * 40 * 1.1 > 345 and a["tile_size"] == 416  # the preferred tile exceeds every photo
    assert a["min_size"] == a["max_size"] == 416 and a["median_object_px_in_detector"] == 40
    assert "no tiling" in tiling_note(a, sizes)


def test_inspect_without_boxes_is_a_clear_error(tmp_path, capsys):
    coco = _dataset(tmp_path / "empty.json", [])
    assert cli_main(["inspect", str(coco)]) == 2
    assert "no boxes" in capsys.readouterr().err


def _photos_and_tiles(tmp_path, size=(512, 384), n=40, tile=128, overlap=48):
    """Two synthetic photos with known plants, and module 5's tiles of them."""
    from matchplant.core.runtime.config import load_config
    from matchplant.detection.synth import make_photo
    from matchplant.img_splitter.config import ImgSplitterConfig
    from matchplant.img_splitter.run import run as run_tiling

    ds = new_dataset(["plant"])
    for k, name in enumerate(("p0.png", "p1.png")):
        boxes = make_photo(tmp_path / "photos" / name, *size, n_plants=n, radius=(8, 14), seed=20 + k)
        ds["images"].append({"id": k + 1, "file_name": name, "width": size[0], "height": size[1]})
        for b in boxes:
            ds["annotations"].append(
                make_annotation(len(ds["annotations"]) + 1, k + 1, [b[0], b[1], b[2] - b[0], b[3] - b[1]])
            )
    write_dataset(tmp_path / "ann.json", ds)
    run_tiling(
        load_config(
            ImgSplitterConfig,
            None,
            [
                f"images={tmp_path / 'photos'}",
                f"annotations={tmp_path / 'ann.json'}",
                f"output_dir={tmp_path / 'tiles'}",
                f"tile_size={tile}",
                f"overlap={overlap}",
                "split=[1.0, 0.0, 0.0]",
                "negative_share=1",
                "workers=1",
            ],
        )
    )
    return tmp_path / "ann.json", tmp_path / "tiles" / "train.json"


def test_tiles_give_the_advice_of_their_photos(tmp_path, capsys):
    """Issue 28: the same advice from the photos and from module 5's tiles of them (a plant in several tiles is
    one plant, the photo size comes from the tiles)."""
    photos, tiles = _photos_and_tiles(tmp_path)
    reports = {}
    for name, coco in (("photos", photos), ("tiles", tiles)):
        assert cli_main(["inspect", str(coco), "--report", str(tmp_path / f"{name}.json")]) == 0
        reports[name] = json.loads((tmp_path / f"{name}.json").read_text())
    printed = capsys.readouterr().out
    assert "distinct plants on 2 photo(s)" in printed
    a, b = reports["photos"], reports["tiles"]
    assert json.loads((tiles).read_text())["annotations"].__len__() > a["objects_px"]["boxes"]  # copies in tiles
    assert b["objects_px"]["boxes"] == a["objects_px"]["boxes"] == 80
    assert b["image_sizes"] == a["image_sizes"] == [[512, 384]]
    for key in ("tile_size", "overlap", "min_size", "anchor_sizes", "aspect_ratios", "tiling"):
        assert b["recommended"][key] == a["recommended"][key], key
    assert b["objects_px"]["sqrt_area"] == pytest.approx(a["objects_px"]["sqrt_area"], abs=0.05)


def test_a_tile_equal_to_the_photo_is_called_no_tiling(tmp_path, capsys):
    rng = np.random.default_rng(1)
    w, h = rng.normal(110, 10, 200), rng.normal(110, 10, 200)  # large plants: tile capped at the photo side
    coco = _dataset(tmp_path / "a.json", zip(w, h), image=(1024, 1024))
    assert cli_main(["inspect", str(coco)]) == 0
    out = capsys.readouterr().out
    assert "tile_size: 1024" in out and "no tiling, each photo is one whole tile" in out
    # smaller plants on the same photos: several tiles per photo, and said so
    coco = _dataset(tmp_path / "b.json", zip(w / 4, h / 4), image=(1024, 1024))
    assert cli_main(["inspect", str(coco)]) == 0
    out = capsys.readouterr().out
    assert "no tiling" not in out and "tiles per photo (1024x1024)" in out


@pytest.mark.parametrize(
    "breakage, said",
    [
        (lambda ds: ds["annotations"][1].pop("bbox"), "annotation 2: no 'bbox'"),
        (lambda ds: ds["annotations"][0].update(bbox="10, 10, 40, 40"), "'bbox' = '10, 10, 40, 40' (str)"),
        (lambda ds: ds["images"][0].pop("width"), "no valid 'width'/'height'"),
        (lambda ds: ds["images"][0].update(height="3648"), "no valid 'width'/'height'"),
    ],
)
def test_broken_coco_structure_is_a_clear_error(tmp_path, capsys, breakage, said):
    coco = _dataset(tmp_path / "a.json", [(40, 40)] * 3)
    ds = json.loads(coco.read_text())
    breakage(ds)
    coco.write_text(json.dumps(ds))
    assert cli_main(["inspect", str(coco)]) == 2
    err = capsys.readouterr().err
    assert said in err and "a.json" in err and "fix:" in err and "Traceback" not in err
