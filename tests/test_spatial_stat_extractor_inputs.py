"""Module 9's inputs on real files: which band is which (a 5-band reflectance file whose TIFF says "RGB + 2
extra samples", band_order), boxes in pixels of a georeferenced image (DeepForest's CSV, COCO, module 7's
predictions), plant ids (id_column), and rasters in degrees (EPSG:4326) under plants in UTM.

Every number is checked against an independent computation: numpy over the pixels whose centres
shapely finds inside each plant, and rasterio.transform.xy of the box corners."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from rasterio.enums import ColorInterp, Resampling
from rasterio.transform import from_origin
from rasterio.warp import calculate_default_transform, reproject

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.spatial_stat_extractor.config import BandFile, Formula, RasterSet
from matchplant.spatial_stat_extractor.inputs import read_polygons
from matchplant.spatial_stat_extractor.zonal import extract_stats

DATA = Path(__file__).parent / "data"
MS = DATA / "plantcv-geospatial" / "615.tif"  # blue, green, red, red edge, NIR; GDAL labels 1-3 red/green/blue
OSBS = DATA / "deepforest" / "OSBS_029.tif"
OSBS_CSV = DATA / "deepforest" / "OSBS_029.csv"
LAI = DATA / "cercospora-lai" / "2022_06_14_crop.tif"  # EPSG:4326
ORDER = ["blue", "green", "red", "rededge", "nir"]


# -- independent computations --------------------------------------------------------------------------------


def pixels_inside(path: Path, geoms, band_list) -> list[dict[int, np.ndarray]]:
    """For each polygon (in the raster's CRS), the valid values of each band at the pixels whose centre shapely
    finds inside it."""
    with rasterio.open(path) as ds:
        data = {b: ds.read(b).astype(float) for b in band_list}
        nodata, t = ds.nodata, ds.transform
    cols, rows = np.meshgrid(np.arange(data[band_list[0]].shape[1]) + 0.5, np.arange(data[band_list[0]].shape[0]) + 0.5)
    xs, ys = t @ (cols, rows)
    valid = np.ones(xs.shape, bool)
    for a in data.values():
        valid &= np.isfinite(a) & ((a != nodata) if nodata is not None else True)
    out = []
    for g in geoms:
        inside = shapely.contains_xy(g, xs, ys) & valid
        out.append({b: a[inside] for b, a in data.items()})
    return out


def ndvi_truth(path: Path, geoms, red: int, nir: int) -> np.ndarray:
    vals = pixels_inside(path, geoms, [red, nir])
    return np.array([np.mean((v[nir] - v[red]) / (v[nir] + v[red])) for v in vals])


def plants_on(path: Path, n: int = 6, size: float = 0.9, seed: int = 3):
    """Squares of ``size`` m at random places inside the raster (corners off the pixel grid)."""
    with rasterio.open(path) as ds:
        b = ds.bounds
    rng = np.random.default_rng(seed)
    x = rng.uniform(b.left + 0.1, b.right - size - 0.1, n)
    y = rng.uniform(b.bottom + 0.1, b.top - size - 0.1, n)
    return gpd.GeoDataFrame(
        {"plant_id": np.arange(1, n + 1)}, geometry=list(shapely.box(x, y, x + size, y + size)), crs="EPSG:32615"
    )


def write_generic_5band(path: Path, dtype: str, descriptions=None) -> np.ndarray:
    """A 5-band raster as generic writers write it (photometric RGB + 2 extra samples), from 615.tif's bands;
    with ``descriptions``, each band named as a camera's software names it."""
    with rasterio.open(MS) as src:
        data, profile = src.read(), src.profile
    if dtype == "uint16":  # reflectance scaled to 0..65535, as many cameras store it; nodata 0
        valid = data > -1
        data = np.where(valid, np.round(data * 60000) + 1, 0).astype("uint16")
        profile.update(nodata=0)
    profile.update(dtype=dtype, photometric="RGB", driver="GTiff")
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data.astype(dtype))
        for i, d in enumerate(descriptions or [], start=1):
            dst.set_band_description(i, d)
    return data


