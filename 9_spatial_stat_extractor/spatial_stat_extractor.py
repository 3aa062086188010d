"""Module 9: plant polygons to GIS files (GeoPackage, shapefile) and one row of statistics per plant
(height from a CHM or DSM - DTM, NDVI, any band; one or several dates). Add --gui for the window.

    python 9_spatial_stat_extractor/spatial_stat_extractor.py --config 9_spatial_stat_extractor/config.yaml
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
