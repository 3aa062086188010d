"""Module 9's compiled kernels (outlines and canopy statistics) against the plain numpy/scipy computations
they replace, on random data with holes, ties and edges."""

import ast
import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

import matchplant.spatial_stat_extractor as m9
from matchplant.spatial_stat_extractor.canopy.grouping import (
    LabelRules,
    Placement,
    gather_ranges,
    label_boxes,
    labelled_pixels,
    pixel_window,
    relabel,
    sort_within_groups,
    values_at,
)
from matchplant.spatial_stat_extractor.canopy.maxima import line_saddles, local_maxima
from matchplant.spatial_stat_extractor.zonal import LARGE_GROUP, quantiles


@pytest.mark.parametrize("size", [3, 5])
def test_local_maxima_are_the_maximum_filters_peaks(size):
    rng = np.random.default_rng(size)
    a = np.round(rng.random((60, 83)), 1)  # rounded: many ties (plateaus count as maxima, as with the filter)
    a[rng.random(a.shape) < 0.05] = -np.inf  # holes
    want = (a == ndi.maximum_filter(a, size=size)) & (a >= 0.3)
    got = local_maxima(a, size, 0.3)
    assert got.dtype == bool and np.array_equal(got, want) and want.sum() > 20
    assert np.array_equal(local_maxima(np.where(np.isinf(a), np.nan, a), size, 0.3), want)  # NaN holes: the same
    assert np.array_equal(local_maxima(a[:1, :2], size, 0.3), (a[:1, :2] == a[:1, :2].max()) & (a[:1, :2] >= 0.3))


def test_gather_ranges_concatenates_each_groups_range():
    """Groups made of (repeated, empty, out-of-order) ranges: a Python concatenation of the slices."""
    rng = np.random.default_rng(2)
    pix = rng.integers(0, 10**9, 300)
    src, length = rng.integers(0, 250, 40), rng.integers(0, 50, 40)
    length[::7] = 0
    src[5] = src[6]  # two groups share one range (a duplicate box and its plant)
    p, start = gather_ranges(src, length, pix)
    assert np.array_equal(p, np.concatenate([pix[a : a + n] for a, n in zip(src, length)]))
    assert np.array_equal(np.diff(start), length) and start[0] == 0


def test_label_boxes_and_sorted_runs():
    rng = np.random.default_rng(2)
    labels, n = ndi.label(rng.random((40, 70)) < 0.4)
    size, box = label_boxes(labels, n)
    assert np.array_equal(size, np.bincount(labels.ravel(), minlength=n + 1))
    want = [(s[0].start, s[0].stop, s[1].start, s[1].stop) for s in ndi.find_objects(labels)]
    assert [tuple(b) for b in box[1:]] == want
    v = rng.random(300)
    first = np.array([0, 0, 1, 40, 41, 300])
    got = sort_within_groups(v, first)
    want = np.concatenate([np.sort(v[a:b]) for a, b in itertools.pairwise(first)])
    assert np.array_equal(got, want) and not np.array_equal(v, got)


