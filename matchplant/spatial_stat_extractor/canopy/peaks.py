"""Which boxes found one plant's top: the duplicate rule of module 9's outlines.

Two boxes of one plant (the detector split it, or two photos' boxes were not merged) each find the highest
local maximum of the CHM in their box. On an exact CHM both find the same pixel. On a photogrammetric CHM
(a few cm of noise, tops smoothed by the gridding) a plant's top holds several local maxima a few cm apart,
so the two boxes find different ones. Two tops are therefore one plant's when no real valley parts them:
the lowest CHM on the way from one top to the other (the saddle) stays within a tolerance of the lower
top. The tolerance is the larger of

* ``K_DIP`` x the ground noise's SD (measured by :mod:`~matchplant.spatial_stat_extractor.canopy.ground`): a dip
  this shallow is what the noise itself digs into a canopy (the same 3 SD that separates soil from leaves);
* ``REL_DIP`` x the lower top's height: two distinct plants whose canopies touch meet in a valley far
  below their tops (their leaves slope down to their rims), while one plant's top is one dome;

and never more than ``MAX_DIP`` x the lower top: a short plant (tops of a few noise SDs) beside another is
parted from it by a valley of half its height, however noisy the CHM.

A box whose top is thus another box's plant may still hold its own plant: a short plant's box whose highest
local maximum is a noise bump on a taller neighbour's leaves reaching into it. Such a box takes the highest
local maximum in its box that a real valley parts from the other plant's top and that lies nearer the box's
centre than that top (:func:`second_tops`; a split box centred on one plant does not move to a low leaf at
its edge) and that is canopy (with NDVI, a leaf: a ground bump beside the plant is no plant's top), and the
rule is applied again; a box whose new top is again another box's plant keeps its first top and keeper (a
split box reaching over a neighbour stays its own plant's duplicate). :func:`one_plant_boxes` does it all.

The way between two tops is the straight line, sampled once per pixel step, each sample the highest CHM
of its 3 x 3 pixels, so the path may step round a one-pixel noise pit or hole. Only boxes whose windows (box plus
margin) overlap are compared (pairs from a k-d tree of the tops, all pairs of one strip checked at once);
each box points to the highest top joined to its own (the first box on ties) and the pointers are followed
to their end: that box keeps the plant, the others are its duplicates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from matchplant.spatial_stat_extractor.canopy.maxima import line_saddles, local_maxima

K_DIP = 3.0  # ground-noise SDs: a shallower dip between two tops is noise, not a valley
REL_DIP = 0.4  # share of the lower top: a deeper dip is the valley between two plants (one plant's leaves
# part its maxima by up to a third of its height on the straight line between them)
MAX_DIP = 0.5  # share of the lower top: a dip deeper than this is a valley, however noisy the CHM


def one_plant_boxes(
    W: np.ndarray,
    tops: np.ndarray,
    ok: np.ndarray,
    windows: np.ndarray,
    boxes: np.ndarray,
    *,
    noise_sd: float,
    min_top: float,
    leaf: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The tops (a duplicate's moved to its own plant where its box holds one) and the box that keeps
    each box's plant (see the module doc; ``windows``/``boxes``: integer ``c0, r0, c1, r1`` of each box
    plus margin / of each box; ``leaf``: the canopy pixels, where a second top must lie)."""
    first = keepers(W, tops, ok, windows, noise_sd)
    moved = second_tops(W, tops, first, boxes, noise_sd=noise_sd, min_top=min_top, leaf=leaf)
    keep = keepers(W, moved, ok, windows, noise_sd)
    own = np.arange(len(keep))
    still = (first != own) & (keep != own)
    moved[still] = tops[still]
    keep[still] = keep[first[still]]
    return moved, keep


def keepers(W: np.ndarray, tops: np.ndarray, ok: np.ndarray, windows: np.ndarray, noise_sd: float) -> np.ndarray:
    """For each box (``tops``: local row, col, height; ``ok``: the top is a plant's; ``windows``: integer
    ``c0, r0, c1, r1`` of box plus margin), the box that keeps its plant: itself, or (a duplicate) the box
    with the highest top of the tops joined to its own by no real valley. Boxes without a top keep
    themselves."""
    n = len(tops)
    keep = np.arange(n)
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return keep
    rc = tops[idx, :2].astype(np.int64)
    reach = float(np.hypot(windows[idx, 2] - windows[idx, 0], windows[idx, 3] - windows[idx, 1]).max())
    pairs = cKDTree(rc).query_pairs(reach, output_type="ndarray")
    if not len(pairs):
        return keep
    a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
    wa, wb = windows[a], windows[b]
    meet = (wa[:, 0] < wb[:, 2]) & (wb[:, 0] < wa[:, 2]) & (wa[:, 1] < wb[:, 3]) & (wb[:, 1] < wa[:, 3])
    a, b = a[meet], b[meet]
    lower = np.minimum(tops[a, 2], tops[b, 2])
    dip = lower - _saddle(W, tops[a, :2].astype(np.int64), tops[b, :2].astype(np.int64))
    one = dip <= _tolerance(lower, noise_sd)
    a, b = a[one], b[one]
    # each box points to the highest top joined to its own (itself when none is higher; the first box on
    # ties), and the pointers are followed to their end: only the box's own pairs decide, so a strip of the
    # field that sees the box and its neighbours decides as a pass over the whole field does
    rank = np.empty(n, np.int64)
    rank[np.lexsort((-np.arange(n), np.nan_to_num(tops[:, 2], nan=-np.inf)))] = np.arange(n)
    hi = np.concatenate([np.where(rank[a] > rank[b], a, b), keep])
    lo = np.concatenate([np.where(rank[a] > rank[b], b, a), keep])
    best = np.full(n, -1)
    np.maximum.at(best, lo, rank[hi])
    by_rank = np.argsort(rank)
    keep = by_rank[best]
    while (keep[keep] != keep).any():
        keep = keep[keep]
    return keep


