"""One :class:`~.outlines.Outlines` from what the strips found (:class:`Found`): the flags, each plant's canopy
pixels (its own, a duplicate's keeper's, or a flagged plant's box), canopy area and volume, the tightened boxes,
the tops on the map, and the outline polygons traced on the label image, made valid where they may not be."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely

from matchplant.spatial_stat_extractor.canopy.grid import PlantGrid, apply_affine
from matchplant.spatial_stat_extractor.canopy.grouping import gather_ranges
from matchplant.spatial_stat_extractor.canopy.outlines import Outlines, SegmentSettings
from matchplant.spatial_stat_extractor.canopy.trace import outline_pieces
from matchplant.spatial_stat_extractor.zonal import ranges


@dataclass
class Found:
    """What the strips found: per plant (arrays over the ``n`` plants, filled in each plant's home strip) its top,
    the plant a duplicate box shares its top with, its canopy pixels' range in the concatenated parts, their
    height sum and extent; and part by part (one per strip) the canopy pixels, the canopies no box claims and the
    outlines traced."""

    tops: np.ndarray  # (n, 3) row, col, height above ground of the top (NaN: none)
    dup: np.ndarray  # (n,) the plant whose top a duplicate box shares, -1 for the others
    no_peak: np.ndarray  # (n,) bool: the top is no local maximum
    soil_top: np.ndarray  # (n,) bool: the top lies on soil by the mask (NDVI)
    own_src: np.ndarray  # (n,) int64: start of the plant's canopy pixels in the concatenated parts
    own_len: np.ndarray  # (n,) int64: their count
    own_sum: np.ndarray  # (n,) their heights' sum
    own_ext: np.ndarray  # (n, 4) int64: their row min, row max, col min, col max
    pix: list = field(default_factory=list)  # per strip: flat indices of its home plants' canopy pixels
    free: list = field(default_factory=list)  # per strip: (m, 4) row, col, height, pixels of unclaimed canopies
    owner: list = field(default_factory=list)  # per strip: the plants traced
    polys: list = field(default_factory=list)  # per strip: their (multi)polygons
    suspect: list = field(default_factory=list)  # per strip: whether each may be invalid
    taken: int = 0  # canopy pixels in the parts so far

    @classmethod
    def empty(cls, n: int) -> Found:
        """Nothing found yet of ``n`` plants."""
        return cls(
            tops=np.full((n, 3), np.nan),
            dup=np.full(n, -1),
            no_peak=np.zeros(n, bool),
            soil_top=np.zeros(n, bool),
            own_src=np.zeros(n, np.int64),
            own_len=np.zeros(n, np.int64),
            own_sum=np.zeros(n),
            own_ext=np.zeros((n, 4), np.int64),
        )


def trace_plants(
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


def collect(geoms, g: PlantGrid, s: SegmentSettings, found: Found, outside: np.ndarray, crs=None) -> Outlines:
    """One :class:`Outlines` of the plants ``geoms`` on the grid ``g`` from what the strips ``found`` (each
    plant's canopy pixels grouped by plant within a part, the plants traced and their polygons); ``outside``:
    the plants no strip outlined (off the raster, or another band's)."""
    n, t, W_, H_ = len(geoms), g.transform, g.width, g.height
    tops, dup, no_peak, box_i = found.tops, found.dup, found.no_peak, g.box_i
    own_src, own_len, own_sum, own_ext = found.own_src, found.own_len, found.own_sum, found.own_ext
    pix = np.concatenate(found.pix) if found.pix else np.zeros(0, np.int64)
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
    px_area = g.res * g.res
    area = count * px_area
    volume = vol * px_area
    # tightened box: the canopy pixels' extent (pixel edges)
    tight = np.full((n, 4), np.nan)
    has = count > 0
    if has.any():
        rmin, rmax, cmin, cmax = ext[has].T
        x0, y0 = apply_affine(t, cmin, rmax + 1)
        x1, y1 = apply_affine(t, cmax + 1, rmin)
        tight[has] = np.stack([x0, y0, x1, y1], axis=1)
    top = np.full((n, 3), np.nan)
    tx, ty = apply_affine(t, tops[:, 1] + 0.5, tops[:, 0] + 0.5)
    top[:, 0], top[:, 1], top[:, 2] = tx, ty, tops[:, 2]
    geometry = np.asarray(geoms, dtype=object).copy()
    owner = np.concatenate(found.owner) if found.owner else np.zeros(0, np.int64)
    polys = np.concatenate(found.polys) if found.polys else np.zeros(0, dtype=object)
    suspect = np.concatenate(found.suspect) if found.suspect else np.zeros(0, bool)
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
        crs=crs,
        duplicate_of=np.where(flag == "duplicate", dup, -1),
    )
