"""Module 9: zonal statistics (exact vs brute force, rasterstats, exactextract), inputs, outputs, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import shapely
from affine import Affine

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.spatial_stat_extractor.inputs import ArraySource
from matchplant.spatial_stat_extractor.zonal import zonal_stats

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "9_spatial_stat_extractor"
STATS = ["count", "min", "max", "mean", "median", "std", "sum", "nodata"]
CRS = "EPSG:32615"


# --------------------------------------------------------------------------------------------------
# synthetic rasters and polygons


def make_raster(seed=1, h=120, w=160, nodata=-9999.0):
    rng = np.random.default_rng(seed)
    data = rng.gamma(2.0, 1.5, (h, w)).astype("float32")
    holes = rng.random((h, w)) < 0.04
    data[holes] = nodata
    data[rng.random((h, w)) < 0.01] = np.nan
    transform = Affine(0.5, 0, 600000.0, 0, -0.5, 4500000.0)
    return data, transform


def make_polygons(transform, h, w, n=45, seed=2):
    """Boxes, discs, polygons with holes and multipolygons; a few off or partly off the raster."""
    rng = np.random.default_rng(seed)
    x0, y1 = transform.c, transform.f
    W, H = w * transform.a, h * -transform.e
    geoms = []
    for i in range(n):
        cx, cy = x0 + rng.uniform(-3, W + 3), y1 - rng.uniform(-3, H + 3)
        kind = i % 4
        if kind == 0:
            g = shapely.box(cx, cy, cx + rng.uniform(0.2, 6), cy + rng.uniform(0.2, 6))
        elif kind == 1:
            g = shapely.Point(cx, cy).buffer(rng.uniform(0.4, 5), quad_segs=5)
        elif kind == 2:
            g = (
                shapely.Point(cx, cy)
                .buffer(rng.uniform(2.5, 6))
                .difference(shapely.Point(cx + 0.4, cy - 0.3).buffer(1.3))
            )
        else:
            g = shapely.MultiPolygon(
                [shapely.box(cx, cy, cx + 1.7, cy + 2.2), shapely.box(cx + 3.1, cy + 0.3, cx + 4.4, cy + 1.9)]
            )
        geoms.append(g)
    geoms.append(shapely.box(x0 - 50, y1 + 10, x0 - 40, y1 + 20))  # far outside
    return geoms


def pixel_grid(transform, h, w):
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    return cols, rows


def to_map(t, cols, rows):
    return t.a * cols + t.b * rows + t.c, t.d * cols + t.e * rows + t.f


def brute_force(data, transform, geoms, mode, percentiles):
    """Per polygon, in plain loops: pixel centres inside (shapely) or exact pixel/polygon areas."""
    values = np.where(data == -9999, np.nan, data.astype(float))
    h, w = data.shape
    cols, rows = pixel_grid(transform, h, w)
    xc, yc = to_map(transform, cols + 0.5, rows + 0.5)
    out = {k: [] for k in STATS + [f"p{q:g}" for q in percentiles]}
    area = transform.a * -transform.e
    for g in geoms:
        if mode == "center":
            wts = shapely.contains_xy(g, xc, yc).astype(float)
        else:
            x0, y0 = to_map(transform, cols, rows)
            x1, y1 = to_map(transform, cols + 1, rows + 1)
            cells = shapely.box(x0, y1, x1, y0)
            touch = shapely.intersects(g, cells)
            wts = np.zeros(data.shape)
            wts[touch] = shapely.area(shapely.intersection(g, cells[touch])) / area
        sel = wts > 1e-6
        v, wt = values[sel], wts[sel]
        ok = np.isfinite(v)
        out["nodata"].append(wt[~ok].sum())
        v, wt = v[ok], wt[ok]
        out["count"].append(wt.sum())
        if v.size == 0:
            for k in out:
                if k not in ("count", "nodata"):
                    out[k].append(np.nan)
            continue
        mean = np.sum(wt * v) / wt.sum()
        out["sum"].append(np.sum(wt * v))
        out["mean"].append(mean)
        out["std"].append(np.sqrt(np.sum(wt * (v - mean) ** 2) / wt.sum()))
        out["min"].append(v.min())
        out["max"].append(v.max())
        qs = [q / 100 for q in percentiles] + [0.5]
        if mode == "center":
            res = np.quantile(v, qs)
        else:
            res = [weighted_quantile(v, wt, q) for q in qs]
        for q, r in zip(percentiles, res):
            out[f"p{q:g}"].append(r)
        out["median"].append(res[-1])
    return {k: np.array(v, float) for k, v in out.items()}


def weighted_quantile(v, w, q):
    """exactextract's weighted quantile, element by element (Wikipedia's weighted percentile method) over
    the distinct values, each with its summed weight (exactextract keeps a histogram of values)."""
    v, inverse = np.unique(v, return_inverse=True)
    w = np.bincount(inverse.ravel(), weights=w)
    n = len(v)
    s = [0.0]
    for k in range(1, n):
        s.append(k * w[k] + (n - 1) * w[:k].sum())
    target = q * (n - 1) * w.sum()
    for k in range(n):
        if s[k] > target:
            return v[k - 1] + (target - s[k - 1]) * (v[k] - v[k - 1]) / (s[k] - s[k - 1])
    return v[-1]


def assert_stats_equal(got, ref, rtol=1e-9, atol=1e-9, keys=None):
    for k in keys or ref:
        np.testing.assert_allclose(got[k], ref[k], rtol=rtol, atol=atol, equal_nan=True, err_msg=k)


@pytest.fixture(scope="module")
def synthetic():
    data, transform = make_raster()
    geoms = make_polygons(transform, *data.shape)
    return data, transform, geoms


@pytest.fixture(scope="module")
def raster_file(tmp_path_factory, synthetic):
    import rasterio

    data, transform, _ = synthetic
    path = tmp_path_factory.mktemp("r") / "raster.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[1],
        height=data.shape[0],
        count=1,
        dtype="float32",
        crs=CRS,
        transform=transform,
        nodata=-9999.0,
    ) as dst:
        dst.write(data, 1)
    return path


# --------------------------------------------------------------------------------------------------
# the engine


@pytest.mark.slow
@pytest.mark.independent
@pytest.mark.parametrize("mode", ["center", "coverage"])
def test_equals_brute_force(synthetic, mode):
    data, transform, geoms = synthetic
    res = zonal_stats(
        geoms, ArraySource(data, transform, nodata=-9999), STATS, [10, 90], mode=mode, max_cells=3000, max_window=6000
    )  # small batches: exercise batching and windows
    ref = brute_force(data, transform, geoms, mode, [10, 90])
    assert_stats_equal(res.stats, ref)
    assert res.outside[-1] and res.outside.sum() >= 1
    assert res.partial.sum() >= 3
    assert res.stats["nodata"].sum() > 0


@pytest.mark.independent
def test_equals_rasterstats(synthetic, raster_file):
    rasterstats = pytest.importorskip("rasterstats")
    data, transform, geoms = synthetic
    res = zonal_stats(
        geoms,
        ArraySource(data, transform, nodata=-9999),
        ["count", "min", "max", "mean", "median", "std", "sum"],
        [25, 95],
    )
    ref = rasterstats.zonal_stats(
        geoms, str(raster_file), stats="count min max mean median std sum percentile_25 percentile_95"
    )
    names = {
        "count": "count",
        "min": "min",
        "max": "max",
        "mean": "mean",
        "median": "median",
        "std": "std",
        "sum": "sum",
        "p25": "percentile_25",
        "p95": "percentile_95",
    }
    for ours, theirs in names.items():
        b = np.array([np.nan if r[theirs] is None else r[theirs] for r in ref], float)
        if ours == "count":
            b = np.nan_to_num(b)
        # rasterstats sums float32 pixels in float32; we sum in float64
        np.testing.assert_allclose(res.stats[ours], b, rtol=2e-6, atol=1e-9, equal_nan=True, err_msg=ours)


@pytest.mark.independent
def test_equals_exactextract(synthetic, raster_file):
    exactextract = pytest.importorskip("exactextract")
    import geopandas as gpd

    data, transform, geoms = synthetic
    res = zonal_stats(
        geoms,
        ArraySource(data, transform, nodata=-9999),
        ["count", "min", "max", "mean", "median", "std", "sum"],
        [25, 95],
        mode="coverage",
    )
    gdf = gpd.GeoDataFrame({"i": range(len(geoms))}, geometry=geoms, crs=CRS)
    ee = exactextract.exact_extract(
        str(raster_file),
        gdf,
        ["count", "min", "max", "mean", "median", "stdev", "sum", "quantile(q=0.25)", "quantile(q=0.95)"],
        output="pandas",
        include_cols=["i"],
    )
    names = {
        "count": "count",
        "min": "min",
        "max": "max",
        "mean": "mean",
        "median": "median",
        "std": "stdev",
        "sum": "sum",
        "p25": "quantile_25",
        "p95": "quantile_95",
    }
    empty = ee["count"].to_numpy() == 0
    for ours, theirs in names.items():
        b = ee[theirs].to_numpy(float).copy()
        if ours != "count":
            b[empty] = np.nan  # exactextract: sum 0 for no pixels; we say "no value"
        # exactextract keeps coverage fractions in float32
        np.testing.assert_allclose(res.stats[ours], b, rtol=1e-5, atol=1e-5, equal_nan=True, err_msg=ours)


@pytest.mark.independent
def test_coverage_equals_exactextract_on_integer_raster_with_ties(tmp_path):
    """Many equal pixel values (a class or count raster): quantiles as exactextract's value histogram."""
    exactextract = pytest.importorskip("exactextract")
    import geopandas as gpd
    import rasterio

    data, transform = make_raster()
    data = np.where(data == -9999, -9999, np.round(data * 3)).astype("float32")
    geoms = make_polygons(transform, *data.shape)
    path = tmp_path / "ints.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[1],
        height=data.shape[0],
        count=1,
        dtype="float32",
        crs=CRS,
        transform=transform,
        nodata=-9999.0,
    ) as dst:
        dst.write(data, 1)
    res = zonal_stats(
        geoms, ArraySource(data, transform, nodata=-9999), ["count", "mean", "median"], [10, 90], mode="coverage"
    )
    gdf = gpd.GeoDataFrame({"i": range(len(geoms))}, geometry=geoms, crs=CRS)
    ee = exactextract.exact_extract(
        str(path),
        gdf,
        ["count", "mean", "median", "quantile(q=0.10)", "quantile(q=0.90)"],
        output="pandas",
        include_cols=["i"],
    )
    empty = ee["count"].to_numpy() == 0
    for ours, theirs in {
        "count": "count",
        "mean": "mean",
        "median": "median",
        "p10": "quantile_10",
        "p90": "quantile_90",
    }.items():
        b = ee[theirs].to_numpy(float).copy()
        if ours != "count":
            b[empty] = np.nan
        # exactextract returns quantiles in the raster's type (float32): 1e-6 covers that rounding
        np.testing.assert_allclose(res.stats[ours], b, rtol=1e-6, atol=1e-6, equal_nan=True, err_msg=ours)
    assert len(np.unique(data)) < data.size // 100  # the case this test is about: ties everywhere


