"""Module 8's DSM as users export it: in another CRS, with heights in feet, pixel-is-point, other nodata values.
Each gives the plants the demo field's own DSM gives (the boxes on the original photos, through ODM, Metashape and
Pix4D projects), or is refused by name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import rasterio
from PIL import Image
from pyproj import CRS, Transformer
from rasterio.warp import Resampling, calculate_default_transform, reproject

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.projects import open_project
from matchplant.core.geometry.units import height_unit, metric_heights
from matchplant.core.runtime.errors import GeometryError, InputError
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.views import project_predictions

FINE = 2  # the warped DSMs' cells: the demo's 4 mm cell / FINE
FT = 0.3048  # metres per international foot (exact by definition)


@pytest.fixture(scope="module")
def exports(tiny_field, camera_exports):
    """The tiny field's ODM poses as a Metashape camera export and a Pix4D params folder, and the raw boxes."""
    out = camera_exports
    ds = read_dataset(tiny_field.boxes_raw, validate=False)
    preds = {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }
    return {"metashape": out / "meta" / "cameras.xml", "pix4d": out / "p4d", "preds": preds, "dir": out}


def _dsm(field):
    return field.root / "odm_dem" / "dsm.tif"


def _warp(src_path, dst_path, crs: str, fine: float = FINE):
    """The DSM warped to ``crs`` on a grid ``fine`` times finer (bilinear), ODM's nodata outside."""
    with rasterio.open(src_path) as src:
        t, w, h = calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds, resolution=src.transform.a / fine
        )
        a = np.full((h, w), -9999.0, np.float32)
        reproject(rasterio.band(src, 1), a, dst_transform=t, dst_crs=crs, resampling=Resampling.bilinear)
        profile = dict(src.profile, crs=crs, transform=t, width=w, height=h)
    with rasterio.open(dst_path, "w", **profile) as dst:
        dst.write(a, 1)
    return dst_path


def _rewrite(src_path, dst_path, scale: float = 1.0, unit: str | None = None, crs=None, tags=None, nodata=None):
    """The DSM written again: heights x ``scale``, a band unit, a CRS, tags, holes as ``nodata``."""
    with rasterio.open(src_path) as src:
        a, profile = src.read(1), dict(src.profile)
    holes = a <= -9999
    a = (a.astype(np.float64) * scale).astype(np.float32)
    if nodata is not None:
        profile["nodata"] = nodata
        a[holes] = nodata
    if crs is not None:
        profile["crs"] = crs
    with rasterio.open(dst_path, "w", **profile) as dst:
        if tags:
            dst.update_tags(**tags)
        if unit:
            dst.set_band_unit(1, unit)
        dst.write(a, 1)
    return dst_path


def _hits(views, crs=None):
    """Every outline ray's hit (N, P, 3), back in the demo's CRS (EPSG:32614) when ``crs`` is given."""
    p = views.outlines()
    if crs is None:
        return p
    back = Transformer.from_crs(CRS(crs).to_3d(), CRS("EPSG:32614").to_3d(), always_xy=True)
    return np.stack(back.transform(p[..., 0], p[..., 1], p[..., 2]), axis=-1)


def _odm(field, exports, dsm):
    settings = dataclasses.replace(ProjectionSettings.from_config(), dsm=dsm)
    return project_predictions(ODMProject(field.root), exports["preds"], settings)


@pytest.mark.parametrize("program, crs", [("metashape", "EPSG:3857"), ("pix4d", "EPSG:32615")])
def test_dsm_in_another_crs_gives_the_same_plants(tiny_field, exports, tmp_path, program, crs):
    """The DSM warped to Web Mercator or the next UTM zone (2 mm bilinear grid): the cameras are converted to its
    CRS exactly and the hits, converted back, agree with the original DSM's as closely as the same resampling in
    the original CRS allows (the control): the warp changes the surface only where bilinear-of-bilinear rounds the
    plants' edges (the 4 mm cell's kinks), so the median hit moves 0.01 mm and a ray grazing a plant's edge may
    fall on the other side of it (the 1% beyond 1 cm, up to the plant's height x the ray's tangent)."""
    ref, _ = project_predictions(open_project(exports[program], program, dsm=_dsm(tiny_field)), exports["preds"])
    control = _warp(_dsm(tiny_field), tmp_path / "same_crs.tif", "EPSG:32614")
    warped = _warp(_dsm(tiny_field), tmp_path / "other_crs.tif", crs)
    for dsm, dsm_crs in ((control, None), (warped, crs)):
        got, rejected = project_predictions(open_project(exports[program], program, dsm=dsm), exports["preds"])
        assert len(rejected) == 0 and len(got.table) == len(ref.table)
        assert CRS(got.crs).equals(CRS(dsm_crs or "EPSG:32614"))  # the plants come out in the DSM's CRS
        d = np.linalg.norm(_hits(got, dsm_crs) - ref.outlines(), axis=-1)
        assert np.median(d) < 1e-4 and (d < 0.01).mean() >= 0.99, (np.median(d), (d < 0.01).mean())
        if dsm_crs is None:
            within = (d < 0.01).mean()
        else:  # the conversion adds nothing to the resampling's own error
            assert (d < 0.01).mean() >= within - 0.005


def test_odm_refuses_a_dsm_in_another_crs(tiny_field, exports, tmp_path):
    """An ODM project's DSM must be in the reconstruction's CRS: another is named, with the fix."""
    warped = _warp(_dsm(tiny_field), tmp_path / "other_crs.tif", "EPSG:32615", fine=1)
    with pytest.raises(InputError, match="the DSM is in EPSG:32615 but the reconstruction in") as err:
        _odm(tiny_field, exports, warped)
    assert str(warped) in str(err.value) and "reproject it" in str(err.value)


