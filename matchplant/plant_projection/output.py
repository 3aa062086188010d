"""Step 8's files: the plants as a GeoPackage (and CSV, optionally a shapefile), and plain tables.

Every file is written to a temporary name and moved into place, so an interrupted run never leaves a
half-written table that a later step would read.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.runtime.io import atomic_open, atomic_path
from matchplant.plant_projection.views import ProjectedViews


def plant_geometries(plants: pd.DataFrame, views: ProjectedViews, geometry: str = "outline"):
    """Shapely polygons of the plants: the representative view's projected outline, or the box."""
    boxes = shapely.box(plants["xmin"], plants["ymin"], plants["xmax"], plants["ymax"])
    if geometry == "box" or len(plants) == 0:
        return boxes
    rings = views.outlines(plants["view_index"].to_numpy())
    polys = shapely.polygons(rings)  # 3D: the heights where the rays met the surface
    polys = shapely.make_valid(polys)
    polys = shapely.intersection(polys, boxes)  # the outline overshoots the sides hidden behind the plant
    # a self-crossing outline (rays hitting a steep plant edge) falls back to the box
    bad = ~shapely.is_valid(polys) | (shapely.get_type_id(polys) != 3)
    return np.where(bad, boxes, polys)


def write_plants(plants: pd.DataFrame, views: ProjectedViews, out_dir: Path, *, layer: str = "plants",
                 geometry: str = "outline", shapefile: bool = False) -> dict[str, Path]:
    """``plants.gpkg`` (for GIS and step 9) and ``plants.csv`` (the same table without geometry, for
    spreadsheets); the representative view's index stays internal."""
    out_dir = Path(out_dir)
    cols = [c for c in plants.columns if c != "view_index"]
    gdf = gpd.GeoDataFrame(plants[cols].copy(), geometry=plant_geometries(plants, views, geometry), crs=views.crs)
    written = {}
    with atomic_path(out_dir / "plants.gpkg") as tmp:
        gdf.to_file(tmp, layer=layer, driver="GPKG")
    written["gpkg"] = out_dir / "plants.gpkg"
    with atomic_open(out_dir / "plants.csv") as fh:
        plants[cols].to_csv(fh, index=False, float_format="%.4f")
    written["csv"] = out_dir / "plants.csv"
    if shapefile:
        written["shp"] = _write_shapefile(gdf, out_dir / "plants.shp")
    return written


SHAPEFILE_NAMES = {"source_image": "src_image", "off_nadir_deg": "off_nadir", "category_id": "cat_id",
                   "score_max": "score_max", "truth_plant_id": "truth_id"}


def _write_shapefile(gdf, path: Path) -> Path:
    """A shapefile is several files: write them in a temporary folder, then move each into place."""
    tmp = Path(tempfile.mkdtemp(prefix=".plants_shp_", dir=path.parent))
    try:
        g = gdf.rename(columns=SHAPEFILE_NAMES)
        g["cut"] = g["cut"].astype(int)
        g.to_file(tmp / path.name, driver="ESRI Shapefile")
        for f in tmp.iterdir():
            os.replace(f, path.parent / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_table(df: pd.DataFrame, path: Path) -> Path:
    """A CSV at 0.1 mm precision (map coordinates in metres), written atomically."""
    with atomic_open(path) as fh:
        df.to_csv(fh, index=False, float_format="%.4f")
    return Path(path)