def test_overlapping_polygons_are_independent():
    data = np.arange(100, dtype=float).reshape(10, 10)
    t = Affine(1, 0, 0, 0, -1, 10)
    a = shapely.box(0, 0, 6, 6)
    b = shapely.box(3, 3, 10, 10)
    res = zonal_stats([a, b, a], ArraySource(data, t), ["count", "sum"])
    rows, cols = np.mgrid[0:10, 0:10]
    in_a = (cols < 6) & (rows >= 4)
    in_b = (cols >= 3) & (rows < 7)
    assert res.stats["count"].tolist() == [in_a.sum(), in_b.sum(), in_a.sum()]
    assert res.stats["sum"].tolist() == [data[in_a].sum(), data[in_b].sum(), data[in_a].sum()]


def test_tiny_polygon_coverage_and_nan_handling():
    """A plant smaller than a pixel: the centre rule may see nothing, coverage weighting still measures it."""
    data = np.full((4, 4), 2.0)
    data[0, 0] = np.nan
    t = Affine(1, 0, 0, 0, -1, 4)
    tiny = shapely.box(1.1, 1.1, 1.4, 1.3)  # 0.06 of one pixel, centre (1.5, 1.5) not inside
    on_nan = shapely.box(0.2, 3.2, 0.8, 3.8)  # only over the NaN pixel
    res_c = zonal_stats([tiny, on_nan], ArraySource(data, t), ["count", "mean", "nodata"])
    res_w = zonal_stats([tiny, on_nan], ArraySource(data, t), ["count", "mean", "nodata"], mode="coverage")
    assert res_c.stats["count"][0] == 0 and np.isnan(res_c.stats["mean"][0]) and res_c.no_valid[0]
    assert res_w.stats["count"][0] == pytest.approx(0.06) and res_w.stats["mean"][0] == 2.0
    assert res_w.no_valid[1] and res_w.stats["nodata"][1] == pytest.approx(0.36)


