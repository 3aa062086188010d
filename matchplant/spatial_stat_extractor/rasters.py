"""Module 9's rasters in: each :class:`~matchplant.spatial_stat_extractor.config.Layer` as a source
that :func:`~matchplant.spatial_stat_extractor.zonal.zonal_stats` reads window by window, and a
reduced-resolution preview for the window.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.enums import Resampling
from rasterio.vrt import WarpedVRT

from matchplant.core.errors import InputError
from matchplant.core.log import get_logger
from matchplant.spatial_stat_extractor.config import Layer
from matchplant.spatial_stat_extractor.zonal import DifferenceSource, NDVISource, RasterFileSource, pyproj_crs

log = get_logger("stats")

ODM_NODATA = -9999.0  # ODM's DEM nodata, masked on elevation rasters even when the file does not declare it


def _open(path: Path, stack: contextlib.ExitStack):
    path = Path(path)
    if not path.is_file():
        raise InputError("raster not found", path=path, fix="check the raster paths in your config")
    try:
        return stack.enter_context(rasterio.open(path))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"cannot read the raster: {exc}", path=path, fix="give a GeoTIFF") from exc


def _band(ds, band: int, layer: Layer, nodata: float | None) -> RasterFileSource:
    if not 1 <= band <= ds.count:
        raise InputError(f"{layer.name}: band {band} asked for, but the raster has {ds.count} band(s)",
                         path=ds.name, fix="set the band number (1 = first band)")
    extra = [ODM_NODATA] if layer.elevation else []
    if nodata is not None:
        extra.append(nodata)
    return RasterFileSource(ds, band, extra_nodata=extra)


def open_layer(layer: Layer, stack: contextlib.ExitStack, nodata: float | None = None):
    """A raster source (``transform, width, height, crs, read()``) for a layer; files stay open in ``stack``."""
    if layer.kind == "band":
        return _band(_open(layer.paths[0], stack), layer.bands[0], layer, nodata)
    if layer.kind == "ndvi":
        ds = _open(layer.paths[0], stack)
        return NDVISource(_band(ds, layer.bands[0], layer, nodata), _band(ds, layer.bands[1], layer, nodata))
    dsm = _open(layer.paths[0], stack)
    dtm = _open(layer.paths[1], stack)
    if (dsm.crs and dtm.crs and dsm.crs != dtm.crs) or dsm.transform != dtm.transform \
            or dsm.shape != dtm.shape:
        # put the DTM on the DSM's grid (ODM writes them on one grid; other tools may not)
        log.info("DTM %s is on another grid than the DSM; resampling it (bilinear) onto the DSM grid",
                 Path(layer.paths[1]).name)
        dtm = stack.enter_context(WarpedVRT(dtm, crs=dsm.crs or dtm.crs, transform=dsm.transform,
                                            width=dsm.width, height=dsm.height, resampling=Resampling.bilinear))
    return DifferenceSource(_band(dsm, 1, layer, nodata), _band(dtm, 1, layer, nodata))



def preview_layer(layer: Layer, max_side: int = 800, nodata: float | None = None):
    """The layer at reduced resolution (at most ``max_side`` pixels a side), for a quick look: rasterio
    reads overviews or decimates while reading, so the full raster is never in memory.
    Returns ``(array with NaN holes, extent (left, right, bottom, top), crs)``."""
    with contextlib.ExitStack() as stack:
        ds = _open(layer.paths[0], stack)
        scale = max(ds.width, ds.height) / max_side
        h, w = (ds.height, ds.width) if scale <= 1 else (max(int(ds.height / scale), 1), max(int(ds.width / scale), 1))

        def small(dataset, band):
            src = _band(dataset, band, layer, nodata)
            arr = dataset.read(band, out_shape=(h, w), resampling=Resampling.nearest).astype(float)
            for v in src.nodata:
                arr[arr == v] = np.nan
            return arr

        if layer.kind == "band":
            arr = small(ds, layer.bands[0])
        elif layer.kind == "ndvi":
            red, nir = small(ds, layer.bands[0]), small(ds, layer.bands[1])
            with np.errstate(invalid="ignore", divide="ignore"):
                arr = np.where(nir + red != 0, (nir - red) / (nir + red), np.nan)
        else:
            dtm = _open(layer.paths[1], stack)
            arr = small(ds, 1) - (small(dtm, 1) if dtm.shape == ds.shape else np.nan)
        t: Affine = ds.transform
        b = rasterio.transform.array_bounds(ds.height, ds.width, t)
        return arr, (b[0], b[2], b[1], b[3]), pyproj_crs(ds.crs)
