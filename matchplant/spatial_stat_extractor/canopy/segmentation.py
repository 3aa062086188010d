"""The outlining run: :func:`segment` reads the CHM strip by strip (never the whole raster), finds in each strip
the tops and canopies of the plants that live there (:mod:`~.claims`), parts two boxes of one plant
(:mod:`~.peaks`), gathers each home plant's canopy pixels and traces its outline, and makes one
:class:`~.outlines.Outlines` of them all (:mod:`~.collect`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import shapely

from matchplant.core.runtime.progress import progress
from matchplant.spatial_stat_extractor.canopy.claims import assign, holes_low, leafy, tops_in_boxes, tops_near
from matchplant.spatial_stat_extractor.canopy.collect import Found, collect, trace_plants
from matchplant.spatial_stat_extractor.canopy.grid import (
    STRIP_ROWS,
    PlantGrid,
    Window,
    home_strip,
    local_windows,
    on_map,
    pixel_size,
    plant_windows,
)
from matchplant.spatial_stat_extractor.canopy.grouping import LabelRules, Placement, labelled_pixels
from matchplant.spatial_stat_extractor.canopy.outlines import Outlines, SegmentSettings
from matchplant.spatial_stat_extractor.canopy.peaks import one_plant_boxes


class Strip(NamedTuple):
    """One strip of rows: its number, the plants that live in it, every plant on the raster, rows per strip."""

    index: int
    home: np.ndarray
    live: np.ndarray
    rows: int


class Read(NamedTuple):
    """A strip's window of the CHM: where it was read, its heights, the canopy mask, the mask layer (NDVI)."""

    at: Window
    W: np.ndarray
    mask: np.ndarray
    mv: np.ndarray | None


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
    """Outlines of the plants whose boxes are ``geoms`` (in the CHM's CRS) on the CHM source ``chm``.

    Parameters
    ----------
    geoms : array of shapely geometries
        The plant boxes, in the CHM's CRS.
    chm : raster source
        ``transform, width, height, read(row0, row1, col0, col1)`` (an ``ArraySource`` or an opened layer).
    s : SegmentSettings
        How a canopy is cut out of the CHM.
    mask_source : raster source, optional
        A layer on the same grid (NDVI) whose value must reach ``s.mask_threshold`` on canopy pixels.
    seeds : (n, 2) array, optional
        Map x, y of earlier tops, to re-centre each plant within ``s.max_shift`` (later dates).
    strip_rows : int
        Raster rows read at once (plus padding for the boxes crossing a strip's edges).
    band : (int, int), optional
        Only the strips ``band[0] <= strip < band[1]`` (:mod:`~.strips` runs a field band by band); the plants of
        other strips are flagged ``skipped`` (their neighbours still compete).

    Returns
    -------
    Outlines
        Per plant, in the order of ``geoms``.
    """
    geoms = np.asarray(geoms, dtype=object)
    n = len(geoms)
    t = chm.transform
    g = PlantGrid(*plant_windows(geoms, t, s, seeds), t, chm.width, chm.height, pixel_size(t))
    win_i = g.win_i
    outside = (
        (win_i[:, 2] <= 0)
        | (win_i[:, 0] >= g.width)
        | (win_i[:, 3] <= 0)
        | (win_i[:, 1] >= g.height)
        | shapely.is_empty(geoms)
        | shapely.is_missing(geoms)
    )
    found = Found.empty(n)
    live = np.flatnonzero(~outside)
    live_strip = home_strip(win_i[live], g.height, strip_rows)
    strips = np.unique(live_strip) if len(live) else []
    skipped = np.zeros(n, bool)
    if band is not None:
        skipped[live] = (live_strip < band[0]) | (live_strip >= band[1])
        strips = [st for st in strips if band[0] <= st < band[1]]
    bar = progress(None, desc="outlines", total=len(strips), unit="strip")
    for strip in strips:
        _outline_strip(chm, mask_source, s, g, Strip(strip, live[live_strip == strip], live, strip_rows), found)
        bar.update(1)
    bar.close()
    out = collect(geoms, g, s, found, outside | skipped, getattr(chm, "crs", None))
    out.flag[skipped] = "skipped"
    out.flag[found.soil_top & (out.flag == "small")] = "low"
    free = np.concatenate(found.free) if found.free else np.zeros((0, 4))
    plant_like = free[:, 2] >= max(s.min_top, s.unclaimed_min_top)
    out.noise_bumps = int((~plant_like).sum())
    out.unclaimed = on_map(t, free[plant_like])
    if mask_source is not None and s.mask_threshold is not None:
        # their pixels are leaves by NDVI, so not ground bumps: weeds, or the smallest plants the detector
        # missed (a seedling whose smoothed top stays within the CHM's noise); the CHM alone cannot tell these
        # from bumps, and they stay only counted
        out.faint = on_map(t, free[~plant_like])
    return out