# --------------------------------------------------------------------------------------------------
# files in and out


def write_raster(path, data, transform, crs=CRS, nodata=-9999.0):
    import rasterio

    data = np.asarray(data, dtype="float32")
    if data.ndim == 2:
        data = data[None]
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[2],
        height=data.shape[1],
        count=data.shape[0],
        dtype="float32",
        crs=crs,
        transform=transform,
        nodata=nodata,
    ) as dst:
        dst.write(data)
    return path


@pytest.fixture()
def field(tmp_path):
    """Plants with known heights on a DSM/DTM pair and a 2-band multispectral raster; two dates."""
    import geopandas as gpd

    t = Affine(0.01, 0, 500000.0, 0, -0.01, 4000000.0)
    h, w = 300, 400
    ground = 300.0 + 0.002 * np.arange(w)[None, :] + np.zeros((h, 1))
    ids = np.arange(1, 7)
    cx = 500000.0 + 0.5 + 0.55 * (ids - 1)
    cy = np.full(6, 4000000.0 - 1.5)
    heights = np.array([0.21, 0.33, 0.47, 0.18, 0.55, 0.40])
    boxes = shapely.box(cx - 0.2, cy - 0.2, cx + 0.2, cy + 0.2)
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    xc, yc = to_map(t, cols + 0.5, rows + 0.5)
    chm = np.zeros((h, w))
    for x, y, hh in zip(cx, cy, heights):
        r2 = ((xc - x) ** 2 + (yc - y) ** 2) / 0.15**2
        chm = np.maximum(chm, np.where(r2 < 1, hh * (1 - r2), 0))
    red = np.where(chm > 0, 0.05, 0.20)
    nir = np.where(chm > 0, 0.45, 0.27)
    dsm = ground + chm
    dsm[5:8, 5:8] = -9999  # an ODM hole, away from the plants
    write_raster(tmp_path / "dsm.tif", dsm, t)
    write_raster(tmp_path / "dtm.tif", ground, t)
    write_raster(tmp_path / "ms.tif", np.stack([red, nir]), t)
    write_raster(tmp_path / "chm_w4.tif", chm * 1.5, t)
    gdf = gpd.GeoDataFrame({"plant_id": ids, "note": ["a"] * 6}, geometry=boxes, crs=CRS)
    gdf.to_file(tmp_path / "plants.gpkg", layer="plants", driver="GPKG")
    return {"dir": tmp_path, "t": t, "heights": heights, "ids": ids, "boxes": boxes, "gdf": gdf}


