"""Module 9's canopy on a photogrammetric-looking CHM (issue 26, points 3 and 4; issue 27, CHM sanity): the
ground noise measured against the noise put in, outlines that stay inside low plants (canopy/box <= 0.7)
and match the true footprint, no ground bump counted as a plant, valid polygons in every GIS file of a run,
and clear errors for a CHM that cannot be right."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from noisy_chm import noisy_chm
from rasterio.features import rasterize
from scipy import ndimage as ndi

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.spatial_stat_extractor.canopy import (
    GroundSample,
    SegmentSettings,
    check_chm,
    measure_ground,
    segment,
    thresholds,
)
from matchplant.spatial_stat_extractor.canopy.collect import valid_polygons  # the role's own polygon repair
from matchplant.spatial_stat_extractor.canopy.ground import robust_sd  # the role's own robust statistics
from matchplant.spatial_stat_extractor.config import (
    CanopyConfig,
    RasterSet,
    SpatialStatExtractorConfig,
)
from matchplant.spatial_stat_extractor.inputs import ArraySource, read_polygons
from matchplant.spatial_stat_extractor.run import extract_and_write
from matchplant.spatial_stat_extractor.traits import canopy_traits

CRS = "EPSG:32614"


@pytest.fixture(scope="module")
def field():
    return noisy_chm(seed=1)


def pixel_iou(geoms, f) -> np.ndarray:
    """IoU of each outline (rasterised, pixel centres) with its plant's true footprint (leaf pixels)."""
    n = len(geoms)
    pred = rasterize(
        ((g, k + 1) for k, g in enumerate(geoms)), out_shape=f.chm.shape, transform=f.transform, dtype="int32"
    ).ravel()
    truth = f.truth.ravel()
    inter = np.bincount(pred[(pred == truth) & (pred > 0)], minlength=n + 1)[1:]
    union = np.bincount(pred, minlength=n + 1)[1:] + np.bincount(truth, minlength=n + 1)[1:] - inter
    return inter / union


def auto_settings(src, f):
    noise = measure_ground(src, f.boxes, guard_m=0.1)
    th = thresholds("auto", "auto", noise)
    return (
        noise,
        th,
        SegmentSettings(min_height=th.min_height, min_top=th.min_top, unclaimed_min_top=th.unclaimed_min_top),
    )


def test_ground_noise_measured_and_outlines_inside_low_plants(field):
    f = field
    src = ArraySource(f.chm, f.transform)
    noise, th, s = auto_settings(src, f)
    # the noise put in (correlated N(1.5 cm, 3 cm) between the plants), measured from the CHM alone
    assert noise.p50 == pytest.approx(f.ground_p50, abs=0.003)
    assert noise.p95 == pytest.approx(f.ground_p95, abs=0.005)
    assert noise.sd == pytest.approx(f.ground_sd, rel=0.1)
    assert th.min_height == pytest.approx(f.ground_p50 + 3 * f.ground_sd, abs=0.01)
    o = segment(f.boxes, src, s)
    out = ~o.from_box
    assert out.mean() > 0.85  # only plants of 15-30 cm, which the CHM cannot tell from soil, keep their box
    assert (f.height[o.from_box] < 0.3).all()
    ratio = o.area[out] / shapely.area(f.boxes[out])
    assert np.median(ratio) <= 0.5 and ratio.max() <= 0.7
    iou = pixel_iou(o.geometry, f)
    assert np.median(iou[out]) >= 0.5
    # no ground bump is taken for a plant the detector missed
    assert len(o.unclaimed) == 0 and o.noise_bumps > 0
    # the old fixed thresholds (2 cm, 5 cm) on the same CHM: outlines spill over the boxes, bumps are plants
    old = segment(f.boxes, src, SegmentSettings())
    assert np.median(old.area / shapely.area(f.boxes)) > 0.7 and len(old.unclaimed) > 50
    assert np.median(pixel_iou(old.geometry, f)) < np.median(iou[out]) - 0.15


