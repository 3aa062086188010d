"""Module 2 (2_odm_runner): run OpenDroneMap and check its outputs.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``)."""

from matchplant.odm_runner.config import OdmRunnerConfig
from matchplant.odm_runner.run import run

__all__ = ["OdmRunnerConfig", "run"]