def test_chm_ndvi_outputs_and_crs(field):
    import geopandas as gpd
    import pyogrio

    from matchplant.spatial_stat_extractor.config import RasterSet
    from matchplant.spatial_stat_extractor.inputs import read_polygons
    from matchplant.spatial_stat_extractor.run import write_outputs
    from matchplant.spatial_stat_extractor.zonal import extract_stats

    d = field["dir"]
    polys = read_polygons(d / "plants.gpkg")
    table, report = extract_stats(
        polys, [RasterSet(dsm=d / "dsm.tif", dtm=d / "dtm.tif", multispectral=d / "ms.tif")], ["max", "mean"], [50]
    )
    # CHM = DSM - DTM: each plant's maximum is its true height within float32 precision at 300 m
    np.testing.assert_allclose(table["chm_max"], field["heights"], atol=2e-3)
    assert np.all(table["ndvi_max"].round(6) == 0.8)
    assert np.all((table["ndvi_mean"] > 0.149) & (table["ndvi_mean"] < 0.8))
    written = write_outputs(polys, table, report, d / "out")
    for key in ("polygons_gpkg", "polygons_shp", "stats_csv", "stats_gpkg", "report"):
        assert written[key].is_file()
    shp = gpd.read_file(written["polygons_shp"])
    assert shp.crs.to_epsg() == 32615 and shp["plant_id"].tolist() == field["ids"].tolist()
    back = gpd.read_file(written["stats_gpkg"], layer="stats")
    assert back.crs.to_epsg() == 32615 and np.allclose(back["chm_max"], table["chm_max"])
    assert pyogrio.list_layers(written["polygons_gpkg"])[0][0] == "plants"
    csv = pd.read_csv(written["stats_csv"])
    assert csv["plant_id"].tolist() == field["ids"].tolist()
    np.testing.assert_allclose(csv["x"], shapely.get_x(shapely.centroid(field["boxes"])), atol=1e-6)

    # a DTM on a coarser grid is resampled onto the DSM's (bilinear: exact on this planar ground)
    import rasterio

    with rasterio.open(d / "dtm.tif") as src:
        coarse = src.read(1)[::2, ::2] + 0.001  # the ground at the centres of 2 x 2 blocks
    write_raster(d / "dtm_coarse.tif", coarse, field["t"] @ Affine.scale(2))
    t3, _ = extract_stats(polys, [RasterSet(dsm=d / "dsm.tif", dtm=d / "dtm_coarse.tif")], ["max"], [])
    np.testing.assert_allclose(t3["chm_max"], table["chm_max"], atol=1e-4)

    # the same polygons in another CRS are reprojected to the raster's, and the numbers stay the same
    polys_ll = polys.to_crs("EPSG:4326")
    t2, rep2 = extract_stats(polys_ll, [RasterSet(chm=d / "chm_w4.tif")], ["max"], [])
    assert rep2["layers"][0]["reprojected_from"] == "EPSG:4326"
    np.testing.assert_allclose(t2["chm_max"], 1.5 * field["heights"], atol=2e-3)


