"""Module 1 (1_gcp_finder): find the images that see each GCP, mark them, write gcp_list.txt.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``), ``gui`` (``launch(cfg, config_path)``)."""

from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.gui import launch
from matchplant.gcp_finder.run import run

__all__ = ['GcpFinderConfig', 'launch', 'run']
