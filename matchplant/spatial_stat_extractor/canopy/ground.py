"""The CHM's bare ground: how noisy it is, the canopy thresholds that follow, and whether the CHM is plausible.

A photogrammetric CHM (ODM's DSM - DTM) is not zero on bare soil: real ones have a median of ~1.6 cm and a
95th percentile of ~7 cm there, so a fixed 2 cm threshold takes half the soil for leaves. The noise is
measured from the data: windows around plants spread over the field are read (a few dozen, never the
whole raster), and the CHM on the pixels farther than ``guard`` from every plant box is the ground sample.
Its spread is robust to the weeds and missed plants in it: the larger of 1.4826 x MAD and
(p90 - p50) / 1.2816 (the upper half, which a skewed, heavy-tailed ground noise widens), the latter at most
3 x the former: where more than a tenth of the sample is canopy (plants left out of the plant list, a crop of
the field, a detector that missed many) the upper tail is leaves, not noise (it gave an SD of 0.30 m on a crop
whose edge plants were not listed, and every plant came out 'low'), while a ground noise's own tail stays
well inside 3 MAD spreads. With
``canopy.min_height`` / ``min_top`` left at ``auto``:

* ``min_height`` = max(2 cm, p50 + 3 SD): a canopy pixel is above almost all of the ground (0.1 % of a
  Gaussian ground);
* ``min_top`` = max(5 cm, p50 + 4 SD, min_height): a box whose top stays lower holds nothing the CHM tells
  from soil (flagged ``low``);
* a canopy no box claims is a plant only with a top of at least max(min_top, p50 + 6 SD) (always, numbers
  given or not): the highest ground bumps of a whole field reach ~5 SD, and the detector did not see these.

With an NDVI layer on the CHM's grid (``canopy.ndvi_threshold: auto``), the same windows give the soil's
NDVI (the ground sample's pixels) and the NDVI at each sampled plant's top. A pixel is soil below the soil's
p50 + 3 SD (the same robust spread; at least p50 + 0.05, at most halfway to the tops' median, so that a weak,
pale plant keeps its leaves), used when that separates the two populations (at least 90 % of the soil below
it and 75 % of the tops above it; not so on a closed canopy, or an NDVI raster shifted against the CHM).
A photogrammetric CHM cannot tell a leaf's low edge from a ground
bump of the same height (both a few SD of the noise), but NDVI can: with leaves told from soil by NDVI the
CHM thresholds drop to ``min_height`` = p50 + 1 SD and ``min_top`` = p50 + 2 SD (a box's top must then also
be a leaf, so a bump under a false box still does not make a plant), and so does the top of a canopy no box
claims (max(min_top, p50 + 3 SD)): its pixels are leaves by NDVI, so it is not a ground bump, and the 6 SD
kept every plant the detector missed under ~20 cm out of the stand counts on a noisy CHM.

The same windows give each sampled box's highest and lowest CHM value, from which :func:`check_chm` tells
a CHM that cannot be right: negative under the plants (DSM and DTM swapped), bare ground far from zero (a
DSM given as the CHM, DSM and DTM in different units or datums), plants taller than ``canopy.max_height``
(a CHM in centimetres), a ``min_height`` / ``min_top`` above every plant's top (5 meant as 5 cm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import shapely
from scipy import ndimage as ndi

from matchplant.core.runtime.errors import ConfigError, InputError

FLOOR_HEIGHT, FLOOR_TOP = 0.02, 0.05  # m: the thresholds of an exact CHM (no noise measured)
K_HEIGHT, K_TOP, K_UNCLAIMED = 3.0, 4.0, 6.0  # SDs of the ground noise (see the module doc)
K_HEIGHT_NDVI, K_TOP_NDVI, K_UNCLAIMED_NDVI = 1.0, 2.0, 3.0  # the same where NDVI tells leaves from soil
SOIL_BELOW, TOPS_ABOVE = 0.9, 0.75  # shares of the soil / tops an automatic NDVI threshold must separate
K_NDVI, MIN_NDVI_GAP = 3.0, 0.05  # soil NDVI: SDs above its median, and the least margin (mixed pixels)
MIN_GROUND = 500  # ground pixels needed to measure the noise
MAX_WINDOWS = 32
MIN_WINDOWS = 4
MAX_HALF = 256  # px: half the side of a sample window
GROUND_PER_WINDOW = 20000  # ground values kept per window (evenly strided)
K_EDGE, K_TALL = 3.0, 8.0  # lower spreads above the ground's mode: a tall region's edge, and the top it must reach
MIN_SPREAD = 0.002  # m: the least lower spread (an exact CHM's ground has none; its leaves are still not ground)


@dataclass
class GroundSample:
    """The CHM on bare ground (m) and what the same windows saw of the plants (box tops, NDVI); ``sd`` NaN when
    too little ground was seen to measure it. Not module 8's ``SoilLevel`` (the soil's level above a DSM's
    opening, a correction for the rays): a CHM's bare-ground distribution, for thresholds and checks."""

    pixels: int = 0
    windows: int = 0
    p50: float = np.nan
    p95: float = np.nan
    p99: float = np.nan
    sd: float = np.nan
    box_max: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per sampled box (plant tops)
    box_min: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ndvi_soil: np.ndarray = field(default_factory=lambda: np.zeros(0))  # NDVI of the ground sample
    ndvi_tops: np.ndarray = field(default_factory=lambda: np.zeros(0))  # NDVI at each sampled box's top
    guarded: bool = True  # the sample keeps the guard from the boxes (False: the plants stand too close)
    excluded: float = 0.0  # share of the pixels between the plants taken out as tall things no box covers
    excluded_above: float = np.nan  # m: the level they were above (the lowest edge level of a window)
    excluded_heights: np.ndarray = field(default_factory=lambda: np.zeros(0))  # a sample of their heights

    @property
    def measured(self) -> bool:
        """Whether enough ground was found to measure its noise."""
        return bool(np.isfinite(self.sd))

    def report(self) -> dict:
        """The sample for the JSON report: pixels and windows used, and the noise's percentiles and SD."""
        r = {"ground_pixels": self.pixels, "windows": self.windows, "guarded": self.guarded}
        if self.measured:
            r.update(p50=round(self.p50, 4), p95=round(self.p95, 4), p99=round(self.p99, 4), sd=round(self.sd, 4))
        r["excluded_tall"] = round(self.excluded, 4)
        if self.excluded_heights.size:
            h = self.excluded_heights
            r.update(
                excluded_above=round(self.excluded_above, 4),
                excluded_median=round(float(np.median(h)), 3),
                excluded_max=round(float(h.max()), 3),
            )
        return r

    def excluded_text(self) -> str:
        """What was taken out of the sample, for the log."""
        if not self.excluded_heights.size:
            return "nothing tall left out"
        h = self.excluded_heights
        return (
            f"{self.excluded:.1%} of the pixels left out as tall things no box covers (trees, buildings, "
            f"missed plants: above {self.excluded_above:.3f} m, median {np.median(h):.2f} m, highest {h.max():.2f} m)"
        )


