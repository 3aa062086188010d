"""Module 9's raster and polygon inputs: a 5-band reflectance raster written as generic writers write it
("RGB + 2 extra samples": GDAL labels its blue band red), band_order, boxes in pixels of the orthophoto (a
DeepForest CSV, a COCO file), plant ids (id_column), and rasters in degrees (EPSG:4326) under plants in UTM.
Bad ones are refused with the key and the fix; the must-work ones are checked against numpy over the
field's own pixels."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import geopandas as gpd
import numpy as np
import rasterio
import shapely
from cases_spatial_stat_extractor import DSM, DTM, ORTHO, args, gpkg, rows
from harness import Case, Work
from rasterio.enums import ColorInterp, Resampling
from rasterio.warp import calculate_default_transform, reproject

MS = "multispectral/multispectral.tif"  # the field's 2-band red, NIR
ORDER = "[blue,green,red,rededge,nir]"


# -- inputs -------------------------------------------------------------------------------------------------------


def five_band(w: Work) -> Path:
    """The field's red and NIR as bands 3 and 5 of a 5-band float32 file saved photometric RGB (+ 2 extra
    samples), as rasterio/tifffile write it: GDAL then labels bands 1-3 red, green, blue."""
    with rasterio.open(w.artifacts / "field" / MS) as src:
        red, nir = src.read(1), src.read(2)
        profile = src.profile
    valid = red != src.nodata
    blue, green = np.where(valid, red * 0.6, red), np.where(valid, red * 1.3, red)
    edge = np.where(valid, (red + nir) / 2, red)
    profile.update(count=5, photometric="RGB", dtype="float32")
    path = w.inputs / "reflectance.tif"
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.stack([blue, green, red, edge, nir]).astype("float32"))
    with rasterio.open(path) as ds:  # the precondition: the default labels are there
        assert list(ds.colorinterp[:3]) == [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
    return path


def ms_case(*extra: str):
    def prepare(w: Work) -> list[str]:
        return args(w, gpkg(w), f"rasters.multispectral={five_band(w)}", *extra)

    return prepare


def pixel_boxes(w: Work) -> tuple[list[dict], Path]:
    """Module 8's plant boxes in pixels of the orthophoto (copied beside them), as DeepForest rows."""
    ortho = w.copy("field/" + ORTHO)
    with rasterio.open(ortho) as ds:
        inv = ~ds.transform
    out = []
    for p in rows(w.artifacts / "plants" / "plants.csv"):
        c0, r0 = inv @ (float(p["xmin"]), float(p["ymax"]))
        c1, r1 = inv @ (float(p["xmax"]), float(p["ymin"]))
        out.append(
            {
                "image_path": ortho.name,
                "xmin": f"{c0:.4f}",
                "ymin": f"{r0:.4f}",
                "xmax": f"{c1:.4f}",
                "ymax": f"{r1:.4f}",
                "label": "plant",
            }
        )
    return out, ortho


def write_boxes(w: Work, table: list[dict], name: str = "boxes.csv") -> Path:
    path = w.inputs / name
    with open(path, "w", newline="") as fh:
        out = csv.DictWriter(fh, fieldnames=list(table[0]))
        out.writeheader()
        out.writerows(table)
    return path


def deepforest_csv(w: Work) -> list[str]:
    table, _ = pixel_boxes(w)
    return args(w, write_boxes(w, table))


def coco_on_ortho(w: Work) -> list[str]:
    table, ortho = pixel_boxes(w)
    with rasterio.open(ortho) as ds:
        size = {"width": ds.width, "height": ds.height}
    anns = [
        {
            "id": i + 1,
            "image_id": 1,
            "category_id": 1,
            "iscrowd": 0,
            "bbox": [
                float(r["xmin"]),
                float(r["ymin"]),
                float(r["xmax"]) - float(r["xmin"]),
                float(r["ymax"]) - float(r["ymin"]),
            ],
        }
        for i, r in enumerate(table)
    ]
    data = {
        "images": [{"id": 1, "file_name": ortho.name, **size}],
        "categories": [{"id": 1, "name": "plant"}],
        "annotations": anns,
    }
    path = w.inputs / "boxes_coco.json"
    path.write_text(json.dumps(data))
    return args(w, path)


def deepforest_broken(change):
    def prepare(w: Work) -> list[str]:
        table, ortho = pixel_boxes(w)
        return args(w, write_boxes(w, change(w, table, ortho)))

    return prepare


