"""Merging a photo's detections: boxes from overlapping tiles (NMS, cut plants, nested duplicates across
tiles), then one pass over the photo's final boxes for nested duplicates. Of a nested pair the box kept is the
better one: the higher score, then the larger (containing) box."""

from __future__ import annotations

import numpy as np

from matchplant.core.geometry.boxes import nms, overlapping_pairs


def _box_intersections(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = np.clip(rb - lt, 0, None)
    return wh[..., 0] * wh[..., 1]


def _touching(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, intersection area)`` of the box pairs ``a[i]``, ``b[j]`` that overlap, in ``(i, j)`` order, found
    through the core's grid (:func:`matchplant.core.geometry.boxes.overlapping_pairs`): a photo's thousands of boxes
    meet only their neighbours, so the pairs are few where a dense matrix would be n x m."""
    if not len(a) or not len(b):
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    i, j, _ = overlapping_pairs(a, b)
    wh = np.clip(np.minimum(a[i, 2:], b[j, 2:]) - np.maximum(a[i, :2], b[j, :2]), 0, None)
    inter = wh[:, 0] * wh[:, 1]
    ok = inter > 0
    return i[ok], j[ok], inter[ok]


def merge_tile_boxes(
    boxes: np.ndarray,
    scores: np.ndarray,
    labels: np.ndarray,
    cut: np.ndarray,
    iou: float = 0.5,
    tiles: np.ndarray | None = None,
    containment: float = 0.8,
) -> np.ndarray:
    """Indices of the boxes kept after merging detections of overlapping tiles (image pixels).

    Whole boxes: class-wise NMS at ``iou`` (the same plant seen whole in two tiles). A ``cut`` box (it
    touches a tile border inside the image) is a part of a plant; it is dropped when at least half of
    it lies inside a kept whole box of its class, else kept through the same NMS (a plant larger than
    the overlap, seen cut in every tile). With ``tiles`` (each box's tile number), of two kept boxes of a
    class from two tiles, one at least ``containment`` inside the other (IoU too low for NMS), the
    lower-scoring one is a nested duplicate and is dropped, unless its own tile also saw the other's plant
    (then they are two plants; :func:`_nested`); boxes of one tile keep the model's decision.
    """
    if len(boxes) == 0:
        return np.zeros(0, dtype=int)
    whole = np.flatnonzero(~cut)
    keep_whole = whole[nms(boxes[whole], scores[whole], iou, labels[whole])]
    parts = np.flatnonzero(cut)
    if len(parts) and len(keep_whole):
        i, j, inter = _touching(boxes[parts], boxes[keep_whole])
        area = np.prod(boxes[parts, 2:] - boxes[parts, :2], axis=1)
        hit = (inter / np.maximum(area[i], 1e-9) >= 0.5) & (labels[parts][i] == labels[keep_whole][j])
        covered = np.zeros(len(parts), bool)
        covered[i[hit]] = True
        parts = parts[~covered]
    if len(parts):
        parts = parts[nms(boxes[parts], scores[parts], iou, labels[parts])]
    kept = np.concatenate([keep_whole, parts])
    if tiles is not None and len(kept) > 1:
        kept = kept[~_nested(boxes, labels, np.asarray(tiles), kept, containment, iou, scores)]
    return kept[np.argsort(-scores[kept], kind="stable")]


def _nested(
    boxes: np.ndarray,
    labels: np.ndarray,
    tiles: np.ndarray,
    kept: np.ndarray,
    containment: float,
    iou: float,
    scores: np.ndarray,
) -> np.ndarray:
    """Which of the ``kept`` boxes are nested duplicates: one of a pair of their class from two tiles, one at
    least ``containment`` inside the other, the worse of the two (:func:`_pairs_best_first`) - unless its own
    tile also saw the better one's plant (a box of that tile with IoU >= ``iou`` with it: then the two are two
    plants that tile told apart). A dropped box drops nothing."""
    b, lab, til = boxes[kept], labels[kept], tiles[kept]
    area = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    all_area = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    groups: dict[tuple, np.ndarray] = {}  # the boxes of each (tile, class)
    dropped = np.zeros(len(b), bool)
    for better, worse in _pairs_best_first(b, lab, scores[kept], area, containment, til):
        if dropped[better] or dropped[worse]:
            continue
        key = (int(til[worse]), int(lab[worse]))
        if key not in groups:
            groups[key] = np.flatnonzero((tiles == key[0]) & (labels == key[1]))
        own = groups[key]
        own = own[own != kept[worse]]
        inter = _box_intersections(b[better][None], boxes[own])[0]
        seen = inter / np.maximum(area[better] + all_area[own] - inter, 1e-9) >= iou
        dropped[worse] = not seen.any()
    return dropped


def _pairs_best_first(b, lab, scores, area, containment: float, tiles=None):
    """The nested pairs ``(better, worse)`` of ``b``: one box at least ``containment`` inside the other, of one
    class (and, with ``tiles``, from two tiles), the better the higher-scoring one - on equal scores the
    larger, which holds the other (a part of a plant is found less surely than the plant; but where the
    inner box scores higher, the outer is a false merge of the plant with its surroundings: on real sorghum
    photos the inner box was the right panicle in 5 of 12 nested pairs). Sorted by the better box's rank,
    best first, so that a greedy pass keeps the best box of every chain."""
    inner, outer = _inside_pairs(b, lab, area, containment)
    if tiles is not None:
        other = tiles[inner] != tiles[outer]
        inner, outer = inner[other], outer[other]
    rank = np.empty(len(b), int)
    rank[np.lexsort((-area, -scores))] = np.arange(len(b))  # score first, then the larger (containing) box
    inner_better = rank[inner] < rank[outer]
    better, worse = np.where(inner_better, inner, outer), np.where(inner_better, outer, inner)
    order = np.argsort(rank[better], kind="stable")
    return zip(better[order].tolist(), worse[order].tolist())


def _inside_pairs(b: np.ndarray, lab: np.ndarray, area: np.ndarray, containment: float):
    """``(inner, outer)``: box ``inner`` lies at least ``containment`` inside the larger box ``outer`` of its
    class (equal areas: the later one is the inner)."""
    i, j, inter = _touching(b, b)
    larger = (area[i] < area[j]) | ((area[i] == area[j]) & (i > j))
    ok = (i != j) & larger & (inter >= containment * np.maximum(area[i], 1e-9)) & (lab[i] == lab[j])
    return i[ok], j[ok]


def merge_nested(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, containment: float = 0.8) -> np.ndarray:
    """Indices of a photo's final boxes kept after one pass over them: of two boxes of a class on the photo, one
    lying at least ``containment`` inside the other, the worse (lower score; on equal scores the inner one,
    :func:`_pairs_best_first`) is a nested duplicate (a part of the plant, or the plant merged with its
    surroundings) and is merged into the better. The same rule as across tiles (:func:`_nested`; a dropped box
    drops nothing), without its exception for boxes of one tile: the photo's output holds no box that far
    inside another."""
    n = len(boxes)
    if n < 2:
        return np.arange(n)
    area = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    dropped = np.zeros(n, bool)
    for better, worse in _pairs_best_first(boxes, labels, np.asarray(scores, float), area, containment):
        if not (dropped[better] or dropped[worse]):
            dropped[worse] = True
    return np.flatnonzero(~dropped)