def test_close_planted_field_measures_the_ground_just_outside_the_boxes(field):
    """A guard wider than the gaps between the boxes (a close-planted field) leaves no pixel a guard from every
    box: the ground outside the boxes is the sample, not the exact CHM's fixed thresholds."""
    f = field
    noise = measure_ground(ArraySource(f.chm, f.transform), f.boxes, guard_m=5.0)
    assert not noise.guarded and noise.pixels >= 500 and noise.report()["guarded"] is False
    assert noise.p50 == pytest.approx(f.ground_p50, abs=0.005)
    assert noise.sd == pytest.approx(f.ground_sd, rel=0.25)
    assert measure_ground(ArraySource(f.chm, f.transform), f.boxes, guard_m=0.1).guarded


def outline_means(geoms, f, layer) -> np.ndarray:
    """Each outline's mean of ``layer`` over its pixels (rasterised, pixel centres): numpy, not module 9."""
    pred = rasterize(
        ((g, k + 1) for k, g in enumerate(geoms)), out_shape=layer.shape, transform=f.transform, dtype="int32"
    ).ravel()
    n = len(geoms)
    return np.bincount(pred, weights=layer.ravel(), minlength=n + 1)[1:] / np.bincount(pred, minlength=n + 1)[1:]


def test_ndvi_tells_leaf_edges_from_ground_bumps(field):
    """With an NDVI raster on the CHM's grid the soil's NDVI and the tops' are measured, leaves are told from
    the ground's bumps by NDVI and the CHM thresholds drop: outlines reach the plants' low edges (IoU with the
    true footprint), every plant is outlined (the pale ones too), and the canopy NDVI follows each plant's
    leaf NDVI; without NDVI the soft edges are cut and the low plants keep their boxes."""
    f = field
    src, ndvi = ArraySource(f.chm, f.transform), ArraySource(f.ndvi, f.transform)
    noise = measure_ground(src, f.boxes, guard_m=0.1, ndvi=ndvi)
    th = thresholds("auto", "auto", noise, "auto")
    assert th.ndvi_soil == pytest.approx(0.15, abs=0.01) and 0.16 < th.ndvi_threshold < 0.3
    assert th.min_height < 0.06 and th.source["ndvi_threshold"].startswith("auto")
    s = SegmentSettings(
        min_height=th.min_height,
        min_top=th.min_top,
        unclaimed_min_top=th.unclaimed_min_top,
        mask_threshold=th.ndvi_threshold,
        mask_soil=th.ndvi_soil,
    )
    o = segment(f.boxes, src, s, mask_source=ndvi)
    assert not o.from_box.any() and len(o.unclaimed) == 0  # the pale plants (NDVI 0.35-0.45) too
    assert (o.area / shapely.area(f.boxes)).max() <= 0.7
    iou, mean = pixel_iou(o.geometry, f), outline_means(o.geometry, f, f.ndvi)
    assert np.median(iou) >= 0.8 and np.corrcoef(mean, f.leaf_ndvi)[0, 1] >= 0.95
    _, _, s_chm = auto_settings(src, f)
    chm_only = segment(f.boxes, src, s_chm)
    assert np.median(pixel_iou(chm_only.geometry, f)) < np.median(iou) - 0.2
    assert np.corrcoef(outline_means(chm_only.geometry, f, f.ndvi), f.leaf_ndvi)[0, 1] < 0.9
    # a false box on a 12 cm ground bump between the rows: its top is soil by NDVI, flagged low (not a plant)
    t = f.transform
    cx, cy = t.c + 3.0, t.f - 0.775
    rows, cols = np.mgrid[0 : f.chm.shape[0], 0 : f.chm.shape[1]]
    xs, ys = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
    assert not f.truth[np.hypot(xs - cx, ys - cy) < 0.1].any()
    bumpy = f.chm + 0.12 * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * 0.02**2))
    boxes = np.append(f.boxes, shapely.box(cx - 0.04, cy - 0.04, cx + 0.04, cy + 0.04))
    o2 = segment(boxes, ArraySource(bumpy, t), s, mask_source=ndvi)
    assert o2.flag[-1] == "low" and (o2.flag[:-1] == "").all()
    # NDVI that does not tell leaves from soil (a closed canopy): not used
    closed = ArraySource(np.full(f.chm.shape, 0.8), f.transform)
    assert thresholds("auto", "auto", measure_ground(src, f.boxes, 0.1, ndvi=closed), "auto").ndvi_threshold is None


