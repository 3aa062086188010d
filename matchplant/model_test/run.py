"""Module 7: evaluate a trained detector on test tiles, and detect plants on whole new images.

Evaluation (``evaluate`` section): every box the model finds (no score threshold) is scored by
pycocotools' COCOeval with ``maxDets`` raised for dense tiles; AP, AP50, AP75, AP by size (from the
ground-truth area), precision, recall and F1 at the operating threshold, a precision-recall curve, a
confidence histogram, images with drawn boxes and ``metrics.json``.

Detection (``detect`` section): whole undistorted images of any size are cut into overlapping tiles,
detected in batches, and the boxes merged across tiles, so a plant cut by a tile border is found once.
``predictions.json`` (docs/DESIGN.md §2, the input of module 8) holds the boxes in source-image pixels with each
image's name.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from matchplant.core.formats.images import image_size, read_rgb8
from matchplant.core.formats.odm import SUBMODELS_DIR
from matchplant.core.formats.predictions import write_predictions
from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.guard import staged_outputs
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.manifest import previous_files, remove_stale, write_manifest
from matchplant.core.runtime.progress import progress
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.data import CocoDetection
from matchplant.detection.device import configure_threads, select_device
from matchplant.detection.distributed import join
from matchplant.detection.evaluate import (
    coco_evaluate,
    draw_boxes,
    matches_at_iou50,
    operating_point,
    plot_pr_curve,
    plot_score_histogram,
    predict_dataset,
    summarise_stats,
    write_image,
)
from matchplant.detection.foreign import read_any_checkpoint
from matchplant.detection.model import set_score_threshold
from matchplant.detection.tile_objects import distinct_objects, found_objects
from matchplant.model_test.config import EvalConfig, ModelTestConfig
from matchplant.model_test.cover import images_to_detect
from matchplant.model_test.estimate import estimate
from matchplant.model_test.gpu_feed import detect_batch, detections, device_predictor
from matchplant.model_test.inputs import nothing_found, nothing_in_test
from matchplant.model_test.merge import merge_nested, merge_tile_boxes
from matchplant.model_test.runtime_onnx import torch_threads, with_runtime
from matchplant.model_test.scale import check_detect_scale, check_found_scale, check_test_scale, with_detect_settings

log = get_logger("model_test")


# --------------------------------------------------------------------------------------------------
# evaluation


METRIC_UNITS = (
    "fractions 0..1 for every AP, AR, precision, recall, F1 and threshold (no percents); 'images' "
    "counts test tiles, 'tile_boxes' annotated boxes in them, 'plants' distinct plants (one seen in two "
    "overlapping tiles counts once); 'coco' and 'at_threshold' score tile boxes, 'plants_found' "
    "distinct plants (found when any of their tile boxes is matched at IoU 0.5)"
)


def evaluate(
    cfg: ModelTestConfig,
    device=None,
    out: Path | None = None,
    *,
    ck: dict | None = None,
    ds: CocoDetection | None = None,
) -> dict:
    """COCO evaluation of the checkpoint on ``evaluate.dataset_json``; writes metrics, figures and predictions
    into ``out`` (by default ``output_dir``; :func:`run` gives a staging folder moved into place at the end).
    ``ck``, ``ds``: the checkpoint and test tiles, when :func:`run` has read and checked them already."""
    ecfg = cfg.evaluate
    final = Path(cfg.output_dir)
    out = Path(out) if out is not None else final
    device = device or select_device(cfg.device)
    amp = cfg.amp and device.type == "cuda"
    ck = ck or read_model(cfg)
    ds = ds or test_tiles(cfg, ck)
    # no score threshold before COCOeval, and as many boxes as maxDets
    model, ck = load_detector(
        ck, device, overrides={"roi": {"detections_per_img": ecfg.max_detections}}, source=cfg.checkpoint
    )
    set_score_threshold(model, 0.0)
    results = predict_dataset(
        model, ds, device, batch_size=cfg.batch_size, num_workers=cfg.num_workers, amp=amp, desc="evaluating"
    )
    if not results:
        raise nothing_in_test(len(ds), Path(ecfg.dataset_json), Path(cfg.checkpoint))
    stats, ev = coco_evaluate(ds.data, results, max_dets=ecfg.max_detections)
    object_of, n_plants = distinct_objects(ds.data)  # a plant in two overlapping tiles is one plant
    metrics = {
        "checkpoint": str(cfg.checkpoint),
        "dataset": str(ecfg.dataset_json),
        "units": METRIC_UNITS,
        "images": len(ds),
        "plants": n_plants,
        "tile_boxes": len(ds.data["annotations"]),
        "detections": len(results),
        "max_detections": ecfg.max_detections,
        "coco": stats,
        "plant_scale_vs_training": check_test_scale(ds.data, ck),
    }
    scores, hits, n_gt = matches_at_iou50(ev)
    metrics["at_threshold"] = operating_point(scores, hits, n_gt, ecfg.operating_threshold)
    found = found_objects(ev, object_of, ecfg.operating_threshold)
    metrics["plants_found"] = {
        "threshold": ecfg.operating_threshold,
        "plants": n_plants,
        "found": found,
        "recall": found / n_plants if n_plants else 0.0,
    }
    plot_pr_curve(ev, out / "pr_curve.png", metrics["at_threshold"], ck["class_names"])
    plot_score_histogram(scores, hits, out / "score_histogram.png", ecfg.operating_threshold)
    write_predictions(
        out / "test_predictions.json",
        [dict(im) for im in ds.images],
        ds.data["categories"],
        [dict(r, id=i + 1) for i, r in enumerate(results)],
        info={
            "description": "MatchPlant module 7 predictions on test tiles (no threshold)",
            "checkpoint": str(cfg.checkpoint),
        },
    )
    _draw_eval_images(ds, results, ecfg, out / "drawn")
    metrics["config"] = to_dict(cfg)
    write_json(out / "metrics.json", metrics)
    op = metrics["at_threshold"]
    log.info(
        "test: %s; at score >= %.2f: precision %.1f%%, recall %.1f%%, F1 %.1f%% (%s)",
        summarise_stats(stats),
        op["threshold"],
        100 * op["precision"],
        100 * op["recall"],
        100 * op["f1"],
        final / "metrics.json",
    )
    return metrics


def read_model(cfg: ModelTestConfig) -> dict:
    """The checkpoint: module 6's, the paper's layout or bare torchvision weights (their classes from
    ``class_names``)."""
    ck = read_any_checkpoint(cfg.checkpoint, class_names=list(cfg.class_names) or None)
    if cfg.class_names and "foreign" not in ck and list(cfg.class_names) != ck["class_names"]:
        log.warning(
            "class_names %s ignored: the module 6 checkpoint %s holds its own classes %s",
            list(cfg.class_names),
            cfg.checkpoint,
            ck["class_names"],
        )
    return ck


def test_tiles(cfg: ModelTestConfig, ck: dict) -> CocoDetection:
    """The test tiles, checked against their files and the checkpoint's classes."""
    return CocoDetection(
        cfg.evaluate.dataset_json,
        cfg.evaluate.images,
        class_names=ck["class_names"],
        classes_from=f"the checkpoint {cfg.checkpoint}",
    )


