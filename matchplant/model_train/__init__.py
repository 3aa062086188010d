"""Module 6 (6_model_train): train a plant detector (transfer learning from YAML).

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``)."""

from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import run

__all__ = ["ModelTrainConfig", "run"]