def test_an_exact_chm_keeps_the_fixed_floor():
    """A CHM without noise (bare ground exactly 0) falls back to 2 cm and 5 cm."""
    f = noisy_chm(seed=2, noise_sd=1e-9, bias=0.0)
    src = ArraySource(np.where(np.isfinite(f.chm), np.round(f.chm, 6), np.nan), f.transform)
    th = thresholds("auto", "auto", measure_ground(src, f.boxes, guard_m=0.1))
    assert (th.min_height, th.min_top) == (0.02, 0.05)
    assert thresholds(0.03, "auto", measure_ground(src, f.boxes, 0.1)).source["min_height"] == "set"


def test_valid_polygons_keep_every_pixel():
    """Pixels touching only at a corner: a ring that touches itself is invalid; the repair keeps its area."""
    bow = shapely.Polygon([(0, 0), (1, 0), (1, 1), (2, 1), (2, 2), (1, 2), (1, 1), (0, 1)])
    cross = shapely.Polygon([(0, 0), (2, 2), (2, 0), (0, 2)])
    assert not bow.is_valid and not cross.is_valid
    fixed = valid_polygons(np.array([bow, cross, shapely.box(0, 0, 1, 1), None], dtype=object))
    assert shapely.is_valid(fixed[:3]).all() and fixed[3] is None
    assert fixed[0].area == pytest.approx(2.0) and fixed[1].area == pytest.approx(2.0)
    # a checkerboard canopy outlined: valid, and its area is the pixels' area
    t = rasterio.Affine(0.01, 0, 0, 0, -0.01, 1)
    chm = np.zeros((40, 40))
    rr, cc = np.mgrid[0:40, 0:40]
    chm[(rr > 5) & (rr < 35) & (cc > 5) & (cc < 35)] = 0.2
    chm[((rr + cc) % 2 == 0) & (rr > 8) & (rr < 20)] = 0.0  # leaves touching at their corners
    chm[20, 20] = 0.3
    o = segment([shapely.box(0.05, 0.65, 0.35, 0.95)], ArraySource(chm, t), SegmentSettings(margin=0.0))
    assert o.flag[0] == "" and shapely.is_valid(o.geometry[0])
    assert o.geometry[0].area == pytest.approx(o.pixels[0] * 1e-4, abs=1e-4)


def write_field(f, folder):
    folder.mkdir(parents=True, exist_ok=True)
    chm = write_chm(folder / "chm.tif", f.chm, f.transform)
    boxes = folder / "plants.gpkg"
    gpd.GeoDataFrame({"plant_id": np.arange(1, len(f.boxes) + 1)}, geometry=list(f.boxes), crs=CRS).to_file(boxes)
    return chm, boxes