def image_missing(w, table, ortho):
    return [dict(r, image_path="ortho_tile_07.tif") for r in table]


def image_not_georeferenced(w, table, ortho):
    with rasterio.open(ortho) as src:
        data = src.read([1, 2, 3])
    png = w.inputs / "ortho_export.png"
    with rasterio.open(
        png, "w", driver="PNG", width=data.shape[2], height=data.shape[1], count=3, dtype="uint8"
    ) as dst:
        dst.write(data)
    return [dict(r, image_path=png.name) for r in table]


def boxes_outside(w, table, ortho):
    return [
        dict(r, xmin=str(float(r["xmin"]) + 50000), xmax=str(float(r["xmax"]) + 50000)) if i == 2 else r
        for i, r in enumerate(table)
    ]


def ids_repeat(w: Work) -> list[str]:
    gdf = gpd.read_file(w.artifacts / "plants" / "plants.gpkg")
    gdf["id"] = 7
    path = w.inputs / "plants_ids.gpkg"
    gdf.drop(columns=[c for c in ("plant_id",) if c in gdf.columns]).to_file(path, driver="GPKG")
    return args(w, path)


def to_wgs84(src_path: Path, dst_path: Path) -> Path:
    with rasterio.open(src_path) as src:
        t, wd, h = calculate_default_transform(src.crs, "EPSG:4326", src.width, src.height, *src.bounds)
        profile = src.profile
        profile.update(crs="EPSG:4326", transform=t, width=wd, height=h)
        for k in ("blockxsize", "blockysize", "tiled"):
            profile.pop(k, None)
        with rasterio.open(dst_path, "w", **profile) as dst:
            for b in range(1, src.count + 1):
                reproject(
                    rasterio.band(src, b), rasterio.band(dst, b), resampling=Resampling.nearest, dst_nodata=src.nodata
                )
    return dst_path


def dem_in_wgs84(w: Work) -> list[str]:
    dsm = to_wgs84(w.artifacts / "field" / DSM, w.inputs / "dsm_4326.tif")
    dtm = to_wgs84(w.artifacts / "field" / DTM, w.inputs / "dtm_4326.tif")
    return args(w, gpkg(w), dsm=dsm, dtm=dtm)


def ms_in_wgs84(w: Work) -> list[str]:
    ms = to_wgs84(w.artifacts / "field" / MS, w.inputs / "ms_4326.tif")
    return args(w, gpkg(w), f"rasters.multispectral={ms}")


# -- checks -------------------------------------------------------------------------------------------------------


def plant_boxes(w: Work, ids: list[str] | None = None) -> list:
    """Module 8's plant boxes (plants.csv), in file order or in the order of ``ids``."""
    by_id = {
        p["plant_id"]: shapely.box(float(p["xmin"]), float(p["ymin"]), float(p["xmax"]), float(p["ymax"]))
        for p in rows(w.artifacts / "plants" / "plants.csv")
    }
    return list(by_id.values()) if ids is None else [by_id[i] for i in ids]


def plant_polygons(w: Work, ids: list[str]) -> list:
    """Module 8's plant polygons (plants.gpkg, the file these cases give) in the order of ``ids``."""
    gdf = gpd.read_file(w.artifacts / "plants" / "plants.gpkg")
    by_id = dict(zip(gdf["plant_id"].astype(str), gdf.geometry.values))
    return [by_id[i] for i in ids]


def centre_values(path: Path, boxes, bands):
    """Per polygon, the valid values of ``bands`` at the pixels whose centre shapely finds inside (each
    polygon's bounding window of the raster only)."""
    with rasterio.open(path) as ds:
        data = [ds.read(b).astype(float) for b in bands]
        t, nodata = ds.transform, ds.nodata
    ok = np.all([(a != nodata) & np.isfinite(a) for a in data], axis=0)
    out = []
    for g in boxes:
        x0, y0, x1, y1 = g.bounds
        c0, r0 = ~t @ (x0, y1)
        c1, r1 = ~t @ (x1, y0)
        ca, cb = sorted((c0, c1))
        ra, rb = sorted((r0, r1))
        ca, ra = max(int(np.floor(ca)) - 1, 0), max(int(np.floor(ra)) - 1, 0)
        cb, rb = int(np.ceil(cb)) + 1, int(np.ceil(rb)) + 1
        cols, rws = np.meshgrid(np.arange(ca, min(cb, ok.shape[1])) + 0.5, np.arange(ra, min(rb, ok.shape[0])) + 0.5)
        xs, ys = t @ (cols, rws)
        inside = shapely.contains_xy(g, xs, ys) & ok[ra:rb, ca:cb]
        out.append([a[ra:rb, ca:cb][inside] for a in data])
    return out