def _draw_eval_images(ds: CocoDetection, results: list[dict], ecfg: EvalConfig, folder: Path) -> None:
    if ecfg.drawn_images == 0:
        return
    picks = np.unique(np.linspace(0, len(ds) - 1, min(ecfg.drawn_images, len(ds))).round().astype(int))
    for i in picks:
        im = ds.images[i]
        img = read_rgb8(ds.paths[i])
        gt = ds.target(i)["boxes"].numpy()
        dets = [r for r in results if r["image_id"] == im["id"] and r["score"] >= ecfg.operating_threshold]
        b = np.asarray([r["bbox"] for r in dets], dtype=float).reshape(-1, 4)
        b[:, 2:] += b[:, :2]
        drawn = draw_boxes(draw_boxes(img, gt, (0, 200, 0)), b, (230, 30, 30), np.asarray([r["score"] for r in dets]))
        write_image(folder / (Path(im["file_name"]).stem + ".png"), drawn)


# --------------------------------------------------------------------------------------------------
# tiled detection


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Tile origins along one axis: a step of ``tile - overlap``, the last tile flush with the edge."""
    if length <= tile:
        return [0]
    step = tile - overlap
    starts = list(range(0, length - tile + 1, step))
    if starts[-1] != length - tile:
        starts.append(length - tile)
    return starts


Predictor = Callable[[list[np.ndarray]], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]


def model_predictor(model, device, amp: bool = False) -> Predictor:
    """A function from RGB uint8 tiles to ``(boxes xyxy, scores, labels)`` per tile."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    def predict(tiles: list[np.ndarray]):
        batch = [torch.from_numpy(t).to(device).permute(2, 0, 1).float().div_(255.0) for t in tiles]
        with torch.inference_mode(), torch.autocast(device_type=device.type, enabled=amp and device.type == "cuda"):
            outputs = model(batch)
        return [
            (o["boxes"].float().cpu().numpy(), o["scores"].float().cpu().numpy(), o["labels"].cpu().numpy())
            for o in outputs
        ]

    return predict


