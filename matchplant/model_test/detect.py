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

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from matchplant.core.coco import write_predictions
from matchplant.core.config import param, section, to_dict
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.images import list_images as list_image_files
from matchplant.core.images import read_rgb8
from matchplant.core.io import write_json
from matchplant.core.log import get_logger
from matchplant.core.progress import progress
from matchplant.detection.data import CocoDetection
from matchplant.detection.device import select_device
from matchplant.detection.evaluate import (coco_evaluate, draw_boxes, matches_at_iou50, operating_point, plot_pr_curve,
                                           plot_score_histogram, predict_dataset, summarise_stats, write_image)
from matchplant.detection.model import load_detector, read_checkpoint

log = get_logger("model_test")


@dataclass
class EvalConfig:
    """Evaluation on annotated tiles (module 5's test split)."""

    dataset_json: Path | None = param(None, "COCO JSON of the test tiles; null = no evaluation", path="file")
    images: Path | None = param(None, "folder of the test tiles; null = the JSON's folder", path="dir")
    max_detections: int = param(300, "boxes per tile kept and scored (COCOeval maxDets; COCO's 100 loses "
                                     "plants on dense tiles)", min=1)
    operating_threshold: float = param(0.5, "score threshold for precision, recall, F1 and drawn boxes",
                                       min=0, max=1)
    drawn_images: int = param(8, "how many tiles to draw with their true (green) and found (red) boxes", min=0)


@dataclass
class DetectConfig:
    """Detection on whole new images (undistorted photos), tiled with overlap and merged."""

    images: Path | None = param(None, "an image or a folder of images (e.g. ODM's opensfm/undistorted/images); "
                                      "null = no detection", path="exists")
    tile_size: int = param(1024, "tile side in pixels (use the size the model was trained on)", min=32)
    overlap: int = param(256, "overlap between tiles in pixels; make it larger than the largest plant", min=0)
    score_threshold: float = param(0.5, "keep boxes scoring at least this", min=0, max=1)
    merge_iou: float = param(0.5, "boxes of the same class from overlapping tiles with IoU above this are "
                                  "one plant", min=0, max=1)
    edge_margin: float = param(2.0, "a box within this many pixels of a tile border inside the image is "
                                    "'cut'; it is dropped when another tile sees the whole plant", min=0)
    drawn_images: int = param(4, "how many images to draw with their detections", min=0)


@dataclass
class ModelTestConfig:
    """Module 7: COCO evaluation of a trained detector and detection on new images."""

    checkpoint: Path = param(None, "model checkpoint from module 6 (e.g. runs/train/checkpoints/best.pt)",
                             path="file", required=True)
    output_dir: Path = param(Path("runs/test"), "where metrics, figures and predictions go", path="out")
    evaluate: EvalConfig = section(EvalConfig)
    detect: DetectConfig = section(DetectConfig)
    batch_size: int = param(4, "tiles per batch", min=1)
    num_workers: int = param(0, "processes loading test tiles (0 = in the main process)", min=0)
    device: str = param("auto", "auto picks CUDA, then Apple MPS, then CPU; or cpu, cuda, cuda:N, mps")
    amp: bool = param(True, "mixed precision on CUDA GPUs")

    def check(self) -> None:
        if self.detect.overlap >= self.detect.tile_size:
            raise ConfigError(f"detect.overlap ({self.detect.overlap}) must be smaller than detect.tile_size "
                              f"({self.detect.tile_size})", fix="lower detect.overlap (e.g. a quarter of the tile)")
        if self.evaluate.dataset_json is None and self.detect.images is None:
            raise ConfigError("nothing to do: neither evaluate.dataset_json nor detect.images is set",
                              fix="set evaluate.dataset_json (test tiles) and/or detect.images (new images)")


# --------------------------------------------------------------------------------------------------
# evaluation


