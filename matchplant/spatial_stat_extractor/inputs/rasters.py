"""Rasters in: each :class:`~matchplant.spatial_stat_extractor.inputs.layer.Layer` as a source
that :func:`~matchplant.spatial_stat_extractor.zonal.engine.zonal_stats` reads window by window, and a
reduced-resolution preview for the window.

A raster in degrees (EPSG:4326, as many LAI/NDVI products and GIS exports are): box statistics reproject the
plants to it (exact: the file's own pixels); for outlines and canopy statistics it is read through a warp onto
a metric grid (the plants' CRS when that is projected, else the raster's UTM zone), nearest neighbour at its
own resolution: pixel values stay the file's, and canopy areas, margins and shifts are in metres, never in
square degrees.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.enums import ColorInterp, Resampling
from rasterio.vrt import WarpedVRT
from rasterio.warp import transform_bounds

from matchplant.core.geometry.frames import utm_crs_for
from matchplant.core.geometry.units import not_metres
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate_gis import check_raster_once
from matchplant.spatial_stat_extractor.inputs.bands import (
    band_names,
    check_bands,
    file_name,
    pick_band,
)
from matchplant.spatial_stat_extractor.inputs.indices import FormulaSource, parse_formula
from matchplant.spatial_stat_extractor.inputs.layer import Layer
from matchplant.spatial_stat_extractor.inputs.sources import (
    ArraySource,
    DifferenceSource,
    NDVISource,
    RasterFileSource,
    pyproj_crs,
)

log = get_logger("spatial_stat_extractor")

ODM_NODATA = -9999.0  # ODM's DEM nodata, masked on elevation rasters even when the file does not declare it


def _open(path: Path, stack: contextlib.ExitStack, metric_crs=None, warp: bool = True):
    """The raster, open in ``stack``; with ``warp``, one in degrees is seen through a warp onto a metric grid
    (``metric_crs`` when it is projected, else the raster's UTM zone)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("raster not found", path=path, fix="check the raster paths in your config")
    try:
        ds = stack.enter_context(rasterio.open(path))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"cannot read the raster: {exc}", path=path, fix="give a GeoTIFF") from exc
    if warp and ds.crs is not None and (ds.crs.is_geographic or not_metres(ds.crs)):
        return _in_metres(ds, stack, metric_crs)
    return ds


def _in_metres(ds, stack: contextlib.ExitStack, metric_crs=None):
    """A raster in degrees (or a projected CRS in feet: its values are not heights, checked apart) warped
    (nearest neighbour, its own resolution) onto a metric grid."""
    if metric_crs is not None and (not getattr(metric_crs, "is_projected", False) or not_metres(metric_crs)):
        metric_crs = None
    if metric_crs is None:
        west, south, east, north = transform_bounds(ds.crs, "EPSG:4326", *ds.bounds)
        metric_crs = utm_crs_for((west + east) / 2, (south + north) / 2)
    target = rasterio.crs.CRS.from_wkt(metric_crs.to_wkt()) if hasattr(metric_crs, "to_wkt") else metric_crs
    nodata = ds.nodata
    if nodata is None:  # cells outside the file's footprint must not read as 0
        nodata = np.nan if np.issubdtype(np.dtype(ds.dtypes[0]), np.floating) else np.iinfo(ds.dtypes[0]).max
    vrt = stack.enter_context(WarpedVRT(ds, crs=target, resampling=Resampling.nearest, nodata=nodata))
    key = (ds.name, str(target))
    if key not in _warned:
        _warned.add(key)
        log.info(
            "%s is in %s (%s); read on a %.3g m grid in %s (nearest neighbour), so that areas and "
            "distances are in metres",
            Path(ds.name).name,
            "degrees" if ds.crs.is_geographic else not_metres(ds.crs),
            ds.crs.to_string(),
            abs(vrt.transform.a),
            pyproj_crs(target).name,
        )
    return vrt


_warned: set = set()


def _band(ds, band: int, layer: Layer, nodata: float | None, key: str = "band", check: bool = True) -> RasterFileSource:
    """Band ``band`` (config key ``key``) of ``ds``; with ``check``, a band of only nodata/NaN is an error."""
    if not 1 <= band <= ds.count:
        raise InputError(
            f"{layer.name}: {key} = {band}, but the raster has {ds.count} band(s), no band {band}",
            path=ds.name,
            fix=f"set {key} to a band number from 1 to {ds.count} (1 = first band)",
        )
    # a raster that is all nodata/NaN in this band is named here, not found out as "0 plants with values"
    if check:
        check_raster_once(file_name(ds), band, f"{layer.name} raster")
    extra = [ODM_NODATA] if layer.elevation else []
    if nodata is not None:
        extra.append(nodata)
    return RasterFileSource(ds, band, extra_nodata=extra)


