"""Shared input checks of GIS files: a raster (:func:`check_raster`) or a vector file (:func:`check_vector`) that
opens, has what the step needs and holds data; one clear error naming the file, the problem and the fix.

Apart from :mod:`matchplant.core.runtime.validate` so that training and detection, which read no GIS file, do not
load GDAL (rasterio, pyogrio) to check a JSON file.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyogrio
import rasterio
import rasterio.windows

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import did_you_mean


@dataclass
class RasterInfo:
    """What :func:`check_raster` found: path, CRS, band count, size and nodata value."""

    path: Path
    crs: Any
    count: int
    width: int
    height: int
    nodata: float | None


def check_raster(
    path: str | Path,
    *,
    bands: Sequence[int] | int | None = None,
    require_crs: bool = True,
    allow_empty: bool = False,
    what: str = "raster",
) -> RasterInfo:
    """A GeoTIFF (any GDAL raster) that opens, has a CRS and georeferencing, has the ``bands`` asked for (a
    count or 1-based indices) and holds some valid data (not all nodata/NaN) in each of them."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} not found", path=path, fix="check the path in your config")
    try:
        with warnings.catch_warnings(), rasterio.open(path) as ds:
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)  # said below, in words
            info = RasterInfo(path, ds.crs, ds.count, ds.width, ds.height, ds.nodata)
            wanted = list(range(1, bands + 1)) if isinstance(bands, int) else list(bands or range(1, ds.count + 1))
            if wanted and max(wanted) > ds.count:
                raise InputError(
                    f"{what} has {ds.count} band(s), band {max(wanted)} is needed",
                    path=path,
                    fix="check the band numbers in your config, or use the right raster",
                )
            if require_crs and (ds.crs is None or ds.transform.is_identity):
                raise InputError(
                    f"{what} has no {'CRS' if ds.crs is None else 'georeferencing'}",
                    path=path,
                    fix="use the georeferenced raster (e.g. ODM's odm_dem/*.tif), or assign its "
                    "CRS with gdal_edit.py -a_srs EPSG:xxxx",
                )
            if not allow_empty:
                for b in wanted:
                    if not _has_valid(ds, b):
                        raise InputError(
                            f"{what}: band {b} holds no valid data (all nodata or NaN)",
                            path=path,
                            fix="check the raster in a GIS; regenerate it or choose another band",
                        )
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(
            f"{what} cannot be read as a raster: {exc}",
            path=path,
            fix="use a GeoTIFF; a truncated or interrupted copy must be copied again",
        ) from exc
    return info


_checked: set = set()  # (resolved path, band, mtime, size) already checked in this process


def check_raster_once(path: str | Path, band: int, what: str) -> None:
    """:func:`check_raster` of one band (no CRS required) once per file version and band in a process: a step
    that opens one raster for several purposes (module 9: the CHM's units check, box statistics, outlines,
    plots) pays for the sampled blocks' decompression once. A file changed since (time or size) is checked
    again."""
    path = Path(path)
    st = path.stat() if path.is_file() else None
    key = (str(path.resolve()), band, st.st_mtime_ns, st.st_size) if st is not None else None
    if key is None or key not in _checked:
        check_raster(path, bands=[band], require_crs=False, what=what)
        if key is not None:
            _checked.add(key)


def _valid(ds, block: np.ndarray) -> bool:
    data = np.ma.masked_invalid(block) if np.issubdtype(block.dtype, np.floating) else np.ma.asarray(block)
    if ds.nodata is not None and not (isinstance(ds.nodata, float) and math.isnan(ds.nodata)):
        data = np.ma.masked_equal(data, ds.nodata)
    return bool(data.count())


SAMPLED_BLOCKS = 8  # per side: blocks read spread over the raster before any full scan


def _sampled_windows(ds, band: int) -> list:
    """Up to SAMPLED_BLOCKS² of the band's own blocks (tiles or strips), spread evenly over the raster."""
    bh, bw = ds.block_shapes[band - 1]
    nr, nc = -(-ds.height // bh), -(-ds.width // bw)
    rows = np.unique(np.linspace(0, nr - 1, min(nr, SAMPLED_BLOCKS)).round().astype(int))
    cols = np.unique(np.linspace(0, nc - 1, min(nc, SAMPLED_BLOCKS)).round().astype(int))
    return [
        rasterio.windows.Window(c * bw, r * bh, min(bw, ds.width - c * bw), min(bh, ds.height - r * bh))
        for r in rows
        for c in cols
    ]


def _has_valid(ds, band: int) -> bool:
    """A look at a few of the band's blocks spread over it first (cheap: a decimated read of a raster without
    overviews decompresses all of it, 14 s for a 30,000² CHM); a band that looks empty there is scanned in full
    strips before saying so."""
    try:
        # every sampled block is read (no stop at the first valid one): the last block, at the end of the file,
        # is among them, so a truncated copy fails here
        if any([_valid(ds, ds.read(band, window=w)) for w in _sampled_windows(ds, band)]):
            return True
        rows = max(1, 2**24 // max(ds.width, 1))
        for r0 in range(0, ds.height, rows):
            window = rasterio.windows.Window(0, r0, ds.width, min(rows, ds.height - r0))
            if _valid(ds, ds.read(band, window=window)):
                return True
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(
            f"raster band {band} cannot be read (truncated file?): {exc}",
            path=ds.name,
            fix="copy or regenerate the raster",
        ) from exc
    return False


def check_vector(
    path: str | Path,
    *,
    layer: str | None = None,
    require_crs: bool = True,
    allow_empty: bool = False,
    what: str = "vector file",
) -> str:
    """A GeoPackage/shapefile/GeoJSON that opens, has the ``layer`` (did you mean), a CRS and features; returns
    the layer name (the only one when ``layer`` is None; several layers and no ``layer`` is an error)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{what} not found", path=path, fix="check the path in your config")
    try:
        layers = [str(name) for name, _ in pyogrio.list_layers(path)]
    except Exception as exc:  # noqa: BLE001 - pyogrio raises DataSourceError and GDAL errors of several kinds
        raise InputError(
            f"{what} cannot be opened as vector data: {exc}",
            path=path,
            fix="use a GeoPackage, shapefile or GeoJSON; copy a truncated file again",
        ) from exc
    if not layers:
        raise InputError(f"{what} has no layer", path=path, fix="point the config at a file with features")
    if layer is None:
        if len(layers) > 1:
            raise InputError(
                f"{what} has {len(layers)} layers ({', '.join(layers)}); which one?",
                path=path,
                fix="set the layer name in the config",
            )
        layer = layers[0]
    elif layer not in layers:
        hint = did_you_mean(layer, layers)
        raise InputError(
            f"{what} has no layer '{layer}'{'; ' + hint if hint else ''} (layers: {', '.join(layers)})",
            path=path,
            fix="set the layer to one of those",
        )
    meta = pyogrio.read_info(path, layer=layer)
    if require_crs and not meta.get("crs"):
        raise InputError(
            f"{what}, layer '{layer}', has no CRS",
            path=path,
            fix="assign the CRS in a GIS (or ogr2ogr -a_srs EPSG:xxxx), or give it in the config",
        )
    if not allow_empty and meta.get("features", 0) == 0:
        raise InputError(
            f"{what}, layer '{layer}', has no features",
            path=path,
            fix="point the config at the file that holds the plants/polygons",
        )
    return layer
