"""Overlapping box pairs (matchplant.core.geometry.boxes) against a brute-force numpy reference over all pairs."""

import numpy as np
import pytest

from matchplant.core.geometry import boxes
from matchplant.core.geometry.boxes import iou_pairs, match_boxes, overlapping_pairs

UTM = np.array([500000.0, 4000000.0, 500000.0, 4000000.0])


def brute_force(a, b=None):
    """Every pair (i, j) with IoU > 0 and its IoU, from one broadcast over all pairs, in (i, j) order."""
    same = b is None
    b = a if same else b
    with np.errstate(invalid="ignore", over="ignore"):
        iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
        ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
        inter = np.maximum(iw, 0) * np.maximum(ih, 0)
        area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
        area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        union = area_a[:, None] + area_b[None, :] - inter
        iou = np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)
        keep = iou > 0
    if same:
        keep &= np.triu(np.ones(keep.shape, dtype=bool), 1)
    i, j = np.nonzero(keep)  # row-major: sorted by (i, j)
    return i, j, iou[i, j]


def assert_same(got, ref):
    i, j, iou = got
    assert i.dtype == np.int64 and j.dtype == np.int64 and iou.dtype == np.float64
    assert np.array_equal(i, ref[0]) and np.array_equal(j, ref[1])  # the same pairs, in the same order
    np.testing.assert_allclose(iou, ref[2], rtol=0, atol=1e-12)


def random_boxes(rng, n, kind):
    """``n`` boxes of one size distribution, at UTM-sized coordinates."""
    xy = rng.uniform(0, 5, (n, 2))
    if kind == "plants":  # views of plants: 0.1-0.4 m, many overlaps
        wh = rng.uniform(0.1, 0.4, (n, 2))
    elif kind == "log":  # sizes over four orders of magnitude
        wh = 10 ** rng.uniform(-3, 1, (n, 2))
    elif kind == "thin":  # slivers, long and narrow either way
        wh = np.where(rng.random((n, 1)) < 0.5, [[3.0, 0.01]], [[0.01, 3.0]]) * rng.uniform(0.5, 1, (n, 2))
    elif kind == "huge":  # small boxes and a few covering everything
        wh = rng.uniform(0.05, 0.2, (n, 2))
        big = rng.choice(n, min(n, 4), replace=False)
        xy[big], wh[big] = rng.uniform(-50, 0, (len(big), 2)), rng.uniform(60, 200, (len(big), 2))
    else:
        raise ValueError(kind)
    return np.hstack([xy, xy + wh]) + UTM


def with_awkward_boxes(rng, b):
    """Duplicates, NaN, infinite, zero-area and inverted boxes mixed in."""
    b = b.copy()
    n = len(b)
    b[rng.choice(n, 5, replace=False)] = b[rng.choice(n, 5, replace=False)]  # exact duplicates
    b[rng.choice(n, 3, replace=False), rng.integers(0, 4, 3)] = np.nan
    b[rng.choice(n, 2, replace=False), 2] = np.inf
    k = rng.choice(n, 4, replace=False)
    b[k[:2], 2] = b[k[:2], 0]  # zero width
    b[k[2:], 1] = b[k[2:], 3] + 0.1  # inverted: ymin above ymax
    return b


@pytest.mark.parametrize("kind", ["plants", "log", "thin", "huge"])
def test_pairs_within_one_set_match_brute_force(kind):
    rng = np.random.default_rng(["plants", "log", "thin", "huge"].index(kind))
    for n in (1, 2, 37, 400):
        b = random_boxes(rng, n, kind)
        if n > 10:
            b = with_awkward_boxes(rng, b)
        assert_same(overlapping_pairs(b), brute_force(b))


@pytest.mark.parametrize("kind", ["plants", "log", "huge"])
def test_pairs_across_two_sets_match_brute_force(kind):
    rng = np.random.default_rng(10 + ["plants", "log", "huge"].index(kind))
    for na, nb in ((300, 120), (50, 400), (1, 300), (300, 1)):
        a, b = random_boxes(rng, na, kind), random_boxes(rng, nb, kind)
        if na > 10 and nb > 10:
            a, b = with_awkward_boxes(rng, a), with_awkward_boxes(rng, b)
        assert_same(overlapping_pairs(a, b), brute_force(a, b))


def test_unordered_pairs_are_the_same_pairs_in_a_fixed_order():
    rng = np.random.default_rng(8)
    a, b = random_boxes(rng, 400, "huge"), random_boxes(rng, 300, "log")
    for args in ((a,), (a, b)):
        i, j, iou = overlapping_pairs(*args, ordered=False)
        o = np.lexsort((j, i))
        assert_same((i[o], j[o], iou[o]), brute_force(*args))
        again = overlapping_pairs(*args, ordered=False)
        assert all(np.array_equal(x, y) for x, y in zip((i, j, iou), again))


def test_iou_is_that_of_iou_pairs_to_the_bit():
    b = random_boxes(np.random.default_rng(3), 300, "log")
    i, j, iou = overlapping_pairs(b)
    assert len(i) > 100
    assert np.array_equal(iou, iou_pairs(b[i], b[j]))