def test_dates_wide_and_long(field):
    from matchplant.spatial_stat_extractor.config import RasterSet
    from matchplant.spatial_stat_extractor.inputs import read_polygons
    from matchplant.spatial_stat_extractor.zonal import extract_stats

    d = field["dir"]
    polys = read_polygons(d / "plants.gpkg")
    sets = [RasterSet(date="w3", dsm=d / "dsm.tif", dtm=d / "dtm.tif"), RasterSet(date="w4", chm=d / "chm_w4.tif")]
    wide, _ = extract_stats(polys, sets, ["max"], [], layout="wide")
    assert list(wide.columns) == ["plant_id", "x", "y", "chm_max_w3", "chm_max_w4"]
    np.testing.assert_allclose(wide["chm_max_w4"], 1.5 * wide["chm_max_w3"], atol=3e-3)
    long, _ = extract_stats(polys, sets, ["max"], [], layout="long")
    assert list(long.columns) == ["plant_id", "date", "x", "y", "chm_max"] and len(long) == 12
    assert long.groupby("date")["chm_max"].sum().round(3).tolist() == [
        round(float(wide["chm_max_w3"].sum()), 3),
        round(float(wide["chm_max_w4"].sum()), 3),
    ]


def test_csv_inputs(field, tmp_path):
    from matchplant.spatial_stat_extractor.inputs import read_polygons

    b = shapely.bounds(field["boxes"])
    pd.DataFrame({"id": field["ids"], "xmin": b[:, 0], "ymin": b[:, 1], "xmax": b[:, 2], "ymax": b[:, 3]}).to_csv(
        tmp_path / "boxes.csv", index=False
    )
    pd.DataFrame({"plant": field["ids"] * 10, "geometry": shapely.to_wkt(field["boxes"])}).to_csv(
        tmp_path / "wkt.csv", index=False
    )
    a = read_polygons(tmp_path / "boxes.csv", crs=CRS)
    assert a.crs.to_epsg() == 32615 and a["plant_id"].tolist() == field["ids"].tolist()
    assert shapely.equals(a.geometry.values, field["boxes"]).all()
    w = read_polygons(tmp_path / "wkt.csv")
    assert w.crs is None and w["plant_id"].tolist() == (field["ids"] * 10).tolist()
    # a module-8 CSV carries its CRS in a 'crs' column (not kept as an attribute); a summary beside it is not read
    (tmp_path / "projection_summary.json").write_text(json.dumps({"crs": "EPSG:32615"}))
    assert read_polygons(tmp_path / "boxes.csv").crs is None
    pd.read_csv(tmp_path / "boxes.csv").assign(crs="EPSG:32615").to_csv(tmp_path / "plants.csv", index=False)
    m8 = read_polygons(tmp_path / "plants.csv")
    assert m8.crs.to_epsg() == 32615 and "crs" not in m8.columns


