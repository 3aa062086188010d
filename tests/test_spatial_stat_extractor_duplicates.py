"""Module 9's duplicate rule on a photogrammetric-looking CHM (issue 26, stand counts): a second, split box
of one noisy-topped plant finds another local maximum of the plant's top than the plant's own box, and is
still one plant (``duplicate``); two distinct plants whose canopies touch stay two. Checked against the
construction's truth (tests/noisy_chm.py: each plant's footprint)."""

from __future__ import annotations

import numpy as np
import shapely
from noisy_chm import noisy_chm
from scipy import ndimage as ndi

from matchplant.spatial_stat_extractor.canopy import SegmentSettings, measure_ground, segment, thresholds
from matchplant.spatial_stat_extractor.canopy.peaks import _saddle, keepers, one_plant_boxes
from matchplant.spatial_stat_extractor.inputs import ArraySource


def touching_pairs(truth: np.ndarray) -> set[tuple[int, int]]:
    """Pairs of plants (0-based) whose true footprints touch (8-neighbour pixels)."""
    pairs = set()
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = truth[max(0, -dr) : truth.shape[0] - max(0, dr), max(0, -dc) : truth.shape[1] - max(0, dc)]
        b = truth[max(0, dr) :, max(0, dc) :][: a.shape[0], : a.shape[1]]
        m = (a > 0) & (b > 0) & (a != b)
        pairs |= {(min(p, q) - 1, max(p, q) - 1) for p, q in zip(a[m], b[m])}
    return pairs


def split_boxes(f) -> tuple[np.ndarray, np.ndarray]:
    """The detector's second box on each plant whose true footprint holds two or more local maxima of the
    CHM: the part of the plant's box on the side of its second-highest maximum, cut halfway between the two
    (so it holds the second maximum, not the top). Returns the plants split and the boxes."""
    W = np.nan_to_num(f.chm, nan=-np.inf)
    peak = (W == ndi.maximum_filter(W, 5)) & (f.truth > 0)
    r, c = np.nonzero(peak)
    plants, boxes = [], []
    for k in range(len(f.boxes)):
        mine = np.flatnonzero(f.truth[r, c] == k + 1)
        if len(mine) < 2:
            continue
        (r1, c1), (r2, c2) = ((r[m], c[m]) for m in mine[np.argsort(-W[r[mine], c[mine]])[:2]])
        (x1, x2), (y1, y2) = f.transform @ (np.array([c1, c2]) + 0.5, np.array([r1, r2]) + 0.5)
        x0, y0, xe, ye = f.boxes[k].bounds
        if abs(x2 - x1) >= abs(y2 - y1):
            xm = (x1 + x2) / 2
            x0, xe = (xm, xe) if x2 > x1 else (x0, xm)
        else:
            ym = (y1 + y2) / 2
            y0, ye = (ym, ye) if y2 > y1 else (y0, ym)
        plants.append(k)
        boxes.append(shapely.box(x0, y0, xe, ye))
    return np.array(plants), np.array(boxes, dtype=object)


def test_split_boxes_of_one_noisy_plant_are_one_plant_touching_neighbours_two():
    # 5 mm pixels and a 8 mm gridding blur (the demo's noisy field): a plant's top holds several maxima;
    # plants 22 cm apart in the rows: the tall ones' leaves touch
    f = noisy_chm(seed=3, res=0.005, smooth_m=0.008, heights=(0.4, 0.9), spacing=0.22)
    src = ArraySource(f.chm, f.transform)
    noise = measure_ground(src, f.boxes, guard_m=0.1)
    th = thresholds("auto", "auto", noise)
    s = SegmentSettings(
        min_height=th.min_height, min_top=th.min_top, unclaimed_min_top=th.unclaimed_min_top, noise_sd=th.noise_sd
    )
    n = len(f.boxes)
    split, extra = split_boxes(f)
    o = segment(np.concatenate([f.boxes, extra]), src, s)
    plant_of = np.concatenate([np.arange(n), split])
    # most split boxes find another maximum of the plant than its own box (the same-pixel rule misses them)
    moved = (o.top[n:, 0] != o.top[split, 0]) | (o.top[n:, 1] != o.top[split, 1])
    assert len(split) >= 20 and moved.mean() >= 0.5
    # the split boxes are duplicates of their own plant: they share its outline
    dup = o.flag[n:] == "duplicate"
    assert dup.mean() >= 0.9 and dup[moved].mean() >= 0.9
    assert all(o.geometry[n + i].equals(o.geometry[split[i]]) for i in np.flatnonzero(dup))
    # the plant's own boxes stay plants, touching neighbours included
    assert (o.flag[:n] != "duplicate").all()
    touching = touching_pairs(f.truth)
    outlined = o.flag[:n] == ""
    assert sum(outlined[p] and outlined[q] for p, q in touching) >= 8
    # every box counted as a plant (not flagged) is a distinct true plant
    counted = np.flatnonzero(o.flag == "")
    assert len(np.unique(plant_of[counted])) == len(counted)


