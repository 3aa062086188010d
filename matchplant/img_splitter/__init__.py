"""Module 5 (5_img_splitter): tile annotated images and split train/val/test.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``), ``gui`` (``launch(cfg, config_path)``)."""

from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.gui import launch
from matchplant.img_splitter.run import run

__all__ = ['ImgSplitterConfig', 'launch', 'run']