def test_module_9_on_a_noisy_chm_writes_only_valid_polygons(field, tmp_path):
    """A whole module 9 run (outlines, plots from a grid): every geometry of every GIS file is valid; the
    outlines' area is their pixels' area; plants under 1 m keep to their boxes; the unclaimed bumps stay
    out of the stand counts; the noise and thresholds are reported."""
    f = field
    chm, boxes = write_field(f, tmp_path / "in")
    x0, y0, x1, y1 = f.transform.c, f.transform.f - 3.2, f.transform.c + 6.0, f.transform.f
    corners = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={boxes}",
            f"rasters.chm={chm}",
            f"output_dir={tmp_path / 'out'}",
            "vector_formats=[gpkg, shp, geojson]",
            f"plots.corners={json.dumps(corners)}",
            "plots.columns=2",
            "plots.ranges=2",
            "plots.rows_per_plot=2",
            "plots.plant_spacing=0.3",
        ],
    )
    _, _, report, written = extract_and_write(cfg)
    gis = [p for p in written.values() if str(p).endswith((".gpkg", ".shp", ".geojson"))]
    assert {"outlines.gpkg", "plots.gpkg", "stats.gpkg", "polygons.gpkg"} <= {p.name for p in gis}
    for path in gis:
        g = gpd.read_file(path)
        assert len(g) and g.geometry.is_valid.all(), path.name
    outlines = gpd.read_file(written["outlines_gpkg"])
    mine = outlines["outline_from"] == "chm"
    assert np.allclose(outlines.area[mine], outlines["canopy_pixels"][mine] * 1e-4, atol=1e-4)
    ratio = outlines["canopy_box_ratio"][mine]
    assert ratio.max() <= 0.7 and not outlines["fills_box"].any()
    entry = report["canopy"]["dates"][0]
    assert entry["ground_noise"]["sd"] == pytest.approx(f.ground_sd, rel=0.1)
    assert entry["thresholds_from"]["min_height"].startswith("auto")
    assert entry["unclaimed_below_noise"] > 0 and entry["unclaimed_canopies"] == 0
    plots = pd.read_csv(written["plots_csv"])
    assert plots["unclaimed"].sum() == 0
    assert plots["stand_count"].sum() == (~outlines["outline_flag"].isin(["low", "no_peak"])).sum()


def test_fills_box_flagged_when_the_threshold_is_below_the_soil(field, tmp_path):
    f = field
    chm, boxes = write_field(f, tmp_path / "in")
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={boxes}",
            f"rasters.chm={chm}",
            f"output_dir={tmp_path / 'out'}",
            "vector_formats=[]",
            "canopy.min_height=0.0",
            "canopy.min_top=0.05",
            "canopy.margin=0",
            "canopy.relative=0",
        ],
    )
    _, table, report, _ = extract_and_write(cfg)
    assert report["canopy"]["dates"][0]["fills_box"] == int(table["fills_box"].sum()) > len(table) // 2
    assert (table.loc[table["fills_box"], "canopy_box_ratio"] >= 0.9).all()


def sample(f, chm):
    src = ArraySource(chm, f.transform)
    noise = measure_ground(src, f.boxes, 0.1)
    return noise


def test_chm_sanity(field):
    f = field
    auto = ("auto", "auto")
    # DSM and DTM swapped: the CHM is negative under the plants
    n = sample(f, -f.chm)
    with pytest.raises(
        InputError,
        match=r"(?s)negative under \d+ of \d+ plants.*rasters.dsm and rasters.dtm "
        r"look swapped.*swap rasters.dsm and rasters.dtm",
    ):
        check_chm(n, thresholds(*auto, n), 10.0, "dsm.tif, dtm.tif", ("rasters.dsm", "rasters.dtm"))
    # in centimetres
    n = sample(f, 100 * f.chm)
    with pytest.raises(InputError, match=r"(?s)above canopy.max_height = 10 m.*centimetres.*A/100"):
        check_chm(n, thresholds(*auto, n), 10.0, "chm.tif", ("rasters.chm",))
    check_chm(n, thresholds(*auto, n), 100.0, "chm.tif", ("rasters.chm",))  # trees: max_height raised
    # a DSM given as the CHM: the ground 350 m above zero
    n = sample(f, 350 + f.chm)
    with pytest.raises(InputError, match="bare ground 350"):
        check_chm(n, thresholds(*auto, n), 1000.0, "dsm.tif", ("rasters.chm",))
    # canopy.min_top: 5 meant as 5 cm
    n = sample(f, f.chm)
    with pytest.raises(
        ConfigError,
        match=r"(?s)canopy.min_top = 5 m is above the top of every plant.*set canopy.min_top"
        r": 0.05 for 5 cm",
    ):
        check_chm(n, thresholds("auto", 5.0, n), 10.0, "chm.tif", ("rasters.chm",))
    check_chm(n, thresholds(*auto, n), 10.0, "chm.tif", ("rasters.chm",))  # the right CHM passes


