"""Module 3 (3_min_img_finder): the fewest undistorted images that cover the field.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets)."""

from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.run import run

__all__ = ["MinImgFinderConfig", "run"]