def open_layer(layer: Layer, stack: contextlib.ExitStack, nodata: float | None = None, crs=None, warp: bool = True):
    """A raster source (``transform, width, height, crs, read()``) for a layer; files stay open in ``stack``.
    A raster in degrees is warped onto a metric grid (``crs``, the plants' CRS, when it is projected; else its
    UTM zone), as outlines need; ``warp=False`` leaves it in degrees (box statistics, with the polygons
    reprojected to it, exact)."""
    if layer.kind == "band":
        ds = _open(layer.paths[0], stack, crs, warp)
        key = "band" if layer.name == "chm" else f"band of '{layer.name}' (bands)"
        band = layer.bands[0]
        if isinstance(band, str):
            band = pick_band(ds, band_names(ds, layer.band_order), band, band, key)
        return _band(ds, band, layer, nodata, key=key)
    if layer.kind == "ndvi":
        ds = _open(layer.paths[0], stack, crs, warp)
        red, nir = ndvi_bands(ds, layer)
        return NDVISource(_band(ds, red, layer, nodata, key="red_band"), _band(ds, nir, layer, nodata, key="nir_band"))
    if layer.kind == "formula":
        return _formula(_open(layer.paths[0], stack, crs, warp), layer, nodata)
    dsm = _open(layer.paths[0], stack, crs, warp)
    dtm = _open(layer.paths[1], stack, warp=False)  # put on the DSM's grid below, whatever its CRS
    _check_overlap(dsm, dtm)
    check_raster_once(dtm.name, 1, f"{layer.name} DTM")
    if (dsm.crs and dtm.crs and dsm.crs != dtm.crs) or dsm.transform != dtm.transform or dsm.shape != dtm.shape:
        # put the DTM on the DSM's grid (ODM writes them on one grid; other tools may not)
        log.info(
            "DTM %s is on another grid than the DSM; resampling it (bilinear) onto the DSM grid",
            Path(layer.paths[1]).name,
        )
        dtm = stack.enter_context(
            WarpedVRT(
                dtm,
                crs=dsm.crs or dtm.crs,
                transform=dsm.transform,
                width=dsm.width,
                height=dsm.height,
                resampling=Resampling.bilinear,
            )
        )
    return DifferenceSource(_band(dsm, 1, layer, nodata), _band(dtm, 1, layer, nodata, check=False))


def ndvi_bands(ds, layer: Layer) -> tuple[int, int]:
    """The red and NIR band numbers of an NDVI layer: as configured (numbers or names), or named by band_order
    or the raster's band descriptions; a 2-band raster with neither is red, NIR (said in the log)."""
    names = band_names(ds, layer.band_order)
    red, nir = layer.bands
    if (red is None or nir is None) and ds.count == 2 and not names.roles:
        log.info(
            "%s: 2 bands, not named; %s (set red_band/nir_band or band_order if not)",
            Path(file_name(ds)).name,
            " and ".join(f"{k} = {v}" for k, v, g in (("red_band", 1, red), ("nir_band", 2, nir)) if g is None),
        )
        red, nir = 1 if red is None else red, 2 if nir is None else nir
    red = pick_band(ds, names, "red", red, "red_band")
    nir = pick_band(ds, names, "nir", nir, "nir_band")
    if red == nir:
        raise InputError(
            f"red_band and nir_band are both band {red}",
            path=file_name(ds),
            fix="set band_order (every band's name in file order) or red_band and nir_band",
        )
    check_bands(ds, names, {"red": red, "nir": nir}, {"red": "red_band", "nir": "nir_band"})
    return red, nir


def _check_overlap(dsm, dtm) -> None:
    """The DTM must cover some of the DSM (same field), whatever its grid."""
    a = dsm.bounds
    b = dtm.bounds
    if dsm.crs and dtm.crs and dsm.crs != dtm.crs:
        b = transform_bounds(dtm.crs, dsm.crs, *b)
    if b[0] >= a[2] or b[2] <= a[0] or b[1] >= a[3] or b[3] <= a[1]:
        raise InputError(
            f"the DTM does not overlap the DSM {Path(dsm.name).name} (DSM bounds "
            f"{tuple(round(v, 1) for v in a)}, DTM bounds {tuple(round(v, 1) for v in b)})",
            path=dtm.name,
            fix="give the DTM of the same field and flight as the DSM",
        )


