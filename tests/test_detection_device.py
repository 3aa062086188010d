"""Device selection (matchplant.detection.device): chosen out loud, CUDA's failures named (issue 17). Module 7
announces slow detection from a probe of the real model (tests/test_model_test.py)."""

from __future__ import annotations

import logging
import warnings
from types import SimpleNamespace

import pytest
import torch
from log_records import log_records, messages

from matchplant.core.runtime.errors import ConfigError
from matchplant.detection.device import (
    cuda_unusable_reason,
    explain_device,
    select_device,
)


def test_device_selection():
    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type in ("cpu", "cuda", "mps")
    with pytest.raises(ConfigError):
        select_device("tpu")


def test_device_is_chosen_out_loud():
    dev, why = explain_device("auto")
    if torch.cuda.is_available():
        assert dev.type == "cuda" and "CUDA GPU found" in why
    else:
        assert dev.type in ("cpu", "mps") and cuda_unusable_reason(torch) in why
    assert explain_device("cpu") == (torch.device("cpu"), "asked for (device: cpu)")
    with log_records("matchplant.device", logging.INFO) as records:
        select_device("cpu")
    assert messages(records) == ["device: cpu (asked for (device: cpu))"]
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA cannot be used"):
            explain_device("cuda")


def test_cuda_reasons_name_the_cause():
    cpu_build = SimpleNamespace(version=SimpleNamespace(cuda=None))
    assert "CPU-only" in cuda_unusable_reason(cpu_build)

    def old_driver():
        warnings.warn(
            "CUDA initialization: The NVIDIA driver on your system is too old (found version 11040)", stacklevel=2
        )
        return False

    cuda_build = SimpleNamespace(version=SimpleNamespace(cuda="13.0"), cuda=SimpleNamespace(is_available=old_driver))
    assert "driver on your system is too old" in cuda_unusable_reason(cuda_build)
