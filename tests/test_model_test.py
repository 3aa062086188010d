"""Module 7: COCO evaluation equal to pycocotools, tiled detection that finds each plant once."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from small_detector import save_small, small_detector

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.detection.evaluate import coco_evaluate, matches_at_iou50, operating_point
from matchplant.detection.synth import make_photo, make_tiles
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.merge import merge_nested, merge_tile_boxes
from matchplant.model_test.run import run
from matchplant.model_test.tiles import detect_image, tile_starts
from matchplant.model_train.config import ModelTrainConfig

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """An (untrained) small detector saved as a module 6 checkpoint: the file contract, not accuracy."""
    model, model_cfg = small_detector()
    with torch.no_grad():  # every box scores about 0.01: below the usual 0.05 cut
        model.roi_heads.box_predictor.cls_score.bias.copy_(torch.tensor([2.5, -2.5]))
    path = tmp_path_factory.mktemp("ck") / "model.pt"
    return save_small(path, model, model_cfg)


def pycocotools_direct(gt_path: Path, results: list[dict], max_dets: int) -> np.ndarray:
    """pycocotools' 12 numbers. Its summarize() takes AP (IoU .50:.95) at maxDets=100 whatever maxDets
    says (-1 when 100 is not among them); that one is taken here from its accumulated precision the way
    summarize() averages it, at ``max_dets``."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO(str(gt_path))
        ev = COCOeval(gt, gt.loadRes(results), "bbox")
        ev.params.maxDets = [1, 10, max_dets]
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    stats = ev.stats.copy()
    if max_dets != 100:
        p = ev.eval["precision"][:, :, :, 0, -1]
        stats[0] = p[p > -1].mean() if (p > -1).any() else -1
    return stats


