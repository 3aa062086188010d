"""Module 9's CHM checked before any work (issue 39): a CHM of one value everywhere (all zeros, DSM given as the
DTM) and a CHM whose CRS says feet (horizontal or vertical) are errors naming the file, the key, what was found and
the fix; a CHM of zeros with one small plant, or in metres with a vertical CRS in metres, is not; any other raster
in a feet CRS is read on a metric grid."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import rasterio
import rasterio.crs
from affine import Affine
from odm_builder import Raster, write_raster

from matchplant.core.runtime.errors import InputError
from matchplant.spatial_stat_extractor.config import RasterSet
from matchplant.spatial_stat_extractor.inputs import Layer, check_elevation, not_metres, open_layer

UTM = "EPSG:32614"
T = Affine(0.01, 0, 500000.0, 0, -0.01, 4500000.0)
FT = 0.3048006096012192


def write(path, data, crs=UTM, transform=T):
    write_raster(path, Raster(data.astype("float32"), transform), crs, nodata=-9999)
    return path


def field(shape=(300, 400), seed=0):
    rng = np.random.default_rng(seed)
    chm = 0.015 + 0.03 * rng.standard_normal(shape)
    chm[100:140, 100:140] += 0.5  # a plant
    chm[:3, :3] = -9999  # nodata
    return chm


def test_a_chm_of_one_value_is_named_before_work(tmp_path):
    zero = write(tmp_path / "chm_zero.tif", np.where(field() == -9999, -9999, 0.0))
    with pytest.raises(InputError) as e:
        check_elevation([RasterSet(chm=zero)])
    text = str(e.value)
    assert "chm_zero.tif" in text and "0 everywhere" in text and "rasters.chm" in text and "'low'" in text
    dsm = write(tmp_path / "dsm.tif", 350 + field())
    copy = write(tmp_path / "dtm.tif", 350 + field())  # the DSM again, given as the DTM
    with pytest.raises(InputError) as e:
        check_elevation([RasterSet(chm=write(tmp_path / "ok.tif", field())), RasterSet(date="d2", dsm=dsm, dtm=copy)])
    text = str(e.value)
    assert "same surface" in text and "more_dates (date 'd2').dsm and more_dates (date 'd2').dtm" in text
    check_elevation([RasterSet(dsm=dsm, dtm=write(tmp_path / "dtm_real.tif", 350 + field() * 0))])  # a real CHM


def test_zeros_with_one_small_plant_are_a_chm(tmp_path):
    """The quick read skips most pixels of a large raster; one small plant it misses still makes a CHM."""
    chm = np.zeros((2100, 2100))
    chm[1000:1002, 1000:1002] = 0.3  # 2 x 2 px: between the decimated read's pixels (every 4th, from the 3rd)
    path = write(tmp_path / "sparse.tif", chm)
    with rasterio.open(path) as ds:
        quick = ds.read(1, out_shape=(525, 525))
    assert np.ptp(quick) == 0  # the quick read alone would call it constant
    check_elevation([RasterSet(chm=path)])


def test_a_chm_in_feet_is_named_with_its_unit(tmp_path):
    chm = field()
    epsg = 32614
    vertical = write(tmp_path / "chm_v.tif", chm / FT, rasterio.crs.CRS.from_user_input(f"EPSG:{epsg}+6360"))
    proj4 = "+proj=utm +zone=14 +datum=WGS84 +units=us-ft +no_defs"
    horizontal = write(tmp_path / "chm_h.tif", chm / FT, rasterio.crs.CRS.from_proj4(proj4), Affine.scale(1 / FT) @ T)
    for path, axes in ((vertical, "Gravity-related height"), (horizontal, "Easting, Northing")):
        with pytest.raises(InputError) as e:
            check_elevation([RasterSet(chm=path)])
        text = str(e.value)
        assert path.name in text and "rasters.chm" in text and f"US survey foot ({axes})" in text
        assert "0.3048" in text and "gdalwarp" in text
    in_metres = write(tmp_path / "chm_m.tif", chm, rasterio.crs.CRS.from_user_input(f"EPSG:{epsg}+5703"))
    check_elevation([RasterSet(chm=in_metres)])  # NAVD88 height in metres: fine
    assert not_metres(rasterio.crs.CRS.from_user_input("EPSG:4326")) == ""  # degrees: warped where read


def test_another_raster_in_feet_is_read_on_a_metric_grid(tmp_path):
    """A band raster in a projected CRS in feet (its values are no heights): warped onto metres like one in
    degrees, its pixel size the file's in metres."""
    proj4 = "+proj=utm +zone=14 +datum=WGS84 +units=us-ft +no_defs"
    path = write(tmp_path / "ms_ft.tif", field(), rasterio.crs.CRS.from_proj4(proj4), Affine.scale(1 / FT) @ T)
    with contextlib.ExitStack() as stack:
        src = open_layer(Layer("band1", "band", (path,)), stack)
        assert not_metres(src.crs) == "" and src.crs.is_projected
        assert abs(src.transform.a) == pytest.approx(0.01, rel=1e-3)


def test_each_raster_is_checked_once_per_version(tmp_path, monkeypatch):
    """The units check and every later opening of a CHM (box statistics, outlines, plots) share one check of its
    sampled blocks per file version; a file rewritten since is checked again."""
    from matchplant.core.runtime import validate_gis

    seen = []
    real = validate_gis.check_raster
    monkeypatch.setattr(validate_gis, "check_raster", lambda path, **kw: seen.append(path.name) or real(path, **kw))
    dsm, dtm = write(tmp_path / "dsm.tif", 350 + field()), write(tmp_path / "dtm.tif", 350 + field() * 0)
    check_elevation([RasterSet(dsm=dsm, dtm=dtm)])
    for _ in range(3):
        with contextlib.ExitStack() as stack:
            open_layer(Layer("chm", "difference", (dsm, dtm), elevation=True), stack)
    assert sorted(seen) == ["dsm.tif", "dtm.tif"]
    write(dsm, 351 + field(seed=1))  # a new version of the DSM
    check_elevation([RasterSet(dsm=dsm, dtm=dtm)])
    assert sorted(seen) == ["dsm.tif", "dsm.tif", "dtm.tif"]
