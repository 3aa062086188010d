"""Plant outlines from the canopy height model: each projected box becomes the plant's canopy.

For every plant box (plus a margin) the CHM is read window by window (strips of rows, never the whole
raster). The plant's top is the highest local maximum of the CHM inside its box (on a later date: the
local maximum nearest to the earlier top moved by the plants' median shift, within ``max_shift``).
Canopy pixels are those at least ``min_height`` above the ground; connected groups of them
(8-connectivity, ``scipy.ndimage.label``) holding one top belong to that plant, and groups holding
several tops (touching neighbours) are split by a seeded watershed from the tops (flooding the canopy
from the tops down, :func:`~.claims.flood`). A pixel is then kept for its plant when it lies in the plant's box
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
is repaired by :func:`~.collect.valid_polygons`), the tightened boxes, the tops, canopy area and volume, and the canopy
pixels themselves (flat raster indices grouped by plant) for canopy-only statistics
(:mod:`~matchplant.spatial_stat_extractor.canopy.stats`). See docs/DESIGN.md §2 (module 9).

This file holds the two records, :class:`SegmentSettings` and :class:`Outlines`; the run is
:func:`~.segmentation.segment`, strip by strip: the plants on the CHM's grid (:mod:`~.grid`), which pixels are
whose (:mod:`~.claims`), and one :class:`Outlines` from the strips' parts (:mod:`~.collect`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
        """Where each plant kept its box (flagged) instead of a canopy outline."""
        return self.flag != ""

    def same_grid(self, source) -> bool:
        """Whether the raster ``source`` lies on the CHM's grid (its canopy pixels can be read directly)."""
        return (source.width, source.height) == (self.width, self.height) and source.transform.almost_equals(
            self.transform
        )
