"""Module 9 (9_spatial_stat_extractor): plant polygons to GIS files, per-plant statistics."""