def _saddle(W: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The lowest CHM on the straight line from each ``p`` to its ``q`` (local row, col), each sample the
    highest of its 3 x 3 pixels. Samples in a hole (NaN: the matching failed there) tell nothing and are
    skipped; a line mostly in holes counts as parted (-inf)."""
    if not len(p):  # no pair of boxes meets (their windows do not overlap)
        return np.zeros(0)
    own = np.abs(q - p).max(axis=1) + 1  # each line's own samples: one per pixel step
    # every line sampled at its own steps only (the longest line's grid rounded to them): a line's saddle
    # does not depend on which other pairs are tested with it (a denser grid meets more pixels)
    return line_saddles(W, p, q, np.linspace(0.0, 1.0, int(own.max()) + 1), own)


def _tolerance(lower: np.ndarray, noise_sd: float) -> np.ndarray:
    return np.minimum(np.maximum(K_DIP * noise_sd, REL_DIP * lower), MAX_DIP * lower)


def second_tops(
    W: np.ndarray,
    tops: np.ndarray,
    keep: np.ndarray,
    boxes: np.ndarray,
    *,
    noise_sd: float,
    min_top: float,
    leaf: np.ndarray | None = None,
) -> np.ndarray:
    """``tops`` with each duplicate box (``keep`` not itself) moved to the highest local maximum (5 x 5,
    at least ``min_top``, on a ``leaf`` pixel) inside its box (integer ``c0, r0, c1, r1``) that a real
    valley parts from its keeper's top, where there is one. A loop over the duplicate boxes (a few per
    hundred plants) with a local-maximum pass over each box; the valleys of all candidates are tested at
    once."""
    lost = np.flatnonzero(keep != np.arange(len(keep)))
    box, rc, h = [], [], []
    for k in lost:
        c0, r0, c1, r1 = boxes[k]
        # the filter sees 2 pixels around the box, so a maximum is one of the whole CHM's
        R0, C0 = max(0, r0 - 2), max(0, c0 - 2)
        win = np.fmax(W[R0 : r1 + 2, C0 : c1 + 2], -np.inf)  # holes lower than any height
        if win.size == 0:
            continue
        pr, pc = np.nonzero(local_maxima(win, 5, min_top))  # the tops' own rule (claims.tops_in_boxes)
        pr, pc = pr + R0, pc + C0
        inside = (pr >= r0) & (pr < r1) & (pc >= c0) & (pc < c1)
        if leaf is not None:  # a second top must be canopy: with NDVI, a ground bump beside the plant is soil
            inside &= leaf[pr, pc]
        box.append(np.full(int(inside.sum()), k))
        rc.append(np.stack([pr[inside], pc[inside]], axis=1))
        h.append(win[pr[inside] - R0, pc[inside] - C0])
    out = tops.copy()
    if not box or not sum(len(b) for b in box):
        return out
    box, rc, h = np.concatenate(box), np.concatenate(rc), np.concatenate(h)
    j = keep[box]
    lower = np.minimum(h, tops[j, 2])
    dip = lower - _saddle(W, rc, tops[j, :2].astype(np.int64))
    # the box's own plant is nearer its centre than the keeper's top: a split box centred on a plant does not
    # move to a low leaf at its edge (on a noisy CHM such leaves are parted from the top by noise valleys)
    centre = (boxes[box][:, [1, 0]] + boxes[box][:, [3, 2]] - 1) / 2
    nearer = np.hypot(*(rc - centre).T) < np.hypot(*(tops[j, :2] - centre).T)
    apart = (dip > _tolerance(lower, noise_sd)) & nearer
    box, rc, h = box[apart], rc[apart], h[apart]
    order = np.lexsort((-h, box))
    first = order[np.r_[True, box[order][1:] != box[order][:-1]]] if len(order) else order
    out[box[first], 0], out[box[first], 1], out[box[first], 2] = rc[first, 0], rc[first, 1], h[first]
    return out
