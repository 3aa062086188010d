"""A date's CHM checked before any work: rasters whose CRS says their units are not metres, and a CHM that is one
value everywhere.

Module 9 reads heights (and, through the outlines, distances and areas) in metres. A CHM whose CRS is in US survey
feet (a state plane CRS, a NAVD88 height in ftUS) was read as metres: every plant 3.28x too tall, its canopy
thresholds and outlines wrong, and exit 0. And a CHM of all zeros (DSM and DTM the same file, a DTM given as the
DSM) gave every plant 'low' and exit 0. Both are errors naming the file, what its CRS or its pixels say, and the
fix, raised before the statistics start (a decimated read: a constant raster is confirmed block by block).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import rasterio
import rasterio.windows

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.geometry.units import height_unit, not_metres
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate_gis import check_raster_once

ODM_NODATA = -9999.0  # ODM's DEM nodata, masked even when the file does not declare it
DECIMATED = 512  # cells along the longer side of the quick read
FLAT = 1e-6  # m: a raster whose values span less than this is one value
FOOT_FIXES = {"US survey foot": 0.3048006096, "foot": 0.3048}


def chm_keys(rs, first: bool) -> tuple[str, ...]:
    """The config keys of a date's CHM, for messages."""
    where = "rasters" if first else f"more_dates (date '{rs.date}')"
    return (f"{where}.chm",) if rs.chm is not None else (f"{where}.dsm", f"{where}.dtm")


def _units_fix(unit: str) -> str:
    factor = next((f for name, f in FOOT_FIXES.items() if unit.startswith(name)), None)
    scale = f"A*{factor:g}" if factor else "A*<metres per unit>"
    return (
        "reproject it to a CRS in metres and convert its heights to metres, e.g. gdalwarp -t_srs EPSG:<UTM zone> "
        f'in.tif in_m.tif, then gdal_calc.py -A in_m.tif --calc="{scale}" --outfile=out_m.tif (a CHM as DSM - DTM '
        "of ODM's own outputs is in metres)"
    )


def check_elevation(date_sets) -> None:
    """Every date's CHM rasters (``rasters.chm``, or ``rasters.dsm`` and ``rasters.dtm``): in metres, and not one
    value everywhere (module doc)."""
    for i, rs in enumerate(date_sets):
        layer = next((la for la in rs.layers() if la.elevation), None)
        if layer is None:
            continue
        keys = chm_keys(rs, i == 0)
        for path, key in zip(layer.paths, keys):  # opens, has data, not truncated: said before it is read here
            check_raster_once(path, 1, key)
        with contextlib.ExitStack() as stack:
            files = [stack.enter_context(rasterio.open(p)) for p in layer.paths]
            for ds, key, path in zip(files, keys, layer.paths):
                units = not_metres(ds.crs)
                if units:
                    raise InputError(
                        f"{key}: the raster's CRS ('{parse_crs(ds.crs).name}') is in {units}; module 9 reads heights, "
                        "distances and areas in metres, so a CHM in feet makes every plant 3.28 times too tall",
                        path=path,
                        fix=_units_fix(units),
                    )
                factor, unit = height_unit(None, ds.units[0], path)  # the band's unit type (gdal_edit.py -units)
                if factor != 1.0:
                    raise InputError(
                        f"{key}: the raster's heights are in {unit} (its band unit type); module 9 reads heights in "
                        "metres, so a CHM in feet makes every plant 3.28 times too tall",
                        path=path,
                        fix=_units_fix(unit) + ", then gdal_edit.py -units m out_m.tif",
                    )
            _check_not_constant(files, keys, layer.paths)


def _decimated(ds, shape: tuple[int, int]) -> np.ndarray:
    """The raster read at ``shape`` (overviews or decimation: never whole), nodata, ODM's -9999 and NaN as NaN."""
    a = ds.read(1, out_shape=shape, masked=True).astype(float).filled(np.nan)
    a[a <= ODM_NODATA] = np.nan
    return a


def _check_not_constant(files: list, keys: tuple[str, ...], paths) -> None:
    """A CHM (one raster, or the difference of two on one grid) of one value everywhere is an error."""
    first = files[0]
    if any((ds.width, ds.height) != (first.width, first.height) for ds in files):
        return  # a DTM on another grid is resampled when read; two such rasters are not one surface
    f = max(1, int(np.ceil(max(first.width, first.height) / DECIMATED)))
    shape = (max(1, first.height // f), max(1, first.width // f))
    chm = _decimated(first, shape)
    for ds in files[1:]:
        chm = chm - _decimated(ds, shape)
    values = chm[np.isfinite(chm)]
    if not values.size or values.max() - values.min() > FLAT or not _constant_everywhere(files):
        return
    named = " and ".join(keys)
    what = f"DSM - DTM ({', '.join(Path(p).name for p in paths)})" if len(files) == 2 else Path(paths[0]).name
    same = " (the DSM and the DTM are the same surface: one file given twice, or a DTM copied as the DSM)"
    raise InputError(
        f"the CHM from {what} is {float(values[0]):g} everywhere (every valid pixel){same if len(files) == 2 else ''}:"
        " every plant would be flagged 'low' with no height above the ground",
        path=paths[0],
        fix=f"check {named}: a CHM is the surface minus the terrain of one flight (ODM's odm_dem/dsm.tif and "
        "dtm.tif, ODM run with --dsm --dtm), in metres",
    )


def _constant_everywhere(files: list) -> bool:
    """The full-resolution check behind a constant decimated read, block row by block row (a rare case: an error
    is coming, or a few plants the decimation missed)."""
    first = files[0]
    rows = max(1, 2**22 // max(1, first.width))
    lo, hi = np.inf, -np.inf
    for r0 in range(0, first.height, rows):
        win = rasterio.windows.Window(0, r0, first.width, min(rows, first.height - r0))
        chm = None
        for ds in files:
            a = ds.read(1, window=win, masked=True).astype(float).filled(np.nan)
            a[a <= ODM_NODATA] = np.nan
            chm = a if chm is None else chm - a
        v = chm[np.isfinite(chm)]
        if v.size:
            lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
            if hi - lo > FLAT:
                return False
    return True
