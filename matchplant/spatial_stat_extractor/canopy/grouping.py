"""Grouping canopy pixels by plant in linear time (compiled kernels for outlines and canopy statistics).

A strip's canopy pixels lie in its label image in raster order, the plants interleaved; a stable ``argsort``
of their plant numbers and three gathers (pixel, plant, height) took a fifth of the outlining time on a
survey, and the percentiles' sort of every value (one ``argsort`` of millions of floats, then a gather) as
much again. A counting sort (a histogram, then one scatter pass, :func:`labelled_pixels`) groups them by
plant as they are taken from the image, and sorting each plant's few thousand values on its own is cheaper
than one sort across the strip.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _gather_ranges(src, length, values):
    total = 0
    for k in range(len(length)):
        total += length[k]
    out = np.empty(total, values.dtype)
    j = 0
    for k in range(len(length)):
        out[j : j + length[k]] = values[src[k] : src[k] + length[k]]
        j += length[k]
    return out


def gather_ranges(src: np.ndarray, length: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group ``k`` made of ``values[src[k]:src[k] + length[k]]``, groups in order: the values, and ``start``:
    group ``k`` is ``[start[k]:start[k + 1]]``. Ranges may repeat (two groups sharing one set of pixels). One
    pass, no index arrays the size of the output."""
    src, length = np.ascontiguousarray(src, np.int64), np.ascontiguousarray(length, np.int64)
    return _gather_ranges(src, length, np.ascontiguousarray(values)), np.concatenate([[0], np.cumsum(length)])


@numba.njit(cache=True, nogil=True)
def _relabel(labels, lut):
    out = np.empty(labels.size, lut.dtype)
    flat = labels.ravel()
    for i in range(flat.size):
        out[i] = lut[flat[i]]
    return out


def relabel(labels: np.ndarray, lut: np.ndarray) -> np.ndarray:
    """``lut[labels]`` for a label image (numpy's gather first widens the labels to 64-bit indices: a third
    of a strip's canopy assignment)."""
    return _relabel(np.ascontiguousarray(labels), np.ascontiguousarray(lut)).reshape(labels.shape)


@numba.njit(cache=True, nogil=True)
def _label_boxes(labels, n):
    size = np.zeros(n + 1, np.int64)
    box = np.empty((n + 1, 4), np.int64)  # row min, row end, col min, col end
    box[:, 0], box[:, 1], box[:, 2], box[:, 3] = labels.shape[0], 0, labels.shape[1], 0
    for r in range(labels.shape[0]):
        for c in range(labels.shape[1]):
            v = labels[r, c]
            size[v] += 1
            if v:
                box[v, 0] = min(box[v, 0], r)
                box[v, 1] = max(box[v, 1], r + 1)
                box[v, 2] = min(box[v, 2], c)
                box[v, 3] = max(box[v, 3], c + 1)
    return size, box


def label_boxes(labels: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels per label ``0..n`` of a label image, and each label's bounding box (row start, row end, col
    start, col end; empty where it has no pixel) in one pass: ``np.bincount`` (which first copies the image as
    64-bit integers) and ``ndimage.find_objects`` took a third of a strip's canopy assignment."""
    return _label_boxes(np.ascontiguousarray(labels), int(n))


@numba.njit(cache=True, nogil=True)
def _values_at(window, pix, width, row0, col0):
    out = np.empty(len(pix))
    for i in range(len(pix)):
        r = pix[i] // width
        out[i] = window[r - row0, pix[i] - r * width - col0]
    return out


def values_at(window: np.ndarray, pix: np.ndarray, width: int, row0: int, col0: int) -> np.ndarray:
    """``window[row - row0, col - col0]`` as float for flat raster indices ``pix = row * width + col`` (a
    window read at ``row0, col0`` of a raster ``width`` wide): numpy's ``divmod`` and two-array gather took 70 %
    of a strip's canopy statistics."""
    return _values_at(window, np.ascontiguousarray(pix, np.int64), int(width), int(row0), int(col0))


@numba.njit(cache=True, nogil=True)
def _pixel_window(pix, width):
    r0, r1, c0, c1 = pix[0] // width, 0, width, 0
    for p in pix:
        r = p // width
        c = p - r * width
        r0, r1, c0, c1 = min(r0, r), max(r1, r + 1), min(c0, c), max(c1, c + 1)
    return r0, r1, c0, c1


