"""Module 9's traits (issue 19): plant outlines from the CHM, canopy-only statistics, growth across dates,
and RGB indices / band formulas (issue 17) - against the tiny synthetic field's truth (a field with
per-plant vigour and a second date) and against independent numpy references."""

from __future__ import annotations

import contextlib

import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from affine import Affine
from rasterio.features import geometry_mask, rasterize

from matchplant.core.runtime.errors import ConfigError
from matchplant.simfield import generate_field
from matchplant.simfield.scoring import growth_scores, outline_ious, trait_scores
from matchplant.spatial_stat_extractor.canopy import SegmentSettings, canopy_stats, grouped_stats, segment
from matchplant.spatial_stat_extractor.config import CanopyConfig, Formula, RasterSet
from matchplant.spatial_stat_extractor.inputs import ArraySource, Layer, open_layer, parse_formula, read_polygons
from matchplant.spatial_stat_extractor.traits import canopy_traits, merge_columns
from matchplant.spatial_stat_extractor.zonal import extract_stats


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """The tiny field with per-plant vigour and a second date with grown, shifted plants."""
    return generate_field(
        preset="tiny", seed=0, out=tmp_path_factory.mktemp("tiny_traits"), vigour=True, second_date=True
    )


@pytest.fixture(scope="module")
def plants(field):
    return read_polygons(field.map_boxes)


def chm_layer(root) -> Layer:
    return Layer("chm", "difference", (root / "odm_dem" / "dsm.tif", root / "odm_dem" / "dtm.tif"), elevation=True)


def run_canopy(field, plants, **canopy):
    sets = [
        RasterSet(date="d1", dsm=field.dsm, dtm=field.dtm, multispectral=field.multispectral, rgb=field.orthophoto),
        RasterSet(date="d2", dsm=field.later.dsm, dtm=field.later.dtm),
    ]
    table, _ = extract_stats(plants, sets, ["mean", "max"], [95])
    per_date, outlines, unclaimed, report = canopy_traits(plants, sets, CanopyConfig(**canopy), ["mean", "max"], [95])
    assert len(unclaimed) == 0  # every plant has its box
    return merge_columns(table, per_date, "wide", 2), outlines, report


@pytest.fixture(scope="module")
def result(field, plants):
    return run_canopy(field, plants)


def first_date(table: pd.DataFrame) -> pd.DataFrame:
    return table.rename(columns=lambda c: c[:-3] if c.endswith("_d1") else c)


def test_canopy_traits_follow_the_true_plants(field, result):
    table, outlines, report = result
    s = trait_scores(first_date(table), field)
    assert s["matched"] == s["true_plants"] == len(table)
    assert s["height_r"] > 0.99 and s["height_mae_m"] < 0.01
    # canopy NDVI is each plant's vigour; the box mean mixes leaves and soil (the 0.24-0.32)
    assert s["ndvi_r"] > 0.99 and s["ndvi_mae"] < 0.01
    assert s["ndvi_box_r"] < 0.8
    assert report["dates"][0]["outlined"] == len(table)


def test_outlines_match_the_true_canopy(field, result):
    table, outlines, _ = result
    d1 = outlines[outlines["date"] == "d1"]
    iou = outline_ious(d1.geometry.values, first_date(table), field)
    assert np.median(iou) > 0.85 and np.min(iou) > 0.7
    assert d1.geometry.is_valid.all()
    # tightened boxes lie inside the boxes plus the margin; tops inside the boxes
    boxes = pd.read_csv(field.map_boxes)
    m = CanopyConfig().margin + 1e-9
    assert np.all((d1["tight_xmin"].to_numpy() >= boxes.xmin - m) & (d1["tight_xmax"].to_numpy() <= boxes.xmax + m))
    assert np.all((d1["tight_ymin"].to_numpy() >= boxes.ymin - m) & (d1["tight_ymax"].to_numpy() <= boxes.ymax + m))
    assert np.all(
        shapely.area(shapely.box(d1.tight_xmin, d1.tight_ymin, d1.tight_xmax, d1.tight_ymax))
        < shapely.area(shapely.box(boxes.xmin - m, boxes.ymin - m, boxes.xmax + m, boxes.ymax + m))
    )
    assert np.all(
        shapely.contains_xy(shapely.box(boxes.xmin, boxes.ymin, boxes.xmax, boxes.ymax), d1["top_x"], d1["top_y"])
    )
    true_area = pd.read_csv(field.traits_csv)["canopy_area_m2"].to_numpy()
    assert np.median(d1["canopy_area_m2"].to_numpy() / true_area) == pytest.approx(0.9, abs=0.08)


