"""Mixed precision and the GPU options modules 6 and 7 share (issue 38): bf16 autocast where the GPU supports it
(fp16 otherwise), and the switches ``MATCHPLANT_GPU`` sets for a measurement (``bf16=0,fused=0,channels_last=1,
compile=1``: the GPU benchmark, ``python -m bench --device cuda``, times them one against another)."""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

ENV = "MATCHPLANT_GPU"


@dataclass(frozen=True)
class GpuOptions:
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


def amp_dtype(device, amp: bool):
    """The autocast dtype on this device: bf16 where supported (and not switched off), fp16 otherwise; None
    without mixed precision (a CPU, or ``amp: false``)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    if device.type != "cuda" or not amp:
        return None
    return torch.bfloat16 if GpuOptions.from_env().bf16 and torch.cuda.is_bf16_supported() else torch.float16
