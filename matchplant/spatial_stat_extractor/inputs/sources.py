"""Rasters as the statistics read them: anything with ``transform``, ``width``, ``height`` and
``read(row0, row1, col0, col1)`` returning float64 with nodata as NaN - an array, one band of a file, a
difference of two files (the CHM), NDVI of two bands.

:mod:`~matchplant.spatial_stat_extractor.inputs.rasters` opens them from the settings' layers; the engine
(:mod:`~matchplant.spatial_stat_extractor.zonal.engine`) only calls ``read``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from rasterio.windows import Window

from matchplant.core.geometry.frames import parse_crs


@dataclass
class ArraySource:
    """An in-memory raster (tests, previews). NaN and ``nodata`` are masked."""

    data: np.ndarray
    transform: object
    nodata: float | None = None
    crs: object = None

    def __post_init__(self):
        self.data = np.asarray(self.data, dtype=float)
        if self.nodata is not None:
            self.data = np.where(self.data == self.nodata, np.nan, self.data)
        self.height, self.width = self.data.shape

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """The array's window (rows ``row0:row1``, cols ``col0:col1``), a view."""
        return self.data[row0:row1, col0:col1]


def pyproj_crs(crs):
    """A rasterio CRS as a pyproj CRS (what GeoPandas uses), None stays None."""
    return None if crs is None else parse_crs(crs)


class RasterFileSource:
    """One band of an open rasterio dataset, read window by window. The file's nodata, any
    ``extra_nodata`` values (ODM's -9999 on elevation rasters) and NaN are masked."""

    def __init__(self, dataset, band: int = 1, nodata: float | None = None, extra_nodata: Sequence[float] = ()):
        self.ds = dataset
        self.band = band
        self.transform = dataset.transform
        self.crs = pyproj_crs(dataset.crs)
        self.width, self.height = dataset.width, dataset.height
        file_nodata = dataset.nodatavals[band - 1] if dataset.nodatavals else None
        # each value once (an elevation raster's nodata is often ODM's -9999 too): a pass per value per read
        self.nodata = list(
            dict.fromkeys(
                v
                for v in (nodata if nodata is not None else file_nodata, *extra_nodata)
                if v is not None and not np.isnan(v)
            )
        )

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """The band's window (rows ``row0:row1``, cols ``col0:col1``) as float64, NaN where no data."""
        # GDAL converts to float64 as it reads (no second pass over the window)
        arr = self.ds.read(self.band, window=Window(col0, row0, col1 - col0, row1 - row0), out_dtype="float64")
        for v in self.nodata:
            np.copyto(arr, np.nan, where=arr == v)
        return arr


class DifferenceSource:
    """``a - b`` window by window (a CHM from a DSM and a DTM on the same grid)."""

    def __init__(self, a, b):
        if (a.width, a.height) != (b.width, b.height) or not a.transform.almost_equals(b.transform):
            raise ValueError("the two rasters are not on the same grid")
        self.a, self.b = a, b
        self.transform, self.crs, self.width, self.height = a.transform, a.crs, a.width, a.height

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """``a - b`` over a window (rows ``row0:row1``, cols ``col0:col1``)."""
        return self.a.read(row0, row1, col0, col1) - self.b.read(row0, row1, col0, col1)


class NDVISource:
    """(NIR - red) / (NIR + red) window by window; NaN where the sum is 0 or a band is masked."""

    def __init__(self, red, nir):
        self.red, self.nir = red, nir
        self.transform, self.crs, self.width, self.height = red.transform, red.crs, red.width, red.height

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """NDVI over a window (rows ``row0:row1``, cols ``col0:col1``), NaN where NIR + red is 0."""
        r = self.red.read(row0, row1, col0, col1)
        n = self.nir.read(row0, row1, col0, col1)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = n + r
            return np.where(s != 0, (n - r) / s, np.nan)
