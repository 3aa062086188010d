"""The interactive field map as a command: plants with their traits (and plots, an orthophoto, crops) in, one
self-contained HTML file out (``map.html`` in the output folder)."""

from pathlib import Path

from matchplant.spatial_stat_extractor.inputs import read_polygons
from matchplant.steps import StepSpec
from matchplant.views.config import FieldMapConfig
from matchplant.views.fieldmap import read_plots, write_field_map


def run(cfg: FieldMapConfig) -> Path:
    """Write the map the config asks for."""
    plants = read_polygons(cfg.plants, cfg.id_column, cfg.layer, cfg.polygons_crs)
    plots = read_plots(cfg.plots, cfg.plot_id_column) if cfg.plots else None
    return write_field_map(
        cfg.output_dir / "map.html",
        plants,
        plots=plots,
        orthophoto=cfg.orthophoto,
        crops=cfg.crops,
        title=cfg.title,
        trait=cfg.trait,
    )


SPEC = StepSpec(
    name="map",
    config=FieldMapConfig,
    run=run,
    flags={
        "--plants": ("plants", "plant polygons with traits (module 9's stats.gpkg)"),
        "--plots": ("plots", "plot polygons with statistics (module 9's plots.gpkg)"),
        "--crops": ("crops", "the crops' index.csv (matchplant crops)"),
        "--orthophoto": ("orthophoto", "orthophoto GeoTIFF"),
    },
)