@pytest.mark.slow
def test_folder_config_and_help():
    cfg = load_config(ModelTestConfig, ROOT / "7_model_test" / "test_config.yaml", check_paths=False)
    assert cfg.evaluate.max_detections > 100 and cfg.evaluate.operating_threshold == 0.5
    r = subprocess.run(
        [sys.executable, str(ROOT / "7_model_test" / "model_test.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--config" in r.stdout


def test_coco_evaluation_equals_pycocotools_and_dense_maxdets(tmp_path):
    """Noisy detections on a dense dataset (150 plants on one image): our numbers are pycocotools' own,
    and maxDets above 100 matters."""
    rng = np.random.default_rng(0)
    ds = new_dataset(["plant"])
    ann = 1
    for img_id, n in ((1, 150), (2, 20), (3, 0)):
        ds["images"].append({"id": img_id, "file_name": f"t{img_id}.png", "width": 2000, "height": 2000})
        for _ in range(n):
            x, y = rng.uniform(0, 1900, 2)
            w, h = rng.uniform(8, 90, 2)  # small and medium plants
            ds["annotations"].append(make_annotation(ann, img_id, [x, y, w, h]))
            ann += 1
    gt_path = write_dataset(tmp_path / "gt.json", ds)
    results = []
    for a in ds["annotations"]:
        if rng.random() < 0.85:  # found, with some box noise
            x, y, w, h = a["bbox"]
            results.append(
                {
                    "image_id": a["image_id"],
                    "category_id": 1,
                    "score": float(rng.uniform(0.3, 1)),
                    "bbox": [x + rng.normal(0, 0.05 * w), y + rng.normal(0, 0.05 * h), w, h],
                }
            )
    for img_id in (1, 2, 3):  # false positives
        for _ in range(10):
            results.append(
                {
                    "image_id": img_id,
                    "category_id": 1,
                    "score": float(rng.uniform(0, 0.6)),
                    "bbox": [*rng.uniform(0, 1900, 2), 30.0, 30.0],
                }
            )
    stats, ev = coco_evaluate(ds, results, max_dets=300)
    direct = pycocotools_direct(gt_path, results, 300)
    ours = [stats[k] if stats[k] is not None else -1 for k in stats]
    assert ours == pytest.approx(list(direct), abs=1e-12)
    assert stats["AP_small"] is not None and stats["AP_medium"] is not None and stats["AP_large"] is None
    # with maxDets 100 our AP is pycocotools' summarize() output itself
    at100, _ = coco_evaluate(ds, results, max_dets=100)
    direct100 = pycocotools_direct(gt_path, results, 100)
    assert [v if v is not None else -1 for v in at100.values()] == pytest.approx(list(direct100), abs=1e-12)
    # COCO's default cap of 100 loses plants on the dense image
    assert direct100[8] < stats["AR_max"] - 0.1 and direct100[1] < stats["AP50"]
    # precision / recall at a threshold from COCOeval's matches, checked against a direct count
    scores, hits, n_gt = matches_at_iou50(ev)
    assert n_gt == 170 and len(scores) == len(results)
    op = operating_point(scores, hits, n_gt, 0.5)
    found = sum(1 for r in results[: len(results) - 30] if r["score"] >= 0.5)  # noisy true boxes have IoU > 0.5
    fps = sum(1 for r in results[len(results) - 30 :] if r["score"] >= 0.5)
    assert (op["tp"], op["fp"], op["fn"]) == (found, fps, 170 - found)
    assert op["f1"] == pytest.approx(2 * op["precision"] * op["recall"] / (op["precision"] + op["recall"]))


def test_evaluate_writes_metrics_figures_and_matches_pycocotools(checkpoint, tmp_path):
    tiles = make_tiles(
        tmp_path / "tiles", n_images=4, size=64, plants=(1, 3), radius=(5, 9), negatives=1, name="test.json"
    )
    out = tmp_path / "out"
    from matchplant.cli import run_module

    code = run_module(
        "model_test",
        [
            "--set",
            f"checkpoint={checkpoint}",
            "--set",
            f"evaluate.dataset_json={tiles}",
            "--set",
            f"output_dir={out}",
            "--set",
            "evaluate.drawn_images=2",
            "--set",
            "device=cpu",
        ],
    )
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("pr_curve.png", "score_histogram.png"):
        assert (out / name).stat().st_size > 1000
    assert len(list((out / "drawn").glob("*.png"))) == 2
    preds = read_predictions(out / "test_predictions.json")
    assert all({"source_image", "x0", "y0"} <= set(im) for im in preds["images"])
    # no threshold before COCOeval: boxes scoring below 0.05 are all there
    assert metrics["detections"] == len(preds["predictions"]) > 0
    assert max(p["score"] for p in preds["predictions"]) < 0.05
    results = [{k: p[k] for k in ("image_id", "category_id", "bbox", "score")} for p in preds["predictions"]]
    direct = pycocotools_direct(tiles, results, metrics["max_detections"])
    ours = [v if v is not None else -1 for v in metrics["coco"].values()]
    assert ours == pytest.approx(list(direct), abs=1e-12)
    assert set(metrics["at_threshold"]) >= {"precision", "recall", "f1", "threshold"}


# -- tiled detection ------------------------------------------------------------------------------------


def oracle(truth: np.ndarray, origins_seen: list):
    """A perfect detector: each plant's box clipped to the tile (cut plants give partial boxes)."""

    def predict(tiles):
        out = []
        for tile in tiles:
            x0, y0 = origins_seen.pop(0)
            th, tw = tile.shape[:2]
            b = truth - [x0, y0, x0, y0]
            b = np.clip(b, 0, [tw, th, tw, th])
            keep = ((b[:, 2] - b[:, 0]) > 1) & ((b[:, 3] - b[:, 1]) > 1)
            out.append((b[keep], np.full(keep.sum(), 0.9), np.ones(keep.sum(), dtype=int)))
        return out

    return predict


def test_tiled_detection_finds_each_cut_plant_once(tmp_path):
    truth = make_photo(tmp_path / "photo.png", 700, 520, n_plants=60, radius=(8, 14), seed=3)
    img = np.zeros((520, 700, 3), np.uint8)
    tile, overlap = 200, 48  # overlap larger than the largest plant (28 px)
    xs, ys = tile_starts(700, tile, overlap), tile_starts(520, tile, overlap)
    assert xs == [0, 152, 304, 456, 500] and ys == [0, 152, 304, 320]
    origins = [(x, y) for y in ys for x in xs]
    # how many plants do tile borders cut? (the test must contain some)
    cut = sum(any((b[0] < x + tile < b[2]) or (b[0] < x < b[2]) for x in xs) for b in truth)
    assert cut >= 10
    boxes, scores, labels = detect_image(
        img, oracle(truth, list(origins)), tile_size=tile, overlap=overlap, batch_size=3
    )
    assert len(boxes) == len(truth)
    # each true plant matched by exactly one box, the whole box
    from torchvision.ops import box_iou

    iou = box_iou(torch.as_tensor(truth), torch.as_tensor(boxes)).numpy()
    assert (iou.max(axis=1) > 0.99).all() and ((iou > 0.5).sum(axis=1) == 1).all()
    # without the merge every cut plant would be counted several times
    raw = sum(len(b) for b, _, _ in oracle(truth, list(origins))([np.zeros((tile, tile, 3))] * len(origins)))
    assert raw > len(truth) + cut


def test_merge_keeps_plants_larger_than_the_overlap():
    # one plant cut in two tiles with no whole view, and a whole plant with a duplicate from another tile
    boxes = np.array([[90, 10, 100, 40], [100, 10, 130, 40], [10, 10, 30, 30], [10.5, 10, 30, 30]], float)
    keep = merge_tile_boxes(
        boxes, np.array([0.9, 0.8, 0.95, 0.7]), np.ones(4, int), np.array([True, True, False, False])
    )
    assert sorted(keep.tolist()) == [0, 1, 2]


def test_detect_on_new_images_writes_predictions_for_module_8(checkpoint, tmp_path):
    make_photo(tmp_path / "imgs" / "DJI_0001.JPG.tif", 300, 200, n_plants=10, seed=1)
    make_photo(tmp_path / "imgs" / "DJI_0002.JPG.tif", 150, 260, n_plants=5, seed=2)
    (tmp_path / "imgs" / "notes.txt").write_text("not an image")
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={checkpoint}",
            f"detect.images={tmp_path / 'imgs'}",
            f"output_dir={tmp_path / 'out'}",
            "detect.tile_size=128",
            "detect.overlap=32",
            "detect.score_threshold=0.0",
            "device=cpu",
        ],
    )
    run(cfg)
    preds = read_predictions(tmp_path / "out" / "predictions.json")
    assert [im["file_name"] for im in preds["images"]] == ["DJI_0001.JPG.tif", "DJI_0002.JPG.tif"]
    for im in preds["images"]:
        assert im["source_image"] == im["file_name"] and im["x0"] == 0 and im["y0"] == 0
    assert preds["predictions"] and preds["categories"][0]["name"] == "plant"
    sizes = {im["id"]: (im["width"], im["height"]) for im in preds["images"]}
    assert sizes == {1: (300, 200), 2: (150, 260)}
    for p in preds["predictions"]:
        w, h = sizes[p["image_id"]]
        x, y, bw, bh = p["bbox"]
        assert -0.01 <= x and x + bw <= w + 0.01 and -0.01 <= y and y + bh <= h + 0.01
    assert len(list((tmp_path / "out" / "detections").glob("*.png"))) == 2


def test_errors(checkpoint, tmp_path):
    with pytest.raises(ConfigError, match="nothing to do"):
        load_config(ModelTestConfig, None, [f"checkpoint={checkpoint}"])
    with pytest.raises(ConfigError, match="overlap"):
        load_config(
            ModelTestConfig,
            None,
            [f"checkpoint={checkpoint}", f"detect.images={tmp_path}", "detect.tile_size=100", "detect.overlap=100"],
        )
    (tmp_path / "empty").mkdir()
    cfg = load_config(
        ModelTestConfig,
        None,
        [f"checkpoint={checkpoint}", f"detect.images={tmp_path / 'empty'}", f"output_dir={tmp_path / 'o'}"],
    )
    with pytest.raises(InputError, match="no images"):
        run(cfg)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    cfg.checkpoint = tmp_path / "bad.pt"
    with pytest.raises(InputError, match="checkpoint"):
        run(cfg)


# -- the synthetic field: module 5's tiles feed module 6, and tiled detection on a whole photo ------------


def test_tiny_field_tiles_and_whole_image_detection(tiny_field, tmp_path):
    from matchplant.core.formats.coco import read_dataset
    from matchplant.core.formats.images import read_rgb8
    from matchplant.detection.data import CocoDetection
    from matchplant.img_splitter.config import ImgSplitterConfig
    from matchplant.img_splitter.run import run as run_tiling

    truth = read_dataset(tiny_field.boxes_undistorted)
    sizes = np.asarray([a["bbox"][2:] for a in truth["annotations"]])
    overlap = int(sizes.max()) + 4  # more than the largest plant
    tiling = load_config(
        ImgSplitterConfig,
        None,
        [
            f"images={tiny_field.undistorted_images}",
            f"annotations={tiny_field.boxes_undistorted}",
            f"output_dir={tmp_path / 'tiles'}",
            "tile_size=192",
            f"overlap={overlap}",
            "negative_share=1",
            "workers=1",
        ],
    )
    run_tiling(tiling)
    ds = CocoDetection(tmp_path / "tiles" / "train.json")  # module 5's layout is found as it is
    image, target = ds[0]
    assert image.shape[0] == 3 and image.shape[1:] == (ds.images[0]["height"], ds.images[0]["width"])
    assert all(p is not None for p in ds.paths)

    im = truth["images"][0]
    photo = read_rgb8(tiny_field.undistorted_images / im["file_name"])
    gt = np.asarray([a["bbox"] for a in truth["annotations"] if a["image_id"] == im["id"]], float)
    gt[:, 2:] += gt[:, :2]
    xs, ys = tile_starts(photo.shape[1], 192, overlap), tile_starts(photo.shape[0], 192, overlap)
    origins = [(x, y) for y in ys for x in xs]
    assert len(origins) > 1
    boxes, _, _ = detect_image(photo, oracle(gt, list(origins)), tile_size=192, overlap=overlap)
    from torchvision.ops import box_iou

    iou = box_iou(torch.as_tensor(gt), torch.as_tensor(boxes)).numpy()
    assert len(boxes) == len(gt) and (iou.max(axis=1) > 0.99).all()


@pytest.mark.slow
def test_torchrun_two_processes_write_the_single_process_predictions(checkpoint, tmp_path):
    """``torchrun --nproc_per_node 2`` (gloo on the CPU): the images are split across the processes and one
    predictions file results, equal to a single process's."""
    for k, (w, h) in enumerate([(300, 200), (150, 260), (200, 200), (260, 150), (180, 220)]):
        make_photo(tmp_path / "imgs" / f"DJI_{k:04d}.JPG.tif", w, h, n_plants=6, seed=k)
    common = [
        f"checkpoint={checkpoint}",
        f"detect.images={tmp_path / 'imgs'}",
        "detect.tile_size=128",
        "detect.overlap=32",
        "detect.score_threshold=0.0",
        "device=cpu",
        "evaluate.dataset_json=null",
        "detect.drawn_images=0",
    ]
    run(load_config(ModelTestConfig, None, common + [f"output_dir={tmp_path / 'one'}"]))
    sets = [a for c in common + [f"output_dir={tmp_path / 'two'}"] for a in ("--set", c)]
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc_per_node",
            "2",
            str(ROOT / "7_model_test" / "model_test.py"),
            *sets,
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "by 2 processes" in proc.stderr + proc.stdout
    one = json.loads((tmp_path / "one" / "predictions.json").read_text())
    two = json.loads((tmp_path / "two" / "predictions.json").read_text())
    assert len(one["images"]) == 5 and one["predictions"]
    assert two["images"] == one["images"] and two["categories"] == one["categories"]
    assert two["predictions"] == one["predictions"]


# -- issue 16: the training geometry, distinct plants, nested duplicates --------------------------------------


class _Records:
    """The log records of the 'matchplant' logger (it does not propagate to pytest's caplog)."""

    def __enter__(self):
        import logging

        self.records, self.logger = [], logging.getLogger("matchplant")
        self.handler = logging.Handler(logging.INFO)
        self.handler.emit = self.records.append
        self.level = self.logger.level
        self.logger.addHandler(self.handler)
        self.logger.setLevel(logging.INFO)
        return self

    def __exit__(self, *exc):
        self.logger.removeHandler(self.handler)
        self.logger.setLevel(self.level)

    def warnings(self) -> list[str]:
        return [r.getMessage() for r in self.records if r.levelname == "WARNING"]


@pytest.mark.slow
def test_module7_tiles_at_the_checkpoints_training_tile_size(tmp_path):
    """A model trained on 128 px tiles: module 7 tiles at 128 by default (tile_size null), and warns when
    asked for 1024 px tiles (plants 8x smaller in the detector's input than in training)."""
    from matchplant.model_test.scale import check_found_scale
    from matchplant.model_train.run import train

    tiles = make_tiles(
        tmp_path / "tiles", n_images=4, size=128, plants=(1, 3), radius=(8, 12), negatives=0, name="train.json"
    )
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            f"train_json={tiles}",
            f"output_dir={tmp_path / 'run'}",
            "epochs=1",
            "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
            "model.pretrained=none",
            "model.min_size=64",
            "model.max_size=64",
            "model.anchor_sizes=auto",
            "batch_size=4",
            "num_workers=0",
            "warmup_iters=1",
            "save_every=0",
            "model.rpn.post_nms_top_n_test=50",
        ],
    )
    train(cfg)
    ck_path = tmp_path / "run" / "checkpoints" / "last.pt"
    make_photo(tmp_path / "imgs" / "a.png", 300, 200, n_plants=8, radius=(8, 12), seed=1)
    common = [
        f"checkpoint={ck_path}",
        f"detect.images={tmp_path / 'imgs'}",
        "detect.score_threshold=0.0",
        "device=cpu",
        "detect.drawn_images=0",
    ]
    with _Records() as rec:
        run(load_config(ModelTestConfig, None, common + [f"output_dir={tmp_path / 'default'}"]))
    info = read_predictions(tmp_path / "default" / "predictions.json")["info"]
    assert info["tile_size"] == 128 and 0 < info["overlap"] <= 64
    # no tile-size warning before detection (the 1-epoch model's boxes may still warn about "the plants found")
    assert not any("training size" in w for w in rec.warnings() if w.startswith("detect.tile_size")), rec.warnings()
    with _Records() as rec:
        run(
            load_config(
                ModelTestConfig,
                None,
                common + [f"output_dir={tmp_path / 'big'}", "detect.tile_size=1024", "detect.overlap=64"],
            )
        )
    assert read_predictions(tmp_path / "big" / "predictions.json")["info"]["tile_size"] == 1024
    assert any("detect.tile_size 1024" in w and "0.12x" in w for w in rec.warnings()), rec.warnings()
    # after detection: plants found at 3x their training size (photos of another ground resolution)
    from matchplant.detection.checkpoint import read_checkpoint

    ck = read_checkpoint(ck_path)
    med = ck["training_geometry"]["objects_input_px"] * 128 / 64  # training plants in tile pixels
    big = np.array([[0, 0, 3 * med, 3 * med]] * 5)
    with _Records() as rec:
        assert check_found_scale(ck, [(big, 300, 200)], 128) == pytest.approx(3.0, rel=0.02)
    assert any("the plants found" in w and "detect.tile_size about 384" in w for w in rec.warnings())