def pixel_window(pix: np.ndarray, width: int) -> tuple[int, int, int, int]:
    """Row start, row end, col start, col end of the flat raster indices ``pix`` (not empty)."""
    return tuple(int(v) for v in _pixel_window(np.ascontiguousarray(pix, np.int64), int(width)))


class LabelRules(NamedTuple):
    """What :func:`labelled_pixels` keeps of each label ``k`` (arrays indexed by ``k``)."""

    windows: np.ndarray  # (n, 4) int64: col0, row0, col1, row1 in the image's pixels, end excluded
    reach: np.ndarray  # (n,) float: the least value kept
    home: np.ndarray  # (n,) bool: the label is gathered here (its home strip)
    ids: np.ndarray  # (n,) int32: its value in the image of kept pixels


class Placement(NamedTuple):
    """Where an image was cut from its raster: the raster's width, the image's first row and column on it."""

    width: int
    row0: int
    col0: int


@numba.njit(cache=True, nogil=True)
def _labelled_pixels(labels, values, rules, at):
    windows, reach, home, ids = rules
    width, row0, col0 = at
    rows, cols = labels.shape
    n = len(home)
    count = np.zeros(n + 1, np.int64)
    total = np.zeros(n)
    extent = np.empty((n, 4), np.int64)  # row min, row max, col min, col max
    extent[:, 0], extent[:, 1], extent[:, 2], extent[:, 3] = rows, -1, cols, -1
    image = np.zeros((rows, cols), np.int32)
    for r in range(rows):
        for c in range(cols):
            k = labels[r, c] - 1
            if k < 0 or not home[k]:
                continue
            if windows[k, 0] <= c < windows[k, 2] and windows[k, 1] <= r < windows[k, 3] and values[r, c] >= reach[k]:
                image[r, c] = ids[k]
                count[k + 1] += 1
                total[k] += np.float64(np.float32(values[r, c]))
                extent[k, 0] = min(extent[k, 0], r)
                extent[k, 1] = max(extent[k, 1], r)
                extent[k, 2] = min(extent[k, 2], c)
                extent[k, 3] = max(extent[k, 3], c)
    start = np.cumsum(count)
    nxt = start[:-1].copy()
    pix = np.empty(start[-1], np.int64)
    for r in range(rows):
        for c in range(cols):
            if image[r, c] != 0:
                k = labels[r, c] - 1
                j = nxt[k]
                nxt[k] = j + 1
                pix[j] = (r + row0) * width + c + col0
    return pix, start, total, extent, image


def labelled_pixels(labels: np.ndarray, values: np.ndarray, rules: LabelRules, at: Placement):
    """The pixels of a label image (1 + an index ``k`` into the arrays of ``rules``, 0: none) that lie in their
    label's window (``windows[k]``: col0, row0, col1, row1 in the image's pixels, end excluded), whose value
    reaches ``reach[k]`` (NaN never does) and whose ``home[k]`` is set, grouped by ``k`` (raster order within
    one): their flat indices ``(row + row0) * width + col + col0`` on the raster the image was cut from at
    ``row0, col0`` (``at``) and ``start`` (``k``'s pixels: ``[start[k]:start[k + 1]]``); per ``k`` the sum of their
    values (each rounded to float32, as the canopy's volume always was), and their extent (row min, row max, col min,
    col max in the image;
    min > max where none); and the image of these pixels holding ``ids[k]`` (0 elsewhere). Two passes over the
    image instead of a dozen over millions of pixels and a sort by plant."""
    rules = LabelRules(
        np.ascontiguousarray(rules.windows, dtype=np.int64),
        np.ascontiguousarray(rules.reach, dtype=float),
        np.ascontiguousarray(rules.home, dtype=np.bool_),
        np.ascontiguousarray(rules.ids, dtype=np.int32),
    )
    at = Placement(int(at.width), int(at.row0), int(at.col0))
    return _labelled_pixels(np.ascontiguousarray(labels), np.ascontiguousarray(values), rules, at)


def sort_within_groups(values: np.ndarray, first: np.ndarray) -> np.ndarray:
    """A copy of ``values`` with each run ``values[first[k]:first[k + 1]]`` sorted ascending (no NaN). A loop
    over the groups (plants, not pixels): numpy's own sort of each run in place is several times faster than
    one argsort of all the values by group and value, and than numba's sort."""
    out = np.array(values, dtype=float, copy=True)
    for a, b in zip(first[:-1].tolist(), first[1:].tolist()):
        if b - a > 1:
            out[a:b].sort()
    return out
