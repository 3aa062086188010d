"""Step 8's projection settings as one record, built once from the config and handed down unchanged.

The defaults live in :class:`~matchplant.plant_projection.config.PlantProjectionConfig` only: library use
builds the record from a config (``ProjectionSettings.from_config(PlantProjectionConfig(edge_points=8))``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.plant_projection.config import PlantProjectionConfig


@dataclass(frozen=True)
class ProjectionSettings:
    """What decides where a box lands (help texts: :class:`PlantProjectionConfig`)."""

    image_type: str
    dsm: Path | None
    min_score: float
    edge_points: int
    map_box: str
    border_pixels: float
    clearance: float
    hidden_height: float
    ground_window: float
    fill_holes: float

    @classmethod
    def from_config(cls, cfg: PlantProjectionConfig | None = None) -> ProjectionSettings:
        """The settings of ``cfg`` (None: the config's defaults)."""
        cfg = cfg if cfg is not None else PlantProjectionConfig()
        return cls(
            image_type=cfg.image_type,
            dsm=Path(cfg.dsm) if cfg.dsm is not None else None,
            min_score=float(cfg.min_score),
            edge_points=int(cfg.edge_points),
            map_box=cfg.map_box,
            border_pixels=float(cfg.border_pixels),
            clearance=float(cfg.silhouette_clearance),
            hidden_height=float(cfg.hidden_height),
            ground_window=float(cfg.ground_window),
            fill_holes=float(cfg.fill_holes),
        )
