"""Module 5 (5_img_splitter): tile annotated images and split train/val/test.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``); the window, ``gui.launch(cfg,
config_path)``, is imported only for ``--gui`` (a plain run needs none of matplotlib's widgets)."""

from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.run import run

__all__ = ["ImgSplitterConfig", "run"]
