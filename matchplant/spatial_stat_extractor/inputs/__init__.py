"""Module 9's inputs: the plant polygons, the rasters and their bands, vegetation indices, the Layer record.

Imports nothing of the step above it (the settings, canopy, plots), so the readers stand alone."""