def detect_image(
    image: np.ndarray,
    predictor: Predictor,
    *,
    tile_size: int,
    overlap: int,
    batch_size: int = 4,
    score_threshold: float = 0.5,
    merge_iou: float = 0.5,
    edge_margin: float = 2.0,
    merge_containment: float = 0.8,
    counts: dict | None = None,
):
    """Plants on one whole image: ``(boxes xyxy, scores, labels)`` in image pixels, merged across tiles, then
    nested duplicates on the photo merged (:func:`merge_nested`). ``counts`` (a dict) adds up the tiles run, the
    boxes found in them and the nested boxes merged."""
    h, w = image.shape[:2]
    origins = [(x0, y0) for y0 in tile_starts(h, tile_size, overlap) for x0 in tile_starts(w, tile_size, overlap)]
    all_b, all_s, all_l, all_cut, all_t = [], [], [], [], []
    for start in range(0, len(origins), batch_size):
        chunk = origins[start : start + batch_size]
        tiles = [image[y0 : y0 + tile_size, x0 : x0 + tile_size] for x0, y0 in chunk]
        for (x0, y0), tile, (b, s, lab) in zip(chunk, tiles, predictor(tiles)):
            sel = s >= score_threshold
            b, s, lab = b[sel].astype(float), s[sel], lab[sel]
            th, tw = tile.shape[:2]
            # a border of the tile that is not a border of the image cuts plants
            cut = (
                ((b[:, 0] <= edge_margin) & (x0 > 0))
                | ((b[:, 1] <= edge_margin) & (y0 > 0))
                | ((b[:, 2] >= tw - edge_margin) & (x0 + tw < w))
                | ((b[:, 3] >= th - edge_margin) & (y0 + th < h))
            )
            all_b.append(b + [x0, y0, x0, y0])
            all_s.append(s)
            all_l.append(lab)
            all_cut.append(cut)
            all_t.append(np.full(len(b), len(all_t)))
    boxes, scores = np.concatenate(all_b).reshape(-1, 4), np.concatenate(all_s)
    labels, cut = np.concatenate(all_l).astype(int), np.concatenate(all_cut).astype(bool)
    keep = merge_tile_boxes(boxes, scores, labels, cut, merge_iou, np.concatenate(all_t), merge_containment)
    boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
    keep = merge_nested(boxes, scores, labels, merge_containment)
    if counts is not None:
        for key, n in (("tiles", len(origins)), ("tile_boxes", len(cut)), ("nested_merged", len(boxes) - len(keep))):
            counts[key] = counts.get(key, 0) + n
    return boxes[keep], scores[keep], labels[keep]


