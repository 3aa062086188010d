"""The run's device and what follows from it, chosen once (issue 44): :func:`choose_runtime` gives modules 6 and 7
one :class:`Runtime` record (precision, feed, batch sizing, optimizer and loader settings) and their parts read its
fields instead of testing the device's kind again. Mixed precision is bf16 autocast where the GPU supports it (fp16
otherwise); ``MATCHPLANT_GPU`` switches the GPU options for a measurement (``bf16=0,fused=0,channels_last=1,
compile=1``: the GPU benchmark, ``python -m bench --device cuda``, times them one against another)."""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from typing import Any

ENV = "MATCHPLANT_GPU"
AHEAD = 4  # module 7 on CUDA: photos decoded ahead of the GPU (a 20 MP photo is 60 MB as RGB)
IN_FLIGHT = 2  # module 7 on CUDA: photos detected at once, so one photo's merge (CPU) overlaps the next one's tiles


@dataclass(frozen=True)
class GpuOptions:
    """The GPU switches a measurement may turn off or on (``MATCHPLANT_GPU``)."""

    bf16: bool = True
    fused: bool = True
    channels_last: bool = False
    compile: bool = False

    @classmethod
    def from_env(cls) -> GpuOptions:
        """The defaults, overruled by ``MATCHPLANT_GPU`` (``key=0/1`` pairs, comma-separated)."""
        known = {f.name for f in fields(cls)}
        values = {}
        for part in filter(None, os.environ.get(ENV, "").split(",")):
            key, _, value = part.partition("=")
            if key.strip() in known:
                values[key.strip()] = value.strip() not in ("0", "false", "no", "")
        return cls(**values)


@dataclass(frozen=True)
class Runtime:
    """A run's device and every choice that follows from its kind, made once by :func:`choose_runtime`.

    On a CPU every feature below is off and the code runs as it always did; on CUDA they keep the GPU busy.
    """

    device: Any  # the torch.device
    kind: str  # "cpu", "cuda", "mps": torch.autocast's device_type, and messages (never tested by the parts)
    amp: bool  # mixed precision on (CUDA with ``amp: true``)
    amp_dtype: Any  # its dtype (bf16 where supported, else fp16), None in fp32
    on_cpu: bool  # torch's CPU threads follow the free cores; the CPU recipes and advice (module 6); estimates
    asynchronous: bool  # the device runs behind the host: synchronised before a clock is read; its peak memory
    own_rng: bool  # the device has its own random generator, saved and restored with the host's (module 6)
    ddp_device_ids: tuple | None  # DistributedDataParallel's device_ids (this process's GPU)
    pin_memory: bool  # host memory pinned for copies to the device (photos, loader batches)
    tiles_on_device: bool  # module 7: a photo sent once, its tiles cut on the device
    decode_ahead: int  # module 7: photos decoded ahead by threads (0: one after another)
    photos_in_flight: int  # module 7: photos detected at once by threads (0: one after another)
    batch_from_memory: bool  # module 7: a default batch_size sized from the free memory, probed warm at that batch
    loader_workers: bool  # module 6: loader workers raised to the free cores, persistent, prefetching
    fused: bool  # module 6: the optimizer's step fused into one kernel
    losses_on_device: bool  # module 6: losses summed on the device, read every few steps
    options: GpuOptions  # the GPU switches as set (MATCHPLANT_GPU) on CUDA; all off elsewhere


def choose_runtime(device, amp: bool = False) -> Runtime:
    """The run's :class:`Runtime` on ``device`` (from :func:`~matchplant.detection.device.select_device`, after
    joining a torchrun job); the one place that tests the device's kind.

    Parameters
    ----------
    device : torch.device
        The device the run uses.
    amp : bool
        The config's ``amp``: mixed precision where the device supports it (CUDA).

    Returns
    -------
    Runtime
        The record every part of the run reads.
    """
    kind = str(getattr(device, "type", "cpu"))
    cuda = kind == "cuda"
    opts = GpuOptions.from_env() if cuda else GpuOptions(bf16=False, fused=False, channels_last=False, compile=False)
    dtype = None
    if cuda and amp:
        import torch  # lazy: PyTorch is heavy; configs load without it

        dtype = torch.bfloat16 if opts.bf16 and torch.cuda.is_bf16_supported() else torch.float16
    return Runtime(
        device=device,
        kind=kind,
        amp=cuda and amp,
        amp_dtype=dtype,
        on_cpu=kind == "cpu",
        asynchronous=cuda,
        own_rng=cuda,
        ddp_device_ids=(getattr(device, "index", None),) if cuda else None,
        pin_memory=cuda,
        tiles_on_device=cuda,
        decode_ahead=AHEAD if cuda else 0,
        photos_in_flight=IN_FLIGHT if cuda else 0,
        batch_from_memory=cuda,
        loader_workers=cuda,
        fused=opts.fused,
        losses_on_device=cuda,
        options=opts,
    )


def as_runtime(device_or_runtime, amp: bool = False) -> Runtime:
    """A :class:`Runtime` as it is, or the one :func:`choose_runtime` gives a bare device (callers outside a run:
    benches, tests)."""
    if isinstance(device_or_runtime, Runtime):
        return device_or_runtime
    return choose_runtime(device_or_runtime, amp)


def amp_dtype(device, amp: bool):
    """The autocast dtype on this device: bf16 where supported (and not switched off), fp16 otherwise; None
    without mixed precision (a CPU, or ``amp: false``)."""
    return as_runtime(device, amp).amp_dtype
