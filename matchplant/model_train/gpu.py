"""What module 6 does differently on a CUDA GPU to keep it busy (issue 38); on a CPU nothing here applies.

- precision: bf16 autocast where the GPU supports it (no loss scaling, so no GradScaler and its per-step host sync),
  else fp16 autocast with the GradScaler (``amp: false``: fp32);
- the optimizer's step fused into one kernel (``torch.optim.SGD/AdamW(fused=True)``);
- ``channels_last`` memory layout and ``torch.compile`` of the backbone: off unless asked (unmeasured gains);
- the losses summed on the device and read every :data:`READ_EVERY` steps (and at the end of an epoch): a loss read
  to the host waits for the GPU to finish every queued step, so reading it at every step makes the CPU and the GPU
  take turns instead of overlapping. The non-finite check runs on those reads.
- the DataLoader: workers sized to the free cores, kept from epoch to epoch (the epoch's augmentation seed then
  travels with each index: :class:`~matchplant.detection.data.EpochSampler`), pinned memory, a deeper prefetch.

Each option can be switched for a measurement with ``MATCHPLANT_GPU`` (:mod:`matchplant.detection.gpu`):
``bf16=0,fused=0,channels_last=1,compile=1``; the GPU benchmark (``python -m bench --device cuda``) times them.
"""

from __future__ import annotations

import os

from matchplant.detection.gpu import GpuOptions, amp_dtype, as_runtime

__all__ = ["READ_EVERY", "GpuOptions", "amp_dtype", "fused_ok", "loader_settings", "prepare_model"]

READ_EVERY = 25  # CUDA: steps between reads of the losses (the non-finite check, the progress bar)
MAX_WORKERS = 8  # loader processes on a GPU machine: decoding PNG tiles keeps up with a GPU step at 4-8


def loader_settings(num_workers: int, device) -> dict:
    """DataLoader keywords: where the run's runtime raises the loader's workers (CUDA) at least as many workers as
    the free cores allow (up to :data:`MAX_WORKERS`; the config's ``num_workers`` when larger), persistent, pinned,
    prefetching; on a CPU the config's as they are. ``device``: the run's Runtime (or a bare device)."""
    runtime = as_runtime(device)
    if not runtime.loader_workers:
        return {"num_workers": num_workers, "pin_memory": False}
    free = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = max(num_workers, min(MAX_WORKERS, free - 1))
    extra = {"persistent_workers": True, "prefetch_factor": 4} if workers else {}
    return {"num_workers": workers, "pin_memory": runtime.pin_memory, **extra}


def prepare_model(model, device):
    """channels_last and ``torch.compile`` of the backbone where asked, on CUDA; the model unchanged elsewhere."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    opts = as_runtime(device).options  # all off on a CPU
    if opts.channels_last:
        model.to(memory_format=torch.channels_last)
    if opts.compile and hasattr(model, "backbone"):
        model.backbone = torch.compile(model.backbone, dynamic=True)
    return model


def fused_ok(params, device) -> bool:
    """Whether the optimizer's step may be fused: the runtime fuses it (CUDA, not switched off) and every parameter
    is on the GPU."""
    return device is not None and as_runtime(device).fused and all(p.is_cuda for p in params)