def test_labelled_pixels_keep_the_pixels_in_window_reaching_their_height():
    """Against numpy: the pixels kept, grouped by label in raster order (a stable sort), as flat indices on the
    raster the image was cut from, with each label's float32 sum and extent, and the image of the kept pixels."""
    rng = np.random.default_rng(3)
    L = rng.integers(0, 6, (30, 40)).astype(np.int32)  # labels 1..5 = 1 + k
    W = rng.random((30, 40))
    W[rng.random(W.shape) < 0.05] = np.nan
    windows = np.array([[0, 0, 40, 30], [5, 3, 20, 25], [10, 10, 11, 30], [0, 0, 40, 30], [-5, -5, 50, 50]])
    reach = np.array([0.5, 0.0, 0.2, np.nan, 0.9])
    home = np.array([True, True, True, True, False])
    ids = np.array([11, 12, 13, 14, 15])
    width, row0, col0 = 1000, 7, 300
    pix, start, total, extent, image = labelled_pixels(
        L, W, LabelRules(windows, reach, home, ids), Placement(width, row0, col0)
    )
    r, c = np.nonzero(L)
    kk = L[r, c] - 1
    keep = (
        (c >= windows[kk, 0])
        & (c < windows[kk, 2])
        & (r >= windows[kk, 1])
        & (r < windows[kk, 3])
        & (W[r, c] >= reach[kk])
        & home[kk]
    )
    assert keep.sum() > 50
    r, c, kk = r[keep], c[keep], kk[keep]
    order = np.argsort(kk, kind="stable")
    assert np.array_equal(pix, ((r + row0) * width + c + col0)[order])
    assert np.array_equal(start, np.searchsorted(kk[order], np.arange(6)))
    h = W[r, c].astype(np.float32)
    assert np.array_equal(total, np.bincount(kk, weights=h, minlength=5))
    for k in np.unique(kk):
        assert extent[k].tolist() == [r[kk == k].min(), r[kk == k].max(), c[kk == k].min(), c[kk == k].max()]
    assert extent[3, 0] > extent[3, 1] and extent[4, 0] > extent[4, 1]  # none kept: reach NaN, not home
    want = np.zeros(L.shape, np.int32)
    want[r, c] = ids[kk]
    assert np.array_equal(image, want)


def test_line_saddles_are_the_lowest_3x3_maximum_along_each_line():
    """Against nine gathers of every sample (the numpy code it replaced), each line at its own pixel steps,
    with NaN and -inf holes, a large
    hole that blinds some lines, lines at the edge and lines of one pixel."""
    rng = np.random.default_rng(0)
    a = np.round(rng.random((120, 150)), 2)
    a[rng.random(a.shape) < 0.3] = np.nan
    a[rng.random(a.shape) < 0.05] = -np.inf
    a[40:80, 40:100] = np.nan
    p = rng.integers(0, [120, 150], (500, 2))
    q = np.clip(p + rng.integers(-40, 40, (500, 2)), 0, [119, 149])
    q[:5] = p[:5]
    own = np.abs(q - p).max(axis=1) + 1
    s = np.linspace(0.0, 1.0, int(own.max()) + 1)
    t = np.rint(s[None, :] * own[:, None]) / own[:, None]  # each line's own steps
    r = np.rint(p[:, 0, None] + (q[:, 0] - p[:, 0])[:, None] * t).astype(int)
    c = np.rint(p[:, 1, None] + (q[:, 1] - p[:, 1])[:, None] * t).astype(int)
    best = np.full(r.shape, -np.inf)
    for dr, dc in itertools.product((-1, 0, 1), repeat=2):
        best = np.fmax(best, a[np.clip(r + dr, 0, 119), np.clip(c + dc, 0, 149)])
    seen = best > -np.inf
    want = np.where(seen.mean(axis=1) >= 0.5, np.where(seen, best, np.inf).min(axis=1), -np.inf)
    got = line_saddles(a, p, q, s, own)
    assert np.array_equal(got, want) and 10 < (want == -np.inf).sum() < 400


def test_relabel_is_a_lookup():
    rng = np.random.default_rng(4)
    labels = rng.integers(0, 30, (37, 41)).astype(np.int32)
    lut = rng.integers(0, 1000, 30).astype(np.int32)
    got = relabel(labels, lut)
    assert got.dtype == np.int32 and np.array_equal(got, lut[labels])
    assert np.array_equal(relabel(labels[:, ::2], lut), lut[labels[:, ::2]])  # a strided view


