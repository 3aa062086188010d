"""Module 9's statistics engine: exact zonal statistics of polygons over rasters, the statistics' names, the
per-plant table. Empty on purpose: the settings import ``zonal.names`` without loading the engine."""