@dataclass
class Thresholds:
    """The canopy thresholds in effect (m) and where each came from (set, or auto from the ground's noise)."""

    min_height: float
    min_top: float
    unclaimed_min_top: float
    source: dict  # key -> "auto (...)" or "set"
    ndvi_threshold: float | None = None
    ndvi_soil: float | None = None  # the soil's NDVI (median), with an automatic ndvi_threshold
    noise_sd: float = 0.0  # m: the ground noise's SD (0 when not measured), for the duplicate rule (peaks.py)


def _covered(shape: tuple[int, int], rects: np.ndarray) -> np.ndarray:
    """Pixels inside any of the integer rectangles (c0, r0, c1, r1), clipped to ``shape``: a 2-D
    difference array summed twice (no loop over boxes)."""
    h, w = shape
    r = rects.copy()
    r[:, [0, 2]] = np.clip(r[:, [0, 2]], 0, w)
    r[:, [1, 3]] = np.clip(r[:, [1, 3]], 0, h)
    r = r[(r[:, 2] > r[:, 0]) & (r[:, 3] > r[:, 1])]
    d = np.zeros((h + 1, w + 1), np.int32)
    np.add.at(d, (r[:, 1], r[:, 0]), 1)
    np.add.at(d, (r[:, 1], r[:, 2]), -1)
    np.add.at(d, (r[:, 3], r[:, 0]), -1)
    np.add.at(d, (r[:, 3], r[:, 2]), 1)
    return d.cumsum(0).cumsum(1)[:h, :w] > 0


