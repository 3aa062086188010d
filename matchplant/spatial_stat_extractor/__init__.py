"""Module 9 (9_spatial_stat_extractor): plant polygons to GIS files, per-plant statistics.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets). Beside them,
the step's stages: ``traits`` (the canopy part over every date) and ``compare`` (two plant sets).

Under the face, the roles, each a folder (docs/DESIGN.md §1; tests/test_layers.py keeps them apart):

* ``inputs/``: the plant polygons (any vector file, WKT or box CSVs, pixel boxes), the rasters and their bands,
  vegetation indices, the ``Layer`` record;
* ``zonal/``: the statistics engine (exact zonal statistics, its compiled coverage kernels, runs per group),
  the statistics' names, the per-plant table;
* ``canopy/``: plant outlines from the CHM (tops, peaks, tracing, grouping), the ground's noise and thresholds,
  later dates, canopy-only statistics, strips in bounded memory;
* ``plots/``: plant rows to plot rows (the table, the layout, crop rows, the figure, field books, their settings).

inputs and zonal never reach canopy, plots or the face; canopy and plots never reach each other."""

from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.run import run

__all__ = ["SpatialStatExtractorConfig", "run"]
