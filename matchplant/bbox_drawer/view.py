"""What module 4's window draws, made cheap for 20 MP photos with thousands of boxes.

- :class:`PyramidImage`: the photo as a display pyramid (each level half the previous one, area
  averaged). At every draw it shows only the visible part of the coarsest level that still has at
  least one image pixel per screen pixel, so the full-resolution photo is never resampled: a redraw
  costs about the same for a 0.3 MP and a 20 MP photo.
- :class:`BoxLayer`: every box of an image in one collection (one artist, not one per box), colours
  per category, dashed for imported model predictions.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from matplotlib.collections import PathCollection
from matplotlib.image import AxesImage
from matplotlib.path import Path

MIN_LEVEL_SIDE = 256  # the pyramid stops when a level's long side would be shorter than this


def build_pyramid(img: np.ndarray) -> list[np.ndarray]:
    """``[img, img/2, img/4, ...]`` (area averaging), down to a long side of about ``MIN_LEVEL_SIDE``."""
    levels = [np.ascontiguousarray(img)]
    while max(levels[-1].shape[:2]) >= 2 * MIN_LEVEL_SIDE:
        prev = levels[-1]
        h, w = prev.shape[:2]
        levels.append(cv2.resize(prev, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA))
    return levels


class PyramidImage(AxesImage):
    """An image artist over a display pyramid; data coordinates are full-resolution pixel edges
    (``x = 0`` is the left edge of the first pixel, as COCO has it).

    :meth:`make_image` resamples the visible part of one level straight to the screen pixels with
    OpenCV (nearest neighbour when zoomed in past the photo's pixels, so they stay crisp; bilinear
    below, from a level at most twice the screen's resolution), instead of Matplotlib's resampling of
    the whole array.
    """

    def __init__(self, ax, img: np.ndarray, **kwargs):
        super().__init__(ax, interpolation="nearest", origin="upper", **kwargs)
        if img.ndim == 2:  # grey: shown as grey RGB
            img = np.repeat(img[:, :, None], 3, axis=2)
        self.levels = build_pyramid(img[:, :, :3])
        self.full_h, self.full_w = img.shape[:2]
        self.shown_level: int | None = None  # the level used by the last draw (tests, benchmark)
        self.set_data(self.levels[-1])  # for Matplotlib's own queries (cursor data, limits)
        # the extent is set directly: AxesImage.set_extent would also autoscale the axes' limits
        self._extent = (0, self.full_w, self.full_h, 0)

    def level_for(self, px_per_screen: float) -> int:
        """The coarsest level with at least one of its pixels per screen pixel."""
        return int(min(max(math.floor(math.log2(max(px_per_screen, 1e-9))), 0), len(self.levels) - 1))

    def make_image(self, renderer, magnification=1.0, unsampled=False):
        """Resample the visible part of the best pyramid level to the screen pixels (Matplotlib's draw hook)."""
        ax = self.axes
        (vx0, vx1), (vy0, vy1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
        x0, x1 = max(vx0, 0.0), min(vx1, float(self.full_w))
        y0, y1 = max(vy0, 0.0), min(vy1, float(self.full_h))
        if x1 <= x0 or y1 <= y0:
            return None, 0, 0, None
        to_disp = ax.transData
        (ax0, ay0), (ax1, ay1) = to_disp.transform([(x0, y0), (x1, y1)])
        clip = ax.bbox
        left, right = max(min(ax0, ax1), clip.x0), min(max(ax0, ax1), clip.x1)
        bottom, top = max(min(ay0, ay1), clip.y0), min(max(ay0, ay1), clip.y1)
        L, B = math.floor(left), math.floor(bottom)
        R, T = math.ceil(right), math.ceil(top)
        out_w, out_h = int((R - L) * magnification), int((T - B) * magnification)
        if out_w <= 0 or out_h <= 0:
            return None, 0, 0, None
        # data x = cx + kx * display x (the same for y): the axes' linear, axis-aligned transform
        inv = to_disp.inverted()
        (dx0, dy0), (dx1, dy1) = inv.transform([(0.0, 0.0), (1.0, 1.0)])
        kx, ky = dx1 - dx0, dy1 - dy0
        px_per_screen = max(abs(kx), abs(ky)) / magnification
        level = self.level_for(px_per_screen)
        arr = self.levels[level]
        sx, sy = self.full_w / arr.shape[1], self.full_h / arr.shape[0]
        # output pixel (c, r) has its centre at display (L + (c + .5) / m, B + (r + .5) / m) (the renderer
        # takes row 0 at the bottom); level pixel i has its centre at data (i + .5) * s
        m = magnification
        M = np.array(
            [
                [kx / m / sx, 0.0, (dx0 + kx * (L + 0.5 / m)) / sx - 0.5],
                [0.0, ky / m / sy, (dy0 + ky * (B + 0.5 / m)) / sy - 0.5],
            ]
        )
        flags = (cv2.INTER_NEAREST if px_per_screen < 1 else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
        rgb = cv2.warpAffine(arr, M, (out_w, out_h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        rgba = np.empty((out_h, out_w, 4), np.uint8)
        rgba[..., :3] = rgb
        rgba[..., 3] = int(round(255 * (self.get_alpha() if self.get_alpha() is not None else 1.0)))
        self.shown_level = level
        return rgba, L, B, None


class PanelImage(AxesImage):
    """Fixed RGBA pixels filling an axes, drawn as they are (no resampling on each draw; scaled once
    only when the axes changes size): the help panel."""

    def __init__(self, ax, rgba: np.ndarray):
        super().__init__(ax, interpolation="nearest", origin="upper")
        self.rgba = np.ascontiguousarray(rgba[::-1])  # the renderer takes row 0 at the bottom
        self.set_data(rgba)
        self._extent = (0, 1, 0, 1)
        self.set_transform(ax.transAxes)

    def make_image(self, renderer, magnification=1.0, unsampled=False):
        """The panel's pixels at the axes' size, rescaled only when that size changed (Matplotlib's draw hook)."""
        box = self.axes.bbox
        w, h = int(round(box.width * magnification)), int(round(box.height * magnification))
        if w <= 0 or h <= 0:
            return None, 0, 0, None
        if self.rgba.shape[:2] != (h, w):
            self.rgba = np.ascontiguousarray(cv2.resize(self.rgba, (w, h), interpolation=cv2.INTER_AREA))
        return self.rgba, box.x0, box.y0, None


def box_outlines(xyxy: np.ndarray) -> np.ndarray:
    """(N, 5, 2) closed outlines of boxes ``[x1, y1, x2, y2]``."""
    b = np.asarray(xyxy, float).reshape(-1, 4)
    x1, y1, x2, y2 = b.T
    return np.stack(
        [
            np.stack([x1, y1], 1),
            np.stack([x2, y1], 1),
            np.stack([x2, y2], 1),
            np.stack([x1, y2], 1),
            np.stack([x1, y1], 1),
        ],
        axis=1,
    )


class BoxLayer:
    """All boxes of the shown image as one collection of a few compound paths (one per colour and
    line style: drawing 3,000 separate rectangles is what made the window slow); ``hidden`` leaves one
    box out (the one being dragged, drawn by the window's preview instead)."""

    def __init__(self, ax, colors: list[str], lw: float = 1.3):
        self.colors = colors
        self.collection = PathCollection([], facecolors="none", linewidths=lw, zorder=3)
        self.collection.set_transform(ax.transData)
        ax.add_collection(self.collection, autolim=False)

    def set_boxes(self, boxes: list[dict], hidden: int | None = None) -> None:
        """Show ``boxes`` by category, predictions dashed and drawn boxes solid, leaving out box ``hidden``."""
        groups: dict[tuple[int, bool], list] = {}
        for b in boxes:
            if b["id"] != hidden:
                groups.setdefault((b["category_id"], "score" in b), []).append(b["xyxy"])
        keys = sorted(groups)
        self.collection.set_paths([compound_path(groups[k]) for k in keys])
        self.collection.set_edgecolor([self.colors[c - 1] for c, _ in keys] or "none")
        self.collection.set_linestyle([(0, (4, 2)) if dashed else "solid" for _, dashed in keys] or "solid")


def compound_path(xyxy: list) -> Path:
    """One path made of the closed outlines of many boxes."""
    verts = box_outlines(xyxy).reshape(-1, 2)
    codes = np.tile(
        np.array([Path.MOVETO, Path.LINETO, Path.LINETO, Path.LINETO, Path.CLOSEPOLY], dtype=Path.code_type), len(xyxy)
    )
    return Path(verts, codes)


__all__ = ["build_pyramid", "PyramidImage", "PanelImage", "BoxLayer", "box_outlines", "compound_path"]
