"""Device selection (matchplant.detection.device): chosen out loud, CUDA's failures named, slow CPU work
announced (issue 17)."""

from __future__ import annotations

import logging
import warnings
from types import SimpleNamespace

import pytest
import torch
from log_records import log_records, messages

from matchplant.core.runtime.errors import ConfigError
from matchplant.detection.architectures import get_architecture
from matchplant.detection.device import (
    cuda_unusable_reason, explain_device, select_device, warn_if_slow,
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
        warnings.warn("CUDA initialization: The NVIDIA driver on your system is too old (found version 11040)")
        return False

    cuda_build = SimpleNamespace(version=SimpleNamespace(cuda="13.0"), cuda=SimpleNamespace(is_available=old_driver))
    assert "driver on your system is too old" in cuda_unusable_reason(cuda_build)


def test_slow_cpu_work_is_announced():
    with log_records("matchplant.device", logging.INFO) as records:
        arch = "fasterrcnn_resnet50_fpn"
        est = warn_if_slow(torch.device("cpu"), arch, 1000, 5472, 3648)
        assert est == pytest.approx(19961.856 * get_architecture(arch).cpu_seconds_per_megapixel)  # 1000 x 19.961856 megapixels
        assert warn_if_slow(torch.device("cpu"), arch, 2, 400, 300) < 600
        assert warn_if_slow(torch.device("cuda"), arch, 1000, 5472, 3648) is None
    warned = messages(records, logging.WARNING)
    assert len(warned) == 1 and f"{est / 3600:.1f} h" in warned[0] and "1000 image(s) of 5472 x 3648" in warned[0]