def test_bad_inputs_are_explained(field, tmp_path):
    from matchplant.spatial_stat_extractor.config import RasterSet
    from matchplant.spatial_stat_extractor.inputs import read_polygons
    from matchplant.spatial_stat_extractor.zonal import extract_stats

    d = field["dir"]
    pd.DataFrame({"a": [1], "b": [2]}).to_csv(tmp_path / "nogeom.csv", index=False)
    with pytest.raises(InputError, match="xmin,ymin,xmax,ymax"):
        read_polygons(tmp_path / "nogeom.csv")
    with pytest.raises(InputError, match="not found"):
        read_polygons(tmp_path / "missing.gpkg")
    with pytest.raises(InputError, match="id column 'nope'"):
        read_polygons(d / "plants.gpkg", id_column="nope")
    polys = read_polygons(d / "plants.gpkg")
    with pytest.raises(InputError, match="band 5"):
        extract_stats(polys, [RasterSet(multispectral=d / "ms.tif", nir_band=5)])
    far = polys.copy()
    far["geometry"] = far.translate(5000, 0)
    with pytest.raises(InputError, match="none of the 6 plants overlaps"):
        extract_stats(far, [RasterSet(chm=d / "chm_w4.tif")])
    with pytest.raises(ConfigError, match="DTM"):
        RasterSet(dsm=d / "dsm.tif").layers()
    (tmp_path / "bad.tif").write_text("not a tiff")
    with pytest.raises(InputError, match="cannot read the raster"):
        extract_stats(polys, [RasterSet(chm=tmp_path / "bad.tif")])


def test_outside_and_nodata_reported(field, caplog):
    from matchplant.spatial_stat_extractor.config import RasterSet
    from matchplant.spatial_stat_extractor.inputs import read_polygons
    from matchplant.spatial_stat_extractor.zonal import extract_stats

    d = field["dir"]
    polys = read_polygons(d / "plants.gpkg")
    polys.loc[0, "geometry"] = shapely.box(499000, 3999000, 499001, 3999001)  # off the raster
    polys.loc[1, "geometry"] = shapely.box(500000.05, 3999999.92, 500000.075, 3999999.95)  # on the DSM hole
    table, report = extract_stats(polys, [RasterSet(dsm=d / "dsm.tif", dtm=d / "dtm.tif")], ["count", "max", "nodata"])
    layer = report["layers"][0]
    assert layer["outside"] == 1 and layer["outside_ids"] == [1]
    assert layer["only_nodata"] == 1 and layer["only_nodata_ids"] == [2]
    assert table["chm_count"].tolist()[:2] == [0, 0] and table["chm_nodata"][1] > 0
    assert np.isnan(table["chm_max"][:2]).all() and np.isfinite(table["chm_max"][2:]).all()
    assert "outside the raster" in caplog.text


