"""Step 9 (9_spatial_stat_extractor): plant polygons to GIS files; per-plant statistics; GUI."""

from matchplant.spatial_stat_extractor import SpatialStatExtractorConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="spatial_stat_extractor",
    config=SpatialStatExtractorConfig,
    run=run,
    gui="matchplant.spatial_stat_extractor.gui:launch",
    flags={
        "--polygons": ("polygons", "plant polygons (GeoPackage, shapefile, CSV)"),
        "--chm": ("rasters.chm", "canopy height model raster"),
        "--dsm": ("rasters.dsm", "DSM (with --dtm: CHM = DSM - DTM)"),
        "--dtm": ("rasters.dtm", "DTM"),
        "--multispectral": ("rasters.multispectral", "multispectral raster (NDVI)"),
    },
)
