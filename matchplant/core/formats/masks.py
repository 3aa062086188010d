"""Masks (label images) to boxes: a plant's box is the extent of its pixels, in pixel edges.

A mask image has the size of its photo. Two kinds are read:

- an **instance mask** (more than one non-zero value, e.g. uint16 plant ids): one box per id, over all
  pixels of that id;
- a **binary mask** (0 and one other value): one box per 8-connected component.

Objects with fewer than ``min_area`` pixels are dropped (specks, noise).
"""

from __future__ import annotations

import cv2
import numpy as np

from matchplant.core.formats.coco import LabelledBox


def mask_boxes(mask: np.ndarray, min_area: int = 1, label: str = "plant") -> list[LabelledBox]:
    """Boxes ``[x1, y1, x2, y2]`` (pixel edges) of the objects of a mask (2-D, any integer type)."""
    if mask.ndim == 3:
        mask = mask[..., 0] if np.all(mask == mask[..., :1]) else mask.max(axis=2)
    values = np.unique(mask)
    values = values[values != 0]
    out: list[LabelledBox] = []
    if len(values) == 1:  # binary: connected components
        n, _, stats, _ = cv2.connectedComponentsWithStats((mask != 0).astype(np.uint8), connectivity=8)
        for x, y, w, h, area in stats[1:]:
            if area >= min_area:
                out.append(LabelledBox([float(x), float(y), float(x + w), float(y + h)], label))
        return out
    flat = mask.ravel()
    order = np.argsort(flat, kind="stable")
    sorted_ids = flat[order]
    starts = np.searchsorted(sorted_ids, values, side="left")
    ends = np.searchsorted(sorted_ids, values, side="right")
    width = mask.shape[1]
    for s, e in zip(starts, ends):
        if e - s < min_area:
            continue
        idx = order[s:e]
        rows, cols = idx // width, idx % width
        out.append(LabelledBox([float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)],
                               label))
    return out


__all__ = ["mask_boxes"]
