"""Module 4 (4_bbox_drawer): draw plant boxes; COCO and YOLO.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``), ``gui`` (``launch(cfg, config_path)``)."""

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.gui import launch
from matchplant.bbox_drawer.run import run

__all__ = ['BboxDrawerConfig', 'launch', 'run']