def assert_ndvi_equals_numpy(got: list[dict], vals) -> None:
    """Each plant's ndvi_mean equals numpy's over its (red, nir) pixels; at least 5 plants with pixels."""
    checked = 0
    for r, (red, nir) in zip(got, vals):
        if red.size:
            assert math.isclose(float(r["ndvi_mean"]), float(np.mean((nir - red) / (nir + red))), rel_tol=1e-9)
            checked += 1
    assert checked >= 5


def ndvi_right(w: Work) -> None:
    """NDVI per plant equals numpy's over the field's red and NIR at the pixel centres inside its box."""
    got = rows(w.out / "stats.csv")
    vals = centre_values(w.artifacts / "field" / MS, plant_polygons(w, [r["plant_id"] for r in got]), [1, 2])
    assert_ndvi_equals_numpy(got, vals)


def chm_max_truth(w: Work, boxes) -> np.ndarray:
    """Per box, numpy's CHM (DSM - DTM of the field, UTM) maximum over the pixel centres inside; NaN where a
    pixel centre lies on the box's edge (either side is right after a round trip through pixels) or none."""
    with rasterio.open(w.artifacts / "field" / DSM) as a, rasterio.open(w.artifacts / "field" / DTM) as b:
        chm = a.read(1).astype(float) - b.read(1).astype(float)
        chm[(a.read(1) == a.nodata) | (b.read(1) == b.nodata)] = np.nan
        t = a.transform
    cols, rws = np.meshgrid(np.arange(chm.shape[1]) + 0.5, np.arange(chm.shape[0]) + 0.5)
    xs, ys = t @ (cols, rws)
    out = np.full(len(boxes), np.nan)
    for k, g in enumerate(boxes):
        x0, y0, x1, y1 = g.bounds
        inside = (xs > x0) & (xs < x1) & (ys > y0) & (ys < y1)
        on_edge = (
            (np.abs(xs - x0) < 1e-6) | (np.abs(xs - x1) < 1e-6) | (np.abs(ys - y0) < 1e-6) | (np.abs(ys - y1) < 1e-6)
        )
        near = (xs >= x0 - 1e-6) & (xs <= x1 + 1e-6) & (ys >= y0 - 1e-6) & (ys <= y1 + 1e-6)
        if inside.any() and not (on_edge & near).any() and not np.isnan(chm[inside]).all():
            out[k] = np.nanmax(chm[inside])
    return out


def heights_of_pixel_boxes(w: Work) -> None:
    """The boxes placed through the orthophoto's transform: each plant's CHM max equals numpy's over the map
    box of module 8, and ids are numbers (the 'label' column is a class)."""
    got = rows(w.out / "stats.csv")
    boxes = plant_boxes(w)
    assert [r["plant_id"] for r in got] == [str(i) for i in range(1, len(boxes) + 1)]
    want = chm_max_truth(w, boxes)
    have = np.array([float(r["chm_max"] or "nan") for r in got])
    ok = np.isfinite(want)
    assert ok.sum() >= 5 and np.allclose(have[ok], want[ok], atol=1e-6)
    with rasterio.open(w.artifacts / "field" / DSM) as ds:
        assert gpd.read_file(w.out / "stats.gpkg").crs.to_epsg() == ds.crs.to_epsg()


def numbered(w: Work) -> None:
    got = rows(w.out / "stats.csv")
    assert [r["plant_id"] for r in got] == [str(i) for i in range(1, len(got) + 1)]


def heights_in_metres(w: Work) -> None:
    """DSM and DTM in degrees: heights as from the UTM rasters (within the warp's nearest-neighbour
    resampling), canopy areas in m2 (at most the box's area, not square degrees)."""
    got = rows(w.out / "stats.csv")
    boxes = plant_boxes(w, [r["plant_id"] for r in got])
    want = chm_max_truth(w, boxes)
    have = np.array([float(r["chm_max"] or "nan") for r in got])
    ok = np.isfinite(want) & np.isfinite(have)
    assert ok.sum() >= 5 and np.median(np.abs(have[ok] - want[ok])) < 0.02, (have, want)
    area = np.array([float(r["canopy_area_m2"] or "nan") for r in got])
    box_area = np.array([g.area for g in boxes])
    fine = np.isfinite(area)
    assert fine.sum() >= 5 and np.all(area[fine] > 0.05 * box_area[fine]) and np.all(area[fine] <= 1.3 * box_area[fine])
    assert gpd.read_file(w.out / "outlines.gpkg").crs.is_projected


