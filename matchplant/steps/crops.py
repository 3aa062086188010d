"""Crops of every plant from the raw photos as a command: polygons (any file, any CRS) and a project (ODM,
Metashape, Pix4D) in, ``crops/<photo>/<plant>.jpg``, ``index.csv`` and ``index.gpkg`` out."""

from matchplant.spatial_stat_extractor.inputs import read_polygons
from matchplant.steps import StepSpec
from matchplant.views import CropResult, cut_crops, survey_cameras
from matchplant.views.config import CropsConfig


def run(cfg: CropsConfig) -> CropResult:
    """Cut the crops the config asks for."""
    plants = read_polygons(cfg.polygons, cfg.id_column, cfg.layer, cfg.polygons_crs)
    survey = survey_cameras(cfg.project, cfg.photos, cfg.dsm, cfg.project_type)
    return cut_crops(plants, survey, cfg.output_dir, cfg.settings())


SPEC = StepSpec(
    name="crops",
    config=CropsConfig,
    run=run,
    flags={
        "--polygons": ("polygons", "plant or plot polygons (any vector file or CSV, any CRS)"),
        "--project": ("project", "the project: ODM folder, Metashape export (.xml/.psx) or Pix4D folder"),
        "--project-type": ("project_type", "auto, odm, metashape or pix4d"),
        "--best": ("best", "each plant's best N views by off-nadir angle (0: all)"),
    },
)