# -- 1. bands ------------------------------------------------------------------------------------------------


def test_the_real_file_carries_default_colour_labels():
    # the precondition of the tests below: GDAL says band 1 (blue) is red
    with rasterio.open(MS) as ds:
        assert ds.count == 5 and ds.dtypes[0] == "float32"
        assert list(ds.colorinterp[:3]) == [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
        assert not any(ds.descriptions)


def test_the_right_band_numbers_work_on_the_real_5band_file():
    plants = plants_on(MS)
    # refused before (band 3 "is blue"), with a fix that gave an NDVI 50 % too high
    t, _ = extract_stats(plants, [RasterSet(multispectral=MS, red_band=3, nir_band=5)], ["mean"], [])
    want = ndvi_truth(MS, plants.geometry.values, 3, 5)
    assert np.allclose(t["ndvi_mean"], want, rtol=1e-9, atol=0)
    wrong = ndvi_truth(MS, plants.geometry.values, 1, 5)  # the old suggestion, band 1 (blue) as red
    assert np.all(wrong > 1.25 * want)  # 25-115 % too high


def test_band_order_gives_ndvi_formulas_and_bands_by_name():
    plants = plants_on(MS)
    rs = RasterSet(
        multispectral=MS,
        band_order=ORDER,
        formulas=[Formula("ndre", MS, "(nir - rededge) / (nir + rededge)")],
        bands=[BandFile("re", MS, "rededge")],
    )
    t, _ = extract_stats(plants, [rs], ["mean"], [])
    g = plants.geometry.values
    assert np.allclose(t["ndvi_mean"], ndvi_truth(MS, g, 3, 5), rtol=1e-9)
    vals = pixels_inside(MS, g, [4, 5])
    assert np.allclose(t["ndre_mean"], [np.mean((v[5] - v[4]) / (v[5] + v[4])) for v in vals], rtol=1e-9)
    assert np.allclose(t["re_mean"], [np.mean(v[4]) for v in vals], rtol=1e-9)
    # red_band by name, synonyms in band_order
    t2, _ = extract_stats(
        plants,
        [RasterSet(multispectral=MS, band_order=["b", "g", "r", "red edge", "NIR"], red_band="red", nir_band="nir")],
        ["mean"],
        [],
    )
    assert np.allclose(t2["ndvi_mean"], t["ndvi_mean"], rtol=1e-12)


def test_no_band_number_is_suggested_from_default_labels():
    plants = plants_on(MS)
    with pytest.raises(ConfigError) as err:  # nothing says which band is red: ask, suggest no number
        extract_stats(plants, [RasterSet(multispectral=MS)], ["mean"], [])
    text = str(err.value)
    assert "band_order" in text and "red_band" in text and "red_band: 1" not in text
    # band_order contradicting red_band: the fix is band_order's number
    with pytest.raises(ConfigError, match=r"(?s)red_band = 1.*'blue'.*set red_band: 3"):
        extract_stats(plants, [RasterSet(multispectral=MS, band_order=ORDER, red_band=1, nir_band=5)])
    with pytest.raises(ConfigError, match="band_order names 4 band.*the raster has 5"):
        extract_stats(plants, [RasterSet(multispectral=MS, band_order=ORDER[:4])])
    with pytest.raises(ConfigError, match="more than once"):
        RasterSet(multispectral=MS, band_order=["red", "green", "red", "re", "nir"]).layers()
    with pytest.raises(ConfigError, match="no band of the raster is named 'redd'"):
        extract_stats(plants, [RasterSet(multispectral=MS, band_order=ORDER, red_band="redd")])


@pytest.mark.parametrize("dtype", ["float32", "uint16"])
def test_a_generic_writers_5band_file(tmp_path, dtype):
    path = tmp_path / f"ms_{dtype}.tif"
    data = write_generic_5band(path, dtype)
    with rasterio.open(path) as ds:  # what rasterio/GDAL/tifffile give such a file
        assert list(ds.colorinterp[:3]) == [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
    plants = plants_on(path)
    t, _ = extract_stats(plants, [RasterSet(multispectral=path, red_band=3, nir_band=5)], ["mean"], [])
    assert np.allclose(t["ndvi_mean"], ndvi_truth(path, plants.geometry.values, 3, 5), rtol=1e-9)
    assert data.dtype == np.dtype(dtype)


def test_band_descriptions_are_trusted(tmp_path):
    path = tmp_path / "micasense.tif"
    write_generic_5band(path, "float32", ["Blue", "Green", "Red", "Red edge", "NIR"])
    plants = plants_on(path)
    t, _ = extract_stats(plants, [RasterSet(multispectral=path)], ["mean"], [])  # numbers from the names
    assert np.allclose(t["ndvi_mean"], ndvi_truth(path, plants.geometry.values, 3, 5), rtol=1e-9)
    with pytest.raises(ConfigError, match=r"(?s)red_band = 1.*'blue'.*set red_band: 3"):
        extract_stats(plants, [RasterSet(multispectral=path, red_band=1, nir_band=5)])


def test_colour_labels_of_an_8bit_rgb_image_still_count(tmp_path):
    path = tmp_path / "rgba.tif"
    with rasterio.open(OSBS) as src:
        data, profile = src.read(), src.profile
    profile.update(count=4, photometric="RGB", alpha="YES", nodata=None)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.concatenate([data, np.full_like(data[:1], 255)]))
    plants = read_polygons(OSBS_CSV).iloc[:5]
    with pytest.raises(ConfigError, match=r"(?s)rgb_bands\[0\] \(red\) = 3.*'blue'.*set rgb_bands\[0\] \(red\): 1"):
        extract_stats(plants, [RasterSet(rgb=path, rgb_bands=[3, 2, 1], indices=["exg"])])


# -- 2. boxes in pixels of a georeferenced image ---------------------------------------------------------------


def corners_truth(table: pd.DataFrame, transform) -> np.ndarray:
    """Map bounds of each pixel box from rasterio.transform.xy of its corners."""
    x0, y0 = rasterio.transform.xy(transform, table["ymin"].to_numpy(float), table["xmin"].to_numpy(float), offset="ul")
    x1, y1 = rasterio.transform.xy(transform, table["ymax"].to_numpy(float), table["xmax"].to_numpy(float), offset="ul")
    x0, y0, x1, y1 = map(np.asarray, (x0, y0, x1, y1))
    return np.column_stack([np.minimum(x0, x1), np.minimum(y0, y1), np.maximum(x0, x1), np.maximum(y0, y1)])


def test_deepforest_csv_becomes_map_boxes():
    table = pd.read_csv(OSBS_CSV)
    got = read_polygons(OSBS_CSV)
    with rasterio.open(OSBS) as ds:
        want, crs = corners_truth(table, ds.transform), ds.crs
    assert len(got) == len(table) == 61 and got.crs.to_epsg() == crs.to_epsg() == 32617
    assert np.allclose(shapely.bounds(got.geometry.values), want, atol=1e-6)
    assert np.allclose(
        shapely.area(got.geometry.values), (table.xmax - table.xmin) * (table.ymax - table.ymin) * 0.01, rtol=1e-9
    )
    assert got["plant_id"].tolist() == list(range(1, 62))  # 'label' (Tree) is a class, not an id
    assert set(got["label"]) == {"Tree"} and set(got["image"]) == {"OSBS_029.tif"}


def test_coco_and_module7_predictions_on_the_tile(tmp_path):
    table = pd.read_csv(OSBS_CSV)
    shutil.copy(OSBS, tmp_path / OSBS.name)
    bbox = [[r.xmin, r.ymin, r.xmax - r.xmin, r.ymax - r.ymin] for r in table.itertuples()]
    coco = {
        "images": [{"id": 7, "file_name": "OSBS_029.tif", "width": 400, "height": 400}],
        "categories": [{"id": 1, "name": "tree"}],
        "annotations": [
            {"id": 100 + i, "image_id": 7, "category_id": 1, "bbox": b, "area": b[2] * b[3], "iscrowd": 0}
            for i, b in enumerate(bbox)
        ],
    }
    (tmp_path / "boxes.json").write_text(json.dumps(coco))
    # module 7's predictions on two tiles of the orthophoto (offsets x0, y0), boxes in tile pixels
    images = [
        {
            "id": 1,
            "file_name": "OSBS_029_0_0.jpg",
            "width": 200,
            "height": 400,
            "source_image": "OSBS_029.tif",
            "x0": 0,
            "y0": 0,
        },
        {
            "id": 2,
            "file_name": "OSBS_029_200_0.jpg",
            "width": 200,
            "height": 400,
            "source_image": "OSBS_029.tif",
            "x0": 200,
            "y0": 0,
        },
    ]
    preds = []
    for b in bbox:
        tile = 1 if b[0] < 200 else 2
        preds.append(
            {
                "image_id": tile,
                "category_id": 1,
                "score": 0.9,
                "bbox": [b[0] - (0 if tile == 1 else 200), b[1], b[2], b[3]],
            }
        )
    (tmp_path / "predictions.json").write_text(
        json.dumps({"images": images, "categories": coco["categories"], "predictions": preds})
    )
    with rasterio.open(OSBS) as ds:
        want = corners_truth(table, ds.transform)
    for name in ("boxes.json", "predictions.json"):
        got = read_polygons(tmp_path / name)
        assert got.crs.to_epsg() == 32617
        assert np.allclose(shapely.bounds(got.geometry.values), want, atol=1e-6), name
    assert read_polygons(tmp_path / "boxes.json")["plant_id"].tolist() == list(range(100, 161))


def test_deepforest_csv_through_the_module(tmp_path):
    from matchplant.cli import run_module

    out = tmp_path / "out"
    code = run_module(
        "spatial_stat_extractor",
        [
            "--set",
            f"polygons={OSBS_CSV}",
            "--set",
            f"rasters.rgb={OSBS}",
            "--set",
            "rasters.indices=[gli]",
            "--set",
            f"output_dir={out}",
            "--quiet",
        ],
    )
    assert code == 0
    t = pd.read_csv(out / "stats.csv")
    g = read_polygons(OSBS_CSV).geometry.values
    vals = pixels_inside(OSBS, g, [1, 2, 3])
    want = [np.mean((2 * v[2] - v[1] - v[3]) / (2 * v[2] + v[1] + v[3])) for v in vals]
    assert len(t) == 61 and np.allclose(t["gli_mean"], want, rtol=1e-9)
    assert gpd.read_file(out / "stats.gpkg").crs.to_epsg() == 32617


def test_pixel_boxes_refused_with_a_reason(tmp_path):
    table = pd.read_csv(OSBS_CSV)
    table.to_csv(tmp_path / "boxes.csv", index=False)  # the image is not beside this copy
    with pytest.raises(InputError, match="OSBS_029.tif.*not in") as err:
        read_polygons(tmp_path / "boxes.csv")
    assert "boxes_image" in err.value.fix
    assert len(read_polygons(tmp_path / "boxes.csv", images=OSBS.parent)) == 61  # the key finds it
    with rasterio.open(OSBS) as src:  # the same pixels without georeference (a PNG export)
        arr = src.read()
    with (
        pytest.warns(rasterio.errors.NotGeoreferencedWarning),  # on purpose: a PNG without georeference
        rasterio.open(
            tmp_path / "OSBS_029.png", "w", driver="PNG", width=400, height=400, count=3, dtype="uint8"
        ) as dst,
    ):
        dst.write(arr)
    table.assign(image_path="OSBS_029.png").to_csv(tmp_path / "png.csv", index=False)
    with pytest.raises(InputError, match="no CRS"):
        read_polygons(tmp_path / "png.csv")
    table.assign(xmax=table.xmax + 1000).to_csv(tmp_path / "far.csv", index=False)
    with pytest.raises(InputError, match="outside the image 'OSBS_029.tif'"):
        read_polygons(tmp_path / "far.csv", images=OSBS)


# -- 3. plant ids ------------------------------------------------------------------------------------------------


def test_id_column_number_and_label(tmp_path):
    table = pd.read_csv(OSBS_CSV)
    got = read_polygons(OSBS_CSV, id_column="number")
    assert got["plant_id"].tolist() == list(range(1, 62))
    table.assign(id=1).to_csv(tmp_path / "dup.csv", index=False)
    with pytest.raises(InputError) as err:  # auto picks 'id', which repeats: the fix is number, not auto
        read_polygons(tmp_path / "dup.csv", images=OSBS)
    assert "id_column: number" in err.value.fix and "auto" not in err.value.fix
    with pytest.raises(InputError) as err:
        read_polygons(OSBS_CSV, id_column="tree_id")
    assert "'number'" in err.value.fix and "auto" not in err.value.fix
    assert read_polygons(tmp_path / "dup.csv", id_column="number", images=OSBS)["plant_id"].is_unique


# -- 4. rasters in degrees under plants in UTM -------------------------------------------------------------------


def to_wgs84(src_path: Path, dst_path: Path) -> None:
    """``src_path`` reprojected to EPSG:4326 (nearest neighbour, about its own resolution)."""
    with rasterio.open(src_path) as src:
        t, w, h = calculate_default_transform(src.crs, "EPSG:4326", src.width, src.height, *src.bounds)
        profile = src.profile
        profile.update(crs="EPSG:4326", transform=t, width=w, height=h)
        with rasterio.open(dst_path, "w", **profile) as dst:
            for b in range(1, src.count + 1):
                reproject(
                    rasterio.band(src, b), rasterio.band(dst, b), resampling=Resampling.nearest, dst_nodata=src.nodata
                )


def synthetic_chm(path: Path, ms_path: Path | None = None):
    """A UTM CHM (2 cm) with 12 round plants of known radius and height, and (``ms_path``) a red/NIR raster on
    the same grid where plant k has NDVI 0.3 + 0.05 k; returns the plant boxes and disc areas."""
    res, size = 0.02, 300
    x0, y0 = 560000.0, 5706000.0  # EPSG:32632 (Goettingen)
    cols, rows = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    xs, ys = x0 + cols * res, y0 - rows * res
    chm = np.zeros((size, size), "float32")
    red, nir = np.full_like(chm, 0.2), np.full_like(chm, 0.22)
    boxes, areas = [], []
    for k, (cx, cy) in enumerate([(x0 + 0.6 + 1.2 * (i % 4), y0 - 0.6 - 1.6 * (i // 4)) for i in range(12)]):
        r = 0.2 + 0.02 * k
        d = np.hypot(xs - cx, ys - cy)
        chm = np.where(d < r, np.maximum(chm, 0.3 + 0.05 * k), chm)
        ndvi = 0.3 + 0.05 * k
        red = np.where(d < r, 0.05, red)
        nir = np.where(d < r, 0.05 * (1 + ndvi) / (1 - ndvi), nir)
        boxes.append(shapely.box(cx - r - 0.05, cy - r - 0.05, cx + r + 0.05, cy + r + 0.05))
        areas.append(np.pi * r * r)
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=size,
        height=size,
        count=1,
        dtype="float32",
        crs="EPSG:32632",
        transform=from_origin(x0, y0, res, res),
        nodata=-9999,
    ) as dst:
        dst.write(chm, 1)
    if ms_path is not None:
        with rasterio.open(
            ms_path,
            "w",
            driver="GTiff",
            width=size,
            height=size,
            count=2,
            dtype="float32",
            crs="EPSG:32632",
            transform=from_origin(x0, y0, res, res),
            nodata=-9999,
        ) as dst:
            dst.write(np.stack([red, nir]))
    return gpd.GeoDataFrame({"plant_id": np.arange(1, 13)}, geometry=boxes, crs="EPSG:32632"), np.array(areas)


def run_module9(polygons: Path, out: Path, *sets: str) -> pd.DataFrame:
    from matchplant.cli import run_module

    args = ["--set", f"polygons={polygons}", "--set", f"output_dir={out}", "--quiet"]
    for s in sets:
        args += ["--set", s]
    assert run_module("spatial_stat_extractor", args) == 0
    return pd.read_csv(out / "stats.csv")


def test_a_chm_in_degrees_gives_areas_in_square_metres(tmp_path):
    plants, areas = synthetic_chm(tmp_path / "chm_utm.tif", tmp_path / "ms_utm.tif")
    plants.to_file(tmp_path / "plants.gpkg")
    to_wgs84(tmp_path / "chm_utm.tif", tmp_path / "chm_4326.tif")
    to_wgs84(tmp_path / "ms_utm.tif", tmp_path / "ms_4326.tif")
    utm = run_module9(
        tmp_path / "plants.gpkg",
        tmp_path / "a",
        f"rasters.chm={tmp_path / 'chm_utm.tif'}",
        f"rasters.multispectral={tmp_path / 'ms_utm.tif'}",
    )
    deg = run_module9(
        tmp_path / "plants.gpkg",
        tmp_path / "b",
        f"rasters.chm={tmp_path / 'chm_4326.tif'}",
        f"rasters.multispectral={tmp_path / 'ms_4326.tif'}",
    )
    heights = 0.3 + 0.05 * np.arange(12)
    assert np.allclose(utm["chm_max"], heights, atol=1e-6) and np.allclose(deg["chm_max"], heights, atol=1e-6)
    # areas in m2 (square degrees would be ~1e-11): the disc's area within the resampling of two warps
    assert np.allclose(utm["canopy_area_m2"], areas, rtol=0.08)
    assert np.allclose(deg["canopy_area_m2"], utm["canopy_area_m2"], rtol=0.03)  # measured: within 1.1 %
    assert np.allclose(deg["canopy_volume_m3"], utm["canopy_volume_m3"], rtol=0.03)
    # canopy NDVI from a multispectral raster in degrees, on outlines in metres: each plant's own value
    ndvi = 0.3 + 0.05 * np.arange(12)
    assert np.allclose(utm["ndvi_canopy_mean"], ndvi, atol=1e-6)
    assert np.allclose(deg["ndvi_canopy_mean"], ndvi, atol=1e-3)
    outlines = gpd.read_file(tmp_path / "b" / "outlines.gpkg")
    assert outlines.crs.is_projected and np.allclose(outlines.area, deg["canopy_area_m2"], rtol=0.02)


def test_real_lai_in_degrees_under_utm_plants(tmp_path):
    with rasterio.open(LAI) as ds:
        assert ds.crs.to_epsg() == 4326
        b = rasterio.warp.transform_bounds(ds.crs, "EPSG:32632", *ds.bounds)
    rng = np.random.default_rng(5)
    x = rng.uniform(b[0] + 1, b[2] - 3, 20)
    y = rng.uniform(b[1] + 1, b[3] - 3, 20)
    plants = gpd.GeoDataFrame(
        {"plant_id": np.arange(1, 21)}, geometry=list(shapely.box(x, y, x + 2, y + 2)), crs="EPSG:32632"
    )
    plants.to_file(tmp_path / "plants.gpkg")
    t = run_module9(tmp_path / "plants.gpkg", tmp_path / "out", f"rasters.bands=[{{name: lai, path: {LAI}}}]")
    # the truth: the file's own pixels whose centres lie in each plant reprojected to degrees (no resampling)
    vals = pixels_inside(LAI, plants.to_crs(4326).geometry.values, [1])
    n = np.array([len(v[1]) for v in vals])
    assert np.all(n > 40)  # ~54 pixels of 0.27 m in a 2 m square
    assert np.array_equal(t["lai_count"], n)
    assert np.allclose(t["lai_mean"], [np.mean(v[1]) for v in vals], rtol=1e-9)
    assert np.allclose(t["lai_max"], [np.max(v[1]) for v in vals], rtol=1e-9)