def ndvi_in_degrees(w: Work) -> None:
    """A multispectral raster in degrees: NDVI per plant equals numpy's over that file's own pixels whose
    centres lie in the plant's box reprojected to degrees (no resampling)."""
    got = rows(w.out / "stats.csv")
    with rasterio.open(w.artifacts / "field" / DSM) as ds:
        crs = ds.crs
    boxes = gpd.GeoSeries(plant_polygons(w, [r["plant_id"] for r in got]), crs=crs).to_crs(4326).values
    vals = centre_values(w.inputs / "ms_4326.tif", boxes, [1, 2])
    assert_ndvi_equals_numpy(got, vals)


CASES = [
    Case(
        "m9-ms-5band-generic-writer-right-numbers",
        "spatial_stat_extractor",
        ms_case("rasters.red_band=3", "rasters.nir_band=5"),
        expect="ok",
        check=ndvi_right,
    ),
    Case(
        "m9-ms-5band-band-order",
        "spatial_stat_extractor",
        ms_case(f"rasters.band_order={ORDER}"),
        expect="ok",
        check=ndvi_right,
    ),
    Case(
        "m9-ms-5band-bands-not-named",
        "spatial_stat_extractor",
        ms_case(),
        mentions=("reflectance.tif", "red_band", "band_order"),
    ),
    Case(
        "m9-ms-band-order-too-short",
        "spatial_stat_extractor",
        ms_case("rasters.band_order=[blue,green,red,nir]"),
        mentions=("reflectance.tif", "band_order", "has 5"),
    ),
    Case(
        "m9-ms-band-order-contradicts-red-band",
        "spatial_stat_extractor",
        ms_case(f"rasters.band_order={ORDER}", "rasters.red_band=1"),
        mentions=("reflectance.tif", "red_band = 1", "set red_band: 3"),
    ),
    Case(
        "m9-ms-red-band-name-unknown",
        "spatial_stat_extractor",
        ms_case(f"rasters.band_order={ORDER}", "rasters.red_band=redd"),
        mentions=("red_band", "'redd'"),
    ),
    Case(
        "m9-ms-band-order-name-twice",
        "spatial_stat_extractor",
        ms_case("rasters.band_order=[red,green,red,rededge,nir]"),
        mentions=("band_order", "more than once"),
    ),
    Case(
        "m9-deepforest-csv-on-the-orthophoto",
        "spatial_stat_extractor",
        deepforest_csv,
        expect="ok",
        check=heights_of_pixel_boxes,
    ),
    Case(
        "m9-coco-boxes-on-the-orthophoto",
        "spatial_stat_extractor",
        coco_on_ortho,
        expect="ok",
        check=heights_of_pixel_boxes,
    ),
    Case(
        "m9-deepforest-image-missing",
        "spatial_stat_extractor",
        deepforest_broken(image_missing),
        mentions=("boxes.csv", "ortho_tile_07.tif", "boxes_image"),
    ),
    Case(
        "m9-deepforest-image-not-georeferenced",
        "spatial_stat_extractor",
        deepforest_broken(image_not_georeferenced),
        mentions=("ortho_export.png", "no crs"),
    ),
    Case(
        "m9-deepforest-box-outside-the-image",
        "spatial_stat_extractor",
        deepforest_broken(boxes_outside),
        mentions=("boxes.csv", "outside the image", "line 4"),
    ),
    Case(
        "m9-id-column-repeats-fix-is-number",
        "spatial_stat_extractor",
        ids_repeat,
        mentions=("plants_ids.gpkg", "not unique", "id_column: number"),
    ),
    Case(
        "m9-id-column-number",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), "id_column=number"),
        expect="ok",
        check=numbered,
    ),
    Case("m9-dsm-dtm-in-wgs84", "spatial_stat_extractor", dem_in_wgs84, expect="ok", check=heights_in_metres),
    Case("m9-multispectral-in-wgs84", "spatial_stat_extractor", ms_in_wgs84, expect="ok", check=ndvi_in_degrees),
]
