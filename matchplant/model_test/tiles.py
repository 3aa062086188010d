"""Module 7 on one photo: where its tiles start, the predictor that runs the detector on tiles, and one photo's
detection with the merge of its tiles' boxes (a plant cut by a tile border is found once). The step
(:mod:`~matchplant.model_test.engine`), the benches and the tests detect with these."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from matchplant.detection.gpu import as_runtime
from matchplant.model_test.merge import merge_nested, merge_tile_boxes

Predictor = Callable[[list[np.ndarray]], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Tile origins along one axis: a step of ``tile - overlap``, the last tile flush with the edge."""
    if length <= tile:
        return [0]
    step = tile - overlap
    starts = list(range(0, length - tile + 1, step))
    if starts[-1] != length - tile:
        starts.append(length - tile)
    return starts


def model_predictor(model, device, amp: bool = False) -> Predictor:
    """A function from RGB uint8 tiles to ``(boxes xyxy, scores, labels)`` per tile.

    Parameters
    ----------
    model : torch.nn.Module
        A torchvision detector in eval mode, on ``device``.
    device : torch.device or Runtime
        Where the tiles go (a run's :class:`~matchplant.detection.gpu.Runtime`, or a bare device).
    amp : bool
        Mixed precision where the device supports it (CUDA).
    """
    import torch  # lazy: PyTorch is heavy; configs load without it

    runtime = as_runtime(device, amp)

    def predict(tiles: list[np.ndarray]):
        batch = [torch.from_numpy(t).to(runtime.device).permute(2, 0, 1).float().div_(255.0) for t in tiles]
        with torch.inference_mode(), torch.autocast(device_type=runtime.kind, enabled=runtime.amp):
            outputs = model(batch)
        return [
            (o["boxes"].float().cpu().numpy(), o["scores"].float().cpu().numpy(), o["labels"].cpu().numpy())
            for o in outputs
        ]

    return predict


def _cut_by_tile(b: np.ndarray, x0: int, y0: int, tile_shape, image_shape, edge_margin: float) -> np.ndarray:
    """Per box (tile pixels), whether it touches a border of the tile that is not a border of the image: such a
    border cuts plants."""
    (th, tw), (h, w) = tile_shape[:2], image_shape[:2]
    return (
        ((b[:, 0] <= edge_margin) & (x0 > 0))
        | ((b[:, 1] <= edge_margin) & (y0 > 0))
        | ((b[:, 2] >= tw - edge_margin) & (x0 + tw < w))
        | ((b[:, 3] >= th - edge_margin) & (y0 + th < h))
    )


def _tile_boxes(image, predictor, origins, tile_size, batch_size, score_threshold, edge_margin):
    """Every tile's boxes above the threshold, in image pixels: ``(boxes, scores, labels, cut, tile index)``."""
    all_b, all_s, all_l, all_cut, all_t = [], [], [], [], []
    for start in range(0, len(origins), batch_size):
        chunk = origins[start : start + batch_size]
        tiles = [image[y0 : y0 + tile_size, x0 : x0 + tile_size] for x0, y0 in chunk]
        for (x0, y0), tile, (b, s, lab) in zip(chunk, tiles, predictor(tiles)):
            sel = s >= score_threshold
            b, s, lab = b[sel].astype(float), s[sel], lab[sel]
            all_cut.append(_cut_by_tile(b, x0, y0, tile.shape, image.shape, edge_margin))
            all_b.append(b + [x0, y0, x0, y0])
            all_s.append(s)
            all_l.append(lab)
            all_t.append(np.full(len(b), len(all_t)))
    boxes, scores = np.concatenate(all_b).reshape(-1, 4), np.concatenate(all_s)
    labels, cut = np.concatenate(all_l).astype(int), np.concatenate(all_cut).astype(bool)
    return boxes, scores, labels, cut, np.concatenate(all_t)


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
    """Plants on one whole image, merged across tiles, then nested duplicates on the photo merged.

    Parameters
    ----------
    image : numpy.ndarray
        The photo, H x W x 3 RGB uint8.
    predictor : Predictor
        Tiles to ``(boxes, scores, labels)`` (:func:`model_predictor`, or the GPU's
        :class:`~matchplant.model_test.gpu_feed.DevicePredictor`).
    tile_size, overlap : int
        The tiles' side and overlap in pixels.
    batch_size : int
        Tiles per pass of the predictor.
    score_threshold, merge_iou, edge_margin, merge_containment : float
        The ``detect`` settings of the same names.
    counts : dict, optional
        Adds up the tiles run, the boxes found in them and the nested boxes merged.

    Returns
    -------
    tuple of numpy.ndarray
        ``(boxes xyxy, scores, labels)`` in image pixels.
    """
    h, w = image.shape[:2]
    origins = [(x0, y0) for y0 in tile_starts(h, tile_size, overlap) for x0 in tile_starts(w, tile_size, overlap)]
    boxes, scores, labels, cut, tile = _tile_boxes(
        image, predictor, origins, tile_size, batch_size, score_threshold, edge_margin
    )
    keep = merge_tile_boxes(boxes, scores, labels, cut, merge_iou, tile, merge_containment)
    boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
    keep = merge_nested(boxes, scores, labels, merge_containment)
    if counts is not None:
        for key, n in (("tiles", len(origins)), ("tile_boxes", len(cut)), ("nested_merged", len(boxes) - len(keep))):
            counts[key] = counts.get(key, 0) + n
    return boxes[keep], scores[keep], labels[keep]
