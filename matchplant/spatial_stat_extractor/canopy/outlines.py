"""Plant outlines from the canopy height model: each projected box becomes the plant's canopy.

For every plant box (plus a margin) the CHM is read window by window (strips of rows, never the whole
raster). The plant's top is the highest local maximum of the CHM inside its box (on a later date: the
local maximum nearest to the earlier top moved by the plants' median shift, within ``max_shift``).
Canopy pixels are those at least ``min_height`` above the ground; connected groups of them
(8-connectivity, ``scipy.ndimage.label``) holding one top belong to that plant, and groups holding
several tops (touching neighbours) are split by a seeded watershed from the tops (flooding the canopy
from the tops down, :func:`_flood`). A pixel is then kept for its plant when it lies in the plant's box
plus margin and reaches ``relative`` times the plant's own top height, so short plants keep their low
leaves and tall plants do not swallow the soil noise around them.

Plants whose canopy is smaller than ``min_pixels`` (too small for the CHM's resolution) or whose top is
below ``min_top`` (weeds, soil, plants too small for the CHM) keep their box and are flagged
(``outline_flag`` ``small`` or ``low``; ``no_top``: no CHM under the box; ``no_peak``: no local maximum
in the box or its margin, so no plant's top: a box on leaves or between plants). A second box of one
plant (the same top, or a top that no real valley parts from the plant's:
:mod:`~matchplant.spatial_stat_extractor.canopy.peaks`)
is flagged ``duplicate`` and shares that plant's outline and canopy. Canopies that
no box claims but that look like plants (a top of at least ``min_top`` and ``unclaimed_min_top``, above
the ground noise's highest bumps, and ``min_pixels`` or more) are listed too (``Outlines.unclaimed``):
plants the detector missed, for stand counts; the lower ones are counted (``noise_bumps``), and listed apart
(``Outlines.faint``) where NDVI says their pixels are leaves (weeds, or seedlings within the CHM's noise).

The result, :class:`Outlines`, holds the outline polygons (raster pixel edges, traced by
:mod:`~matchplant.spatial_stat_extractor.canopy.trace` with 4-connectivity, as ``rasterio.features.shapes`` would:
pixels that touch only at a corner become separate parts of a multipolygon; a ring that still touches itself
is repaired by :func:`valid_polygons`), the tightened boxes, the tops, canopy area and volume, and the canopy
pixels themselves (flat raster indices grouped by plant) for canopy-only statistics
(:mod:`~matchplant.spatial_stat_extractor.canopy.stats`). See docs/DESIGN.md §2 (module 9).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.progress import progress
from matchplant.spatial_stat_extractor.canopy.grouping import (
    gather_ranges,
    label_boxes,
    labelled_pixels,
    relabel,
)
from matchplant.spatial_stat_extractor.canopy.maxima import box_tops, local_maxima
from matchplant.spatial_stat_extractor.canopy.peaks import one_plant_boxes
from matchplant.spatial_stat_extractor.canopy.trace import outline_pieces
from matchplant.spatial_stat_extractor.zonal import ranges

FLOOD_LEVELS = 24  # heights at which touching canopies are flooded apart (see _flood)
STRIP_ROWS = 1024  # raster rows per strip read at once (plus padding for the boxes crossing its edges)


@dataclass
class SegmentSettings:
    """How a canopy is cut out of the CHM (module 9's ``canopy`` section carries the same keys)."""

    margin: float = 0.05  # m around each box
    relative: float = 0.1  # keep pixels at least this share of the plant's own top height
    min_height: float = 0.02  # m above ground: lower pixels are soil
    min_top: float = 0.05  # m: a lower top is a weed, soil or a plant too small for the CHM (flagged)
    min_pixels: int = 4  # smaller canopies keep their box (flagged)
    max_shift: float = 0.0  # m: later dates search the top within this distance of the earlier top
    mask_threshold: float | None = None  # with a mask layer (NDVI): canopy pixels also need mask >= this
    mask_soil: float | None = None  # the mask's value on soil: a plant's pixels also reach halfway from it to
    # the value at the plant's top (more leaf than soil: a pale plant keeps its leaves, a green one its edges)
    unclaimed_min_top: float = 0.0  # m: a canopy no box claims is a plant only with a top this high (the
    # ground noise's highest bumps, see ground.py; at least min_top); lower ones are counted as noise bumps
    noise_sd: float = 0.0  # m: the ground noise's SD (ground.py); two tops parted by a shallower dip are one
    # plant's (peaks.py)


@dataclass
class Outlines:
    """Per plant (in the order of the boxes given): outline, tightened box, top, canopy measures; plus the
    canopy pixels (``pix``: flat indices ``row * width + col`` on the CHM grid, plant ``k``'s pixels are
    ``pix[start[k]:start[k + 1]]``), and the canopies no box claims that look like plants (``unclaimed``:
    top x, y, height and pixel count; plants the detector missed, for stand counts)."""

    geometry: np.ndarray  # shapely polygons (the box where flagged)
    tight_box: np.ndarray  # (n, 4) xmin, ymin, xmax, ymax of the canopy pixels
    top: np.ndarray  # (n, 3) x, y, height above ground of the top
    pixels: np.ndarray  # canopy pixel count
    area: np.ndarray  # m²
    volume: np.ndarray  # m³ (sum of heights x pixel area)
    flag: np.ndarray  # "" or why the box was kept: "small", "low", "no_top", "outside"
    pix: np.ndarray
    start: np.ndarray
    transform: object
    width: int
    height: int
    crs: object = None
    shift: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (n, 2) m, later dates
    unclaimed: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # x, y, height, pixels
    noise_bumps: int = 0  # unclaimed canopies left out: tops of at least min_top, below unclaimed_min_top
    faint: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # those canopies (as ``unclaimed``)
    # where NDVI tells their pixels are leaves: mostly weeds, but also the smallest plants the detector missed
    # (plots count them only at an empty seed position, plots/table.py)
    duplicate_of: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # the plant a duplicate's
    # box is a second box of (its index), -1 for the others

    @property
    def from_box(self) -> np.ndarray:
        return self.flag != ""

    def same_grid(self, source) -> bool:
        return (source.width, source.height) == (self.width, self.height) and source.transform.almost_equals(
            self.transform
        )


def _apply(t, x, y) -> tuple[np.ndarray, np.ndarray]:
    """An affine transform on arrays."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f


def _pixel_boxes(geoms, transform) -> np.ndarray:
    """(n, 4) col0, row0, col1, row1 (continuous pixel coordinates) of each geometry's bounds."""
    if abs(transform.b) > 1e-12 or abs(transform.d) > 1e-12:
        raise InputError(
            "the CHM raster is rotated; outlines need a north-up raster",
            fix="warp the DSM/DTM to a north-up grid (gdalwarp) first",
        )
    b = shapely.bounds(np.asarray(geoms, dtype=object))
    inv = ~transform
    c0, r0 = _apply(inv, b[:, 0], b[:, 3])
    c1, r1 = _apply(inv, b[:, 2], b[:, 1])
    return np.stack([np.minimum(c0, c1), np.minimum(r0, r1), np.maximum(c0, c1), np.maximum(r0, r1)], axis=1)


def holes_low(W: np.ndarray) -> np.ndarray:
    """``W`` with -inf in its holes (NaN): lower than any height. ``np.fmax`` ignores NaN; ``np.nan_to_num``,
    which also tests for and replaces infinities, took 3x as long, a fifth of the outlining time."""
    return np.fmax(W, -np.inf)


def _tops(W: np.ndarray, boxes: np.ndarray, windows: np.ndarray, min_height: float) -> np.ndarray:
    """(k, 4) local row, col and height of each plant's top: the highest local maximum inside its box
    (integer ``c0, r0, c1, r1``; a taller neighbour's leaves reaching into the box rise towards its own
    top, outside, so they hold no local maximum), else inside its box plus margin (``windows``: a box
    cut short of the plant's centre), else the highest pixel of the box; height NaN where the box is
    empty. Column 3 is 1 where the top is a local maximum."""
    return box_tops(W, local_maxima(W, 5, min_height), boxes, windows)  # a local maximum is never in a hole


def _tops_near(W: np.ndarray, seeds: np.ndarray, radius_px: float, min_top: float) -> np.ndarray:
    """Like :func:`_tops` for a later date: the local maximum nearest to where each plant is expected
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


def _flood(
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


def _assign(
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
            _flood(W[sl], comp[sl] == k, tr[mine] - sl[0].start, tc[mine] - sl[1].start, idx[mine] + 1),
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


def plant_windows(geoms, t, s: SegmentSettings, seeds: np.ndarray | None = None):
    """Each plant's box (pixel centres inside) and window (box + margin, + the reach of ``max_shift`` with
    ``seeds``) as integer (col0, row0, col1, row1) on the grid of ``t``, and the seeds' pixel (row, col) or None.
    An empty or missing geometry gets -1s."""
    res = float(np.sqrt(abs(t.a * t.e - t.b * t.d)))
    m = s.margin / res
    pb = _pixel_boxes(geoms, t)
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
        sc, sr = _apply(~t, seeds[:, 0], seeds[:, 1])
        seed_px = np.stack([sr - 0.5, sc - 0.5], axis=1)  # pixel index (row, col) of the centre
        reach = int(np.ceil(s.max_shift / res)) + 1
        win_i = win_i + np.array([-reach, -reach, reach, reach])
    return box_i, win_i, seed_px


def home_strip(win_i: np.ndarray, height: int, strip_rows: int) -> np.ndarray:
    """The strip each plant belongs to: the one holding its window's centre row (clipped to the raster)."""
    return np.clip((win_i[:, 1] + win_i[:, 3]) // 2, 0, height - 1) // strip_rows


def segment(
    geoms,
    chm,
    s: SegmentSettings,
    *,
    mask_source=None,
    seeds: np.ndarray | None = None,
    strip_rows: int = STRIP_ROWS,
    band: tuple[int, int] | None = None,
) -> Outlines:
    """Outlines of the plants whose boxes are ``geoms`` (in the CHM's CRS) on the CHM source ``chm``
    (``transform, width, height, read(row0, row1, col0, col1)``). ``seeds``: (n, 2) map x, y of earlier
    tops, to re-centre each plant within ``s.max_shift`` (later dates). ``mask_source``: a layer on the
    same grid (NDVI) whose value must reach ``s.mask_threshold`` on canopy pixels. ``band``: only the
    strips ``band[0] <= strip < band[1]`` (:mod:`~matchplant.spatial_stat_extractor.canopy.strips` runs a field
    band by band); the plants of other strips are flagged ``skipped`` (their neighbours still compete)."""
    geoms = np.asarray(geoms, dtype=object)
    n = len(geoms)
    t = chm.transform
    res = float(np.sqrt(abs(t.a * t.e - t.b * t.d)))
    box_i, win_i, seed_px = plant_windows(geoms, t, s, seeds)
    W_, H_ = chm.width, chm.height
    outside = (
        (win_i[:, 2] <= 0)
        | (win_i[:, 0] >= W_)
        | (win_i[:, 3] <= 0)
        | (win_i[:, 1] >= H_)
        | shapely.is_empty(geoms)
        | shapely.is_missing(geoms)
    )
    tops = np.full((n, 3), np.nan)
    dup = np.full(n, -1)  # a duplicate box: the plant whose top it shares
    parts_pix, free_parts = [], []
    # each home plant's canopy pixels: its range in the concatenated parts, their height sum and extent
    own_src, own_len = np.zeros(n, np.int64), np.zeros(n, np.int64)
    own_sum, own_ext = np.zeros(n), np.zeros((n, 4), np.int64)
    taken = 0
    geo_owner, geo_polys, geo_suspect = [], [], []
    no_peak = np.zeros(n, bool)
    soil_top = np.zeros(n, bool)
    live = np.flatnonzero(~outside)
    live_strip = home_strip(win_i[live], H_, strip_rows)
    strips = np.unique(live_strip) if len(live) else []
    skipped = np.zeros(n, bool)
    if band is not None:
        skipped[live] = (live_strip < band[0]) | (live_strip >= band[1])
        strips = [st for st in strips if band[0] <= st < band[1]]
    bar = progress(None, desc="outlines", total=len(strips), unit="strip")
    for strip in strips:
        home = live[live_strip == strip]
        R0 = int(max(0, win_i[home, 1].min()))
        R1 = int(min(H_, win_i[home, 3].max()))
        pad = int((win_i[home, 3] - win_i[home, 1]).max())
        # the strip's full width (its memory was planned for it, strips.py): a canopy no box claims beyond the
        # outermost boxes (a crop row the detector missed at the field's edge) is seen whole, not cut by the
        # window into pieces whose tops lie on the cut
        Rr0, Rr1, Cc0, Cc1 = max(0, R0 - pad), min(H_, R1 + pad), 0, W_
        W = chm.read(Rr0, Rr1, Cc0, Cc1)
        mask = W >= s.min_height  # False in holes (NaN)
        mv = None
        if mask_source is not None and s.mask_threshold is not None:
            mv = holes_low(mask_source.read(Rr0, Rr1, Cc0, Cc1))
            mask &= mv >= s.mask_threshold
        # every plant whose window meets this one competes for the canopy (seeds), only home plants are kept
        near = live[(win_i[live, 2] > Cc0) & (win_i[live, 0] < Cc1) & (win_i[live, 3] > Rr0) & (win_i[live, 1] < Rr1)]
        if seed_px is None:
            tp = _tops(W, _local(box_i[near], Rr0, Rr1, Cc0, Cc1), _local(win_i[near], Rr0, Rr1, Cc0, Cc1), s.min_top)
        else:
            tp = _tops_near(W, seed_px[near] - np.array([Rr0, Cc0]), s.max_shift / res, s.min_top)
        ok = np.isfinite(tp[:, 2]) & (tp[:, 2] >= s.min_top) & (tp[:, 3] == 1)  # a top is a local maximum
        if mv is not None:  # a top on soil by the mask (NDVI) is a ground bump under the box: flagged low
            bare = ok & (
                mv[np.nan_to_num(tp[:, 0]).astype(int), np.nan_to_num(tp[:, 1]).astype(int)] < s.mask_threshold
            )
            soil_top[near[bare & np.isin(near, home)]] = True
        # two boxes of one plant find the same top, or two tops no real valley parts (peaks.py): the box
        # with the highest keeps the plant, the others are duplicates
        tp, keeper = one_plant_boxes(
            W,
            tp,
            ok,
            _local(win_i[near], Rr0, Rr1, Cc0, Cc1),
            _local(box_i[near], Rr0, Rr1, Cc0, Cc1),
            s.noise_sd,
            s.min_top,
            mask,
        )
        first = keeper == np.arange(len(near))
        is_home = np.zeros(n, bool)
        is_home[home] = True
        lost = ok & ~first
        mine = lost & is_home[near]  # (a neighbour's status is settled in its own strip)
        dup[near[mine]] = near[keeper[mine]]
        ok &= first
        L, free = _assign(W, mask, tp, ok, s)
        # canopies no box claims, with their top in this strip's own rows (each is found once)
        in_strip = (free[:, 0] + Rr0) // strip_rows == strip
        free_parts.append(np.column_stack([free[in_strip, 0] + Rr0, free[in_strip, 1] + Cc0, free[in_strip, 2:]]))
        if mv is not None and s.mask_soil is not None:  # a pixel more leaf than soil, by its own plant's top NDVI
            L = _leafy(L, mv, tp, s.mask_soil)
        # a home plant keeps its canopy pixels inside its box + margin that reach `relative` x its top height
        pix, first, total, extent, lab = labelled_pixels(
            L,
            W,
            win_i[near] - [Cc0, Rr0, Cc0, Rr0],
            s.relative * tp[:, 2],
            is_home[near],
            np.arange(1, len(near) + 1),
            W_,
            Rr0,
            Cc0,
        )
        hit = is_home[near]
        mine = near[hit]
        tops[mine, :2] = tp[hit, :2] + [Rr0, Cc0]
        tops[mine, 2] = tp[hit, 2]
        no_peak[mine] = tp[hit, 3] == 0
        own_src[mine], own_len[mine] = taken + first[:-1][hit], np.diff(first)[hit]
        own_sum[mine], own_ext[mine] = total[hit], extent[hit] + [Rr0, Rr0, Cc0, Cc0]
        parts_pix.append(pix)
        taken += len(pix)
        owner, polys, suspect = _trace(lab, near, extent[hit], t, Rr0, Cc0)
        geo_owner.append(owner)
        geo_polys.append(polys)
        geo_suspect.append(suspect)
        bar.update(1)
    bar.close()
    out = _collect(
        geoms,
        n,
        t,
        W_,
        H_,
        res,
        s,
        tops,
        outside | skipped,
        box_i,
        parts_pix,
        (own_src, own_len, own_sum, own_ext),
        (geo_owner, geo_polys, geo_suspect),
        chm,
        dup,
        no_peak,
    )
    out.flag[skipped] = "skipped"
    out.flag[soil_top & (out.flag == "small")] = "low"
    free = np.concatenate(free_parts) if free_parts else np.zeros((0, 4))
    plant_like = free[:, 2] >= max(s.min_top, s.unclaimed_min_top)
    out.noise_bumps = int((~plant_like).sum())
    out.unclaimed = _on_map(t, free[plant_like])
    if mask_source is not None and s.mask_threshold is not None:
        # their pixels are leaves by NDVI, so not ground bumps: weeds, or the smallest plants the detector
        # missed (a seedling whose smoothed top stays within the CHM's noise); the CHM alone cannot tell these
        # from bumps, and they stay only counted
        out.faint = _on_map(t, free[~plant_like])
    return out


def _on_map(t, free: np.ndarray) -> np.ndarray:
    """Unclaimed canopies (row, col, height, pixels) as map x, y (pixel centres), height, pixels."""
    fx, fy = _apply(t, free[:, 1] + 0.5, free[:, 0] + 0.5)
    return np.column_stack([fx, fy, free[:, 2], free[:, 3]])


def _leafy(L: np.ndarray, mv: np.ndarray, tops: np.ndarray, soil: float) -> np.ndarray:
    """The label image ``L`` (1 + the index into ``tops``) without the pixels whose mask value (NDVI) lies below
    halfway from the soil's to the value at their plant's top: a pale plant keeps its leaves, a green one drops
    the mixed pixels at its edges."""
    at_top = mv[np.nan_to_num(tops[:, 0]).astype(int), np.nan_to_num(tops[:, 1]).astype(int)]
    half = np.concatenate([[np.inf], (soil + at_top) / 2])  # label 0 (no plant) stays 0 anyway
    return np.where(mv >= half[L], L, 0)


def _trace(
    lab: np.ndarray, owners: np.ndarray, extent: np.ndarray, t, R0: int, C0: int
) -> tuple[np.ndarray, np.ndarray]:
    """The outline of each plant in the label image ``lab`` (1 + an index into ``owners``, the plants; 0:
    none; the window read at ``R0, C0``), traced over its pixels' extent only (``extent``: row min, row max,
    col min, col max of each plant's pixels; the window's padding rows hold no home plant's pixel). The
    plants, one (multi)polygon each, and whether it may be invalid (:func:`~.trace.outline_pieces`)."""
    some = extent[:, 0] <= extent[:, 1]
    if not some.any():
        return np.zeros(0, np.int64), np.zeros(0, dtype=object), np.zeros(0, bool)
    r0, r1 = int(extent[some, 0].min()), int(extent[some, 1].max()) + 1
    c0, c1 = int(extent[some, 2].min()), int(extent[some, 3].max()) + 1
    labels, polys, suspect = outline_pieces(lab[r0:r1, c0:c1], t, R0 + r0, C0 + c0)  # a view, read in place
    return owners[labels - 1], polys, suspect


def valid_polygons(geoms: np.ndarray, check: np.ndarray | None = None) -> np.ndarray:
    """The polygons made valid where they are not (a ring touching itself at a pixel corner, a box drawn
    with its corners crossed), by GEOS's structure method, which keeps every pixel's area (``buffer(0)``
    may drop one lobe of a bow-tie); collapsed parts (lines, points) are dropped. ``check``: only these may
    be invalid (GEOS's validity test of every outline took half of gathering a strip's outlines)."""
    geoms = np.asarray(geoms, dtype=object).copy()
    present = ~(shapely.is_missing(geoms) | shapely.is_empty(geoms))
    if check is not None:
        present &= check
    bad = np.flatnonzero(present)
    bad = bad[~shapely.is_valid(geoms[bad])]
    if len(bad):
        geoms[bad] = shapely.make_valid(geoms[bad], method="structure", keep_collapsed=False)
    return geoms


def _local(b: np.ndarray, R0: int, R1: int, C0: int, C1: int) -> np.ndarray:
    """Integer windows (c0, r0, c1, r1) in the coordinates of the window read, clipped to it."""
    out = b - np.array([C0, R0, C0, R0])
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, C1 - C0)
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, R1 - R0)
    return out