def detect(
    cfg: ModelTestConfig,
    device=None,
    out: Path | None = None,
    *,
    ck: dict | None = None,
    files: list[Path] | None = None,
    every: list[Path] | None = None,
    listed: list[str] | None = None,
) -> Path:
    """Detect plants on every image of ``detect.images``; writes ``predictions.json`` and drawn images into
    ``out`` (by default ``output_dir``). A run that finds no plant at all is an error that says why.
    ``ck``, ``files``: the checkpoint and the checked images, when :func:`run` has read them already;
    ``listed`` gets the drawn images of every process (relative paths, on the main process)."""
    final = Path(cfg.output_dir)
    out = Path(out) if out is not None else final
    ck = ck or read_model(cfg)
    cfg = with_detect_settings(cfg, ck)  # a null detect.tile_size / overlap: the checkpoint's training tiles'
    dcfg = cfg.detect
    check_detect_scale(dcfg, ck)  # plants >2x or <0.5x their training size in the detector's input
    if files is None:
        files, every = images_to_detect(cfg.detect)
    shard, device = join(device or select_device(cfg.device))  # one share of the images per torchrun process
    model, ck = load_detector(ck, device, source=cfg.checkpoint)
    set_score_threshold(model, dcfg.score_threshold)
    model = with_runtime(model, dcfg.runtime, device, torch_threads())
    predictor = device_predictor(model, device, cfg.amp) or model_predictor(model, device, cfg.amp)
    batch = detect_batch(cfg.batch_size, device, dcfg.tile_size, ck["model_config"])  # CUDA: from free memory
    # before hours of work: the actual tiles and network input of every photo, timed on this device
    plan = estimate(
        predictor,
        read_rgb8(files[0]),
        [image_size(f) for f in files],
        dcfg.tile_size,
        dcfg.overlap,
        ck["model_config"],
        device,
        processes=shard.world,
        every=[image_size(f) for f in every] if every is not None and len(every) != len(files) else None,
        batch=batch if device.type == "cuda" else 1,  # a CPU's time per tile does not depend on the batch
    )
    started = time.perf_counter()
    root = Path(dcfg.images) if Path(dcfg.images).is_dir() else Path(dcfg.images).parent
    cat_ids = [int(c) for c in ck["category_ids"]]
    categories = [{"id": cid, "name": name, "supercategory": "plant"} for cid, name in zip(cat_ids, ck["class_names"])]
    draw_every = max(1, int(np.ceil(len(files) / dcfg.drawn_images))) if dcfg.drawn_images else 0
    tiling = dict(
        tile_size=dcfg.tile_size,
        overlap=dcfg.overlap,
        batch_size=batch,
        merge_iou=dcfg.merge_iou,
        edge_margin=dcfg.edge_margin,
        merge_containment=dcfg.merge_containment,
    )
    mine = []  # (image index, image entry, boxes) of this process's share (all of them without torchrun)
    counts: dict = {}
    drawn: list[str] = []  # this process's drawn images (the manifest lists every process's)
    mine_idx = shard.take(files)

    def detect_one(img, pred, photo_counts):
        return detect_image(img, pred, score_threshold=dcfg.score_threshold, counts=photo_counts, **tiling)

    # on CUDA: photos decoded ahead, two in flight (model_test/gpu_feed.py); elsewhere one after another
    found = detections(mine_idx, files, device, predictor, detect_one)
    for i, img, (boxes, scores, labels), photo_counts in progress(
        found, desc="detecting", unit="image", total=len(mine_idx)
    ):
        path = files[i]
        for key, n in photo_counts.items():
            counts[key] = counts.get(key, 0) + n
        name = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        if (root / SUBMODELS_DIR).is_dir():
            name = path.name  # <shot>.tif: one image of a split-merge project, whichever submodel holds it
        mine.append(
            (
                i,
                {
                    "id": i + 1,
                    "file_name": name,
                    "width": int(img.shape[1]),
                    "height": int(img.shape[0]),
                    "source_image": name,
                    "x0": 0,
                    "y0": 0,
                },
                [
                    (
                        cat_ids[int(lab) - 1],
                        [
                            round(float(b[0]), 2),
                            round(float(b[1]), 2),
                            round(float(b[2] - b[0]), 2),
                            round(float(b[3] - b[1]), 2),
                        ],
                        round(float(s), 5),
                    )
                    for b, s, lab in zip(boxes, scores, labels)
                ],
            )
        )
        if draw_every and i % draw_every == 0:
            write_image(out / "detections" / (path.stem + ".png"), draw_boxes(img, boxes, (230, 30, 30), scores))
            drawn.append(f"detections/{path.stem}.png")
    seconds = time.perf_counter() - started
    gathered = sorted(shard.gather(mine), key=lambda r: r[0])  # a single process's order
    merged = sum(c.get("nested_merged", 0) for c in shard.gather([counts]))
    drawn_by_all = shard.gather(drawn)
    if not shard.main:
        shard.barrier()
        return final / "predictions.json"
    log.info(
        "%d nested box(es) merged: of two boxes of a class on a photo, one >= %.0f %% inside the other "
        "(detect.merge_containment), the lower-scoring one dropped (on equal scores, the inner one)",
        merged,
        100 * dcfg.merge_containment,
    )
    check_found_scale(
        ck,
        [
            (
                np.asarray([[x, y, x + w, y + h] for _, (x, y, w, h), _ in found], float).reshape(-1, 4),
                entry["width"],
                entry["height"],
            )
            for _, entry, found in gathered
        ],
        dcfg.tile_size,
    )
    images, predictions = [], []
    for i, entry, found in gathered:
        images.append(entry)
        predictions += [
            {"id": len(predictions) + k + 1, "image_id": i + 1, "category_id": c, "bbox": b, "score": s}
            for k, (c, b, s) in enumerate(found)
        ]
    if not predictions:  # say why (the best score at any threshold, the scale), rather than write an empty file
        set_score_threshold(model, 0.0)
        _, scores, _ = detect_image(read_rgb8(files[0]), predictor, score_threshold=0.0, **tiling)
        error = nothing_found(
            len(files),
            files[0],
            float(scores.max()) if len(scores) else None,
            dcfg.score_threshold,
            dcfg.tile_size,
            ck["model_config"],
            Path(cfg.checkpoint),
        )
        shard.barrier()
        raise error
    write_predictions(
        out / "predictions.json",
        images,
        categories,
        predictions,
        info={
            "description": "MatchPlant module 7 detections (source-image pixels)",
            "checkpoint": str(cfg.checkpoint),
            "tile_size": dcfg.tile_size,
            "overlap": dcfg.overlap,
            "score_threshold": dcfg.score_threshold,
            "cover": dcfg.cover,
            "timing": {
                "estimated_s": round(plan["seconds"], 3),
                "detection_s": round(seconds, 3),
                "tiles": plan["tiles"],
                "input_megapixels": round(plan["input_megapixels"], 3),
                "device": plan["device"],
            },
        },
    )
    path = final / "predictions.json"
    if listed is not None:
        listed += drawn_by_all
    log.info(
        "%d plants found on %d image(s)%s: %s",
        len(predictions),
        len(files),
        f" by {shard.world} processes" if shard.world > 1 else "",
        path,
    )
    shard.barrier()
    return path


