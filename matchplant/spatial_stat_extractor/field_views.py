"""The plants seen: each plant's crops from the raw photos and the field map (``views`` in the config).

Crops come from the original photos of the project (``views.project``: ODM, Metashape or Pix4D), cut by
:mod:`matchplant.views` into ``crops/`` with ``crops/index.csv``; ``map.html`` shows the plants coloured by any
statistic, the plots with theirs, the orthophoto and the crops, and opens with no network.
"""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd

from matchplant.core.formats.projects import open_project
from matchplant.core.runtime.log import get_logger
from matchplant.views import CropSettings, cut_crops, survey_cameras
from matchplant.views.config import ViewsSection
from matchplant.views.fieldmap import write_field_map

log = get_logger("spatial_stat_extractor")


def write_views(views: ViewsSection, plants, table, out: Path, written: dict) -> dict[str, Path]:
    """Crops (when ``views.project`` is set) and ``map.html`` (when ``views.field_map``) in ``out``."""
    new: dict[str, Path] = {}
    if views.project is not None:
        survey = survey_cameras(views.project, views.photos, project_type=views.project_type)
        result = cut_crops(plants, survey, out / "crops", CropSettings(best=views.best))
        log.info("%d crops of %d plants from %d photos", result.crops, result.plants_seen, result.photos)
        new["crops_index"] = result.index_csv
    if views.field_map:
        geom = plants.set_index("plant_id").geometry
        stats = table.drop_duplicates("plant_id")  # one row per plant (the first date, in the long layout)
        gdf = gpd.GeoDataFrame(stats.copy(), geometry=geom.reindex(stats["plant_id"]).values, crs=plants.crs)
        plots = gpd.read_file(written["plots_gpkg"]) if "plots_gpkg" in written else None
        new["map"] = write_field_map(
            out / "map.html", gdf, plots=plots, orthophoto=_orthophoto(views), crops=new.get("crops_index")
        )
    return new


def _orthophoto(views: ViewsSection) -> Path | None:
    """The orthophoto the map shows: the configured one, else the project's (when it has one)."""
    if views.orthophoto is not None or views.project is None:
        return views.orthophoto
    path = open_project(views.project, views.project_type).path("orthophoto")
    return path if path.is_file() else None