class _Boxes(NamedTuple):
    """The plant boxes in pixels of the CHM: pixel centres inside, plus the guard, pixel edges around; their
    centres (row, col) and the half side of a sample window."""

    inner: np.ndarray
    guarded: np.ndarray
    outer: np.ndarray
    centre: np.ndarray
    half: int


def _boxes(t, geoms, guard_m: float) -> _Boxes | None:
    """The boxes of ``geoms`` on the grid ``t`` (None when no geometry has bounds)."""
    res = float(np.sqrt(abs(t.a * t.e - t.b * t.d)))
    geoms = np.asarray(geoms, dtype=object)
    b = shapely.bounds(geoms)
    ok = np.isfinite(b).all(axis=1)
    if not ok.any():
        return None
    inv = ~t
    c0, r0 = inv @ (b[ok, 0], b[ok, 3])
    c1, r1 = inv @ (b[ok, 2], b[ok, 1])
    box = np.stack([np.minimum(c0, c1), np.minimum(r0, r1), np.maximum(c0, c1), np.maximum(r0, r1)], axis=1)
    inner = np.stack(
        [np.floor(box[:, 0] + 0.5), np.floor(box[:, 1] + 0.5), np.floor(box[:, 2] + 0.5), np.floor(box[:, 3] + 0.5)],
        axis=1,
    ).astype(np.int64)  # pixel centres inside
    g = int(np.ceil(guard_m / res))
    guarded = np.stack(
        [np.floor(box[:, 0]) - g, np.floor(box[:, 1]) - g, np.ceil(box[:, 2]) + g, np.ceil(box[:, 3]) + g], axis=1
    ).astype(np.int64)
    size = np.median(np.maximum(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1]))
    half = int(np.clip(3 * size + 2 * g, 32, MAX_HALF))
    centre = np.stack([(box[:, 1] + box[:, 3]) / 2, (box[:, 0] + box[:, 2]) / 2], axis=1)
    outer = np.stack([np.floor(box[:, 0]), np.floor(box[:, 1]), np.ceil(box[:, 2]), np.ceil(box[:, 3])], axis=1).astype(
        np.int64
    )
    return _Boxes(inner, guarded, outer, centre, half)


class _Gathered(NamedTuple):
    """What the windows gave: the ground pixels a guard from every box and those just outside the boxes, their
    NDVI, what was left out of each, and each whole box's highest and lowest CHM value and NDVI at its top."""

    ground: list
    near_ground: list
    soil_ndvi: list
    near_ndvi: list
    tall_seen: dict
    tops: list
    lows: list
    top_ndvi: list


def _sample(found: _Gathered, windows: int) -> GroundSample:
    """The ground sample from what the windows gave: the guarded pixels where there are enough, else those
    just outside the boxes; a window's roof (far above the whole sample's ground) left out."""
    ground, near_ground, soil_ndvi, near_ndvi, tall_seen, tops, lows, top_ndvi = found
    v = np.concatenate(ground) if ground else np.zeros(0)
    guarded = v.size >= MIN_GROUND
    if not guarded:
        v, soil_ndvi = (np.concatenate(near_ground) if near_ground else np.zeros(0)), near_ndvi
    left = tall_seen[guarded]
    soil = np.concatenate(soil_ndvi) if soil_ndvi else np.zeros(0)
    if v.size >= MIN_GROUND:  # a window whose mode was a roof: far above the whole sample's ground
        m, spread = ground_mode(v)
        high = v > m + K_TALL * spread
        if high.any():
            left.add(v[high], 1, m + K_TALL * spread)
            v = v[~high]
            soil = soil[~high] if soil.size == high.size else soil
    out = GroundSample(
        pixels=int(v.size),
        windows=windows,
        box_max=np.array(tops),
        box_min=np.array(lows),
        ndvi_soil=_finite([soil]),
        ndvi_tops=_finite([np.array(top_ndvi)]),
        guarded=guarded,
    )
    if left.count:
        out.excluded = left.count / (left.count + v.size)
        out.excluded_above = left.above
        out.excluded_heights = np.concatenate(left.heights)
    if v.size >= MIN_GROUND:
        p50, p95, p99 = np.percentile(v, [50, 95, 99])
        out.p50, out.p95, out.p99 = float(p50), float(p95), float(p99)
        out.sd = robust_sd(v, p50)
    return out


