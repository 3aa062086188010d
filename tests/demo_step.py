"""A demo step for the configuration, command-line and logging tests: a config class using every kind of
setting, a writer for its YAML file, and a StepSpec around it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.runtime.config import param, section
from matchplant.steps import StepSpec


@dataclass
class Optim:
    """Optimiser settings."""

    lr: float = param(0.01, "learning rate", min=0.0, max=1.0)
    schedule: str = param("step", "learning-rate schedule", choices=["step", "cosine"])


@dataclass
class DemoConfig:
    """A demo module."""

    images: Path | None = param(None, "folder of images", path="dir", required=True)
    output_dir: Path = param("out", "output folder", path="out")
    tile_size: int = param(1024, "tile side in pixels", min=64)
    overlap: float = param(0.1, "tile overlap fraction", min=0, max=0.9)
    names: list[str] = param(["plant"], "category names")
    mode: Literal["fast", "exact"] = param("fast", "how to compute")
    verbose: bool = param(False, "say more")
    optim: Optim = section(Optim)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def demo_spec(run):
    return StepSpec(name="demo", config=DemoConfig, run=run)