def dome(cx: float, h: float) -> np.ndarray:
    """A plant's canopy h (1 - rho^2), radius 18 px, centred on row 20 and column ``cx`` of a 40 x 80 grid."""
    yy, xx = np.mgrid[0:40, 0:80].astype(float)
    return h * np.clip(1 - ((xx - cx) ** 2 + (yy - 20) ** 2) / 18**2, 0, None)


def test_one_noisy_dome_is_one_plant_a_valley_parts_two():
    """The rule itself: a short dome whose top a noise pit splits into two maxima is one plant when the pit
    is within 3 SD of the measured noise (and two on an exact CHM, where any dip deeper than 40 % of the top
    is a valley); two domes whose flanks meet at under half the lower top are two, whatever the noise."""
    one = dome(20, 0.15)
    one[18:23, 18:23] -= 0.07  # a 7 cm pit (2.3 SD of a 3 cm noise) at the centre, 5 x 5 pixels
    one[20, [17, 23]] += 0.005  # the two maxima on its rim
    tops = np.array([[20, 17, one[20, 17]], [20, 23, one[20, 23]]])
    peak = ndi.maximum_filter(one, 5) == one
    assert peak[20, 17] and peak[20, 23]
    win = np.array([[0, 0, 40, 40], [0, 0, 40, 40]])
    both = np.array([True, True])
    assert keepers(one, tops, both, win, noise_sd=0.03).tolist() == [0, 0]
    assert keepers(one, tops, both, win, noise_sd=0.0).tolist() == [0, 1]
    # a matching hole (NaN) between two maxima of one plant is no valley
    holed = dome(20, 0.6)
    holed[20, [14, 26]] += 0.005
    holed[17:24, 18:23] = np.nan
    tops = np.array([[20, 14, holed[20, 14]], [20, 26, holed[20, 26]]])
    assert keepers(holed, tops, both, win, noise_sd=0.0).tolist() == [0, 0]  # equal tops: the first keeps
    two = np.maximum(dome(20, 0.6), dome(47, 0.5))  # flanks meet at column ~34
    tops = np.array([[20, 20, 0.6], [20, 47, 0.5]])
    win = np.array([[0, 0, 42, 40], [26, 0, 68, 40]])
    assert 0.1 < two[20, 20:48].min() / 0.5 < 0.5  # a real valley, though the canopies touch
    for sd in (0.0, 0.03):
        assert keepers(two, tops, both, win, noise_sd=sd).tolist() == [0, 1]


def test_a_short_plants_box_on_a_bump_of_its_tall_neighbour_keeps_its_own_plant():
    """A short plant beside a tall one: a noise bump on the tall plant's leaves inside the short plant's box
    is the box's highest local maximum, and one plant with the tall top; the box then takes its own top."""
    chm = np.maximum(dome(20, 0.6), dome(50, 0.3))  # they touch at column ~37, far below the short top
    chm[20, 33] += 0.12  # the bump: 0.41 m, higher than the short plant's 0.3 m top
    peak = ndi.maximum_filter(chm, 5) == chm
    assert peak[20, 33] and peak[20, 50] and peak[20, 20]
    boxes = np.array([[2, 2, 38, 38], [32, 2, 68, 38]])  # c0, r0, c1, r1: the short box holds the bump
    tops = np.array([[20, 20, 0.6], [20, 33, chm[20, 33]]])
    both = np.array([True, True])
    assert keepers(chm, tops, both, boxes, noise_sd=0.03).tolist() == [0, 0]  # the bump alone: one plant
    moved, keep = one_plant_boxes(chm, tops, both, boxes, boxes, noise_sd=0.03, min_top=0.05)
    assert keep.tolist() == [0, 1]
    assert moved[1].tolist() == [20, 50, 0.3] and moved[0].tolist() == tops[0].tolist()


