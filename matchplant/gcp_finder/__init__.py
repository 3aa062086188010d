"""Module 1 (1_gcp_finder): find the images that see each GCP, mark them, write gcp_list.txt.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets)."""

from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.run import run

__all__ = ["GcpFinderConfig", "run"]
