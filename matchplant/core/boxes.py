"""Axis-aligned boxes ``[xmin, ymin, xmax, ymax]``: IoU, overlapping pairs and one-to-one matching.

One implementation for every step that compares boxes or plants: merging the views of one plant and
scoring projected plants (step 8), matching two plant sets (step 9). Candidate pairs come from one bulk
R-tree query, so the cost grows with the number of overlaps, not with the product of the set sizes.
"""

from __future__ import annotations

import numpy as np
import shapely


def iou_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of box pairs ``a[i]``, ``b[i]`` (each (N, 4), ``[xmin, ymin, xmax, ymax]``)."""
    iw = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0, None)
    ih = np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0, None)
    inter = iw * ih
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    union = area(a) + area(b) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def overlapping_pairs(a: np.ndarray, b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs of overlapping boxes and their IoU (within one set when ``b`` is None, i < j)."""
    same = b is None
    b = a if same else b
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # one bulk R-tree query of the envelopes (which are the boxes: no geometric predicate needed)
    gb = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    i, j = shapely.STRtree(gb).query(gb if same else shapely.box(a[:, 0], a[:, 1], a[:, 2], a[:, 3]))
    if same:
        keep = i < j
        i, j = i[keep], j[keep]
    iou = iou_pairs(a[i], b[j])
    keep = iou > 0
    return i[keep], j[keep], iou[keep]


def greedy_matches(i: np.ndarray, j: np.ndarray, order: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    """Candidate pairs ``(i[k], j[k])`` kept by a greedy one-to-one matching visiting them in ``order``
    (best first): a pair is kept when neither of its members is taken yet. Returns the kept ``k``, in
    visiting order. Candidate pairs are few (each box overlaps a handful of others), so a loop is cheap."""
    used_a, used_b = np.zeros(n_a, dtype=bool), np.zeros(n_b, dtype=bool)
    kept = []
    for k in order:
        a, b = i[k], j[k]
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            kept.append(k)
    return np.asarray(kept, dtype=np.int64)


def match_boxes(reference: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching, highest IoU first: for each reference box its predicted index (-1) and IoU."""
    i, j, iou = overlapping_pairs(reference, predicted)
    order = np.argsort(-iou, kind="stable")
    kept = greedy_matches(i, j, order, len(reference), len(predicted))
    ref_match = np.full(len(reference), -1, dtype=np.int64)
    ref_iou = np.zeros(len(reference))
    ref_match[i[kept]], ref_iou[i[kept]] = j[kept], iou[kept]
    return ref_match, ref_iou