def test_touching_boxes_are_no_pair_and_overlapping_ones_are():
    # unit squares on a grid (edges and corners touch), and squares shifted half a side (they overlap)
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0)), -1).reshape(-1, 2)
    grid = np.hstack([g, g + 1]) + UTM
    assert len(overlapping_pairs(grid)[0]) == 0
    assert len(overlapping_pairs(grid, grid + [1, 0, 1, 0])[0]) == 30  # each square and its right neighbour
    shifted = grid + [0.5, 0.5, 0.5, 0.5]
    both = np.vstack([grid, shifted])
    assert_same(overlapping_pairs(both), brute_force(both))
    i, j, iou = overlapping_pairs(grid, shifted)
    assert len(i) == 11 * 11  # along each axis, 5 squares overlap 2 shifted ones and 1 overlaps 1
    np.testing.assert_allclose(iou, 0.25 / 1.75, rtol=1e-9)  # a quarter of a square


def test_duplicates_degenerate_and_invalid_boxes():
    box = np.array([[0.0, 0.0, 1.0, 1.0]]) + UTM
    i, j, iou = overlapping_pairs(np.repeat(box, 4, axis=0))
    assert list(zip(i, j)) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] and np.all(iou == 1)
    bad = np.array(
        [
            [np.nan, 0, 1, 1],
            [0, 0, 0, 1],
            [0, 0, 1, 0],
            [1, 1, 0, 0],
            [0, 0, np.inf, 1],
            [-np.inf, 0, 1, 1],
            [0, 0, 1, 1],
        ]
    )
    i, j, iou = overlapping_pairs(bad)  # only the last box is a box: no pair
    assert len(i) == len(j) == len(iou) == 0
    i, j, iou = overlapping_pairs(bad, np.array([[0.2, 0.2, 0.8, 0.8]]))
    assert list(i) == [6] and list(j) == [0] and iou[0] == pytest.approx(0.36)
    assert len(overlapping_pairs(np.full((5, 4), np.nan))[0]) == 0


def test_empty_inputs():
    b = random_boxes(np.random.default_rng(4), 20, "plants")
    for args in ((np.zeros((0, 4)),), (np.zeros((0, 4)), b), (b, np.zeros((0, 4))), ([],), (b, [])):
        i, j, iou = overlapping_pairs(*args)
        assert len(i) == len(j) == len(iou) == 0 and i.dtype == np.int64
    with pytest.raises(ValueError, match="N, 4"):
        overlapping_pairs(np.zeros((3, 3)))


def test_many_boxes_with_a_few_huge_ones():
    # 40,000 small boxes that do not overlap each other and 3 huge ones over all of them: every pair is
    # known without a brute force over 800 million pairs
    g = np.stack(np.meshgrid(np.arange(200.0), np.arange(200.0)), -1).reshape(-1, 2) * 0.5
    small = np.hstack([g, g + 0.3]) + UTM
    huge = np.array([[-10.0, -10, 150, 150], [-1, -1, 101, 101], [20, 20, 300, 300]]) + UTM
    b = np.vstack([small, huge])
    order = np.random.default_rng(5).permutation(len(b))
    b = b[order]
    i, j, iou = overlapping_pairs(b)
    pos = np.argsort(order)  # position of each original box in b
    ref_i, ref_j = [], []
    for h in range(3):
        inside = np.flatnonzero((small[:, 2] > huge[h, 0]) & (small[:, 3] > huge[h, 1]))
        a, c = pos[inside], np.full(len(inside), pos[len(small) + h])
        ref_i.append(np.minimum(a, c))
        ref_j.append(np.maximum(a, c))
    hh = pos[len(small) + np.array([0, 0, 1])], pos[len(small) + np.array([1, 2, 2])]
    ref_i.append(np.minimum(*hh))
    ref_j.append(np.maximum(*hh))
    ref_i, ref_j = np.concatenate(ref_i), np.concatenate(ref_j)
    o = np.lexsort((ref_j, ref_i))
    assert np.array_equal(i, ref_i[o]) and np.array_equal(j, ref_j[o])
    assert np.array_equal(iou, iou_pairs(b[i], b[j]))


def test_buffers_grow_and_sampling_sizes_them(monkeypatch):
    b = with_awkward_boxes(np.random.default_rng(6), random_boxes(np.random.default_rng(6), 400, "huge"))
    ref = brute_force(b)
    monkeypatch.setattr(boxes, "_expected_pairs", lambda *args: 1)  # far too small: doubled, again and again
    assert_same(overlapping_pairs(b), ref)
    monkeypatch.undo()
    monkeypatch.setattr(boxes, "_SAMPLE", 16)  # the capacity estimated from a sample of the queries
    assert_same(overlapping_pairs(b), ref)
    a2 = random_boxes(np.random.default_rng(7), 200, "plants")
    assert_same(overlapping_pairs(a2, b), brute_force(a2, b))


def test_match_boxes_one_to_one_best_first_ties_by_index():
    ref = np.array([[0.0, 0, 1, 1], [2, 0, 3, 1], [10, 10, 11, 11]]) + UTM
    pred = np.array([[0.0, 0, 1, 1], [0.0, 0, 1, 1], [2.1, 0, 3.1, 1], [20, 20, 21, 21]]) + UTM
    match, iou = match_boxes(ref, pred)
    assert list(match) == [0, 2, -1]  # equal IoU with predictions 0 and 1: the lower index wins
    assert iou[0] == 1 and iou[1] == pytest.approx(0.9 / 1.1) and iou[2] == 0