def _collect(
    geoms, n, t, W_, H_, res, s, tops, outside, box_i, parts_pix, own, geo_parts, chm, dup, no_peak
) -> Outlines:
    """One :class:`Outlines` from the strips' parts: ``parts_pix``, each plant's canopy pixels (grouped by
    plant within a part), ``own`` (each plant's range in their concatenation, its heights' sum and extent)
    and ``geo_parts`` (the plants traced and their polygons)."""
    own_src, own_len, own_sum, own_ext = own
    pix = np.concatenate(parts_pix) if parts_pix else np.zeros(0, np.int64)
    flag = np.full(n, "", dtype=object)
    flag[own_len < s.min_pixels] = "small"
    flag[np.isnan(tops[:, 2])] = "no_top"
    flag[no_peak & np.isfinite(tops[:, 2])] = "no_peak"
    flag[np.isfinite(tops[:, 2]) & (tops[:, 2] < s.min_top)] = "low"
    flag[outside] = "outside"
    flag[dup >= 0] = "duplicate"
    ok = flag == ""
    # each plant's pixels as a range of pix to gather: its own; a duplicate's, the canopy of the plant whose
    # top it shares (when that one has a canopy); another flagged plant's, the pixels whose centre is inside
    # its box (appended after the canopy pixels, row by row)
    src, length = own_src.copy(), np.where(ok, own_len, 0)
    ext = own_ext.copy()  # row min, row max, col min, col max of the pixels gathered
    vol = np.where(ok, own_sum, np.nan)
    shared = np.flatnonzero((dup >= 0) & ok[np.maximum(dup, 0)])
    src[shared], length[shared], ext[shared], vol[shared] = (
        src[dup[shared]],
        length[dup[shared]],
        ext[dup[shared]],
        vol[dup[shared]],
    )
    boxed = np.setdiff1d(np.flatnonzero(~ok & ~outside), shared)
    if len(boxed):
        b = box_i[boxed]
        b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, W_)
        b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0, H_)
        w, size = np.maximum(b[:, 2] - b[:, 0], 0), np.maximum(b[:, 2] - b[:, 0], 0) * np.maximum(b[:, 3] - b[:, 1], 0)
        row, col = np.divmod(ranges(np.zeros(len(size), np.int64), size), np.maximum(np.repeat(w, size), 1))
        box_pix = (np.repeat(b[:, 1], size) + row) * W_ + np.repeat(b[:, 0], size) + col
        src[boxed], length[boxed] = len(pix) + np.cumsum(size) - size, size
        ext[boxed] = np.stack([b[:, 1], b[:, 3] - 1, b[:, 0], b[:, 2] - 1], axis=1)
        pix = np.concatenate([pix, box_pix])
    pix, start = gather_ranges(src, length, pix)
    count = length
    px_area = res * res
    area = count * px_area
    volume = vol * px_area
    # tightened box: the canopy pixels' extent (pixel edges)
    tight = np.full((n, 4), np.nan)
    has = count > 0
    if has.any():
        rmin, rmax, cmin, cmax = ext[has].T
        x0, y0 = _apply(t, cmin, rmax + 1)
        x1, y1 = _apply(t, cmax + 1, rmin)
        tight[has] = np.stack([x0, y0, x1, y1], axis=1)
    top = np.full((n, 3), np.nan)
    tx, ty = _apply(t, tops[:, 1] + 0.5, tops[:, 0] + 0.5)
    top[:, 0], top[:, 1], top[:, 2] = tx, ty, tops[:, 2]
    geometry = np.asarray(geoms, dtype=object).copy()
    owner = np.concatenate(geo_parts[0]) if geo_parts[0] else np.zeros(0, np.int64)
    polys = np.concatenate(geo_parts[1]) if geo_parts[1] else np.zeros(0, dtype=object)
    suspect = np.concatenate(geo_parts[2]) if geo_parts[2] else np.zeros(0, bool)
    mine = ok[owner]
    geometry[owner[mine]] = polys[mine]  # a plant is traced in its home strip only: one (multi)polygon
    check = np.ones(n, bool)  # the boxes given (drawn with crossed corners?) and the outlines that may be invalid
    check[owner[mine]] = suspect[mine]
    geometry[shared] = geometry[dup[shared]]
    check[shared] = check[dup[shared]]
    geometry = valid_polygons(geometry, check)
    return Outlines(
        geometry=geometry,
        tight_box=tight,
        top=top,
        pixels=count,
        area=area,
        volume=volume,
        flag=flag,
        pix=pix,
        start=start,
        transform=t,
        width=W_,
        height=H_,
        crs=getattr(chm, "crs", None),
        duplicate_of=np.where(flag == "duplicate", dup, -1),
    )
