"""The plants on the CHM's pixel grid: each box and window in pixels, the strip each plant belongs to, and back
from pixels to map coordinates. North-up rasters only (a rotated CHM is refused with its fix)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import shapely

from matchplant.core.runtime.errors import InputError

STRIP_ROWS = 1024  # raster rows per strip read at once (plus padding for the boxes crossing its edges)


class PlantGrid(NamedTuple):
    """The plants on the grid of a CHM (from :func:`plant_windows`) and the grid itself."""

    box_i: np.ndarray  # (n, 4) int64 col0, row0, col1, row1 of each box (pixel centres inside), -1s where empty
    win_i: np.ndarray  # (n, 4) int64 the box + margin (+ max_shift's reach with seeds), as box_i
    seed_px: np.ndarray | None  # (n, 2) pixel row, col of each earlier top (later dates), else None
    transform: object  # the CHM's affine transform
    width: int
    height: int
    res: float  # m per pixel


class Window(NamedTuple):
    """The rows and columns of the raster read for one strip (ends excluded)."""

    row0: int
    row1: int
    col0: int
    col1: int


def apply_affine(t, x, y) -> tuple[np.ndarray, np.ndarray]:
    """An affine transform on arrays."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f


def pixel_size(t) -> float:
    """The side of a pixel of the grid ``t`` (m)."""
    return float(np.sqrt(abs(t.a * t.e - t.b * t.d)))


def pixel_boxes(geoms, transform) -> np.ndarray:
    """(n, 4) col0, row0, col1, row1 (continuous pixel coordinates) of each geometry's bounds."""
    if abs(transform.b) > 1e-12 or abs(transform.d) > 1e-12:
        raise InputError(
            "the CHM raster is rotated; outlines need a north-up raster",
            fix="warp the DSM/DTM to a north-up grid (gdalwarp) first",
        )
    b = shapely.bounds(np.asarray(geoms, dtype=object))
    inv = ~transform
    c0, r0 = apply_affine(inv, b[:, 0], b[:, 3])
    c1, r1 = apply_affine(inv, b[:, 2], b[:, 1])
    return np.stack([np.minimum(c0, c1), np.minimum(r0, r1), np.maximum(c0, c1), np.maximum(r0, r1)], axis=1)


def plant_windows(geoms, t, s, seeds: np.ndarray | None = None):
    """Each plant's box (pixel centres inside) and window (box + margin, + the reach of ``max_shift`` with
    ``seeds``) as integer (col0, row0, col1, row1) on the grid of ``t``, and the seeds' pixel (row, col) or None.
    An empty or missing geometry gets -1s.

    Parameters
    ----------
    geoms : array of shapely geometries
        The plant boxes, in the CRS of the grid.
    t : affine.Affine
        The grid's transform (north-up).
    s : SegmentSettings
        Its ``margin`` (m) and ``max_shift`` (m) are used.
    seeds : (n, 2) array, optional
        Map x, y of each plant's earlier top (later dates).

    Returns
    -------
    tuple
        ``box_i``, ``win_i`` ((n, 4) int64) and the seeds' pixel row, col ((n, 2) float, or None).
    """
    res = pixel_size(t)
    m = s.margin / res
    pb = pixel_boxes(geoms, t)
    box_i = np.stack(
        [np.floor(pb[:, 0] + 0.5), np.floor(pb[:, 1] + 0.5), np.floor(pb[:, 2] + 0.5), np.floor(pb[:, 3] + 0.5)], axis=1
    )  # pixel centres inside
    win_i = np.stack(
        [np.floor(pb[:, 0] - m), np.floor(pb[:, 1] - m), np.ceil(pb[:, 2] + m), np.ceil(pb[:, 3] + m)], axis=1
    )
    box_i = np.nan_to_num(box_i, nan=-1).astype(np.int64)
    win_i = np.nan_to_num(win_i, nan=-1).astype(np.int64)
    seed_px = None
    if seeds is not None:
        sc, sr = apply_affine(~t, seeds[:, 0], seeds[:, 1])
        seed_px = np.stack([sr - 0.5, sc - 0.5], axis=1)  # pixel index (row, col) of the centre
        reach = int(np.ceil(s.max_shift / res)) + 1
        win_i = win_i + np.array([-reach, -reach, reach, reach])
    return box_i, win_i, seed_px


def home_strip(win_i: np.ndarray, height: int, strip_rows: int) -> np.ndarray:
    """The strip each plant belongs to: the one holding its window's centre row (clipped to the raster)."""
    return np.clip((win_i[:, 1] + win_i[:, 3]) // 2, 0, height - 1) // strip_rows


def local_windows(b: np.ndarray, w: Window) -> np.ndarray:
    """Integer windows (c0, r0, c1, r1) in the coordinates of the window read, clipped to it."""
    out = b - np.array([w.col0, w.row0, w.col0, w.row0])
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, w.col1 - w.col0)
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, w.row1 - w.row0)
    return out


def on_map(t, free: np.ndarray) -> np.ndarray:
    """Unclaimed canopies (row, col, height, pixels) as map x, y (pixel centres), height, pixels."""
    fx, fy = apply_affine(t, free[:, 1] + 0.5, free[:, 0] + 0.5)
    return np.column_stack([fx, fy, free[:, 2], free[:, 3]])