def measure_ground(chm, geoms, guard_m: float, max_windows: int = MAX_WINDOWS, ndvi=None) -> GroundSample:
    """The ground sample (see the module doc) from up to ``max_windows`` windows around plants spread
    over the field, and the highest / lowest CHM value in each box wholly inside a window; ``ndvi``: a
    layer on the CHM's grid, sampled on the same pixels and at each box's top."""
    bx = _boxes(chm.transform, geoms, guard_m)
    if bx is None:
        return GroundSample()
    inner, guarded, outer, centre, half = bx
    inside = (centre[:, 0] >= 0) & (centre[:, 0] < chm.height) & (centre[:, 1] >= 0) & (centre[:, 1] < chm.width)
    order = np.flatnonzero(inside)[np.lexsort((centre[inside, 1], centre[inside, 0]))]  # by row, then column
    if not len(order):
        return GroundSample()
    # no more windows than it takes to cover the raster once (a small field is read about once)
    k_max = int(np.clip(np.ceil(chm.height * chm.width / (2 * half) ** 2), MIN_WINDOWS, max_windows))
    picks = order[np.unique(np.linspace(0, len(order) - 1, k_max).round().astype(int))]
    ground, tops, lows, seen = [], [], [], np.zeros(len(inner), bool)
    soil_ndvi, top_ndvi = [], []
    # a close-planted field (boxes a guard apart or less) has no pixel a guard from every box: there the
    # pixels outside every box are the sample (a few leaf edges a box cut short widen its tail, which
    # robust_sd caps), better than no measurement and the fixed thresholds of an exact CHM
    near_ground, near_ndvi = [], []
    tall_seen = {True: _Tall(), False: _Tall()}  # what was left out of each sample (guarded, just outside)
    for k in picks:
        R0 = int(max(0, centre[k, 0] - half))
        R1 = int(min(chm.height, centre[k, 0] + half))
        C0 = int(max(0, centre[k, 1] - half))
        C1 = int(min(chm.width, centre[k, 1] + half))
        W = np.asarray(chm.read(R0, R1, C0, C1), dtype=float)
        near = (guarded[:, 2] > C0) & (guarded[:, 0] < C1) & (guarded[:, 3] > R0) & (guarded[:, 1] < R1)
        off = np.array([C0, R0, C0, R0])
        free = ~_covered(W.shape, guarded[near] - off) & np.isfinite(W)
        outside = ~_covered(W.shape, outer[near] - off) & np.isfinite(W)
        tall, edge = tall_regions(W, outside)
        N = None if ndvi is None else np.asarray(ndvi.read(R0, R1, C0, C1), dtype=float)
        for mask, values, ndvis, left in (
            (free, ground, soil_ndvi, tall_seen[True]),
            (outside, near_ground, near_ndvi, tall_seen[False]),
        ):
            kept = mask & ~tall
            v = W[kept]
            step = max(1, v.size // GROUND_PER_WINDOW)
            values.append(v[::step])
            if N is not None:
                ndvis.append(N[kept][::step])
            left.add(W[mask & tall], step, edge)
        whole = (
            near
            & ~seen
            & (inner[:, 0] >= C0)
            & (inner[:, 2] <= C1)
            & (inner[:, 1] >= R0)
            & (inner[:, 3] <= R1)
            & (inner[:, 2] > inner[:, 0])
            & (inner[:, 3] > inner[:, 1])
        )
        for j in np.flatnonzero(whole):  # a few dozen boxes per window
            a = W[inner[j, 1] - R0 : inner[j, 3] - R0, inner[j, 0] - C0 : inner[j, 2] - C0]
            if np.isfinite(a).any():
                tops.append(np.nanmax(a))
                lows.append(np.nanmin(a))
                if N is not None:
                    top_ndvi.append(
                        N[inner[j, 1] - R0 : inner[j, 3] - R0, inner[j, 0] - C0 : inner[j, 2] - C0].ravel()[
                            np.nanargmax(a)
                        ]
                    )
        seen |= whole
    return _sample(
        _Gathered(ground, near_ground, soil_ndvi, near_ndvi, tall_seen, tops, lows, top_ndvi), windows=len(picks)
    )


class _Tall:
    """What was left out of one sample: a count on the sample's scale (each window's pixels over its stride),
    a sample of the heights, the lowest level they were above."""

    def __init__(self):
        self.count, self.heights, self.above = 0.0, [], np.inf

    def add(self, values: np.ndarray, step: int, level: float) -> None:
        if values.size:
            self.count += values.size / step
            self.heights.append(values[:: max(1, values.size // 2000)])
            self.above = min(self.above, level)


def half_sample_mode(x: np.ndarray) -> float:
    """The densest point of ``x`` (Bickel's half-sample mode: the shortest half, recursively), robust to any
    population less dense than the main one, however far away or large."""
    x = np.sort(x[np.isfinite(x)])
    while x.size > 3:
        h = (x.size + 1) // 2
        i = int(np.argmin(x[h - 1 :] - x[: x.size - h + 1]))
        x = x[i : i + h]
    return float(np.mean(x)) if x.size else np.nan


def ground_mode(v: np.ndarray) -> tuple[float, float]:
    """The ground's level (the densest mode of ``v``) and its spread below it (1.4826 x the median distance
    below the mode, at least ``MIN_SPREAD``): what lies above the ground does not reach down there."""
    v = v[np.isfinite(v)]
    step = max(1, v.size // GROUND_PER_WINDOW)
    m = half_sample_mode(v[::step])
    below = m - v[v < m]
    spread = 1.4826 * float(np.median(below)) if below.size else 0.0
    return m, max(spread, MIN_SPREAD)


MIN_OUTSIDE = 200  # pixels outside the boxes a window needs to find its ground's mode


def tall_regions(W: np.ndarray, outside: np.ndarray) -> tuple[np.ndarray, float]:
    """The pixels of tall things no box covers in one window (module doc): connected regions outside the boxes
    above the ground's mode + ``K_EDGE`` lower spreads that reach the mode + ``K_TALL``; and the edge level."""
    none = np.zeros(W.shape, bool)
    if outside.sum() < MIN_OUTSIDE:
        return none, np.nan
    m, spread = ground_mode(W[outside])
    edge = m + K_EDGE * spread
    above = outside & (W > edge)
    seeds = above & (W > m + K_TALL * spread)
    if not seeds.any():
        return none, edge
    labels, _ = ndi.label(above)
    hit = np.unique(labels[seeds])
    return np.isin(labels, hit[hit > 0]), edge


TAIL_CAP = 3.0  # the upper-tail spread is at most this many MAD spreads: beyond, the tail is canopy, not noise


def robust_sd(v: np.ndarray, p50: float) -> float:
    """The larger of 1.4826 x MAD and (p90 - p50) / 1.2816, the latter at most ``TAIL_CAP`` x the former
    (module doc)."""
    mad = 1.4826 * float(np.median(np.abs(v - p50)))
    return float(max(mad, min((np.percentile(v, 90) - p50) / 1.2816, TAIL_CAP * mad)))


def _finite(parts: list) -> np.ndarray:
    v = np.concatenate(parts) if parts else np.zeros(0)
    return v[np.isfinite(v)]


def soil_ndvi_threshold(noise: GroundSample) -> tuple[float | None, str]:
    """The NDVI below which a pixel is soil (module doc), when it separates the soil from the plants' tops;
    else None, and why."""
    soil, tops = noise.ndvi_soil, noise.ndvi_tops
    if soil.size < MIN_GROUND or tops.size < 3:
        return None, f"too few pixels to tell soil from leaves ({soil.size} soil, {tops.size} tops)"
    s50, t50 = float(np.median(soil)), float(np.median(tops))
    sd = robust_sd(soil, s50)
    cut = min(s50 + max(K_NDVI * sd, MIN_NDVI_GAP), (s50 + t50) / 2)
    below, above = float(np.mean(soil < cut)), float(np.mean(tops >= cut))
    why = (
        f"soil median {s50:.2f} + {K_NDVI:g} x SD {sd:.3f}, tops median {t50:.2f}: {below:.0%} of the soil "
        f"below {cut:.2f}, {above:.0%} of the tops above"
    )
    if below < SOIL_BELOW or above < TOPS_ABOVE:
        return None, f"NDVI does not tell leaves from soil ({why})"
    return cut, why


def thresholds(min_height, min_top, noise: GroundSample, ndvi_threshold=None) -> Thresholds:
    """The canopy thresholds (m; NDVI): numbers as given, ``"auto"`` from the ground noise and, for NDVI,
    from the soil's and the tops' NDVI (module doc)."""
    src = {}
    auto_ndvi = ndvi_threshold == "auto"
    if auto_ndvi:
        ndvi_threshold, why_ndvi = soil_ndvi_threshold(noise)
        src["ndvi_threshold"] = f"auto ({why_ndvi})"
    else:
        src["ndvi_threshold"] = "set" if ndvi_threshold is not None else "none"
    k_height, k_top, k_unclaimed = (
        (K_HEIGHT_NDVI, K_TOP_NDVI, K_UNCLAIMED_NDVI) if ndvi_threshold is not None else (K_HEIGHT, K_TOP, K_UNCLAIMED)
    )
    base = noise.p50 if noise.measured else 0.0
    sd = noise.sd if noise.measured else 0.0
    why = f"ground p50 {base:.3f} m + {{k:g}} x SD {sd:.3f} m" if noise.measured else "no ground noise measured"
    if min_height == "auto":
        min_height = max(FLOOR_HEIGHT, base + k_height * sd)
        src["min_height"] = f"auto ({why.format(k=k_height)}, at least {FLOOR_HEIGHT} m)"
    else:
        src["min_height"] = "set"
    if min_top == "auto":
        min_top = max(FLOOR_TOP, base + k_top * sd, float(min_height))
        src["min_top"] = f"auto ({why.format(k=k_top)}, at least {FLOOR_TOP} m and min_height)"
    else:
        src["min_top"] = "set"
    unclaimed = max(float(min_top), base + k_unclaimed * sd)
    soil = float(np.median(noise.ndvi_soil)) if auto_ndvi and ndvi_threshold is not None else None
    return Thresholds(
        float(min_height),
        float(min_top),
        float(unclaimed),
        src,
        None if ndvi_threshold is None else float(ndvi_threshold),
        soil,
        float(sd),
    )


def check_chm(noise: GroundSample, th: Thresholds, max_height: float, what: str, keys: tuple[str, ...]) -> None:
    """Clear errors for a CHM that cannot be right (module doc). ``what``: the CHM's files for the
    message; ``keys``: its config keys (``rasters.chm`` or ``rasters.dsm``, ``rasters.dtm``)."""
    tops, lows = noise.box_max, noise.box_min
    base = noise.p50 if noise.measured else 0.0
    sd = noise.sd if noise.measured else 0.0
    named = " and ".join(keys)
    if len(tops) >= 3:
        down, up = base - lows, tops - base
        negative = down > np.maximum(2 * up, max(5 * sd, 0.05))
        if negative.mean() > 0.5:
            if len(keys) == 2:
                fix = f"swap {keys[0]} and {keys[1]} (the DSM is the surface, the higher one)"
            else:
                fix = f"give {keys[0]} as surface minus terrain (DSM - DTM), not the reverse"
            raise InputError(
                f"the CHM from {what} is negative under {int(negative.sum())} of {len(tops)} plants "
                f"sampled (median {np.median(-down):.2f} m below the ground): {named} look swapped",
                fix=fix,
            )
    if len(tops):
        tall = float(np.median(tops) - base)
        if tall > max_height:
            raise InputError(
                f"the CHM from {what} makes the plants {tall:.1f} m tall (median of {len(tops)} "
                f"sampled, highest {np.max(tops):.1f} m), above canopy.max_height = {max_height:g} m: "
                f"are {named} in centimetres?",
                fix='convert them to metres (e.g. gdal_calc.py -A dsm.tif --calc="A/100" '
                "--outfile=dsm_m.tif), or raise canopy.max_height for taller plants",
            )
    if noise.measured and abs(base) > max(1.0, 3 * sd):  # an offset, not a noise in other units
        raise InputError(
            f"the CHM from {what} puts the bare ground {base:.2f} m from zero (median between the "
            f"plants): {named} are not a height above the ground (a DSM given as the CHM, or DSM "
            "and DTM in different units or vertical datums)",
            fix="give the CHM as DSM - DTM of one flight, both in metres (rasters.dsm + rasters.dtm)",
        )
    if len(tops):
        highest = float(np.max(tops))
        for key in ("min_height", "min_top"):
            v = getattr(th, key)
            if th.source[key] == "set" and v > highest:
                raise ConfigError(
                    f"canopy.{key} = {v:g} m is above the top of every plant sampled (the highest "
                    f"{highest:.2f} m, {len(tops)} plants): heights are in metres",
                    fix=f"set canopy.{key}: {v / 100:g} for {v:g} cm, or auto (from the CHM's ground noise)",
                )