def evaluate(cfg: ModelTestConfig, device=None) -> dict:
    """COCO evaluation of the checkpoint on ``evaluate.dataset_json``; writes metrics, figures, predictions."""
    ecfg = cfg.evaluate
    out = Path(cfg.output_dir)
    device = device or select_device(cfg.device)
    amp = cfg.amp and device.type == "cuda"
    # no score threshold before COCOeval, and as many boxes as maxDets
    model, ck = load_detector(cfg.checkpoint, device, overrides={"roi": {"detections_per_img": ecfg.max_detections}})
    model.roi_heads.score_thresh = 0.0
    ds = CocoDetection(ecfg.dataset_json, ecfg.images, class_names=ck["class_names"])
    results = predict_dataset(model, ds, device, batch_size=cfg.batch_size, num_workers=cfg.num_workers, amp=amp,
                              desc="evaluating")
    stats, ev = coco_evaluate(ds.data, results, max_dets=ecfg.max_detections)
    metrics = {"checkpoint": str(cfg.checkpoint), "dataset": str(ecfg.dataset_json), "images": len(ds),
               "plants": len(ds.data["annotations"]), "detections": len(results), "max_detections": ecfg.max_detections,
               "coco": stats}
    if ev is not None:
        scores, hits, n_gt = matches_at_iou50(ev)
        metrics["at_threshold"] = operating_point(scores, hits, n_gt, ecfg.operating_threshold)
        plot_pr_curve(ev, out / "pr_curve.png", metrics["at_threshold"], ck["class_names"])
        plot_score_histogram(scores, hits, out / "score_histogram.png", ecfg.operating_threshold)
    else:
        metrics["at_threshold"] = operating_point(np.zeros(0), np.zeros(0, bool), len(ds.data["annotations"]),
                                                  ecfg.operating_threshold)
    write_predictions(out / "test_predictions.json", [dict(im) for im in ds.images], ds.data["categories"],
                      [dict(r, id=i + 1) for i, r in enumerate(results)],
                      info={"description": "MatchPlant module 7 predictions on test tiles (no threshold)",
                            "checkpoint": str(cfg.checkpoint)})
    _draw_eval_images(ds, results, ecfg, out / "drawn")
    metrics["config"] = to_dict(cfg)
    write_json(out / "metrics.json", metrics)
    op = metrics["at_threshold"]
    log.info("test: %s; at score >= %.2f: precision %.1f%%, recall %.1f%%, F1 %.1f%% (%s)", summarise_stats(stats),
             op["threshold"], 100 * op["precision"], 100 * op["recall"], 100 * op["f1"], out / "metrics.json")
    return metrics


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


