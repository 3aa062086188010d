"""Ground truth computed analytically from the field model (never from the rendered images).

Image boxes: each plant's canopy surface points (leaf tips included) projected through the shot's
camera; the box is their extent, clipped to the image. COCO boxes use pixel *edges*: the image spans
``[0, W] x [0, H]`` and the camera pixel ``(u, v)`` (centres at integers, docs/DESIGN.md §3) is at
``(u + 0.5, v + 0.5)``.
"""

from __future__ import annotations

import numpy as np
from shapely import box, make_valid, polygons, union_all

from matchplant.core.geometry.shot import Shot
from matchplant.simfield.scene import MAX_LEAVES, Plants, Terrain

MIN_BOX_PX = 0.5  # a plant counts as visible when its box reaches a pixel centre (half a pixel in)
RING = 72 + MAX_LEAVES  # points per ring of Plants.surface_points


def image_boxes(
    shot: Shot,
    plants: Plants,
    terrain: Terrain,
    candidates: np.ndarray,
    offsets: np.ndarray | None = None,
    chunk: int = 2000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes ``(n, 4)`` as x0, y0, x1, y1 (pixel edges, clipped), plant indices and a truncated flag,
    for the ``candidates`` plants (indices) that appear in ``shot``'s image. ``offsets`` are
    :meth:`Plants.surface_offsets`, if already computed."""
    cam = shot.camera
    boxes, which, cut = [], [], []
    for start in range(0, len(candidates), chunk):
        idx = candidates[start : start + chunk]
        if offsets is None:
            pts = plants.surface_points(idx, terrain)
        else:
            pts = offsets[idx] + np.stack([plants.x[idx], plants.y[idx], plants.z[idx]], axis=1)[:, None, :]
        uv = shot.project(pts.reshape(-1, 3)).reshape(len(idx), -1, 2) + 0.5
        ok = np.isfinite(uv).all(axis=2).all(axis=1)
        idx, uv = idx[ok], uv[ok]
        raw = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)
        clip = raw.copy()
        clip[:, [0, 2]] = np.clip(raw[:, [0, 2]], 0, cam.width)
        clip[:, [1, 3]] = np.clip(raw[:, [1, 3]], 0, cam.height)
        cut_now = np.any(np.abs(clip - raw) > 1e-9, axis=1)
        for j in np.flatnonzero(cut_now & (clip[:, 2] > clip[:, 0]) & (clip[:, 3] > clip[:, 1])):
            clip[j] = _visible_box(uv[j], cam.width, cam.height)
        seen = (clip[:, 2] - clip[:, 0] >= MIN_BOX_PX) & (clip[:, 3] - clip[:, 1] >= MIN_BOX_PX)
        boxes.append(clip[seen])
        which.append(idx[seen])
        cut.append(cut_now[seen])
    if not boxes:
        return np.zeros((0, 4)), np.zeros(0, int), np.zeros(0, bool)
    return np.concatenate(boxes), np.concatenate(which), np.concatenate(cut)


def _visible_box(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Box of the part of a plant inside the image: its projected canopy rings (polygons) united and
    clipped to the frame, as an annotator would draw a plant cut by the frame."""
    rings = uv.reshape(-1, RING, 2)[1:]  # ring 0 is the top centre, a single point
    shape = union_all(make_valid(polygons(rings))).intersection(box(0, 0, width, height))
    inside = uv[(uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)]
    parts = [np.asarray(shape.bounds, dtype=float)] if not shape.is_empty else []
    if len(inside):  # points above the outlines (the top) may stick out of every ring
        parts.append(np.concatenate([inside.min(axis=0), inside.max(axis=0)]))
    if not parts:
        return np.zeros(4)
    b = np.array(parts)
    return np.concatenate([b[:, :2].min(axis=0), b[:, 2:].max(axis=0)])


def candidates_near(plants: Plants, area: np.ndarray, margin: float) -> np.ndarray:
    """Indices of plants whose centre lies within ``margin`` of the box ``area`` (xmin, ymin, xmax, ymax)."""
    return np.flatnonzero(
        (plants.x > area[0] - margin)
        & (plants.x < area[2] + margin)
        & (plants.y > area[1] - margin)
        & (plants.y < area[3] + margin)
    )
