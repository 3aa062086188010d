"""Module 5 (img_splitter): tiles, recomputed boxes, splits by source image, edge cases, the GUI."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from log_records import log_records, messages
from shapely.geometry import box as shapely_box

from matchplant.core.formats.coco import make_annotation, new_dataset, validate_dataset, write_dataset
from matchplant.core.formats.yolo import coco_to_yolo
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.run import plan_image, run, split_images, tile_grid, tile_origins

ROOT = Path(__file__).resolve().parents[1]


def _dataset(tmp_path: Path, sizes: dict[str, tuple[int, int]], boxes: dict[str, list], suffix_data=None) -> Path:
    """Images with random pixels and a COCO file of the given boxes ([x, y, w, h], category)."""
    d = tmp_path / "images"
    d.mkdir(exist_ok=True)
    ds = new_dataset(["plant", "weed"])
    aid = 1
    for i, (name, (w, h)) in enumerate(sizes.items(), start=1):
        rng = np.random.default_rng(i)
        if not name.startswith("missing"):
            cv2.imwrite(str(d / name), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        ds["images"].append({"id": i, "file_name": name, "width": w, "height": h})
        for bbox, cat in boxes.get(name, []):
            ds["annotations"].append(make_annotation(aid, i, bbox, cat))
            aid += 1
    write_dataset(tmp_path / "annotations.json", ds)
    return tmp_path / "annotations.json"


def _random_boxes(rng, w, h, n):
    out = []
    for _ in range(n):
        bw, bh = rng.uniform(8, 60), rng.uniform(8, 60)
        out.append(([rng.uniform(0, w - bw), rng.uniform(0, h - bh), bw, bh], int(rng.integers(1, 3))))
    return out


def _cfg(tmp_path, **kw) -> ImgSplitterConfig:
    sets = {
        "images": tmp_path / "images",
        "annotations": tmp_path / "annotations.json",
        "output_dir": tmp_path / "out",
        "tile_size": 128,
        "overlap": 20,
        "workers": 1,
        **kw,
    }
    return load_config(ImgSplitterConfig, None, [f"{k}={v}" for k, v in sets.items()])


def _load(out: Path, split: str) -> dict:
    return json.loads((out / f"{split}.json").read_text())


@pytest.fixture
def field(tmp_path):
    rng = np.random.default_rng(0)
    sizes = {f"p{i}.png": (300 + 37 * i, 200 + 11 * i) for i in range(7)}
    sizes["small.png"] = (90, 70)  # smaller than a tile
    sizes["empty.png"] = (260, 140)  # annotated, no plants
    sizes["photo.jpg"] = (250, 210)  # lossy source: tiles become PNG
    boxes = {n: _random_boxes(rng, w, h, 25) for n, (w, h) in sizes.items() if n != "empty.png"}
    boxes["small.png"] = [([10, 10, 30, 20], 1)]
    _dataset(tmp_path, sizes, boxes)
    return tmp_path


def test_folder_config_loads_and_help_works():
    cfg = load_config(ImgSplitterConfig, ROOT / "5_img_splitter" / "config.yaml", strict=False)
    assert (cfg.tile_size, cfg.overlap, cfg.min_visible, cfg.min_box_side) == (1024, 100, 0.3, 10.0)
    assert cfg.split == [0.7, 0.15, 0.15]
    r = subprocess.run(
        [sys.executable, str(ROOT / "5_img_splitter" / "img_splitter.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--gui" in r.stdout


def test_tile_grid_covers_the_image_with_full_tiles():
    assert tile_origins(300, 128, 20).tolist() == [0, 108, 172]
    assert tile_origins(128, 128, 20).tolist() == [0]
    assert tile_origins(90, 128, 20).tolist() == [0]
    g = tile_grid(300, 90, 128, 20)
    assert g.tolist() == [[0, 0, 128, 90], [108, 0, 236, 90], [172, 0, 300, 90]]


def test_every_kept_box_is_its_original_clipped_and_shifted(field):
    cfg = _cfg(field, min_visible=0.3, min_box_side=10, negative_share=1.0)
    summary = run(cfg)
    src = json.loads((field / "annotations.json").read_text())
    src_boxes = {}
    for im in src["images"]:
        src_boxes[im["file_name"]] = [
            (a["bbox"], a["category_id"]) for a in src["annotations"] if a["image_id"] == im["id"]
        ]
    n_tiles = 0
    for split in ("train", "val", "test"):
        ds = _load(cfg.output_dir, split)
        assert not validate_dataset(ds, tolerance=0)
        anns = {}
        for a in ds["annotations"]:
            anns.setdefault(a["image_id"], []).append(a)
        for im in ds["images"]:
            n_tiles += 1
            tile = shapely_box(im["x0"], im["y0"], im["x0"] + im["width"], im["y0"] + im["height"])
            expected = []
            for (x, y, w, h), cat in src_boxes[im["source_image"]]:  # independent geometry: shapely
                inter = tile.intersection(shapely_box(x, y, x + w, y + h))
                if inter.is_empty or inter.area / (w * h) < 0.3:
                    continue
                x1, y1, x2, y2 = inter.bounds
                if x2 - x1 >= 10 and y2 - y1 >= 10:
                    expected.append([x1 - im["x0"], y1 - im["y0"], x2 - x1, y2 - y1, cat])
            got = [a["bbox"] + [a["category_id"]] for a in anns.get(im["id"], [])]
            assert np.allclose(sorted(got), sorted(expected), atol=1e-9) if expected else got == []
            for a in anns.get(im["id"], []):
                assert a["area"] == pytest.approx(a["bbox"][2] * a["bbox"][3])
    assert n_tiles == summary["tiles"]
    assert summary["missing_images"] == []


def test_splits_by_source_image_and_seeded(field):
    cfg = _cfg(field, negative_share=1.0)
    summary = run(cfg)
    owners = {}
    for split in ("train", "val", "test"):
        for im in _load(cfg.output_dir, split)["images"]:
            owners.setdefault(im["source_image"], set()).add(split)
            assert (cfg.output_dir / split / "images" / im["file_name"]).is_file()
    assert all(len(s) == 1 for s in owners.values())  # no photo in two splits
    assert len(owners) == 10
    assert [summary["splits"][k]["images"] for k in ("train", "val", "test")] == [7, 2, 1]
    names = [f"im{i}" for i in range(20)]
    assert split_images(names, [0.7, 0.15, 0.15], seed=3) == split_images(names, [0.7, 0.15, 0.15], seed=3)
    assert split_images(names, [0.7, 0.15, 0.15], seed=3) != split_images(names, [0.7, 0.15, 0.15], seed=4)


def test_spatial_split_keeps_val_and_test_together(tmp_path):
    names = [f"im{i}.png" for i in range(10)]
    positions = {n: (100.0 + 10 * i, 50.0 - 3 * i) for i, n in enumerate(names)}  # a diagonal flight line
    split = split_images(names, [0.6, 0.2, 0.2], positions=positions)
    order = [split[n] for n in names]
    assert order in (["train"] * 6 + ["val"] * 2 + ["test"] * 2, ["test"] * 2 + ["val"] * 2 + ["train"] * 6)


def test_box_across_a_border_is_in_every_tile_where_enough_is_visible(tmp_path):
    # width 300, tile 128, overlap 20: tiles start at x = 0, 108, 172 (one row: height 100)
    box = [96, 30, 50, 40]  # x 96..146: 32/50 in tile 0, 38/50 in tile 108, none in 172
    box2 = [150, 30, 40, 40]  # x 150..190: all in tile 108, 18/40 = 0.45 in tile 172
    box3 = [225, 30, 40, 40]  # x 225..265: 11/40 = 0.275 in tile 108 (dropped), all in 172
    _dataset(tmp_path, {"a.png": (300, 100)}, {"a.png": [(box, 1), (box2, 1), (box3, 1)]})
    cfg = _cfg(tmp_path, tile_size=128, overlap=20, min_visible=0.3, min_box_side=10, split="[1, 0, 0]")
    run(cfg)
    ds = _load(cfg.output_dir, "train")
    per_tile = {
        im["x0"]: sorted(a["bbox"] for a in ds["annotations"] if a["image_id"] == im["id"]) for im in ds["images"]
    }
    assert per_tile == {
        0: [[96, 30, 32, 40]],
        108: [[0, 30, 38, 40], [42, 30, 40, 40]],
        172: [[0, 30, 18, 40], [53, 30, 40, 40]],
    }
    # the paper's name for the threshold: with iou 0.5 the 0.45 piece in tile 172 goes
    cfg = _cfg(tmp_path, iou=0.5, split="[1, 0, 0]")
    run(cfg)
    ds = _load(cfg.output_dir, "train")
    assert sorted(a["bbox"] for a in ds["annotations"] if ds["images"][a["image_id"] - 1]["x0"] == 172) == [
        [53, 30, 40, 40]
    ]


def test_dropped_csv_names_the_limit_that_dropped_each_box(tmp_path):
    """Each dropped box's reason names the limit that applies to it: a box under min_box_side everywhere is
    too small (not "at most 100 % visible"), one cut too thin by every tile is not visible enough."""
    import csv

    tiny = [40, 40, 6, 6]  # whole in a tile, but 6 px < min_box_side 10
    cut = [96, 30, 50, 40]  # x 96..146: 32/50 in tile 0, 38/50 in tile 108, < 0.9 in both
    _dataset(tmp_path, {"a.png": (300, 100)}, {"a.png": [(tiny, 1), (cut, 1), ([150, 30, 40, 40], 1)]})
    cfg = _cfg(tmp_path, tile_size=128, overlap=20, min_visible=0.9, min_box_side=10, split="[1, 0, 0]")
    with log_records("matchplant.img_splitter", logging.WARNING) as records:
        run(cfg)
    rows = list(csv.DictReader(open(cfg.output_dir / "dropped.csv", newline="")))
    assert len(rows) == 2, rows
    text = " | ".join(" ".join(r.values()) for r in rows)
    assert "6x6 px, under min_box_side 10" in text
    assert "at most 76% of it is visible in a tile (min_visible 0.9)" in text
    assert "100%" not in text
    # the console says why, by setting, and which keys keep more (not "2 in no tile")
    (warning,) = [m for m in messages(records) if "not in any tile" in m]
    assert "1 smaller than min_box_side 10 px" in warning and "1 cut by tile edges below min_visible 0.9" in warning
    assert "in no tile" not in warning and "lower min_box_side or min_visible" in warning


def test_edge_cases_small_empty_missing_and_lossless(field, tmp_path):
    ann = json.loads((field / "annotations.json").read_text())
    ann["images"].append({"id": 99, "file_name": "missing_photo.png", "width": 100, "height": 100})
    ann["annotations"].append(make_annotation(999, 99, [1, 1, 20, 20]))
    write_dataset(field / "annotations.json", ann)
    cfg = _cfg(field, negative_share=1.0, split="[1, 0, 0]", yolo=True)
    summary = run(cfg)
    assert summary["missing_images"] == ["missing_photo.png"]  # skipped with a warning
    ds = _load(cfg.output_dir, "train")
    by_source = {}
    for im in ds["images"]:
        by_source.setdefault(im["source_image"], []).append(im)
    small = by_source["small.png"]  # smaller than a tile: one tile
    assert [(t["x0"], t["y0"], t["width"], t["height"]) for t in small] == [(0, 0, 90, 70)]
    empty = by_source["empty.png"]  # no plants: negatives only
    assert len(empty) == len(tile_grid(260, 140, 128, 20))
    assert not [a for a in ds["annotations"] if a["image_id"] in {t["id"] for t in empty}]
    # tiles are lossless crops; a JPEG source gives PNG tiles equal to its decoded pixels
    for name in ("p3.png", "photo.jpg"):
        source = cv2.imread(str(field / "images" / name), cv2.IMREAD_UNCHANGED)
        for t in by_source[name]:
            assert t["file_name"].endswith(".png")
            tile = cv2.imread(str(cfg.output_dir / "train" / "images" / t["file_name"]), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(tile, source[t["y0"] : t["y0"] + t["height"], t["x0"] : t["x0"] + t["width"]])
    # YOLO: one label file per tile, one line per annotation
    lines = sum(
        len((cfg.output_dir / "train" / "labels" / (Path(t["file_name"]).stem + ".txt")).read_text().splitlines())
        for t in ds["images"]
    )
    assert lines == len(ds["annotations"]) and (cfg.output_dir / "data.yaml").is_file()
    # no negatives kept with share 0; the rerun removes the previous run's extra tiles
    cfg0 = _cfg(field, negative_share=0.0, split="[1, 0, 0]")
    run(cfg0)
    ds0 = _load(cfg.output_dir, "train")
    assert "empty.png" not in {im["source_image"] for im in ds0["images"]}
    assert len(list((cfg.output_dir / "train" / "images").iterdir())) == len(ds0["images"])


def test_parallel_equals_serial(field, tmp_path):
    a = run(_cfg(field, workers=1, output_dir=tmp_path / "serial"))
    b = run(_cfg(field, workers=2, output_dir=tmp_path / "parallel"))
    for split in ("train", "val", "test"):
        assert _load(tmp_path / "serial", split) == _load(tmp_path / "parallel", split)
    assert a["tiles"] == b["tiles"]


def test_yolo_labels_as_input_give_the_same_tiles(field, tmp_path):
    coco_to_yolo(json.loads((field / "annotations.json").read_text()), tmp_path / "yolo")
    a = run(_cfg(field, output_dir=tmp_path / "from_coco"))
    b = run(_cfg(field, output_dir=tmp_path / "from_yolo", annotations=tmp_path / "yolo"))
    assert a["tiles"] == b["tiles"] and a["boxes"] == b["boxes"]
    for split in ("train", "val", "test"):
        ca, cb = _load(tmp_path / "from_coco", split), _load(tmp_path / "from_yolo", split)
        assert [im["file_name"] for im in ca["images"]] == [im["file_name"] for im in cb["images"]]
        assert np.allclose([x["bbox"] for x in ca["annotations"]], [x["bbox"] for x in cb["annotations"]], atol=1e-4)


def ann_images(field: Path) -> list[dict]:
    return json.loads((field / "annotations.json").read_text())["images"]


def test_bad_inputs_are_clear_errors(field, tmp_path):
    with pytest.raises(ConfigError, match="overlap"):
        _cfg(field, tile_size=64, overlap=64)
    with pytest.raises(ConfigError, match="split"):
        _cfg(field, split="[0.5, 0.5]")
    with pytest.raises(ConfigError, match="'split' shares must add up to 1"):  # not normalised silently
        _cfg(field, split="[0.6, 0.3, 0.3]")
    # a tile larger than every image: no tiling, each image whole as one tile (inspect's advice for large
    # objects), with its boxes as they are
    whole = run(
        _cfg(field, tile_size=1024, overlap=0, negative_share=1.0, output_dir=field / "whole", split="[1, 0, 0]")
    )
    ds = _load(field / "whole", "train")
    assert whole["tiles"] == len(ds["images"]) and all((im["x0"], im["y0"]) == (0, 0) for im in ds["images"])
    sizes = {im["file_name"]: (im["width"], im["height"]) for im in ann_images(field)}
    assert {im["source_image"]: (im["width"], im["height"]) for im in ds["images"]} == {
        k: v for k, v in sizes.items() if k in {im["source_image"] for im in ds["images"]}
    }
    ann = json.loads((field / "annotations.json").read_text())
    write_dataset(field / "no_boxes.json", dict(ann, annotations=[]))
    with pytest.raises(InputError, match="no box"):  # no silent negatives-only tiles
        run(_cfg(field, annotations=field / "no_boxes.json"))
    assert not (field / "out").exists()  # nothing written by failed runs

    other = tmp_path / "other"
    other.mkdir()
    cv2.imwrite(str(other / "x.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(InputError, match="none of the 10 annotated images"):
        run(_cfg(field, images=other))
    cv2.imwrite(str(field / "images" / "p1.png"), np.zeros((10, 10, 3), np.uint8))  # resized on disk
    with pytest.raises(InputError, match="p1.png"):
        run(_cfg(field))


def test_plan_is_vectorised_and_matches_hand_numbers():
    plan = plan_image(np.array([[96, 30, 146, 70]]), 300, 100, 128, 20, 0.3, 10)
    assert plan.visible[:, 0].tolist() == pytest.approx([32 / 50, 38 / 50, 0.0])
    assert plan.keep[:, 0].tolist() == [True, True, False]


@pytest.mark.slow
@pytest.mark.gui
def test_gui_preview_and_run(field, tmp_path):
    import gui_events as ge

    from matchplant.img_splitter.gui import ImgSplitterGUI

    cfg = _cfg(field, output_dir=tmp_path / "gui_out")
    g = ImgSplitterGUI(cfg, headless=True, dpi=40)  # small: each synthesised event redraws the figure
    s = g.sources[g.index]
    assert len([p for p in g.ax.patches]) == len(s.plan.tiles) + len(s.boxes)
    assert "tiles" in g.summary.get_text()
    g.boxes["tile_size"].set_val("96")
    ge.click(g.fig, g.buttons["Preview"].ax, 0.5, 0.5)
    assert g.cfg.tile_size == 96 and len(g.sources[g.index].plan.tiles) == len(tile_grid(s.width, s.height, 96, 20))
    ge.click(g.fig, g.buttons["image >"].ax, 0.5, 0.5)
    assert g.index == 1
    g.boxes["overlap"].set_val("500")  # a bad value: a message, not a crash
    ge.click(g.fig, g.buttons["Preview"].ax, 0.5, 0.5)
    assert "overlap" in g.status.get_text() and g.status.get_color() == "#c00000"
    g.boxes["overlap"].set_val("20")
    # every yes/no setting is a check box, not a text field holding "False"; a click on it turns it on
    from matchplant.core.runtime.widgets import BoolField

    bools = [k for k, w in g.boxes.items() if isinstance(getattr(cfg, k), bool)]
    assert "yolo" in bools and all(isinstance(g.boxes[k], BoolField) for k in bools)
    assert g.boxes["yolo"].text == "false"
    yolo_ax = g.boxes["yolo"].ax
    x, y = g.boxes["yolo"].check.labels[0].get_position()  # the label's left end, in the axes' coordinates
    ge.click(g.fig, yolo_ax, *yolo_ax.transData.inverted().transform(yolo_ax.transAxes.transform((x + 0.05, y))))
    assert g.boxes["yolo"].value
    ge.click(g.fig, g.buttons["Run"].ax, 0.5, 0.5)
    assert g.result is not None and (tmp_path / "gui_out" / "train.json").is_file()
    assert g.cfg.yolo is True and (tmp_path / "gui_out" / "data.yaml").is_file()
    ge.click(g.fig, g.buttons["Save config"].ax, 0.5, 0.5)
    saved = load_config(ImgSplitterConfig, tmp_path / "gui_out" / "img_splitter.yaml")
    assert saved.tile_size == 96 and saved.yolo is True


def test_tiny_field_tiles(tiny_field, tmp_path):
    f = tiny_field
    cfg = load_config(
        ImgSplitterConfig,
        None,
        [
            f"images={f.undistorted_images}",
            f"annotations={f.boxes_undistorted}",
            f"output_dir={tmp_path / 'out'}",
            "tile_size=256",
            "overlap=40",
            "negative_share=1",
            "workers=1",
            "min_box_side=0",
            "min_visible=0",
        ],
    )
    summary = run(cfg)
    truth = json.loads(f.boxes_undistorted.read_text())
    assert summary["boxes"] == len(truth["annotations"]) and summary["boxes_kept"] == summary["boxes"]
    tiles = [im for k in ("train", "val", "test") for im in _load(cfg.output_dir, k)["images"]]
    assert len(tiles) == len(truth["images"]) * len(tile_grid(400, 300, 256, 40))
    assert all(t["file_name"].endswith(".tif") for t in tiles)  # TIFF sources stay TIFF


def _owned_area_annotation(f, out: Path, record_region: bool) -> Path:
    """The true boxes of every plant touching a tilted quadrilateral 'owned area' of each undistorted
    image (as a person annotating only the owned area would box them), with or without the region."""
    from shapely.geometry import Polygon

    truth = json.loads(f.boxes_undistorted.read_text())
    ds = new_dataset(["plant"])
    for im in truth["images"]:
        W, H = im["width"], im["height"]
        poly = [[0.30 * W, 0.15 * H], [0.80 * W, 0.30 * H], [0.70 * W, 0.85 * H], [0.15 * W, 0.70 * H]]
        entry = {k: im[k] for k in ("id", "file_name", "width", "height")}
        if record_region:
            entry["annotated_region"] = poly
        ds["images"].append(entry)
        for a in truth["annotations"]:
            x, y, w, h = a["bbox"]
            if a["image_id"] == im["id"] and shapely_box(x, y, x + w, y + h).intersects(Polygon(poly)):
                ds["annotations"].append(make_annotation(len(ds["annotations"]) + 1, im["id"], a["bbox"]))
    return write_dataset(out, ds)


def _unlabelled_plants(f, out: Path) -> tuple[int, int]:
    """(unlabelled, visible) true plants over all written tiles, from the rendered truth masks: a plant is
    visible in a tile when at least half of its pixels in the photo are in the tile's unmasked part, and
    labelled when a box of the tile has IoU >= 0.5 with the box of those pixels."""
    from matchplant.img_splitter.regions import mask_outside

    def best_iou(a, b):
        lo, hi = np.maximum(a[:2], b[:, :2]), np.minimum(a[2:], b[:, 2:])
        inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
        return (inter / (np.prod(a[2:] - a[:2]) + np.prod(b[:, 2:] - b[:, :2], axis=1) - inter)).max()

    unlabelled = visible = 0
    for split in ("train", "val", "test"):
        ds = _load(out, split)
        by_image = {im["id"]: [] for im in ds["images"]}
        for a in ds["annotations"]:
            by_image[a["image_id"]].append(a["bbox"])
        for im in ds["images"]:
            ids = cv2.imread(str(f.masks_undistorted / (im["source_image"][:-4] + ".png")), cv2.IMREAD_UNCHANGED)
            counts = np.bincount(ids.ravel())
            x0, y0, w, h = im["x0"], im["y0"], im["width"], im["height"]
            tile = ids[y0 : y0 + h, x0 : x0 + w]
            if im.get("masked_outside_region"):
                region = next(
                    i
                    for i in json.loads((out.parent / "ann" / "annotations.json").read_text())["images"]
                    if i["file_name"] == im["source_image"]
                )["annotated_region"]
                tile = mask_outside(tile, region, x0, y0)
            boxes = np.array([[x, y, x + bw, y + bh] for x, y, bw, bh in by_image[im["id"]]]).reshape(-1, 4)
            for pid in np.unique(tile[tile > 0]):
                rows, cols = np.nonzero(tile == pid)
                if len(rows) < 0.5 * counts[pid]:
                    continue
                visible += 1
                mine = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
                if not len(boxes) or best_iou(mine, boxes) < 0.5:
                    unlabelled += 1
    return unlabelled, visible


def test_owned_area_annotation_teaches_no_plant_as_background(tiny_field, tmp_path):
    """Issue 16: annotating only each image's owned area must not leave unboxed plants in the tiles."""
    f = tiny_field
    results = {}
    for record in (False, True):
        (tmp_path / "ann").mkdir(exist_ok=True)
        ann = _owned_area_annotation(f, tmp_path / "ann" / "annotations.json", record)
        out = tmp_path / f"tiles_{record}"
        summary = run(
            load_config(
                ImgSplitterConfig,
                None,
                [
                    f"images={f.undistorted_images}",
                    f"annotations={ann}",
                    f"output_dir={out}",
                    "tile_size=128",
                    "overlap=32",
                    "negative_share=1",
                    "workers=1",
                    "min_box_side=2",
                    "min_visible=0.3",
                ],
            )
        )
        results[record] = (_unlabelled_plants(f, out), summary)
    (bad, seen_bad), _ = results[False]
    (unlabelled, seen), summary = results[True]
    print(f"unlabelled visible plants: whole tiles {bad}/{seen_bad}, masked to the owned area {unlabelled}/{seen}")
    assert bad > 0.2 * seen_bad  # whole tiles over owned-area boxes: plants taught as soil
    assert seen > 50 and unlabelled == 0  # masked to the annotated region: none
    assert summary["annotated_regions"]["images"] == 9 and summary["annotated_regions"]["tiles_outside_region"] > 0


