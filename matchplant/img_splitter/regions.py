"""Annotated regions in tiling: only the part of a photo whose plants were all boxed may teach the detector.

Module 4 records, per image, the polygon that was annotated (``annotated_region``: its owned area from
module 3, every plant touching it boxed; :mod:`matchplant.core.formats.coco`). Outside it, plants are not
boxed, so a tile there would teach the detector that plants are background. Module 5 therefore

- clips each box to the region (a plant cut by the region's edge keeps its visible part, as a plant cut
  by the image edge does) and drops boxes outside it,
- writes only tiles with at least ``min_region_share`` of their area inside the region, and
- masks (fills with black) every tile pixel outside the region, so what the detector sees is exactly
  what was annotated.
"""

from __future__ import annotations

import cv2
import numpy as np
import shapely

MASK_VALUE = 0  # pixels outside the annotated region
SUBPIXEL_BITS = 4  # polygon vertices are rasterised to 1/16 px


def clip_boxes(boxes_xyxy: np.ndarray, polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each box reduced to the bounding box of its part inside ``polygon``; returns (boxes, inside)
    where ``inside`` is False for boxes that do not reach into the polygon (their row is unchanged)."""
    b = np.asarray(boxes_xyxy, float).reshape(-1, 4)
    if not len(b):
        return b.copy(), np.zeros(0, bool)
    region = shapely.make_valid(shapely.Polygon(polygon))
    parts = shapely.intersection(shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3]), region)
    inside = ~shapely.is_empty(parts) & (shapely.area(parts) > 0)
    out = b.copy()
    if inside.any():
        out[inside] = shapely.bounds(parts[inside])
    return out, inside


def region_share(tiles_xyxy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """The fraction of each tile's area that lies inside ``polygon``."""
    t = np.asarray(tiles_xyxy, float).reshape(-1, 4)
    region = shapely.make_valid(shapely.Polygon(polygon))
    cells = shapely.box(t[:, 0], t[:, 1], t[:, 2], t[:, 3])
    return shapely.area(shapely.intersection(cells, region)) / np.maximum(shapely.area(cells), 1e-12)


def mask_outside(pixels: np.ndarray, polygon: np.ndarray, x0: int, y0: int) -> np.ndarray:
    """A copy of a tile with the pixels whose centres lie outside ``polygon`` (source-image pixel edges,
    the tile's top-left at ``x0``, ``y0``) set to :data:`MASK_VALUE`."""
    h, w = pixels.shape[:2]
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5) in pixel-edge coordinates: shift by half a pixel
    pts = np.round((np.asarray(polygon, float) - [x0 + 0.5, y0 + 0.5]) * (1 << SUBPIXEL_BITS)).astype(np.int32)
    inside = np.zeros((h, w), np.uint8)
    cv2.fillPoly(inside, [pts], 1, lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
    out = pixels.copy()
    out[inside == 0] = MASK_VALUE
    return out


__all__ = ["clip_boxes", "region_share", "mask_outside", "MASK_VALUE"]
