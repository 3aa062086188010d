"""Module 4 (4_bbox_drawer): draw plant boxes; COCO and YOLO.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets)."""

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.run import run

__all__ = ["BboxDrawerConfig", "run"]