def _box_intersections(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = np.clip(rb - lt, 0, None)
    return wh[..., 0] * wh[..., 1]


def merge_tile_boxes(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, cut: np.ndarray,
                     iou: float = 0.5) -> np.ndarray:
    """Indices of the boxes kept after merging detections of overlapping tiles (image pixels).

    Whole boxes: class-wise NMS at ``iou`` (the same plant seen whole in two tiles). A ``cut`` box (it
    touches a tile border inside the image) is a part of a plant; it is dropped when at least half of
    it lies inside a kept whole box of its class, else kept through the same NMS (a plant larger than
    the overlap, seen cut in every tile).
    """
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torchvision.ops import batched_nms

    if len(boxes) == 0:
        return np.zeros(0, dtype=int)
    whole = np.flatnonzero(~cut)
    keep_whole = whole[batched_nms(torch.as_tensor(boxes[whole], dtype=torch.float64),
                                   torch.as_tensor(scores[whole], dtype=torch.float64),
                                   torch.as_tensor(labels[whole]), iou).numpy()] if len(whole) else whole
    parts = np.flatnonzero(cut)
    if len(parts) and len(keep_whole):
        inter = _box_intersections(boxes[parts], boxes[keep_whole])
        area = np.prod(boxes[parts, 2:] - boxes[parts, :2], axis=1)
        covered = ((inter / np.maximum(area, 1e-9)[:, None] >= 0.5)
                   & (labels[parts][:, None] == labels[keep_whole][None, :])).any(axis=1)
        parts = parts[~covered]
    if len(parts):
        parts = parts[batched_nms(torch.as_tensor(boxes[parts], dtype=torch.float64),
                                  torch.as_tensor(scores[parts], dtype=torch.float64),
                                  torch.as_tensor(labels[parts]), iou).numpy()]
    kept = np.concatenate([keep_whole, parts])
    return kept[np.argsort(-scores[kept], kind="stable")]


Predictor = Callable[[list[np.ndarray]], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]


def model_predictor(model, device, amp: bool = False) -> Predictor:
    """A function from RGB uint8 tiles to ``(boxes xyxy, scores, labels)`` per tile."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    def predict(tiles: list[np.ndarray]):
        batch = [torch.from_numpy(t).to(device).permute(2, 0, 1).float().div_(255.0) for t in tiles]
        with torch.inference_mode(), torch.autocast(device_type=device.type, enabled=amp and device.type == "cuda"):
            outputs = model(batch)
        return [(o["boxes"].float().cpu().numpy(), o["scores"].float().cpu().numpy(), o["labels"].cpu().numpy())
                for o in outputs]
    return predict


def detect_image(image: np.ndarray, predictor: Predictor, *, tile_size: int, overlap: int, batch_size: int = 4,
                 score_threshold: float = 0.5, merge_iou: float = 0.5, edge_margin: float = 2.0):
    """Plants on one whole image: ``(boxes xyxy, scores, labels)`` in image pixels, merged across tiles."""
    h, w = image.shape[:2]
    origins = [(x0, y0) for y0 in tile_starts(h, tile_size, overlap) for x0 in tile_starts(w, tile_size, overlap)]
    all_b, all_s, all_l, all_cut = [], [], [], []
    for start in range(0, len(origins), batch_size):
        chunk = origins[start:start + batch_size]
        tiles = [image[y0:y0 + tile_size, x0:x0 + tile_size] for x0, y0 in chunk]
        for (x0, y0), tile, (b, s, lab) in zip(chunk, tiles, predictor(tiles)):
            sel = s >= score_threshold
            b, s, lab = b[sel].astype(float), s[sel], lab[sel]
            th, tw = tile.shape[:2]
            # a border of the tile that is not a border of the image cuts plants
            cut = (((b[:, 0] <= edge_margin) & (x0 > 0)) | ((b[:, 1] <= edge_margin) & (y0 > 0))
                   | ((b[:, 2] >= tw - edge_margin) & (x0 + tw < w)) | ((b[:, 3] >= th - edge_margin) & (y0 + th < h)))
            all_b.append(b + [x0, y0, x0, y0])
            all_s.append(s)
            all_l.append(lab)
            all_cut.append(cut)
    boxes, scores = np.concatenate(all_b).reshape(-1, 4), np.concatenate(all_s)
    labels, cut = np.concatenate(all_l).astype(int), np.concatenate(all_cut).astype(bool)
    keep = merge_tile_boxes(boxes, scores, labels, cut, merge_iou)
    return boxes[keep], scores[keep], labels[keep]


def list_images(path: Path) -> list[Path]:
    """``detect.images``: one image file, or every image of a folder."""
    if path.is_file():
        return [path]
    fix = "point detect.images at the undistorted images (opensfm/undistorted/images)"
    files = list_image_files(path, key="detect.images", fix=fix, min_count=0)
    if not files:
        raise InputError("no images (JPEG, PNG, TIFF) in this folder", path=path, fix=fix)
    return files


def detect(cfg: ModelTestConfig, device=None) -> Path:
    """Detect plants on every image of ``detect.images``; writes ``predictions.json`` and drawn images."""
    dcfg = cfg.detect
    out = Path(cfg.output_dir)
    device = device or select_device(cfg.device)
    ck = read_checkpoint(cfg.checkpoint)
    model, ck = load_detector(ck, device)
    model.roi_heads.score_thresh = dcfg.score_threshold
    predictor = model_predictor(model, device, cfg.amp)
    files = list_images(Path(dcfg.images))
    root = Path(dcfg.images) if Path(dcfg.images).is_dir() else Path(dcfg.images).parent
    cat_ids = [int(c) for c in ck["category_ids"]]
    categories = [{"id": cid, "name": name, "supercategory": "plant"} for cid, name in zip(cat_ids, ck["class_names"])]
    images, predictions = [], []
    draw_every = max(1, int(np.ceil(len(files) / dcfg.drawn_images))) if dcfg.drawn_images else 0
    for i, path in enumerate(progress(files, desc="detecting", unit="image")):
        img = read_rgb8(path)
        boxes, scores, labels = detect_image(img, predictor, tile_size=dcfg.tile_size, overlap=dcfg.overlap,
                                             batch_size=cfg.batch_size, score_threshold=dcfg.score_threshold,
                                             merge_iou=dcfg.merge_iou, edge_margin=dcfg.edge_margin)
        name = path.relative_to(root).as_posix()
        images.append({"id": i + 1, "file_name": name, "width": int(img.shape[1]), "height": int(img.shape[0]),
                       "source_image": name, "x0": 0, "y0": 0})
        for b, s, lab in zip(boxes, scores, labels):
            predictions.append({"id": len(predictions) + 1, "image_id": i + 1, "category_id": cat_ids[int(lab) - 1],
                                "bbox": [round(float(b[0]), 2), round(float(b[1]), 2), round(float(b[2] - b[0]), 2),
                                         round(float(b[3] - b[1]), 2)], "score": round(float(s), 5)})
        if draw_every and i % draw_every == 0:
            write_image(out / "detections" / (path.stem + ".png"), draw_boxes(img, boxes, (230, 30, 30), scores))
    path = write_predictions(out / "predictions.json", images, categories, predictions,
                             info={"description": "MatchPlant module 7 detections (source-image pixels)",
                                   "checkpoint": str(cfg.checkpoint), "tile_size": dcfg.tile_size,
                                   "overlap": dcfg.overlap, "score_threshold": dcfg.score_threshold})
    log.info("%d plants found on %d image(s): %s", len(predictions), len(files), path)
    return path


def run(cfg: ModelTestConfig) -> dict:
    device = select_device(cfg.device)
    result: dict = {}
    if cfg.evaluate.dataset_json is not None:
        result["metrics"] = evaluate(cfg, device)
    if cfg.detect.images is not None:
        result["predictions"] = detect(cfg, device)
    return result