XVFB = """
import sys
from pathlib import Path
import matplotlib
import matplotlib.pyplot as plt
from matchplant.core.runtime.config import load_config
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.gui import ImgSplitterGUI
cfg = load_config(ImgSplitterConfig, None, {sets!r})
g = ImgSplitterGUI(cfg, headless=False)
timer = g.fig.canvas.new_timer(interval=300)
timer.single_shot = True
timer.add_callback(lambda: (g._guarded(g.run), plt.close(g.fig)))  # press Run, then close
timer.start()
plt.show()
print("BACKEND", matplotlib.get_backend(), "TILES", g.result["tiles"])
"""


@pytest.mark.gui
def test_gui_in_a_real_window(field, tmp_path):
    from conftest import run_in_xvfb, xvfb_available

    if not xvfb_available():
        pytest.skip("Xvfb is not installed")
    sets = [
        f"images={field / 'images'}",
        f"annotations={field / 'annotations.json'}",
        f"output_dir={tmp_path / 'xout'}",
        "tile_size=128",
        "overlap=20",
        "workers=1",
    ]
    r = run_in_xvfb(XVFB.format(sets=sets), timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "backend tkagg" in r.stdout.lower()
    tiles = int(r.stdout.split("TILES")[1])
    assert tiles == len(json.loads((tmp_path / "xout" / "train.json").read_text())["images"]) + len(
        json.loads((tmp_path / "xout" / "val.json").read_text())["images"]
    ) + len(json.loads((tmp_path / "xout" / "test.json").read_text())["images"])


def test_the_folders_picture_of_the_window_shows_its_current_widgets():
    """``5_img_splitter/gui.png`` (drawn by docs/gui/folder_windows.py) records each setting's widget: every yes/no
    setting must show as a check box there too (the picture once showed ``yolo`` as a text field holding False)."""
    from PIL import Image

    from matchplant.img_splitter.gui import FIELDS

    with Image.open(Path(__file__).resolve().parents[1] / "5_img_splitter" / "gui.png") as im:
        shown = json.loads(im.text.get("widgets", "{}"))
    assert set(shown) == set(FIELDS), "5_img_splitter/gui.png is older than the window: docs/gui/folder_windows.py"
    defaults = ImgSplitterConfig()
    for key in FIELDS:
        want = "BoolField" if isinstance(getattr(defaults, key), bool) else "QuietTextBox"
        assert shown[key] == want, (key, shown[key], "python docs/gui/folder_windows.py <demo output>")