def test_quantiles_of_small_and_large_groups_are_numpys():
    """Plants' boxes (sorted in padded matrices) and plot polygons over LARGE_GROUP values (partitioned): the
    same numbers as np.percentile, ties and one-value groups included."""
    rng = np.random.default_rng(5)
    counts = np.array([1, 2, 7, 300, LARGE_GROUP + 1, 3 * LARGE_GROUP, 0, 5])
    v = np.round(rng.normal(0, 1, counts.sum()), 2)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    qs = [0.0, 0.1, 0.5, 0.95, 1.0]
    got = quantiles(v, starts, counts, qs)
    for g, (a, n) in enumerate(zip(starts, counts)):
        want = np.percentile(v[a : a + n], [q * 100 for q in qs]) if n else np.full(len(qs), np.nan)
        np.testing.assert_allclose(got[g], want, rtol=0, atol=1e-12, err_msg=str(n))


def _label_images(rng):
    """Label images with what real canopies give the tracer: blobs touching each other, holes, pixels of one
    label touching only at a corner, an island in a hole, pieces of one label apart, labels at the image's
    edges, and noise."""
    lab = np.zeros((40, 52), np.int32)
    for j in range(1, 9):
        r, c = rng.integers(0, 40), rng.integers(0, 52)
        lab[max(0, r - 5) : r + 4, max(0, c - 6) : c + 3] = j
    lab[rng.random(lab.shape) < 0.12] = 0
    yield lab
    ring = np.zeros((9, 9), np.int32)
    ring[1:8, 1:8] = 3
    ring[3:6, 3:6] = 0
    ring[4, 4] = 3  # an island of the same label in the hole
    ring[2, 2] = 0  # a hole pixel touching another at a corner
    ring[0, 0] = ring[8, 8] = 3  # pieces touching the shell only at a corner
    yield ring
    pinch = np.zeros((6, 6), np.int32)
    pinch[1:5, 1:5] = 7
    pinch[2, 2] = 0  # a hole that meets the outside at a corner
    pinch[1, 1] = 0
    yield pinch
    yield rng.integers(0, 4, (23, 31)).astype(np.int32)  # noise: every kind of corner
    yield np.full((3, 4), 5, np.int32)  # one label over the whole image


def test_traced_outlines_are_gdals_polygonize():
    """Every label's outline covers exactly the pixels that ``rasterio.features.shapes`` (GDAL, 4-connectivity)
    outlines for it, on a map transform, also read through a non-contiguous view; shells and holes nest."""
    import shapely
    from affine import Affine
    from rasterio.features import shapes

    from matchplant.spatial_stat_extractor.canopy.collect import valid_polygons
    from matchplant.spatial_stat_extractor.canopy.trace import outline_pieces

    rng = np.random.default_rng(5)
    t = Affine(0.25, 0, 500.0, 0, -0.25, 80.0)
    checked = invalid = 0
    for base in _label_images(rng):
        for lab in (base, base[:, ::-1], base.T):  # views: reversed columns, transposed
            owners, geoms, suspect = outline_pieces(lab, t)
            assert shapely.is_valid(geoms[~suspect]).all()  # only those through a diagonal corner may be invalid
            ref: dict = {}
            for g, v in shapes(np.ascontiguousarray(lab), mask=lab > 0, connectivity=4, transform=t):
                ref.setdefault(int(v), []).append(shapely.geometry.shape(g))
            assert owners.tolist() == sorted(ref)
            geoms = valid_polygons(geoms)
            for k, g in zip(owners, geoms):
                want = shapely.union_all(ref[int(k)])
                assert g.is_valid
                assert g.area == pytest.approx((lab == k).sum() * 0.0625, abs=1e-9)
                assert g.symmetric_difference(want).area < 1e-9
                # pieces: one per 4-connected component of the label
                n_pieces = ndi.label(lab == k)[1]
                assert shapely.get_num_geometries(g) == n_pieces
                checked += 1
            invalid += (~shapely.is_valid(outline_pieces(lab, t)[1])).sum()
    assert checked > 40 and invalid > 0  # the repair was exercised
    empty_owners, empty, suspect = outline_pieces(np.zeros((4, 4), np.int32), t)
    assert len(empty_owners) == 0 and len(empty) == 0 and len(suspect) == 0


