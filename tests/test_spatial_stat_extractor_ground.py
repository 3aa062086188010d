"""Module 9's ground noise from the ground (issue 39, point 4): tall things no box covers (a building, trees,
the plants under and around them left unlisted) are taken out of the ground sample, so the measured noise is
the bare ground's own (known from the construction) and not the 3-4x a sample with them reads; the estimate is
reported and logged with what was left out; a field without them is measured exactly as before (nothing left
out, so the same code path and the same thresholds)."""

from __future__ import annotations

import contextlib
import logging

import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from log_records import log_records, messages
from noisy_chm import noisy_chm
from scipy import ndimage as ndi

from matchplant.simfield import generate_field
from matchplant.spatial_stat_extractor.canopy import measure_ground, thresholds
from matchplant.spatial_stat_extractor.canopy.ground import half_sample_mode, robust_sd  # the role's own statistics
from matchplant.spatial_stat_extractor.config import CanopyConfig, RasterSet
from matchplant.spatial_stat_extractor.inputs import ArraySource, open_layer
from matchplant.spatial_stat_extractor.traits import resolve_thresholds

CRS = "EPSG:32614"


def tall_things(shape, rng, cols, rows, res) -> np.ndarray:
    """Heights (m) of a flat-roofed building (3.2 m, walls smoothed over a few pixels) and five trees (domes
    3-9 m) inside the columns ``cols`` and rows ``rows`` (pixels); zero elsewhere."""
    ny, nx = shape
    rr, cc = np.mgrid[0:ny, 0:nx]
    (c0, c1), (r0, r1) = cols, rows
    split = r0 + (r1 - r0) // 3
    roof = (cc > c0) & (cc < c0 + (c1 - c0) * 2 // 3) & (rr > r0) & (rr < split)
    tall = ndi.gaussian_filter(np.where(roof, 3.2, 0.0), 0.02 / res)
    for _ in range(5):
        cx, cy = rng.uniform(c0, c1), rng.uniform(split + 0.3 / res, r1)
        r, h = rng.uniform(0.25, 0.55) / res, rng.uniform(3, 9)
        tall = np.maximum(tall, h * np.sqrt(np.clip(1 - (np.hypot(cc - cx, rr - cy) / r) ** 2, 0, None)))
    tall = ndi.gaussian_filter(tall, 0.015 / res)
    return np.where(tall > 0.005, tall, 0.0)


def with_tall_things(seed: int):
    """tests/noisy_chm.py's field, 8 m long, with a building and trees on 3-5 m along it; the boxes there are
    not listed (the plants left under and between them are plants the detector missed)."""
    f = noisy_chm(seed=seed, width_m=8.0)
    res = f.transform.a
    tall = tall_things(f.chm.shape, np.random.default_rng(seed + 100), (300, 480), (20, f.chm.shape[0] - 20), res)
    chm = np.where(tall > 0, np.nan_to_num(f.chm, nan=0.0) + tall, f.chm)
    b = shapely.bounds(f.boxes) - [f.transform.c, 0, f.transform.c, 0]
    listed = (b[:, 2] < 2.9) | (b[:, 0] > 5.0)
    return f, chm, f.boxes[listed]


@pytest.mark.parametrize("seed", [1, 2])
def test_unboxed_trees_and_buildings_are_left_out_of_the_ground_sample(seed):
    f, chm, boxes = with_tall_things(seed)
    src = ArraySource(chm, f.transform)
    noise = measure_ground(src, boxes, guard_m=0.1)
    # what the sample held before: every finite pixel 10 cm or more from every box (numpy, not module 9)
    near = np.zeros(chm.shape, bool)
    for g in boxes:
        x0, y0, x1, y1 = g.bounds
        c0, c1 = int((x0 - 0.1 - f.transform.c) / 0.01), int(np.ceil((x1 + 0.1 - f.transform.c) / 0.01))
        r0, r1 = int((f.transform.f - y1 - 0.1) / 0.01), int(np.ceil((f.transform.f - y0 + 0.1) / 0.01))
        near[max(r0, 0) : r1, max(c0, 0) : c1] = True
    all_between = chm[~near & np.isfinite(chm)]
    naive = robust_sd(all_between, float(np.median(all_between)))
    assert naive > 3 * f.ground_sd and np.percentile(all_between, 95) > 2.0  # the 0.099 m for 0.029 m
    # measured from the ground: within 1.5x of the bare ground's own SD (in fact within 10 %)
    assert f.ground_sd / 1.5 < noise.sd < 1.5 * f.ground_sd
    assert noise.sd == pytest.approx(f.ground_sd, rel=0.1)
    assert noise.p50 == pytest.approx(f.ground_p50, abs=0.004)
    th = thresholds("auto", "auto", noise)
    assert th.min_top == pytest.approx(f.ground_p50 + 4 * f.ground_sd, abs=0.015)  # not 0.45 m
    # what was left out: the tall things (metres high; the windows around the plants hold less of them than the
    # whole field), nothing of them left in the sample, reported
    assert 0.05 < noise.excluded < np.mean(all_between > 1.0) + 0.05 and noise.p99 < 0.15
    assert np.median(noise.excluded_heights) > 1.0 and noise.excluded_heights.max() > 3.0
    r = noise.report()
    assert r["excluded_tall"] == pytest.approx(noise.excluded, abs=1e-4) and r["excluded_median"] > 1.0
    assert 3 * f.ground_sd < r["excluded_above"] < 0.2


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    """The tiny synthetic field with noise: realistic: its CHM, its plants' boxes on the map, the bare ground."""
    field = generate_field(preset="tiny", seed=0, out=tmp_path_factory.mktemp("realistic"), noise="realistic")
    with rasterio.open(field.dsm) as a, rasterio.open(field.dtm) as b, rasterio.open(field.plant_ids) as ids:
        chm = a.read(1, masked=True).astype(float).filled(np.nan) - b.read(1, masked=True).astype(float).filled(np.nan)
        transform, label, profile = a.transform, ids.read(1), a.profile
    mb = pd.read_csv(field.map_boxes)
    boxes = shapely.box(mb.xmin, mb.ymin, mb.xmax, mb.ymax)
    bare = ~ndi.binary_dilation(label != 0, iterations=int(np.ceil(0.05 / transform.a))) & np.isfinite(chm)
    return chm, transform, boxes, bare, profile


def test_a_field_without_tall_things_is_measured_as_before(realistic):
    """Nothing is left out of the realistic field's sample, whatever the guard: the estimate is the one the
    sample always gave (the same pixels, the same robust spread), within 10 % of the bare ground's SD."""
    chm, transform, boxes, bare, _ = realistic
    for guard in (0.05, 0.1, 5.0):
        noise = measure_ground(ArraySource(chm, transform), boxes, guard_m=guard)
        assert noise.excluded == 0 and noise.report()["excluded_tall"] == 0
        assert noise.sd == pytest.approx(np.std(chm[bare]), rel=0.1)


def test_the_realistic_field_with_a_building_and_trees(realistic, tmp_path):
    """The realistic field with a building and trees over a third of its length (their plants unlisted), its
    CHM written as a file and read as module 9 reads it: the logged and reported ground noise is within 1.5x of
    the bare ground's own SD (a tenth of what the sample with them reads), with what was left out."""
    chm, transform, boxes, bare, profile = realistic
    res = transform.a
    ny, nx = chm.shape
    b = (shapely.bounds(boxes) - [transform.c, 0, transform.c, 0]) / res
    c0, c1 = int(np.percentile(b[:, 0], 40)), int(np.percentile(b[:, 2], 70))
    tall = tall_things(chm.shape, np.random.default_rng(7), (c0, c1), (int(0.05 * ny), int(0.95 * ny)), res)
    listed = (b[:, 2] < c0 - 0.1 / res) | (b[:, 0] > c1 + 0.1 / res)
    profile.update(dtype="float32", nodata=-9999.0)
    with rasterio.open(tmp_path / "chm.tif", "w", **profile) as out:
        out.write(np.where(np.isfinite(chm), chm + tall, -9999.0).astype("float32"), 1)
    cfg = CanopyConfig()
    rs = RasterSet(chm=tmp_path / "chm.tif")
    entry = {}
    with log_records("matchplant.spatial_stat_extractor", logging.INFO) as records, contextlib.ExitStack() as stack:
        src = open_layer(next(la for la in rs.layers() if la.elevation), stack)
        resolve_thresholds(src, boxes[listed], cfg, rs, True, entry)
    own = float(np.std(chm[bare]))
    got = entry["ground_noise"]
    assert own / 1.5 < got["sd"] < 1.5 * own, (got, own)
    assert got["excluded_tall"] > 0.02 and got["excluded_max"] > 3.0
    line = next(m for m in messages(records) if "CHM ground noise" in m)
    assert f"SD {got['sd']:.3f} m" in line and "left out as tall things no box covers" in line
    assert entry["min_top"] < 0.2  # p50 + 4 SD of the bare ground, not the 0.45 m of a sample with the trees


def test_the_half_sample_mode_finds_the_ground_under_a_larger_population_above():
    """60 % of the sample canopy and roofs (0.5-8 m), 40 % ground N(1.5 cm, 3 cm): the densest mode is the
    ground's, where the median (2 m) is not."""
    rng = np.random.default_rng(4)
    v = np.concatenate([rng.normal(0.015, 0.03, 40_000), rng.uniform(0.5, 8.0, 60_000)])
    assert np.median(v) > 1.0
    assert half_sample_mode(v) == pytest.approx(0.015, abs=0.01)
