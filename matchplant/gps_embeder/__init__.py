"""Module 0 (0_gps_embeder): write GNSS positions into image EXIF by matching timestamps.

The face of every step: ``config`` (its settings), ``run`` (``run(cfg)``)."""

from matchplant.gps_embeder.config import GpsEmbederConfig
from matchplant.gps_embeder.run import run

__all__ = ["GpsEmbederConfig", "run"]