def test_values_at_flat_pixels_and_their_window():
    rng = np.random.default_rng(6)
    width = 57
    pix = rng.choice(40 * width, 300, replace=False)
    rows, cols = np.divmod(pix, width)
    assert pixel_window(pix, width) == (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
    raster = rng.random((40, width)).astype(np.float32)
    r0, r1, c0, c1 = pixel_window(pix, width)
    got = values_at(raster[r0:r1, c0:c1], pix, width, r0, c0)
    assert got.dtype == float and np.array_equal(got, raster[rows, cols].astype(float))


def test_box_tops_are_the_per_plant_argmax():
    """Against the loop it replaced: per box, the first highest local maximum (a slice and an argmax), else in
    the window, else the box's highest pixel; boxes cut by the edge, empty, inverted, on holes only."""
    from matchplant.spatial_stat_extractor.canopy.maxima import box_tops

    rng = np.random.default_rng(7)
    a = np.round(rng.random((50, 70)), 1)  # ties
    a[rng.random(a.shape) < 0.1] = np.nan
    a[30:40, 0:10] = np.nan
    c0, r0 = rng.integers(-5, 65, 200), rng.integers(-5, 45, 200)
    boxes = np.stack([c0, r0, c0 + rng.integers(0, 8, 200), r0 + rng.integers(0, 8, 200)], axis=1)
    boxes[:3] = [[2, 31, 8, 38], [10, 10, 5, 20], [3, 3, 3, 9]]  # holes only, inverted, empty
    windows = boxes + [-4, -4, 4, 4]
    windows[:3] = boxes[:3]
    clip = np.array([a.shape[1], a.shape[0]] * 2)
    kinds = np.zeros(2, int)  # tops that are local maxima, and boxes' highest pixels, over both
    sparse = rng.random(a.shape) < 0.03  # the second set of tops: most boxes and windows hold none
    for peak in (local_maxima(a, 5, 0.3), local_maxima(a, 5, 0.3) & sparse):
        want = np.full((len(boxes), 4), np.nan)
        for k in range(len(boxes)):
            for w in (boxes[k], windows[k]):
                x0, y0, x1, y1 = np.clip(w, 0, clip)
                pk = peak[y0:y1, x0:x1]
                if pk.any():
                    win = a[y0:y1, x0:x1]
                    r, c = divmod(int(np.argmax(np.where(pk, win, -np.inf))), win.shape[1])
                    want[k] = (y0 + r, x0 + c, win[r, c], 1)
                    break
            else:
                x0, y0, x1, y1 = np.clip(boxes[k], 0, clip)
                win = np.fmax(a[y0:y1, x0:x1], -np.inf)
                if win.size and np.isfinite(win).any():
                    r, c = divmod(int(np.argmax(win)), win.shape[1])
                    want[k] = (y0 + r, x0 + c, win[r, c], 0)
        got = box_tops(a, peak, boxes, windows)
        assert np.array_equal(got, want, equal_nan=True)
        kinds += [(want[:, 3] == 1).sum(), (want[:, 3] == 0).sum()]
    assert (kinds > 30).all() and np.isnan(want[:3, 2]).all()


def test_every_kernel_takes_a_few_named_bundles():
    """Issue 37: a compiled kernel takes at most 6 arguments (bundles of arrays as NamedTuples, as module 8's
    Raster and Scene), so that a dozen positional arrays cannot be given in the wrong order."""
    kernels = {}
    for path in Path(m9.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef) and any("njit" in ast.unparse(d) for d in node.decorator_list):
                kernels[f"{path.stem}.{node.name}"] = len(node.args.args)
    assert len(kernels) >= 15, sorted(kernels)  # the reader still finds them
    wide = {k: n for k, n in kernels.items() if n > 6}
    assert not wide, f"kernels with more than 6 arguments: {wide}"