def _tiled_truth(tmp_path: Path):
    """Two photos with known plants tiled by module 5 (overlap: plants in 2-4 tiles); returns the test
    split and, for every tile box, the true plant it is a copy of (an oracle from the truth: the tile box is
    that plant's box clipped to the tile)."""
    from matchplant.core.formats.coco import read_dataset
    from matchplant.img_splitter.config import ImgSplitterConfig
    from matchplant.img_splitter.run import run as run_tiling

    ds = new_dataset(["plant"])
    truth = {}
    for k, name in enumerate(("p0.png", "p1.png")):
        boxes = make_photo(tmp_path / "photos" / name, 400, 300, n_plants=30, radius=(8, 14), seed=10 + k)
        ds["images"].append({"id": k + 1, "file_name": name, "width": 400, "height": 300})
        for b in boxes:
            ds["annotations"].append(
                make_annotation(len(ds["annotations"]) + 1, k + 1, [b[0], b[1], b[2] - b[0], b[3] - b[1]])
            )
        truth[name] = boxes
    write_dataset(tmp_path / "ann.json", ds)
    run_tiling(
        load_config(
            ImgSplitterConfig,
            None,
            [
                f"images={tmp_path / 'photos'}",
                f"annotations={tmp_path / 'ann.json'}",
                f"output_dir={tmp_path / 'tiles'}",
                "tile_size=128",
                "overlap=48",
                "split=[0.0, 0.0, 1.0]",
                "negative_share=0",
                "workers=1",
            ],
        )
    )
    test = read_dataset(tmp_path / "tiles" / "test.json")
    images = {im["id"]: im for im in test["images"]}
    plant_of = {}
    for a in test["annotations"]:
        im = images[a["image_id"]]
        x0, y0, w, h = im["x0"], im["y0"], im["width"], im["height"]
        t = truth[im["source_image"]]
        clipped = np.stack(
            [
                np.maximum(t[:, 0], x0),
                np.maximum(t[:, 1], y0),
                np.minimum(t[:, 2], x0 + w),
                np.minimum(t[:, 3], y0 + h),
            ],
            axis=1,
        )
        x, y, bw, bh = a["bbox"]
        err = np.abs(clipped - [x0 + x, y0 + y, x0 + x + bw, y0 + y + bh]).max(axis=1)
        assert err.min() < 0.02
        plant_of[a["id"]] = (im["source_image"], int(err.argmin()))
    return test, plant_of


