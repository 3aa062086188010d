"""Step 8's files: the plants as vector files (a GeoPackage by default) and a CSV, and plain tables.

Every file is written to a temporary name and moved into place, so an interrupted run never leaves a
half-written table that a later step would read.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.formats.vectors import write_formats
from matchplant.core.runtime.io import atomic_open
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


def write_plants(
    plants: pd.DataFrame,
    views: ProjectedViews,
    out_dir: Path,
    *,
    layer: str = "plants",
    geometry: str = "outline",
    vector_formats: Sequence[str] = ("gpkg",),
) -> dict[str, Path]:
    """The plants as vector files (``plants.gpkg`` for GIS and step 9, ``.shp``, ``.geojson``: one per
    ``vector_formats``) and ``plants.csv`` (the same table without geometry, for spreadsheets, with the CRS
    in a last column ``crs`` so that the file alone places the plants); the representative view's index
    stays internal."""
    out_dir = Path(out_dir)
    cols = [c for c in plants.columns if c != "view_index"]
    gdf = gpd.GeoDataFrame(plants[cols].copy(), geometry=plant_geometries(plants, views, geometry), crs=views.crs)
    written = write_formats({layer: gdf}, out_dir / "plants", vector_formats)
    table = plants[cols]
    if views.crs is not None:
        table = table.assign(crs=views.crs.to_string())
    written["csv"] = write_table(table, out_dir / "plants.csv")
    return written


def write_table(df: pd.DataFrame, path: Path) -> Path:
    """A CSV at 0.1 mm precision (map coordinates in metres), written atomically."""
    with atomic_open(path) as fh:
        df.to_csv(fh, index=False, float_format="%.4f")
    return Path(path)