def run(cfg: ModelTestConfig) -> dict:
    """Evaluation and/or detection; every output appears at the end, together (a failed run leaves none)."""
    shard, device = join(select_device(cfg.device))
    if device.type == "cpu":
        configure_threads(cfg.threads or None)  # the cores free for this process, not every core (issue 29)
    # every input read and checked before the first (slow) model pass
    ck = read_model(cfg)
    cfg = with_detect_settings(cfg, ck)  # a null detect.tile_size / overlap: the checkpoint's training tiles'
    ds = test_tiles(cfg, ck) if cfg.evaluate.dataset_json is not None and shard.main else None
    files, every = images_to_detect(cfg.detect) if cfg.detect.images is not None else (None, None)
    if shard.world > 1:  # every process stages its own files: the folder they move into must exist first
        Path(cfg.output_dir).mkdir(parents=True, exist_ok=True)
    result: dict = {}
    before = previous_files(cfg.output_dir)
    with staged_outputs(cfg.output_dir) as out:
        if cfg.evaluate.dataset_json is not None and shard.main:  # under torchrun: evaluated once
            result["metrics"] = evaluate(cfg, device, out, ck=ck, ds=ds)
        drawn: list[str] = []  # every process's drawn images
        if files is not None:
            result["predictions"] = detect(cfg, device, out, ck=ck, files=files, every=every, listed=drawn)
        now = write_manifest(out, drawn) if shard.main else []
    if shard.main:  # only once the new outputs are in place; the other processes' drawn images are in `now`
        remove_stale(Path(cfg.output_dir), before, now)
    shard.leave()
    return result