def test_distinct_plants_counted_once_across_overlapping_tiles(tmp_path, checkpoint):
    from matchplant.detection.tile_objects import distinct_objects, found_objects

    test, plant_of = _tiled_truth(tmp_path)
    n_true = len(set(plant_of.values()))
    assert len(test["annotations"]) > n_true + 10  # many plants are in several tiles
    object_of, n = distinct_objects(test)
    assert n == n_true
    # the same partition as the truth's
    pairs = {(object_of[a], plant_of[a]) for a in plant_of}
    assert len(pairs) == n_true
    # plants found: a perfect detector on every second tile finds the plants with a copy there
    seen = {im["id"] for im in test["images"][::2]}
    results = [
        {"image_id": a["image_id"], "category_id": 1, "bbox": a["bbox"], "score": 0.9}
        for a in test["annotations"]
        if a["image_id"] in seen
    ]
    _, ev = coco_evaluate(test, results)
    assert found_objects(ev, object_of, 0.5) == len(
        {plant_of[a["id"]] for a in test["annotations"] if a["image_id"] in seen}
    )
    assert found_objects(ev, object_of, 0.95) == 0
    # module 7's metrics.json: plants are distinct plants, tile boxes are counted apart; fractions only
    out = tmp_path / "eval"
    run(
        load_config(
            ModelTestConfig,
            None,
            [
                f"checkpoint={checkpoint}",
                f"evaluate.dataset_json={tmp_path / 'tiles' / 'test.json'}",
                f"output_dir={out}",
                "device=cpu",
                "evaluate.drawn_images=0",
            ],
        )
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["plants"] == n_true and metrics["tile_boxes"] == len(test["annotations"])
    assert "fractions 0..1" in metrics["units"]
    assert metrics["plants_found"]["plants"] == n_true and 0 <= metrics["plants_found"]["recall"] <= 1
    fractions = [v for v in metrics["coco"].values() if v is not None]
    fractions += [metrics["at_threshold"][k] for k in ("precision", "recall", "f1")]
    assert all(0 <= v <= 1 for v in fractions)


def test_nested_duplicates_from_another_tile_are_merged():
    """A plant whole in tile A, and seen by tile B only as a nested part (IoU 0.36: NMS keeps both): one
    plant. When tile B also saw the whole plant, its inner box is a second plant and is kept."""
    img = np.zeros((200, 300, 3), np.uint8)  # tiles at x 0 and 100 (200 px, overlap 100)
    plant, part, small = [120, 50, 170, 100], [130, 60, 160, 90], [135, 65, 155, 85]

    def predictor(answers):
        def predict(tiles):
            return [answers.pop(0) for _ in tiles]

        return predict

    def tile(*boxes, score=0.9):
        b = np.asarray(boxes, float).reshape(-1, 4)
        return b, np.full(len(b), score), np.ones(len(b), int)

    shift = np.array([100, 0, 100, 0])
    boxes, _, _ = detect_image(img, predictor([tile(plant), tile(np.array(part) - shift)]), tile_size=200, overlap=100)
    assert boxes.tolist() == [plant]
    boxes, _, _ = detect_image(
        img, predictor([tile(plant), tile(np.array(part) - shift)]), tile_size=200, overlap=100, merge_containment=1.0
    )  # 'part' is wholly inside: still merged
    assert boxes.tolist() == [plant]
    # a box far inside a larger one of its class on the same photo is merged too (issue 26: one pass over the
    # photo's final boxes), even when one tile saw both: the lower-scoring one goes (issue 39)
    answers = [
        tile(plant),
        (np.array([np.array(plant) - shift, np.array(small) - shift], float), np.array([0.8, 0.7]), np.ones(2, int)),
    ]
    counts: dict = {}
    boxes, _, _ = detect_image(img, predictor(answers), tile_size=200, overlap=100, counts=counts)
    assert boxes.tolist() == [plant] and counts["nested_merged"] == 1 and counts["tiles"] == 2
    # the inner box scoring higher than the outer ones is the plant: the outer boxes go, from either tile
    answers = [
        tile(plant),
        (np.array([np.array(plant) - shift, np.array(small) - shift], float), np.array([0.8, 0.95]), np.ones(2, int)),
    ]
    boxes, scores, _ = detect_image(img, predictor(answers), tile_size=200, overlap=100)
    assert boxes.tolist() == [small] and scores.tolist() == [0.95]


def _nested_pairs(boxes: np.ndarray, labels: np.ndarray, share: float = 0.8) -> int:
    """Pairs (inner, outer) of same-class boxes with the inner one >= share inside the larger: shapely, box by box."""
    from shapely.geometry import box as sbox

    polys = [sbox(*b) for b in boxes]
    return sum(
        1
        for i, a in enumerate(polys)
        for j, b in enumerate(polys)
        if i != j
        and labels[i] == labels[j]
        and a.area <= b.area
        and a.area > 0
        and (a.area < b.area or i > j)
        and a.intersection(b).area >= share * a.area
    )


def test_nested_duplicates_on_one_photo_are_merged_with_known_truth():
    """Synthetic predictions: 30 plants, 12 of them with a nested duplicate (a part, wholly inside) from the
    same tile and 3 of another class inside a plant (kept: another class); one tile covers the photo."""
    rng = np.random.default_rng(5)
    xy = np.stack(np.meshgrid(np.arange(6) * 60 + 10, np.arange(5) * 60 + 10), -1).reshape(-1, 2).astype(float)
    plants = np.hstack([xy, xy + rng.uniform(30, 45, (30, 2))])
    w = plants[:12, 2:] - plants[:12, :2]
    parts = plants[:12] + np.hstack([w * 0.2, -w * 0.15])  # inside, IoU about 0.4: NMS keeps them
    other = plants[12:15] + np.hstack([w[:3] * 0.1, -w[:3] * 0.1])  # class 2 inside class 1
    boxes = np.vstack([plants, parts, other])
    labels = np.r_[np.ones(42, int), np.full(3, 2)]
    assert _nested_pairs(boxes, labels) == 12
    scores = rng.uniform(0.5, 1.0, len(boxes))
    scores[:12] = rng.uniform(0.75, 1.0, 12)
    scores[30:42] = scores[:12] - rng.uniform(0.05, 0.2, 12)  # a part of a plant is found less surely

    def predict(tiles):
        return [(boxes, scores, labels)]

    counts: dict = {}
    out_b, _, out_l = detect_image(np.zeros((340, 400, 3), np.uint8), predict, tile_size=512, overlap=64, counts=counts)
    assert len(out_b) == 33 and counts["nested_merged"] == 12 and _nested_pairs(out_b, out_l) == 0
    assert sorted(map(tuple, out_b[out_l == 1])) == sorted(map(tuple, plants))  # the larger boxes stay


def test_nested_merge_keeps_the_better_box_with_known_truth():
    """Issue 39: nested pairs whose truth is the outer box (a part of the plant found beside it, scoring lower),
    whose truth is the inner box (a panicle, and a false box around it and its surroundings scoring lower), and
    false boxes around two true plants each: the box kept is the true one of every pair, the count the truth's.
    Keeping the larger box (the old rule) lost every true inner box."""
    rng = np.random.default_rng(8)
    xy = np.stack(np.meshgrid(np.arange(8) * 70 + 20, np.arange(5) * 70 + 20), -1).reshape(-1, 2).astype(float)
    truth = np.hstack([xy, xy + rng.uniform(30, 45, (40, 2))])
    w = truth[:, 2:] - truth[:, :2]
    parts = truth[:12] + np.hstack([w[:12] * 0.2, -w[:12] * 0.15])  # inside true plants 0-11
    around = truth[12:24] + np.hstack([-w[12:24] * 0.4, w[12:24] * 0.4])  # false boxes around true plants 12-23
    pair = np.hstack([truth[24:32:2, :2], truth[25:33:2, 2:]])  # false boxes around plants 24+25, 26+27, ...
    boxes = np.vstack([truth, parts, around, pair])
    s_truth = rng.uniform(0.75, 1.0, 40)
    scores = np.r_[s_truth, s_truth[:12] - 0.2, s_truth[12:24] - rng.uniform(0.05, 0.3, 12), np.full(4, 0.6)]
    labels = np.ones(len(boxes), int)
    assert _nested_pairs(boxes, labels) == 12 + 12 + 8
    keep = merge_nested(boxes, scores, labels, 0.8)
    assert sorted(keep.tolist()) == list(range(40))  # every true box, and only the true boxes
    assert _nested_pairs(boxes[keep], labels[keep]) == 0
    # the larger box kept whatever the scores (the old rule) keeps the false outer boxes instead of 20 true ones
    larger = merge_nested(boxes, np.zeros(len(boxes)), labels, 0.8)
    assert len(set(larger.tolist()) & set(range(40))) == 40 - 12 - 8
    # equal scores: the outer box, which holds the other (containment), is kept
    two = np.array([[0, 0, 40, 40], [5, 5, 30, 30]], float)
    assert merge_nested(two, np.array([0.9, 0.9]), np.ones(2, int)).tolist() == [0]
    assert merge_nested(two, np.array([0.8, 0.9]), np.ones(2, int)).tolist() == [1]
    # across tiles (merge_tile_boxes): the same choice, the inner box of tile 1 scoring higher than the outer of 0
    kept = merge_tile_boxes(two, np.array([0.7, 0.9]), np.ones(2, int), np.zeros(2, bool), 0.5, np.array([0, 1]))
    assert kept.tolist() == [1]


def test_detection_output_holds_no_nested_box(checkpoint, tmp_path, caplog):
    """A real run (untrained model, every box kept): predictions.json holds no box >= 80 % inside another of its
    class on the same photo, and the log says how many were merged."""
    make_photo(tmp_path / "imgs" / "a.png", 300, 220, n_plants=12, seed=7)
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={checkpoint}",
            f"detect.images={tmp_path / 'imgs'}",
            f"output_dir={tmp_path / 'out'}",
            "detect.tile_size=128",
            "detect.overlap=32",
            "detect.score_threshold=0.0",
            "device=cpu",
        ],
    )
    with caplog.at_level("INFO"):
        run(cfg)
    preds = read_predictions(tmp_path / "out" / "predictions.json")["predictions"]
    b = np.array([p["bbox"] for p in preds], float)
    b[:, 2:] += b[:, :2]
    assert len(b) > 10 and _nested_pairs(b, np.array([p["category_id"] for p in preds])) == 0
    merged = [r.message for r in caplog.records if "nested box(es) merged" in r.message]
    assert merged and int(merged[0].split()[0]) > 0