def test_growth_recentres_plants(field, result):
    table, outlines, report = result
    g = growth_scores(first_date(table), field, ("top_x_d2", "top_y_d2"))
    assert g["reused_box_centre_error_median_m"] > 0.02
    assert g["recentred_error_median_m"] < 0.5 * g["reused_box_centre_error_median_m"]
    assert g["recentred_error_median_m"] < 0.01
    assert np.all(table["shift_m_d2"] <= CanopyConfig().max_shift + 0.01)
    # the grown plants are taller on the second date, as the truth says
    truth2 = pd.read_csv(field.later.traits_csv)
    assert np.corrcoef(truth2["height"], table["chm_canopy_max_d2"])[0, 1] > 0.99


def test_canopy_stats_equal_a_numpy_reference(field, plants):
    """Every statistic over the canopy pixels equals numpy over the same pixels; on another grid the
    outline polygons are used."""
    with contextlib.ExitStack() as st:
        chm = open_layer(chm_layer(field.root), st)
        o = segment(plants.geometry.values, chm, SegmentSettings())
        ndvi = open_layer(Layer("ndvi", "ndvi", (field.multispectral,), bands=(1, 2)), st)
        got = canopy_stats(o, ndvi, ["count", "min", "max", "mean", "median", "std", "sum"], [10, 95])
        with rasterio.open(field.multispectral) as ds:
            red, nir = ds.read(1).astype(float), ds.read(2).astype(float)
        full = ((nir - red) / (nir + red)).ravel()
        for k in range(len(plants)):
            v = full[o.pix[o.start[k] : o.start[k + 1]]]
            ref = {
                "count": v.size,
                "min": v.min(),
                "max": v.max(),
                "mean": v.mean(),
                "median": np.median(v),
                "std": v.std(),
                "sum": v.sum(),
                "p10": np.percentile(v, 10),
                "p95": np.percentile(v, 95),
            }
            for key, r in ref.items():
                assert got[key][k] == pytest.approx(r, rel=1e-9, abs=1e-12), key
        # the same raster on a coarser grid: measured over the outline polygons (pixel centres inside);
        # the coarse pixels on the outline mix leaves and soil, but the plants keep their order
        # (shifted by half a fine pixel, so that no coarse pixel centre lies exactly on an outline edge)
        coarse = ArraySource(
            full.reshape(red.shape)[::2, ::2], chm.transform @ Affine.translation(0.5, 0.5) @ Affine.scale(2)
        )
        got2 = canopy_stats(o, coarse, ["mean"], [])
        lab = rasterize(
            ((g, k + 1) for k, g in enumerate(o.geometry)),
            out_shape=coarse.data.shape,
            transform=coarse.transform,
            dtype="int32",
        )
        for k in range(len(plants)):
            assert got2["mean"][k] == pytest.approx(np.nanmean(coarse.data[lab == k + 1]), rel=1e-9)
        assert np.corrcoef(got2["mean"], got["mean"])[0, 1] > 0.9


