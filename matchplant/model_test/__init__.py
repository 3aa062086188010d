"""Module 7 (7_model_test): COCO evaluation and detection on new images.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``)."""

from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.run import run

__all__ = ["ModelTestConfig", "run"]
