"""Which canopy pixels belong to which plant, within one strip of the CHM: each plant's top (the highest local
maximum in its box, or on a later date the one nearest its earlier top), the canopy components holding one top,
touching canopies flooded apart from their tops (:func:`flood`), the canopies no box claims, and the NDVI rule
that keeps a plant's leafy pixels (:func:`leafy`). :mod:`~.segmentation` runs them strip by strip."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from matchplant.spatial_stat_extractor.canopy.grouping import label_boxes, relabel
from matchplant.spatial_stat_extractor.canopy.maxima import box_tops, local_maxima
from matchplant.spatial_stat_extractor.canopy.outlines import SegmentSettings

FLOOD_LEVELS = 24  # heights at which touching canopies are flooded apart (see flood)


def holes_low(W: np.ndarray) -> np.ndarray:
    """``W`` with -inf in its holes (NaN): lower than any height. ``np.fmax`` ignores NaN; ``np.nan_to_num``,
    which also tests for and replaces infinities, took 3x as long, a fifth of the outlining time."""
    return np.fmax(W, -np.inf)


def tops_in_boxes(W: np.ndarray, boxes: np.ndarray, windows: np.ndarray, min_height: float) -> np.ndarray:
    """(k, 4) local row, col and height of each plant's top: the highest local maximum inside its box
    (integer ``c0, r0, c1, r1``; a taller neighbour's leaves reaching into the box rise towards its own
    top, outside, so they hold no local maximum), else inside its box plus margin (``windows``: a box
    cut short of the plant's centre), else the highest pixel of the box; height NaN where the box is
    empty. Column 3 is 1 where the top is a local maximum."""
    return box_tops(W, local_maxima(W, 5, min_height), boxes, windows)  # a local maximum is never in a hole


def tops_near(W: np.ndarray, seeds: np.ndarray, radius_px: float, min_top: float) -> np.ndarray:
    """Like :func:`tops_in_boxes` for a later date: the local maximum nearest to where each plant is expected
    (local row, col), within ``radius_px``; the seed itself when there is none. Expected: the earlier top
    moved by the median shift of the plants around (the maps of two flights are shifted against each
    other; a plant's own top is then nearer than its neighbour's, even where the shift nears the
    spacing)."""
    pr, pc = np.nonzero(local_maxima(W, 3, min_top))
    out = np.full((len(seeds), 4), np.nan)
    if len(pr) == 0:
        return out
    tree = cKDTree(np.stack([pr, pc], axis=1))
    offset = np.zeros(2)
    for _ in range(2):  # the nearest peak to the seed, then to the seed + the median shift
        d, j = tree.query(seeds + offset, distance_upper_bound=radius_px)
        found = np.isfinite(d)
        if not found.any():
            break
        shift = np.stack([pr[j[found]], pc[j[found]]], axis=1) - seeds[found]
        offset = np.median(shift, axis=0)
    d, j = tree.query(seeds + offset, distance_upper_bound=radius_px)
    found = np.isfinite(d)
    found &= (
        np.hypot(pr[np.minimum(j, len(pr) - 1)] - seeds[:, 0], pc[np.minimum(j, len(pr) - 1)] - seeds[:, 1])
        <= radius_px
    )
    r, c = pr[j[found]], pc[j[found]]
    out[found] = np.stack([r, c, W[r, c], np.ones(len(r))], axis=1)
    h, w = W.shape
    rs, cs = np.round(seeds[:, 0]).astype(int), np.round(seeds[:, 1]).astype(int)
    keep = ~found & (rs >= 0) & (rs < h) & (cs >= 0) & (cs < w)
    out[keep] = np.stack([rs[keep], cs[keep], W[rs[keep], cs[keep]], np.zeros(int(keep.sum()))], axis=1)
    return out


def flood(
    h: np.ndarray, sub: np.ndarray, rows: np.ndarray, cols: np.ndarray, labels: np.ndarray, levels: int = FLOOD_LEVELS
) -> np.ndarray:
    """Seeded watershed by flooding from the tops down: at each of ``levels`` heights, from the highest
    seed to the lowest canopy pixel, the pixels newly above water join the nearest labelled pixel (a
    Euclidean distance transform). Plants thus meet in the valleys between them, and a short plant
    keeps its own leaves where a taller neighbour's reach down beside them. (``ndimage.watershed_ift``
    breaks the ties of equal path costs arbitrarily and hands one plant's rim to its neighbour.)"""
    L = np.zeros(sub.shape, np.int32)
    L[rows, cols] = labels
    hv = np.where(sub, h, -np.inf)
    top, low = float(hv.max()), float(h[sub].min())
    for level in np.linspace(top, low, levels + 1)[1:]:
        new = sub & (hv >= level) & (L == 0)
        if not new.any():
            continue
        _, (ir, ic) = ndi.distance_transform_edt(L == 0, return_indices=True)
        L[new] = L[ir[new], ic[new]]
    return L


def assign(
    W: np.ndarray, mask: np.ndarray, tops: np.ndarray, ok: np.ndarray, s: SegmentSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Label image: 1 + the index of the top whose canopy each pixel belongs to, 0 elsewhere; and the
    canopies no top claims that look like plants (top at least ``min_top``, ``min_pixels`` pixels or more):
    (m, 4) local row, col, height and pixel count of their tops."""
    comp, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n == 0 or not ok.any():
        return np.zeros(W.shape, np.int32), np.zeros((0, 4))
    idx = np.flatnonzero(ok)
    tr, tc = tops[idx, 0].astype(int), tops[idx, 1].astype(int)
    # a pixel holds one top, the last box's to find it: a duplicate box (same top) loses it, flagged later
    _, last = np.unique((tr * W.shape[1] + tc)[::-1], return_index=True)
    seeded = np.sort(len(idx) - 1 - last)
    idx, tr, tc = idx[seeded], tr[seeded], tc[seeded]
    cid = comp[tr, tc]
    idx, tr, tc, cid = idx[cid > 0], tr[cid > 0], tc[cid > 0], cid[cid > 0]
    nseed = np.bincount(cid, minlength=n + 1)
    lut = np.zeros(n + 1, np.int32)
    single = nseed[cid] == 1
    lut[cid[single]] = idx[single] + 1
    L = relabel(comp, lut)
    # touching neighbours: a seeded watershed, only over each shared component
    size, box = label_boxes(comp, n)
    for k in np.flatnonzero(nseed >= 2):
        sl = np.s_[box[k, 0] : box[k, 1], box[k, 2] : box[k, 3]]
        mine = cid == k
        L[sl] = np.where(
            comp[sl] == k,
            flood(W[sl], comp[sl] == k, tr[mine] - sl[0].start, tc[mine] - sl[1].start, idx[mine] + 1),
            L[sl],
        )
    free = np.flatnonzero((nseed == 0) & (size >= s.min_pixels))
    free = free[free > 0]
    if not len(free):
        return L, np.zeros((0, 4))
    # each free component's highest pixel (first in row order on ties), from its own pixels only: scipy's
    # maximum_position sorts every pixel of the strip's label image (40% of the outlining time on a survey)
    wanted = np.zeros(n + 1, bool)
    wanted[free] = True
    rr, cc = np.nonzero(wanted[comp])
    lab = comp[rr, cc]
    order = np.lexsort((-W[rr, cc], lab))
    first = order[np.searchsorted(lab[order], free)]
    pos = np.stack([rr[first], cc[first]], axis=1).astype(np.int64)
    h = W[pos[:, 0], pos[:, 1]]
    tall = h >= s.min_top
    return L, np.column_stack([pos[tall], h[tall], size[free][tall]])


def leafy(L: np.ndarray, mv: np.ndarray, tops: np.ndarray, soil: float) -> np.ndarray:
    """The label image ``L`` (1 + the index into ``tops``) without the pixels whose mask value (NDVI) lies below
    halfway from the soil's to the value at their plant's top: a pale plant keeps its leaves, a green one drops
    the mixed pixels at its edges."""
    at_top = mv[np.nan_to_num(tops[:, 0]).astype(int), np.nan_to_num(tops[:, 1]).astype(int)]
    half = np.concatenate([[np.inf], (soil + at_top) / 2])  # label 0 (no plant) stays 0 anyway
    return np.where(mv >= half[L], L, 0)