def test_touching_plants_are_split_and_small_ones_flagged():
    """Two paraboloid plants whose canopies touch, seen through overlapping boxes; a plant of two pixels;
    a weed; a second box on the first plant; a box on leaves only; a plant without a box."""
    res = 0.01
    t = Affine(res, 0, 0, 0, -res, 1.0)
    rr, cc = np.mgrid[0:100, 0:100] + 0.5
    a = 0.5 * (1 - (np.hypot(cc - 30, rr - 50) / 16) ** 2)
    b = 0.3 * (1 - (np.hypot(cc - 55, rr - 50) / 12) ** 2)
    chm = np.maximum(np.maximum(a, b), 0)
    truth = np.where((a >= b) & (a > 0), 1, np.where(b > 0, 2, 0))
    chm[80, 80] = chm[80, 81] = 0.2  # a two-pixel plant
    chm[15:18, 80:83] = 0.03  # a weed: too low to be a plant
    c = 0.25 * (1 - (np.hypot(cc - 20, rr - 85) / 8) ** 2)
    chm = np.maximum(chm, c)  # a plant no box holds
    src = ArraySource(chm, t)

    def box(c0, r0, c1, r1):
        return shapely.box(*(t @ (c0, r1)), *(t @ (c1, r0)))

    geoms = [
        box(12, 32, 50, 68),
        box(38, 36, 70, 64),
        box(77, 77, 84, 84),
        box(76, 12, 86, 22),
        box(20, 40, 40, 60),
        box(62, 45, 67, 55),
    ]
    o = segment(geoms, src, SegmentSettings(margin=0.03))
    assert list(o.flag) == ["", "", "small", "low", "duplicate", "no_peak"]
    assert len(o.unclaimed) == 1
    assert o.unclaimed[0, :3] == pytest.approx([0.205, 1 - 0.855, 0.25], abs=0.011)
    for k, label in ((0, 1), (1, 2)):
        pix = o.pix[o.start[k] : o.start[k + 1]]
        mine = truth.ravel()[pix] == label
        assert mine.mean() > 0.97 and mine.sum() > 0.85 * (truth == label).sum()
    assert o.top[0, 2] == pytest.approx(0.5, abs=0.01) and o.top[1, 2] == pytest.approx(0.3, abs=0.01)
    # flagged plants keep their box (and its pixels); the duplicate shares the first plant's canopy
    assert o.geometry[2].equals(geoms[2]) and o.pixels[2] == 49
    assert o.geometry[4].equals(o.geometry[0]) and o.pixels[4] == o.pixels[0]


def test_rgb_indices_per_plant_equal_a_numpy_reference(field, plants, result):
    """ExG, ExGR, VARI, GLI and NGRDI on the synthetic orthophoto: module 9's box means equal numpy's over
    the pixels whose centre is inside each box; canopy means equal numpy's over the outline pixels."""
    names = ["exg", "exgr", "vari", "gli", "ngrdi"]
    # boxes moved by a fraction of 0.1 mm: no pixel centre lies exactly on an edge (a tie, which GDAL and
    # module 9 may settle differently)
    boxes = plants.copy()
    boxes["geometry"] = boxes.translate(0.000031, 0.000017)
    table, _ = extract_stats(boxes, [RasterSet(rgb=field.orthophoto, indices=names)], ["mean"], [])
    with rasterio.open(field.orthophoto) as ds:
        R, G, B = (ds.read(i).astype(float) for i in (1, 2, 3))
        transform, shape = ds.transform, ds.shape
    with np.errstate(invalid="ignore", divide="ignore"):
        s = R + G + B
        r, g, b = R / s, G / s, B / s
        ref = {
            "exg": 2 * g - r - b,
            "exgr": (2 * g - r - b) - (1.4 * r - g),
            "vari": (G - R) / (G + R - B),
            "gli": (2 * G - R - B) / (2 * G + R + B),
            "ngrdi": (G - R) / (G + R),
        }
    inside = [
        geometry_mask([geom], out_shape=shape, transform=transform, invert=True) for geom in boxes.geometry.values
    ]  # one box at a time: boxes overlap
    for name in names:
        v = np.where(np.isfinite(ref[name]), ref[name], np.nan)
        for k in range(len(plants)):
            want = np.nanmean(v[inside[k]])
            assert table[f"{name}_mean"][k] == pytest.approx(want, rel=1e-9), name
    # canopy means (indices are measured over the canopy by default)
    full, outlines, _ = result
    d1 = outlines[outlines["date"] == "d1"]
    lab2 = rasterize(
        ((geom, k + 1) for k, geom in enumerate(d1.geometry.values)),
        out_shape=shape,
        transform=transform,
        dtype="int32",
    )
    for name in ("exg", "vari", "gli"):
        for k in range(len(plants)):
            assert full[f"{name}_canopy_mean_d1"][k] == pytest.approx(np.nanmean(ref[name][lab2 == k + 1]), rel=1e-9)