def test_a_split_box_centred_on_a_plant_does_not_move_to_a_low_leaf_at_its_edge():
    """Two boxes of one plant, both centred on it, the second's highest point a noise bump on the plant's top
    (one plant); at the box's edge a low leaf tip stands parted from the top by a noise valley. The box's own
    plant is the one at its centre: it stays a duplicate (on the noisy demo field such boxes were counted as
    extra plants, flagged small, in 13 of 63 plots' counts)."""
    chm = dome(30, 0.5)
    chm[20, 30] += 0.02  # noise on the top: the second box's highest local maximum
    chm[17:24, 45:48] = 0.02  # a noise valley across the leaves ...
    chm[20, 48] = 0.12  # ... and a leaf tip beyond it, at the second box's edge
    peak = ndi.maximum_filter(chm, 5) == chm
    assert peak[20, 48]
    boxes = np.array([[12, 2, 48, 38], [13, 2, 49, 38]])  # c0, r0, c1, r1: both centred on the dome
    tops = np.array([[20, 30, chm[20, 30]], [20, 30, chm[20, 30]]])
    both = np.array([True, True])
    moved, keep = one_plant_boxes(chm, tops, both, boxes, boxes, noise_sd=0.01, min_top=0.05)
    assert keep.tolist() == [0, 0] and moved[1].tolist() == tops[1].tolist()


def test_boxes_whose_windows_do_not_meet_are_each_their_own_plant():
    """Two plants close enough for the k-d tree's reach but with windows that do not overlap: no pair is
    tested, and each box keeps its plant (this crashed module 9 on a field of six plants)."""
    chm = np.maximum(dome(20, 0.5), dome(60, 0.5))
    tops = np.array([[20, 20, 0.5], [20, 60, 0.5]])
    windows = np.array([[0, 0, 39, 40], [41, 0, 80, 40]])  # c0, r0, c1, r1: apart by a column
    assert keepers(chm, tops, np.array([True, True]), windows, noise_sd=0.01).tolist() == [0, 1]


def test_a_second_top_on_soil_by_ndvi_is_no_plant_and_the_box_stays_a_duplicate():
    """A second box of a plant reaching over a ground bump parted from the plant by bare soil: without a
    leaf mask the bump (a local maximum above min_top, parted by a valley, nearer the box's centre) becomes
    the box's own plant; with the mask (NDVI: the bump is soil) it is no plant's top and the box stays the
    plant's duplicate (on the noisy demo field such boxes were counted, flagged small, in 4 plots)."""
    chm = dome(20, 0.5)
    yy, xx = np.mgrid[0:40, 0:80]
    chm = chm + 0.12 * np.exp(-((xx - 52) ** 2 + (yy - 20) ** 2) / 8.0)  # the bump, soil between
    boxes = np.array([[2, 2, 38, 38], [18, 10, 62, 30]])  # c0, r0, c1, r1: the second holds the top and bump
    tops = np.array([[20, 20, chm[20, 20]], [20, 20, chm[20, 20]]])
    both = np.array([True, True])
    moved, keep = one_plant_boxes(chm, tops, both, boxes, boxes, noise_sd=0.01, min_top=0.05)
    assert keep.tolist() == [0, 1] and moved[1, :2].tolist() == [20, 52]  # the bump taken for a plant
    leaf = dome(20, 0.5) > 0.02  # the plant's pixels; the bump is soil
    moved, keep = one_plant_boxes(chm, tops, both, boxes, boxes, noise_sd=0.01, min_top=0.05, leaf=leaf)
    assert keep.tolist() == [0, 0] and moved[1].tolist() == tops[1].tolist()


def test_a_saddle_is_the_same_whatever_other_pairs_are_tested_with_it():
    """The lowest CHM between two tops samples the line once per pixel step, as a loop over the steps
    computes it, however long the other lines tested at the same time are (a denser grid met other
    pixels, so a pair was one plant or two depending on its neighbours)."""
    rng = np.random.default_rng(3)
    W = ndi.gaussian_filter(rng.normal(size=(120, 120)), 1.2)
    p = rng.integers(20, 100, (40, 2))
    q = p + rng.integers(-12, 13, (40, 2))
    batched = _saddle(W, np.vstack([p, [[2, 3]]]), np.vstack([q, [[117, 110]]]))[:40]
    for (pr, pc), (qr, qc), got in zip(p, q, batched):
        n = max(abs(qr - pr), abs(qc - pc)) + 1
        line = []
        for k in range(n + 1):
            r, c = round(pr + (qr - pr) * k / n), round(pc + (qc - pc) * k / n)
            line.append(W[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2].max())
        assert got == min(line)