def test_dsm_in_feet(tiny_field, exports, tmp_path):
    """Heights in feet whose file says so (the band's unit type) are converted to metres: the same hits as the
    metres DSM to float32 rounding (350 m in float32: 3e-5 m, twice); without a unit, a DSM whose heights lie above
    the cameras is refused, naming feet."""
    ref, _ = _odm(tiny_field, exports, _dsm(tiny_field))
    feet = _rewrite(_dsm(tiny_field), tmp_path / "dsm_ft.tif", scale=1 / FT, unit="ft")
    with rasterio.open(feet) as src:
        assert src.units == ("ft",) and height_unit(src.crs, src.units[0]) == (FT, "foot")
    got, rejected = _odm(tiny_field, exports, feet)
    assert len(rejected) == 0 and len(got.table) == len(ref.table)
    d = np.linalg.norm(got.outlines() - ref.outlines(), axis=-1)
    assert np.median(d) < 1e-4 and (d < 0.01).mean() >= 0.995, (np.median(d), (d < 0.01).mean())
    unnamed = _rewrite(_dsm(tiny_field), tmp_path / "dsm_ft_unnamed.tif", scale=1 / FT)
    with pytest.raises(InputError, match="lies above every camera.*feet, read as metres") as err:
        _odm(tiny_field, exports, unnamed)
    assert str(unnamed) in str(err.value) and "gdal_edit.py -units ft" in str(err.value)


def test_compound_crs_heights_in_feet():
    """A compound CRS's vertical unit is read from it (US survey foot: 1200/3937 m); the rays' CRS is the same
    CRS with heights in metres (PROJ converts between the two by the unit alone); a vertical datum whose geoid
    grid PROJ lacks is refused by name, not shifted by a ballpark."""
    ftus = CRS("EPSG:32614+6360")  # UTM 14N + NAVD88 height (ftUS)
    factor, unit = height_unit(ftus, None)
    assert factor == pytest.approx(1200 / 3937, rel=1e-15) and unit == "US survey foot"
    metric = metric_heights(ftus)
    assert metric.axis_info[2].unit_name == "metre" and metric_heights(CRS("EPSG:32614")) == CRS("EPSG:32614")
    x, y, z = Transformer.from_crs(ftus, metric, always_xy=True).transform(702461.0, 4519327.0, 1000.0)
    assert (x, y) == pytest.approx((702461.0, 4519327.0), abs=1e-6) and z == pytest.approx(1000 * 1200 / 3937)
    from matchplant.core.geometry.geodetic import map_transformer

    try:
        t = map_transformer(CRS("EPSG:4979"), metric, what="test")
    except GeometryError as err:  # no geoid grid installed (the usual case): named
        assert "ballpark" in str(err) and "us_noaa_geoid" in str(err)
    else:  # the grid is installed: the exact conversion, never a ballpark one
        assert "ballpark" not in t.description


def test_pixel_is_point_dsm(tiny_field, exports, tmp_path):
    """A DSM written pixel-is-point (GeoTIFF RasterPixelIsPoint, AREA_OR_POINT=Point) stores the first pixel's
    centre as its tie point; GDAL shifts it back by half a pixel when reading, and the plants are those of the
    pixel-is-area file to the bit (the shift made once, not twice)."""
    point = _rewrite(_dsm(tiny_field), tmp_path / "dsm_point.tif", tags={"AREA_OR_POINT": "Point"})
    with rasterio.open(_dsm(tiny_field)) as src:
        t = src.transform
    tags = Image.open(point).tag_v2  # the file itself, read without GDAL
    keys = tags[34735]
    raster_type = keys[keys.index(1025, 4) + 3]  # GTRasterTypeGeoKey: 1 area, 2 point
    assert raster_type == 2
    assert tags[33922][3:5] == pytest.approx((t.c + t.a / 2, t.f + t.e / 2), abs=1e-6)
    with rasterio.open(point) as src:
        assert src.tags()["AREA_OR_POINT"] == "Point" and src.transform.almost_equals(t)
    ref, _ = _odm(tiny_field, exports, _dsm(tiny_field))
    got, _ = _odm(tiny_field, exports, point)
    np.testing.assert_array_equal(got.outlines(), ref.outlines())
    got, _ = project_predictions(open_project(exports["pix4d"], "pix4d", dsm=point), exports["preds"])
    pix, _ = project_predictions(open_project(exports["pix4d"], "pix4d", dsm=_dsm(tiny_field)), exports["preds"])
    np.testing.assert_array_equal(got.outlines(), pix.outlines())


def test_dsm_nodata_values(tiny_field, exports, tmp_path):
    """Holes marked by the file's nodata value (here -32768, and NaN) are holes as ODM's -9999 is: a square
    hole under the plants gives the same rays reported and the same hits whatever marks it."""
    with rasterio.open(_dsm(tiny_field)) as src:
        a = src.read(1)
    h, w = a.shape
    a[h // 3 : h // 2, w // 3 : w // 2] = -9999.0  # a hole under some plants
    holed = tmp_path / "holed.tif"
    with rasterio.open(_dsm(tiny_field)) as src, rasterio.open(holed, "w", **src.profile) as dst:
        dst.write(a, 1)
    ref, ref_rejected = _odm(tiny_field, exports, holed)
    assert len(ref_rejected) > 0  # the hole is under plants: some boxes are reported, not placed
    for nodata in (-32768.0, np.nan):
        other = _rewrite(holed, tmp_path / f"holed_{nodata}.tif", nodata=nodata)
        got, rejected = _odm(tiny_field, exports, other)
        assert rejected["reason"].tolist() == ref_rejected["reason"].tolist()
        np.testing.assert_array_equal(got.outlines(), ref.outlines())