def test_band_formulas_and_band_checks(field, plants):
    # a formula equal to NDVI (band 1 red, band 2 NIR)
    t, _ = extract_stats(
        plants,
        [
            RasterSet(
                multispectral=field.multispectral,
                formulas=[Formula("nd", field.multispectral, "(b2 - b1) / (b2 + b1)")],
            )
        ],
        ["mean", "max"],
        [],
    )
    assert np.allclose(t["nd_mean"], t["ndvi_mean"]) and np.allclose(t["nd_max"], t["ndvi_max"])
    # the raster names its bands: swapped numbers are refused with the right ones
    with pytest.raises(ConfigError, match="(?s)red_band = 2.*'nir'.*set red_band: 1"):
        extract_stats(plants, [RasterSet(multispectral=field.multispectral, red_band=2, nir_band=1)])
    with pytest.raises(ConfigError, match=r"rgb_bands\[0\] \(red\) = 3.*'blue'"):
        extract_stats(plants, [RasterSet(rgb=field.orthophoto, rgb_bands=[3, 2, 1])])
    with pytest.raises(ConfigError, match="b7"):
        extract_stats(plants, [RasterSet(formulas=[Formula("x", field.multispectral, "b7 - b1")])])
    for bad in ("__import__('os')", "b1.real", "b1 if b2 else b1", "'a' + b1", "b1 +"):
        with pytest.raises(ConfigError):
            parse_formula(bad, {"b1", "b2"}, "formula")


def test_grouped_stats_skip_nan_and_empty_groups():
    v = np.array([1.0, np.nan, 3.0, np.nan, 5.0, 2.0])
    start = np.array([0, 3, 4, 4, 6])
    got = grouped_stats(v, start, ["count", "min", "max", "mean", "median", "nodata"], [50])
    assert list(got["count"]) == [2, 0, 0, 2]
    assert got["mean"][0] == 2 and np.isnan(got["mean"][1]) and got["median"][3] == 3.5
    assert list(got["nodata"]) == [1, 1, 0, 0] and got["max"][3] == 5 and got["min"][0] == 1


def test_vigour_and_second_date_truth(field, tiny_field):
    """The generator's truth for traits: each plant's leaves carry its NDVI in the multispectral raster;
    the second date's plants are taller and shifted; without vigour nothing else changes."""
    truth = pd.read_csv(field.traits_csv)
    with rasterio.open(field.multispectral) as ds, rasterio.open(field.plant_ids) as ids:
        red, nir, lab = ds.read(1).astype(float), ds.read(2).astype(float), ids.read(1)
    ndvi = (nir - red) / (nir + red)
    for pid, want, count in zip(truth["id"], truth["ndvi"], truth["canopy_pixels"]):
        v = ndvi[lab == pid]
        assert v.size == count and np.allclose(v, want, atol=1e-3)
    assert truth["ndvi"].std() > 0.03
    t1, t2 = pd.read_csv(field.plants_csv), pd.read_csv(field.later.plants_csv)
    assert (t2["height"] > 1.2 * t1["height"]).all()
    shift = np.hypot(t2["x"] - t1["x"], t2["y"] - t1["y"])
    assert 0.01 < shift.median() < 0.08 and shift.max() < CanopyConfig().max_shift
    for name in ("dsm", "orthophoto", "plants_csv", "map_boxes"):  # the same field without vigour
        assert getattr(tiny_field, name).read_bytes() == getattr(field, name).read_bytes(), name


def test_long_layout_and_a_date_without_chm(field, plants):
    sets = [
        RasterSet(date="d1", dsm=field.dsm, dtm=field.dtm),
        RasterSet(date="d2", dsm=field.later.dsm, dtm=field.later.dtm),
        RasterSet(date="d3", multispectral=field.later.multispectral),
    ]
    table, _ = extract_stats(plants, sets, ["max"], [], layout="long")
    per_date, outlines, _, report = canopy_traits(plants, sets, CanopyConfig(), ["max"], [])
    t = merge_columns(table, per_date, "long", 3)
    assert len(t) == 3 * len(plants) and set(per_date) == {"d1", "d2"}
    assert (
        t.loc[t["date"] != "d3", "canopy_pixels"].notna().all()
        and t.loc[t["date"] == "d3", "canopy_pixels"].isna().all()
    )
    assert t.loc[t["date"] == "d2", "shift_m"].notna().all()
    assert list(outlines["date"].unique()) == ["d1", "d2"] and len(report["dates"]) == 2
