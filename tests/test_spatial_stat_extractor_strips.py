"""Module 9 in bounded memory (issue 30): outlines and canopy statistics strip by strip (canopy/strips.py), in one
process or a pool, equal plant by plant to one pass over the field (segment + canopy_stats); the strip height
from max_memory; the peak memory in the report; a memory shortage as a clear error."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from affine import Affine

from matchplant.core.runtime.errors import ConfigError, DependencyError
from matchplant.spatial_stat_extractor.canopy import (
    SegmentSettings,
    canopy_stats,
    memory_stage,
    parse_memory,
    segment,
    strips,
)
from matchplant.spatial_stat_extractor.config import (
    Layer,
    RasterSet,
    SpatialStatExtractorConfig,
)
from matchplant.spatial_stat_extractor.inputs import open_layer
from matchplant.spatial_stat_extractor.run import run

RES = 0.01
T = Affine(RES, 0, 1000.0, 0, -RES, 2000.0)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """A 420 x 300 px CHM of domes on a 20 px grid (some touching), a second band (NDVI-like) on the same grid,
    boxes with 1 in 6 plants given a second box shifted by half a box (duplicates, some across strip edges)."""
    root = tmp_path_factory.mktemp("strips")
    rng = np.random.default_rng(3)
    H, W = 420, 300
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    chm = rng.normal(0, 0.003, (H, W))
    cy, cx = np.mgrid[10:H:20, 10:W:20].reshape(2, -1).astype(float)
    cy += rng.uniform(-2, 2, cy.size)
    cx += rng.uniform(-2, 2, cx.size)
    h = rng.uniform(0.03, 0.6, cy.size)  # some below min_top: flagged 'low'
    r = rng.uniform(5, 11, cy.size)
    for k in range(cy.size):
        chm = np.maximum(chm, h[k] * (1 - ((yy - cy[k]) ** 2 + (xx - cx[k]) ** 2) / r[k] ** 2))
    other = np.sin(xx / 7) * np.cos(yy / 5)
    prof = {
        "driver": "GTiff",
        "width": W,
        "height": H,
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:32615",
        "transform": T,
    }
    for name, a in (("chm.tif", chm), ("other.tif", other)):
        with rasterio.open(root / name, "w", **prof) as ds:
            ds.write(a.astype(np.float32), 1)
    x0, y0 = T @ (cx - r, cy - r)
    x1, y1 = T @ (cx + r, cy + r)
    boxes = list(shapely.box(x0, y1, x1, y0))
    dup = np.arange(0, cy.size, 6)
    boxes += list(shapely.box(x0[dup], y1[dup] - r[dup] * RES, x1[dup], y0[dup] - r[dup] * RES))
    geoms = np.array(boxes, dtype=object)
    pd.DataFrame(
        {"plant_id": np.arange(1, len(geoms) + 1), "geometry": shapely.to_wkt(geoms), "crs": "EPSG:32615"}
    ).to_csv(root / "plants.csv", index=False)
    return root, geoms


def measures(root):
    chm = Layer("chm", "band", (root / "chm.tif",), elevation=True)
    other = Layer("other", "band", (root / "other.tif",))
    return chm, [
        strips.Measure("chm_canopy", chm, ("max", "mean"), (50.0, 95.0)),
        strips.Measure("other_canopy", other, ("count", "mean", "std", "median"), (10.0,)),
    ]


def one_pass(root, geoms, rows: int):
    """The reference: segment over the whole field in one call, then canopy_stats (pixels held in memory)."""
    chm_l, ms = measures(root)
    with contextlib.ExitStack() as stack:
        o = segment(geoms, open_layer(chm_l, stack), SegmentSettings(), strip_rows=rows)
        cols = {}
        for m in ms:
            src = open_layer(m.layer, stack)
            cols.update(
                {f"{m.prefix}_{k}": v for k, v in canopy_stats(o, src, list(m.stats), list(m.percentiles)).items()}
            )
    return o, cols


@pytest.fixture
def thin_strips(monkeypatch):
    """Strips of 64 rows (a field needing seven of them), whatever the budget."""
    real = strips.plan_strips

    def plan(geoms, transform, width, height, margin, *, budget, workers):
        real(geoms, transform, width, height, margin, budget=budget, workers=workers)
        return 64, -(-height // 64)

    monkeypatch.setattr(strips, "plan_strips", plan)


def assert_same(o, cols, ref, ref_cols):
    assert list(o.flag) == list(ref.flag)
    assert (o.flag == "duplicate").sum() >= 5 and (o.flag == "").sum() > 100
    assert shapely.equals(o.geometry, ref.geometry).all()
    for a, b in (
        (o.pixels, ref.pixels),
        (o.area, ref.area),
        (o.volume, ref.volume),
        (o.top, ref.top),
        (o.tight_box, ref.tight_box),
    ):
        np.testing.assert_allclose(a, b, rtol=1e-12, equal_nan=True)
    assert sorted(cols) == sorted(ref_cols)
    for k in ref_cols:
        np.testing.assert_allclose(cols[k], ref_cols[k], rtol=1e-9, atol=1e-12, equal_nan=True, err_msg=k)
    assert len(o.pix) == 0  # no canopy pixels kept


def test_strip_by_strip_equals_one_pass(field, thin_strips):
    root, geoms = field
    chm_l, ms = measures(root)
    o, cols = strips.outline_field(
        geoms, chm_l, None, ms, SegmentSettings(), nodata=None, seeds=None, max_memory=parse_memory("1GB"), workers=1
    )
    ref, ref_cols = one_pass(root, geoms, 64)
    # duplicates whose first box is homed in another strip are among them (the merge's own case)
    centre = (shapely.bounds(geoms)[:, 1] + shapely.bounds(geoms)[:, 3]) / 2
    assert len(np.unique(np.floor((T.f - centre) / RES / 64))) == 7
    assert_same(o, cols, ref, ref_cols)
    np.testing.assert_allclose(np.sort(o.unclaimed, axis=0), np.sort(ref.unclaimed, axis=0))


def test_each_strip_handles_only_its_plants_with_the_same_results(field, thin_strips):
    """A band outlines only the plants near it (band_plants): plants off the raster, an empty box and a later
    date's seeds (each plant's top searched near an earlier top) give the numbers of one pass all the same."""
    root, geoms = field
    chm_l, ms = measures(root)
    far = shapely.box(T.c - 5, T.f + 1, T.c - 4, T.f + 2)  # off the raster, left of and above it
    below = shapely.box(T.c + 1, T.f - 10, T.c + 1.1, T.f - 9.9)
    geoms = np.concatenate([geoms, np.array([far, shapely.Polygon(), below], dtype=object)])
    b = shapely.bounds(geoms)
    seeds = np.column_stack([b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]]) / 2 + 0.01  # a centimetre off each box centre
    s = SegmentSettings(max_shift=0.04)
    o, cols = strips.outline_field(
        geoms, chm_l, None, ms, s, nodata=None, seeds=seeds, max_memory=parse_memory("1GB"), workers=1
    )
    with contextlib.ExitStack() as stack:
        ref = segment(geoms, open_layer(chm_l, stack), s, seeds=seeds, strip_rows=64)
    assert list(o.flag[-3:]) == ["outside"] * 3 and list(o.flag) == list(ref.flag)
    assert shapely.equals(o.geometry[:-3], ref.geometry[:-3]).all()
    np.testing.assert_allclose(o.top, ref.top, equal_nan=True)
    np.testing.assert_allclose(o.volume, ref.volume, equal_nan=True)


@pytest.mark.slow
def test_a_process_pool_gives_the_same_results(field, thin_strips):
    """Two worker processes (spawned; each opens the rasters itself) give the numbers of one process."""
    root, geoms = field
    chm_l, ms = measures(root)
    monkey_rows = 64
    o, cols = strips.outline_field(
        geoms, chm_l, None, ms, SegmentSettings(), nodata=None, seeds=None, max_memory=parse_memory("1GB"), workers=2
    )
    ref, ref_cols = one_pass(root, geoms, monkey_rows)
    assert_same(o, cols, ref, ref_cols)


def test_strip_height_follows_max_memory(field):
    _, geoms = field
    rows = {}
    for width in (3000, 30000, 60000):
        r, n = strips.plan_strips(geoms, T, width, 30000, 0.05, budget=parse_memory("3GB"), workers=1)
        rows[width] = r
        # the strip's window (its rows and a box height above and below) within the budget's share
        assert strips.BYTES_PER_PIXEL * width * r <= strips.STRIP_SHARE * parse_memory("3GB") and n == -(-30000 // r)
    assert rows[3000] == strips.MAX_STRIP_ROWS and rows[30000] > rows[60000] >= strips.MIN_STRIP_ROWS
    r1, _ = strips.plan_strips(geoms, T, 30000, 30000, 0.05, budget=parse_memory("3GB"), workers=1)
    r2, _ = strips.plan_strips(geoms, T, 30000, 30000, 0.05, budget=parse_memory("3GB"), workers=2)
    assert r2 < r1  # two workers share the budget


def test_max_memory_is_checked():
    assert parse_memory("3GB") == 3 * 1024**3 and parse_memory("512mb") == 512 * 1024**2
    assert parse_memory("1.5g") == int(1.5 * 1024**3)
    for bad in ("lots", "3 parsecs", "100MB"):
        with pytest.raises(ConfigError, match="max_memory"):
            parse_memory(bad)


def test_a_memory_shortage_names_the_stage_and_the_setting():
    with pytest.raises(DependencyError) as err, memory_stage("the plant outlines", parse_memory("2GB")):
        np.empty(1)  # the stage runs
        raise MemoryError("Unable to allocate 12.7 GiB for an array")
    text = str(err.value)
    assert "out of memory in the plant outlines" in text and "max_memory: 2.00 GB" in text
    assert "max_memory: 1024MB" in text


def test_run_reports_peak_memory_and_strips(field, tmp_path, thin_strips, caplog):
    root, _ = field
    cfg = SpatialStatExtractorConfig(
        polygons=root / "plants.csv",
        rasters=RasterSet(chm=root / "chm.tif"),
        output_dir=tmp_path / "out",
        max_memory="1GB",
        workers=1,
        vector_formats=[],
    )
    caplog.set_level("INFO")
    run(cfg)
    report = json.loads((tmp_path / "out" / "stats_report.json").read_text())
    mem = report["memory"]
    assert mem["max_memory_mb"] == 1024 and mem["peak_mb"] > 50
    assert {"box statistics", "outlines and canopy statistics"} <= set(mem["stages"])
    assert all(s["wall_s"] >= 0 and s["cpu_s"] >= 0 for s in mem["stages"].values())
    assert "7 strip(s) of 64 rows" in caplog.text and "1 worker process(es)" in caplog.text
    assert "peak memory" in caplog.text
    table = pd.read_csv(tmp_path / "out" / "stats.csv")
    assert table["chm_canopy_max"].notna().sum() > 100
