"""Module 9 (9_spatial_stat_extractor): plant polygons to GIS files, per-plant statistics.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets)."""

from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.run import run

__all__ = ['SpatialStatExtractorConfig', 'run']
