"""num_workers sized to the cores (issue 40, point 4): at most the usable cores less one, so on one core the default
loads in the main process and PyTorch's "might freeze" warning (more workers than CPUs) never shows."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from matchplant.core.runtime.config import load_config
from matchplant.model_train import config as train_config
from matchplant.model_train.config import ModelTrainConfig


def _loaded(tmp_path: Path, *sets: str) -> ModelTrainConfig:
    (tmp_path / "train.json").write_text("{}")
    return load_config(ModelTrainConfig, None, [f"train_json={tmp_path / 'train.json'}", *sets])


@pytest.mark.parametrize(("cores", "given", "expected"), [(1, None, 0), (2, None, 1), (8, None, 2), (2, "4", 1)])
def test_workers_fit_the_cores(tmp_path, monkeypatch, cores, given, expected):
    monkeypatch.setattr(train_config, "usable_cores", lambda: (cores, "test"))
    cfg = _loaded(tmp_path, *([f"num_workers={given}"] if given else []))
    assert cfg.num_workers == expected


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity")
def test_no_more_workers_than_pytorch_suggests(tmp_path):
    """PyTorch warns when num_workers exceeds len(os.sched_getaffinity(0)): the default never does."""
    assert _loaded(tmp_path).num_workers <= max(len(os.sched_getaffinity(0)) - 1, 0)
