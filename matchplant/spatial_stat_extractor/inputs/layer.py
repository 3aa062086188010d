"""The Layer record: one trait to measure, as the settings describe it and the raster readers open it.

Here, under the inputs, so that reading rasters does not reach up to the settings for it; the settings build
Layers (:meth:`~matchplant.spatial_stat_extractor.config.RasterSet.layers`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Layer:
    """One trait to measure: a band, a difference of two rasters (CHM) or NDVI."""

    name: str
    kind: str  # "band" | "difference" | "ndvi" | "formula"
    paths: tuple
    bands: tuple = (1,)  # numbers, names of band_order, or None (ndvi: red and NIR named by the raster)
    elevation: bool = False
    expression: str = ""  # formula: RGB (R, G, B, r, g, b from bands = red, green, blue) or b1, b2, ...
    index: bool = False  # a vegetation index (measured over the canopy by default)
    band_order: tuple = ()  # the names of the raster's bands in file order (config band_order), () = the file's
