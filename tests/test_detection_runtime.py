"""The run's device chosen once (issue 44): :func:`choose_runtime` turns every GPU feature on for CUDA and off for a
CPU, and a part given a bare device reads the same record as one given the run's."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from matchplant.detection.gpu import GpuOptions, Runtime, as_runtime, choose_runtime

CPU = torch.device("cpu")
FAKE_CUDA = SimpleNamespace(type="cuda", index=1)


def test_a_cpu_run_has_every_gpu_feature_off():
    rt = choose_runtime(CPU, amp=True)
    assert rt.on_cpu and rt.kind == "cpu" and not rt.amp and rt.amp_dtype is None
    assert not (rt.pin_memory or rt.tiles_on_device or rt.batch_from_memory or rt.loader_workers or rt.fused)
    assert not (rt.asynchronous or rt.own_rng or rt.losses_on_device) and rt.ddp_device_ids is None
    assert rt.decode_ahead == 0 and rt.photos_in_flight == 0
    assert rt.options == GpuOptions(bf16=False, fused=False, channels_last=False, compile=False)


def test_a_cuda_run_has_them_on_and_follows_the_switches(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda: True)
    monkeypatch.setenv("MATCHPLANT_GPU", "fused=0")
    rt = choose_runtime(FAKE_CUDA, amp=True)
    assert not rt.on_cpu and rt.amp and rt.amp_dtype == torch.bfloat16 and not rt.fused
    assert rt.pin_memory and rt.tiles_on_device and rt.batch_from_memory and rt.losses_on_device
    assert rt.decode_ahead > 0 and rt.photos_in_flight == 2 and rt.ddp_device_ids == (1,)
    assert not choose_runtime(FAKE_CUDA, amp=False).amp


def test_a_bare_device_gets_the_same_record_and_a_record_passes_through():
    rt = choose_runtime(CPU)
    assert isinstance(rt, Runtime) and as_runtime(rt) is rt and as_runtime(CPU) == rt