# -- input checks (issue 15): checkpoints that are not MatchPlant's, runs that find nothing ----------------------


def test_checkpoint_errors_say_what_the_file_is(checkpoint, tmp_path):
    from matchplant.detection.checkpoint import load_detector, read_checkpoint

    data = torch.load(checkpoint, map_location="cpu", weights_only=False)
    cases = {
        "weights.pth": (lambda p: torch.save(data["model_state"], p), "bare weights"),
        "whole.pt": (lambda p: torch.save(load_detector(checkpoint)[0], p), "whole pickled model"),
        "cut.pt": (lambda p: p.write_bytes(Path(checkpoint).read_bytes()[:50_000]), "truncated"),
        "empty.pt": (lambda p: p.write_bytes(b""), "empty"),
        "notes.pt": (lambda p: p.write_text("epochs: 30\n"), "text file"),
        "yolo.pt": (
            lambda p: torch.save(dict(data, model_config=dict(data["model_config"], architecture="yolo")), p),
            "'yolo' model",
        ),
        "noclass.pt": (
            lambda p: torch.save({k: v for k, v in data.items() if k != "class_names"}, p),
            "'class_names' is missing",
        ),
    }
    for name, (write, said) in cases.items():
        write(tmp_path / name)
        with pytest.raises(InputError, match=said) as err:
            read_checkpoint(tmp_path / name)
        assert err.value.path == tmp_path / name and err.value.fix
    mixed = dict(data, model_config=dict(data["model_config"], architecture="fasterrcnn_resnet50_fpn"))
    torch.save(mixed, tmp_path / "mixed.pt")
    with pytest.raises(InputError, match="weights do not fit its model") as err:
        load_detector(tmp_path / "mixed.pt")
    assert err.value.path == tmp_path / "mixed.pt"


