"""Module 9's inputs: the plant polygons, the rasters and their bands, vegetation indices, the Layer record.

Imports nothing of the step above it (the settings, canopy, plots), so the readers stand alone. The names below
are the role's face: code outside this folder imports them from here, not from the files."""

from matchplant.spatial_stat_extractor.inputs.bands import check_order
from matchplant.spatial_stat_extractor.inputs.elevation import check_elevation, chm_keys, not_metres
from matchplant.spatial_stat_extractor.inputs.indices import RGB_INDICES, parse_formula
from matchplant.spatial_stat_extractor.inputs.layer import Layer
from matchplant.spatial_stat_extractor.inputs.polygons import read_polygons, with_crs
from matchplant.spatial_stat_extractor.inputs.rasters import open_layer, preview_layer, raster_crs
from matchplant.spatial_stat_extractor.inputs.sources import ArraySource, RasterFileSource

__all__ = [
    "RGB_INDICES",
    "ArraySource",
    "Layer",
    "RasterFileSource",
    "check_elevation",
    "check_order",
    "chm_keys",
    "not_metres",
    "open_layer",
    "parse_formula",
    "preview_layer",
    "raster_crs",
    "read_polygons",
    "with_crs",
]