def write_chm(path, chm, transform):
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=chm.shape[1],
        height=chm.shape[0],
        count=1,
        dtype="float32",
        crs=CRS,
        transform=transform,
        nodata=-9999,
    ) as ds:
        ds.write(np.where(np.isfinite(chm), chm, -9999).astype("float32"), 1)
    return path


def test_a_later_flight_georeferenced_apart_is_caught_and_registered(field, tmp_path):
    """A second flight 1.5 m off (east 1.45 m, north 0.35 m; no GCPs), the plants grown and the ground noise
    its own: an error naming the shift and the keys; with canopy.register the measured offset moves the boxes
    and every plant is found again."""
    f = field
    rng = np.random.default_rng(7)
    noise = ndi.gaussian_filter(rng.normal(0, 1, f.chm.shape), 2.0)
    later = 1.25 * np.nan_to_num(f.chm - f.ground_p50) + f.ground_p50 + 0.02 * noise / noise.std()
    true = np.array([1.45, 0.35])
    chm1 = write_chm(tmp_path / "chm1.tif", f.chm, f.transform)
    chm2 = write_chm(tmp_path / "chm2.tif", later, rasterio.Affine.translation(*true) @ f.transform)
    _, boxes = write_field(f, tmp_path / "in")
    plants = read_polygons(boxes)
    sets = [RasterSet(date="d1", chm=chm1), RasterSet(date="d2", chm=chm2)]
    with pytest.raises(
        InputError,
        match=r"(?s)date 'd2'.*shifted 1\.4\d m.*beyond canopy.max_shift = 0\.1 m.*"
        r"canopy.register: true",
    ):
        canopy_traits(plants, sets, CanopyConfig(), ["mean"], [])
    per_date, _, _, report = canopy_traits(plants, sets, CanopyConfig(register=True), ["mean"], [])
    got = report["dates"][1]["registered"]
    assert np.hypot(got["dx"] - true[0], got["dy"] - true[1]) < 0.02
    d1, d2 = per_date["d1"], per_date["d2"]
    ok = d1["outline_flag"] == ""
    assert (d2.loc[ok, "outline_flag"] == "").mean() > 0.95
    moved = np.hypot(d2["top_x"] - d1["top_x"] - true[0], d2["top_y"] - d1["top_y"] - true[1])[ok]
    assert np.median(moved) < 0.02
    # the same flight, not shifted: no error, the offset reported near zero
    _, _, _, report = canopy_traits(plants, [sets[0], RasterSet(date="d2", chm=chm1)], CanopyConfig(), ["mean"], [])
    assert report["dates"][1]["offset_to_d1"]["distance"] < 0.01 and "registered" not in report["dates"][1]