def test_detection_that_finds_nothing_says_why_and_writes_nothing(checkpoint, tmp_path):
    make_photo(tmp_path / "imgs" / "DJI_0001.JPG", 150, 100, n_plants=4, seed=3)
    common = [
        f"checkpoint={checkpoint}",
        f"detect.images={tmp_path / 'imgs'}",
        "detect.tile_size=128",
        "detect.overlap=32",
        "device=cpu",
    ]
    cfg = load_config(ModelTestConfig, None, [*common, f"output_dir={tmp_path / 'out'}", "detect.score_threshold=0.5"])
    with pytest.raises(InputError, match="no plant found on any of the 1 image") as err:
        run(cfg)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.json"))
    # the best score it reports is the best box of a run that keeps every box
    run(load_config(ModelTestConfig, None, [*common, f"output_dir={tmp_path / 'all'}", "detect.score_threshold=0"]))
    best = max(p["score"] for p in read_predictions(tmp_path / "all" / "predictions.json")["predictions"])
    assert f"scores {best:.3f}" in err.value.problem and "detect.score_threshold" in err.value.fix


def test_detection_on_an_image_smaller_than_the_tile_warns_and_uses_the_image(checkpoint, tmp_path, caplog):
    make_photo(tmp_path / "one.png", 90, 70, n_plants=3, seed=4)
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={checkpoint}",
            f"detect.images={tmp_path / 'one.png'}",
            f"output_dir={tmp_path / 'out'}",
            "detect.tile_size=1024",
            "detect.overlap=256",
            "detect.score_threshold=0",
            "device=cpu",
        ],
    )
    with caplog.at_level("WARNING"):
        run(cfg)
    assert any("larger than 1 of the 1 image" in r.message and "90x70" in r.message for r in caplog.records)
    preds = read_predictions(tmp_path / "out" / "predictions.json")
    assert [(im["file_name"], im["width"], im["height"]) for im in preds["images"]] == [("one.png", 90, 70)]