def _read_strip(chm, mask_source, s: SegmentSettings, g: PlantGrid, home: np.ndarray) -> Read:
    """The window of a strip whose home plants are ``home``: their rows, padded by the tallest window."""
    win_i = g.win_i
    R0 = int(max(0, win_i[home, 1].min()))
    R1 = int(min(g.height, win_i[home, 3].max()))
    pad = int((win_i[home, 3] - win_i[home, 1]).max())
    # the strip's full width (its memory was planned for it, strips.py): a canopy no box claims beyond the
    # outermost boxes (a crop row the detector missed at the field's edge) is seen whole, not cut by the
    # window into pieces whose tops lie on the cut
    at = Window(max(0, R0 - pad), min(g.height, R1 + pad), 0, g.width)
    W = chm.read(*at)
    mask = W >= s.min_height  # False in holes (NaN)
    mv = None
    if mask_source is not None and s.mask_threshold is not None:
        mv = holes_low(mask_source.read(*at))
        mask &= mv >= s.mask_threshold
    return Read(at, W, mask, mv)


def _strip_tops(r: Read, s: SegmentSettings, g: PlantGrid, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each near plant's top in the strip (local row, col, height, 1 where a local maximum) and whether it is a
    plant's top (high enough, a local maximum)."""
    if g.seed_px is None:
        tp = tops_in_boxes(r.W, local_windows(g.box_i[near], r.at), local_windows(g.win_i[near], r.at), s.min_top)
    else:
        tp = tops_near(r.W, g.seed_px[near] - np.array([r.at.row0, r.at.col0]), s.max_shift / g.res, s.min_top)
    ok = np.isfinite(tp[:, 2]) & (tp[:, 2] >= s.min_top) & (tp[:, 3] == 1)  # a top is a local maximum
    return tp, ok


def _outline_strip(chm, mask_source, s: SegmentSettings, g: PlantGrid, st: Strip, found: Found) -> None:
    """Outline the plants at home in one strip, into ``found``."""
    r = _read_strip(chm, mask_source, s, g, st.home)
    Rr0, Rr1, Cc0, Cc1 = r.at
    win_i, live, home, n = g.win_i, st.live, st.home, len(g.win_i)
    # every plant whose window meets this one competes for the canopy (seeds), only home plants are kept
    near = live[(win_i[live, 2] > Cc0) & (win_i[live, 0] < Cc1) & (win_i[live, 3] > Rr0) & (win_i[live, 1] < Rr1)]
    tp, ok = _strip_tops(r, s, g, near)
    if r.mv is not None:  # a top on soil by the mask (NDVI) is a ground bump under the box: flagged low
        bare = ok & (r.mv[np.nan_to_num(tp[:, 0]).astype(int), np.nan_to_num(tp[:, 1]).astype(int)] < s.mask_threshold)
        found.soil_top[near[bare & np.isin(near, home)]] = True
    # two boxes of one plant find the same top, or two tops no real valley parts (peaks.py): the box
    # with the highest keeps the plant, the others are duplicates
    tp, keeper = one_plant_boxes(
        r.W,
        tp,
        ok,
        local_windows(win_i[near], r.at),
        local_windows(g.box_i[near], r.at),
        noise_sd=s.noise_sd,
        min_top=s.min_top,
        leaf=r.mask,
    )
    first = keeper == np.arange(len(near))
    is_home = np.zeros(n, bool)
    is_home[home] = True
    lost = ok & ~first
    mine = lost & is_home[near]  # (a neighbour's status is settled in its own strip)
    found.dup[near[mine]] = near[keeper[mine]]
    ok &= first
    L, free = assign(r.W, r.mask, tp, ok, s)
    # canopies no box claims, with their top in this strip's own rows (each is found once)
    in_strip = (free[:, 0] + Rr0) // st.rows == st.index
    found.free.append(np.column_stack([free[in_strip, 0] + Rr0, free[in_strip, 1] + Cc0, free[in_strip, 2:]]))
    if r.mv is not None and s.mask_soil is not None:  # a pixel more leaf than soil, by its own plant's top NDVI
        L = leafy(L, r.mv, tp, s.mask_soil)
    # a home plant keeps its canopy pixels inside its box + margin that reach `relative` x its top height
    hit = is_home[near]
    pix, first, total, extent, lab = labelled_pixels(
        L,
        r.W,
        LabelRules(win_i[near] - [Cc0, Rr0, Cc0, Rr0], s.relative * tp[:, 2], hit, np.arange(1, len(near) + 1)),
        Placement(g.width, Rr0, Cc0),
    )
    mine = near[hit]
    found.tops[mine, :2] = tp[hit, :2] + [Rr0, Cc0]
    found.tops[mine, 2] = tp[hit, 2]
    found.no_peak[mine] = tp[hit, 3] == 0
    found.own_src[mine], found.own_len[mine] = found.taken + first[:-1][hit], np.diff(first)[hit]
    found.own_sum[mine], found.own_ext[mine] = total[hit], extent[hit] + [Rr0, Rr0, Cc0, Cc0]
    found.pix.append(pix)
    found.taken += len(pix)
    owner, polys, suspect = trace_plants(lab, near, extent[hit], g.transform, Rr0, Cc0)
    found.owner.append(owner)
    found.polys.append(polys)
    found.suspect.append(suspect)