def test_compare_two_sets(field, tmp_path):
    from matchplant.spatial_stat_extractor.compare import compare_tables, match_by_iou

    a = field["boxes"]
    b = shapely.transform(a[[0, 1, 2, 3, 4]], lambda c: c + [0.02, 0.0])  # a "prediction": shifted, one missed
    b = np.append(b, shapely.box(500003.5, 3999998.0, 500003.8, 3999998.3))  # a false positive
    m = match_by_iou(a, b, 0.3)
    assert m["index_a"].tolist() == [0, 1, 2, 3, 4] and m["index_b"].tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(m["iou"], 0.38 / 0.42, rtol=1e-9)
    ta = pd.DataFrame({"plant_id": field["ids"], "chm_max": field["heights"]})
    tb = pd.DataFrame({"plant_id": np.arange(6) + 100, "chm_max": np.r_[field["heights"][:5] + 0.01, 0.9]})
    summary, pairs = compare_tables(ta, tb, m, ["chm_max"], "manual", "predicted")
    row = summary.set_index("trait").loc["chm_max"]
    assert row["n_matched"] == 5 and row["mean_abs_diff"] == pytest.approx(0.01)
    assert row["pearson_r"] == pytest.approx(1.0)
    from scipy.stats import ks_2samp

    assert row["ks_pvalue"] == pytest.approx(ks_2samp(ta["chm_max"], tb["chm_max"]).pvalue)
    assert summary.set_index("trait").loc["iou", "unmatched_predicted"] == 1
    assert pairs["plant_id_predicted"].tolist() == [100, 101, 102, 103, 104]