def test_rerun_into_the_same_folder_leaves_nothing_stale(checkpoint, tmp_path):
    """Issue 29: two runs with different images and settings into one folder; afterwards the folder holds what
    the second run's manifest lists (and a file of the user's), none of the first run's drawn images."""
    for name in ("a.png", "b.png", "c.png"):
        make_photo(tmp_path / "first" / name, 150, 120, n_plants=4, seed=len(name) + ord(name[0]))
    make_photo(tmp_path / "second" / "z.png", 150, 120, n_plants=4, seed=9)
    common = [
        f"checkpoint={checkpoint}",
        f"output_dir={tmp_path / 'out'}",
        "detect.tile_size=128",
        "detect.overlap=32",
        "detect.score_threshold=0.0",
        "device=cpu",
    ]
    run(load_config(ModelTestConfig, None, [*common, f"detect.images={tmp_path / 'first'}", "detect.drawn_images=3"]))

    def files():
        return {
            p.relative_to(tmp_path / "out").as_posix()
            for p in (tmp_path / "out").rglob("*")
            if p.is_file() and "logs" not in p.parts
        }

    assert {"detections/a.png", "detections/b.png", "detections/c.png"} <= files()
    assert files() == set(json.loads((tmp_path / "out" / "manifest.json").read_text())["files"])
    (tmp_path / "out" / "my_notes.txt").write_text("kept")
    run(load_config(ModelTestConfig, None, [*common, f"detect.images={tmp_path / 'second'}", "detect.drawn_images=1"]))
    listed = set(json.loads((tmp_path / "out" / "manifest.json").read_text())["files"])
    assert files() == listed | {"my_notes.txt"}
    assert listed == {"manifest.json", "predictions.json", "detections/z.png"}
    names = [im["file_name"] for im in read_predictions(tmp_path / "out" / "predictions.json")["images"]]
    assert names == ["z.png"]