def raster_crs(date_sets) -> tuple[object, Path] | tuple[None, None]:
    """The CRS of the first raster of ``date_sets`` that declares one, and that raster's path."""
    for s in date_sets:
        for layer in s.layers():
            for path in layer.paths:
                with contextlib.ExitStack() as stack:
                    ds = _open(path, stack, warp=False)
                    if ds.crs is not None:
                        return pyproj_crs(ds.crs), Path(path)
    return None, None


def _formula(ds, layer: Layer, nodata: float | None) -> FormulaSource:
    """An RGB index (layer.bands = red, green, blue) or a user's formula over b1..bN."""
    alpha = next((i + 1 for i, c in enumerate(ds.colorinterp) if c == ColorInterp.alpha), None)
    alpha_src = _band(ds, alpha, layer, None, check=False) if alpha is not None and alpha not in layer.bands else None
    names = band_names(ds, layer.band_order)
    if len(layer.bands) == 3:
        check_bands(
            ds,
            names,
            dict(zip(("red", "green", "blue"), layer.bands)),
            {"red": "rgb_bands[0] (red)", "green": "rgb_bands[1] (green)", "blue": "rgb_bands[2] (blue)"},
            order_key=bool(layer.band_order),
        )
        names = {"R", "G", "B", "r", "g", "b"}
        tree = parse_formula(layer.expression, names, f"index '{layer.name}'")
        bands = {
            c: _band(ds, b, layer, nodata, key=f"rgb_bands[{i}]") for i, (c, b) in enumerate(zip("RGB", layer.bands))
        }
        return FormulaSource(tree, bands, chromatic=True, alpha=alpha_src)
    numbers = {f"b{i}": i for i in range(1, ds.count + 1)}
    if names.source == "band_order":  # the user's names for the bands, beside b1..bN
        numbers.update({name: b for b, name in names.roles.items()})
    tree = parse_formula(
        layer.expression, set(numbers), f"formula '{layer.name}' ({Path(file_name(ds)).name}, {ds.count} bands)"
    )
    # every band is offered to the formula, used or not: an empty unused band is no error
    bands = {k: _band(ds, i, layer, nodata, check=False) for k, i in numbers.items()}
    return FormulaSource(tree, bands, alpha=alpha_src)


def preview_layer(layer: Layer, max_side: int = 800, nodata: float | None = None):
    """The layer at reduced resolution (at most ``max_side`` pixels a side), for a quick look: rasterio
    reads overviews or decimates while reading, so the full raster is never in memory.
    Returns ``(array with NaN holes, extent (left, right, bottom, top), crs)``."""
    with contextlib.ExitStack() as stack:
        ds = _open(layer.paths[0], stack, warp=False)
        scale = max(ds.width, ds.height) / max_side
        h, w = (ds.height, ds.width) if scale <= 1 else (max(int(ds.height / scale), 1), max(int(ds.width / scale), 1))

        def small(dataset, band):
            src = _band(dataset, band, layer, nodata, check=False)
            arr = dataset.read(band, out_shape=(h, w), resampling=Resampling.nearest).astype(float)
            for v in src.nodata:
                arr[arr == v] = np.nan
            return arr

        if layer.kind == "band":
            arr = small(ds, layer.bands[0])
        elif layer.kind == "formula":  # the same formula over decimated bands
            src = _formula(ds, layer, nodata)
            src.bands = {k: ArraySource(small(ds, b.band), ds.transform) for k, b in src.bands.items()}
            if src.alpha is not None:
                src.alpha = ArraySource(small(ds, src.alpha.band), ds.transform)
            arr = src.read(0, h, 0, w)
        elif layer.kind == "ndvi":
            red, nir = (small(ds, b) for b in ndvi_bands(ds, layer))
            with np.errstate(invalid="ignore", divide="ignore"):
                arr = np.where(nir + red != 0, (nir - red) / (nir + red), np.nan)
        else:
            dtm = _open(layer.paths[1], stack, warp=False)
            arr = small(ds, 1) - (small(dtm, 1) if dtm.shape == ds.shape else np.nan)
        t: Affine = ds.transform
        b = rasterio.transform.array_bounds(ds.height, ds.width, t)
        return arr, (b[0], b[2], b[1], b[3]), pyproj_crs(ds.crs)