def test_cli_end_to_end_with_comparison(field):
    import geopandas as gpd

    d = field["dir"]
    pred = field["gdf"].iloc[:5].copy()
    pred["geometry"] = pred.translate(0.01, 0.01)
    pred["plant_id"] = pred["plant_id"] + 100
    pred.to_file(d / "pred.gpkg", driver="GPKG")
    cfg = d / "cfg.yaml"
    cfg.write_text(
        "polygons: plants.gpkg\nrasters:\n  date: w3\n  dsm: dsm.tif\n  dtm: dtm.tif\n"
        "  multispectral: ms.tif\nmore_dates:\n  - date: w4\n    chm: chm_w4.tif\n"
        "percentiles: [5, 95]\nmode: coverage\ncompare:\n  polygons: pred.gpkg\noutput_dir: out\n"
    )
    r = subprocess.run(
        [sys.executable, str(FOLDER / "spatial_stat_extractor.py"), "--config", str(cfg), "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    out = d / "out"
    table = pd.read_csv(out / "stats.csv")
    assert {"chm_max_w3", "chm_p95_w4", "ndvi_mean_w3"} <= set(table.columns)
    summary = pd.read_csv(out / "compare_summary.csv").set_index("trait")
    assert set(summary.index) == {"chm_max_w3", "ndvi_mean_w3", "chm_max_w4", "iou"}
    assert summary.loc["iou", "n_matched"] == 5
    assert (out / "compare.png").stat().st_size > 10_000
    assert gpd.read_file(out / "stats.gpkg").crs.to_epsg() == 32615
    # a wrong key is a clear message and exit code 2, not a traceback
    r = subprocess.run(
        [sys.executable, str(FOLDER / "spatial_stat_extractor.py"), "--config", str(cfg), "--set", "mode=centre"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "did you mean 'center'" in r.stderr and "Traceback" not in r.stderr


def test_folder_config_and_help():
    from matchplant.core.runtime.config import load_config
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig

    cfg = load_config(SpatialStatExtractorConfig, FOLDER / "config.yaml", strict=False)
    assert cfg.mode == "center" and cfg.stats
    r = subprocess.run(
        [sys.executable, str(FOLDER / "spatial_stat_extractor.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--gui" in r.stdout and "--dsm" in r.stdout


def test_config_checks(tmp_path):
    from matchplant.core.runtime.config import load_config
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig

    (tmp_path / "p.gpkg").write_text("x")
    with pytest.raises(ConfigError, match="no raster given"):
        load_config(SpatialStatExtractorConfig, None, [f"polygons={tmp_path / 'p.gpkg'}"])
    with pytest.raises(ConfigError, match="distinct"):
        load_config(
            SpatialStatExtractorConfig,
            None,
            [
                f"polygons={tmp_path / 'p.gpkg'}",
                f"rasters.chm={tmp_path / 'p.gpkg'}",
                f"more_dates=[{{chm: {tmp_path / 'p.gpkg'}}}]",
            ],
        )


# --------------------------------------------------------------------------------------------------
# acceptance on the synthetic field


def test_synthetic_field_heights_and_ndvi(tiny_field, tmp_path):
    import rasterio
    import rasterio.features

    from matchplant.spatial_stat_extractor.config import RasterSet
    from matchplant.spatial_stat_extractor.inputs import read_polygons
    from matchplant.spatial_stat_extractor.zonal import extract_stats

    truth = pd.read_csv(tiny_field.plants_csv).set_index("id")
    res = json.loads(tiny_field.field_json.read_text())["raster_res"]
    sets = [RasterSet(dsm=tiny_field.dsm, dtm=tiny_field.dtm, multispectral=tiny_field.multispectral)]
    # the truth boxes on the map (module 8's output has the same form)
    polys = read_polygons(tiny_field.map_boxes, crs=json.loads(tiny_field.field_json.read_text())["crs"])
    table, report = extract_stats(polys, sets, ["max", "mean"], [])
    h = truth.loc[table["plant_id"], "height"].to_numpy()
    err = np.abs(table["chm_max"].to_numpy() - h)
    assert err.max() < res, f"max CHM differs from the true height by up to {err.max():.4f} m"
    assert np.median(err) < 5e-4
    # a box holds the plant (NDVI 0.8) and soil (0.15): its mean lies between, its maximum is the leaf's
    assert np.all((table["ndvi_mean"] > 0.15) & (table["ndvi_mean"] < 0.8))
    assert np.allclose(table["ndvi_max"], 0.8, atol=1e-6)
    # each plant's exact footprint (vectorised from the truth label raster): NDVI is the leaf's everywhere
    with rasterio.open(tiny_field.plant_ids) as src:
        label = src.read(1)
        shapes = [
            (shapely.geometry.shape(g), int(v))
            for g, v in rasterio.features.shapes(label, mask=label > 0, transform=src.transform)
        ]
        crs = src.crs.to_wkt()
    import geopandas as gpd

    fp = gpd.GeoDataFrame({"plant_id": [v for _, v in shapes]}, geometry=[g for g, _ in shapes], crs=crs)
    fp = fp.dissolve("plant_id").reset_index()
    for mode in ("center", "coverage"):
        t2, _ = extract_stats(fp, sets, ["count", "min", "max", "mean"], [], mode)
        np.testing.assert_allclose(t2[["ndvi_min", "ndvi_max", "ndvi_mean"]].to_numpy(), 0.8, atol=1e-6)
        counts = np.bincount(label[label > 0])[t2["plant_id"]]
        np.testing.assert_allclose(t2["chm_count"], counts, atol=1e-6)
        assert np.all(np.abs(t2["chm_max"] - truth.loc[t2["plant_id"], "height"].to_numpy()) < res)


def test_rerun_into_one_folder_leaves_nothing_stale(field):
    """A run with canopy outlines, then one without into the same folder: the outlines of the first are gone,
    a file the user put there stays, and manifest.json lists exactly what the folder holds of the step."""
    import json

    from matchplant.core.runtime.config import load_config
    from matchplant.spatial_stat_extractor import run
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig

    d, out = field["dir"], field["dir"] / "stats_out"
    base = [
        f"polygons={d / 'plants.gpkg'}",
        f"rasters.dsm={d / 'dsm.tif'}",
        f"rasters.dtm={d / 'dtm.tif'}",
        f"output_dir={out}",
    ]
    run(load_config(SpatialStatExtractorConfig, None, base + ["vector_formats=[gpkg, shp]"]))
    assert (out / "outlines.gpkg").is_file() and (out / "polygons.shp").is_file()
    (out / "my_notes.txt").write_text("mine")
    run(load_config(SpatialStatExtractorConfig, None, base + ["canopy.enabled=false", "vector_formats=[gpkg]"]))
    listed = set(json.loads((out / "manifest.json").read_text())["files"])
    held = {
        p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.relative_to(out).parts[0] != "logs"
    }
    assert held == listed | {"my_notes.txt"}
    assert not (out / "outlines.gpkg").exists() and not (out / "polygons.shp").exists()
    assert (out / "stats.csv").is_file()
