"""A small untrained detector (MobileNetV3-FPN at 64-128 px, random weights) and its module 6 checkpoint: for the
tests of the checkpoint contract and of detection's plumbing, not of accuracy (module 7's tests, the cover's and
the bad-input cases)."""

from __future__ import annotations

from pathlib import Path

import torch

from matchplant.core.runtime.config import load_config
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.detection.model import ModelConfig, build_detector
from matchplant.model_train.config import ModelTrainConfig

SMALL = [
    "train_json=x",
    "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
    "model.pretrained=none",
    "model.min_size=64",
    "model.max_size=128",
]


def small_detector(seed: int = 0) -> tuple[torch.nn.Module, ModelConfig]:
    """The model (two classes: background and plant) and its settings, as module 6 would build them."""
    cfg = load_config(ModelTrainConfig, None, SMALL, check_paths=False, strict=False)
    torch.manual_seed(seed)
    return build_detector(cfg.model, 2), cfg.model


def save_small(path: Path, model: torch.nn.Module, model_cfg: ModelConfig) -> Path:
    """``model`` saved as module 6's checkpoint of one class, 'plant'."""
    return save_checkpoint(path, model, model_cfg, ["plant"], [1], epoch=1)