def test_unclaimed_canopies_need_six_sd_on_the_chm_alone_and_three_where_ndvi_tells_leaves_from_soil():
    """A canopy no box claims is a missed plant. On the CHM alone it must stand above the field's highest ground
    bumps (p50 + 6 SD); where NDVI tells leaves from soil its pixels are leaves, so p50 + 3 SD (and min_top) is
    enough: with 6 SD every missed plant under ~20 cm stayed out of the noisy demo field's stand counts."""
    rng = np.random.default_rng(5)
    soil, tops = rng.normal(0.15, 0.01, 4000), rng.normal(0.7, 0.05, 200)  # NDVI of bare soil and plant tops
    noise = GroundSample(
        pixels=10_000, windows=8, p50=0.017, p95=0.07, p99=0.09, sd=0.032, ndvi_soil=soil, ndvi_tops=tops
    )
    chm_only = thresholds("auto", "auto", noise, None)
    with_ndvi = thresholds("auto", "auto", noise, "auto")
    assert with_ndvi.ndvi_threshold is not None
    assert chm_only.unclaimed_min_top == pytest.approx(0.017 + 6 * 0.032)
    assert with_ndvi.unclaimed_min_top == pytest.approx(max(with_ndvi.min_top, 0.017 + 3 * 0.032))
    assert with_ndvi.min_top <= with_ndvi.unclaimed_min_top < chm_only.unclaimed_min_top


def test_the_ground_spread_survives_canopy_in_the_ground_sample():
    """Plants missing from the plant list (a crop of the field, a subset, a detector that missed many) put their
    canopy into the ground sample; with a third of it canopy the upper-tail spread alone read 0.3 m and every
    plant came out 'low'. Capped at 3 MAD spreads it reads a third of that; a clean, skewed ground noise is read
    as before."""
    rng = np.random.default_rng(11)
    noise = rng.normal(0.016, 0.02, 70_000)
    canopy = rng.uniform(0.2, 0.8, 30_000)
    mixed = np.concatenate([noise, canopy])
    sd = robust_sd(mixed, float(np.median(mixed)))
    tail = (np.percentile(mixed, 90) - np.median(mixed)) / 1.2816
    # the upper tail alone reads 0.30 m; capped, 0.11 m: still 5x the noise's 0.02 m (the MAD itself moves with
    # a third of canopy), so thresholds stay too high on such a sample, but a third as far off
    assert tail > 0.3 and sd < 0.12
    skewed = rng.gamma(2.0, 0.015, 100_000)  # a heavy upper tail of its own: both spreads agree within 3x
    p50 = float(np.median(skewed))
    assert robust_sd(skewed, p50) == pytest.approx((np.percentile(skewed, 90) - p50) / 1.2816)


def test_unclaimed_canopies_beyond_the_outermost_box_are_seen_whole_and_faint_leaves_listed():
    """A plant no box claims, beyond the outermost box of its strip (a row the detector missed at the
    field's edge), is found whole with its own top (the window read used to stop short of it and cut it,
    its top on the cut); a faint canopy (top between min_top and unclaimed_min_top) is listed apart when
    NDVI says its pixels are leaves, and only counted as a bump on the CHM alone."""
    t = rasterio.Affine(0.01, 0, 0, 0, -0.01, 0.6)
    rr, cc = np.mgrid[0:60, 0:300]

    def plant(col, h):
        return h * np.clip(1 - ((cc - col) ** 2 + (rr - 30) ** 2) / 15**2, 0, None)

    chm = plant(220, 0.4) + plant(150, 0.4) + plant(60, 0.07)
    ndvi = np.where(chm > 0, 0.8, 0.15)
    s = SegmentSettings(min_height=0.02, min_top=0.05, unclaimed_min_top=0.1, mask_threshold=0.3)
    box = [shapely.box(2.05, 0.15, 2.35, 0.45)]  # the plant at column 220 only
    o = segment(box, ArraySource(chm, t), s, mask_source=ArraySource(ndvi, t))
    assert o.flag[0] == "" and len(o.unclaimed) == 1
    assert o.unclaimed[0, :3] == pytest.approx([1.505, 0.295, 0.4], abs=1e-6)  # column 150's top, whole
    assert len(o.faint) == 1 and o.faint[0, :3] == pytest.approx([0.605, 0.295, 0.07], abs=1e-6)
    alone = segment(box, ArraySource(chm, t), SegmentSettings(min_height=0.02, min_top=0.05, unclaimed_min_top=0.1))
    assert len(alone.faint) == 0 and alone.noise_bumps == 1 and len(alone.unclaimed) == 1