def test_detection_estimate_counts_tiles_and_network_input():
    """Issue 29: 0.75 MP photos in 128 px tiles enlarged to 800 px cost >10x the same photos in 1024 px tiles."""
    from matchplant.model_test.estimate import plan

    mc = {"min_size": 800, "max_size": 1333}
    small = plan([(1000, 750)] * 40, 128, 32, mc)
    whole = plan([(1000, 750)] * 40, 1024, 256, mc)
    xs, ys = tile_starts(1000, 128, 32), tile_starts(750, 128, 32)
    assert small["tiles"] == 40 * len(xs) * len(ys) and whole["tiles"] == 40
    assert small["input_megapixels"] == pytest.approx(small["tiles"] * 800 * 800 / 1e6)
    assert whole["input_megapixels"] == pytest.approx(40 * 800 * 1088 / 1e6)  # 750 -> 800, 1000 -> 1067 (pad 32)
    assert small["input_megapixels"] / whole["input_megapixels"] > 10


def test_detection_estimate_holds_against_the_measured_run(checkpoint, tmp_path, caplog):
    """The estimate logged before detection is within 50 % of the detection's measured time."""
    for k in range(3):
        make_photo(tmp_path / "imgs" / f"p{k}.png", 420, 300, n_plants=10, seed=30 + k)
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={checkpoint}",
            f"detect.images={tmp_path / 'imgs'}",
            f"output_dir={tmp_path / 'out'}",
            "detect.tile_size=128",
            "detect.overlap=32",
            "detect.score_threshold=0.0",
            "device=cpu",
            "detect.drawn_images=0",
            "batch_size=1",
        ],
    )
    with caplog.at_level("INFO"):
        run(cfg)
    timing = read_predictions(tmp_path / "out" / "predictions.json")["info"]["timing"]
    assert timing["tiles"] == 3 * len(tile_starts(420, 128, 32)) * len(tile_starts(300, 128, 32))
    assert any("detection estimate" in r.message for r in caplog.records)
    assert 0.5 <= timing["estimated_s"] / timing["detection_s"] <= 1.5, timing
