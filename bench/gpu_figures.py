"""What each GPU row records beside its times (issue 38): the GPU's utilisation while it ran and its peak memory, and
the acceptance figures with their targets (PASS/FAIL lines printed by ``python -m bench --device cuda``).

Utilisation: ``torch.cuda.utilization()`` (it needs pynvml) sampled every ``PERIOD_S`` in a thread, else
``nvidia-smi --query-gpu=utilization.gpu``; None where neither answers. Peak memory:
``torch.cuda.max_memory_allocated`` since the row's start.
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
import threading

import torch

PERIOD_S = 0.2
BASELINE_CEILING = 59.0  # images/s: ResNet-50 FPN alone at 1024 px, batch 8, autocast, H200 (../shared/gpu/README.md)


def _nvidia_smi(index: int) -> float | None:
    try:
        out = subprocess.run(
            ["nvidia-smi", f"--id={index}", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"],
            capture_output=True,
            text=True,
            timeout=5,
        )
        return float(out.stdout.strip().splitlines()[0])
    except (OSError, ValueError, IndexError, subprocess.SubprocessError):
        return None


def _sampler(device):
    """A function returning the GPU's utilisation in percent (or None), the cheapest that works here."""
    try:
        torch.cuda.utilization(device)
        return lambda: float(torch.cuda.utilization(device))
    except Exception:  # noqa: BLE001 - no pynvml, or no NVML: try the command line tool
        pass
    if shutil.which("nvidia-smi") and _nvidia_smi(device.index or 0) is not None:
        return lambda: _nvidia_smi(device.index or 0)
    return None


class GpuMonitor:
    """``with GpuMonitor(device) as m: ...`` then ``m.figures()``: utilisation (mean, min, max of the samples, %)
    and peak memory (GiB) over the block; on a CPU both are None."""

    def __init__(self, device):
        self.device = device
        self.samples: list[float] = []
        self.peak_gib: float | None = None
        self._stop = threading.Event()
        self._thread = None

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            sample = _sampler(self.device)
            if sample is not None:
                self._thread = threading.Thread(target=self._run, args=(sample,), daemon=True)
                self._thread.start()
        return self

    def _run(self, sample):
        while not self._stop.wait(PERIOD_S):
            value = sample()
            if value is not None:
                self.samples.append(value)

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak_gib = round(torch.cuda.max_memory_allocated(self.device) / 2**30, 2)
        return False

    def figures(self) -> dict:
        """Mean, min and max GPU utilisation over the samples and the peak memory in GiB."""
        s = self.samples
        util = {"mean": round(statistics.mean(s), 1), "min": min(s), "max": max(s), "samples": len(s)} if s else None
        return {"gpu_utilisation_pct": util, "peak_memory_gib": self.peak_gib}


# each GPU row's acceptance figures (issue 38): (figure, target, at most rather than at least)
TARGETS = {
    "train": [("train 800 px: our loop / the bare loop at equal precision (speed ratio)", 0.95, False)],
    "train-ceiling": [
        ("train 1024 px: our loop on files / the model's ceiling", 0.85, False),
        ("train 1024 px: the model's ceiling (img/s)", round(1.3 * BASELINE_CEILING, 1), False),
    ],
    "detect-photos": [("detect: 20 MP photos/s from disk", 8.0, False), ("detect: 1,000 photos (min)", 2.0, True)],
    "train-real": [
        ("train-real, max_minutes 3: test AP50", 0.53, False),
        ("train-real, max_minutes 3: |estimate / run - 1|", 0.10, True),
    ],
}


def figures_of(name: str, values: list[float | None] | None = None) -> list[dict]:
    """The row's acceptance figures with these values (None: not measured, a failed or skipped row)."""
    targets = TARGETS[name]
    values = values or [None] * len(targets)
    return [accept(figure, value, target, at_most=at_most) for (figure, target, at_most), value in zip(targets, values)]


def accept(figure: str, value: float | None, target: float, unit: str = "", *, at_most: bool = False) -> dict:
    """One acceptance figure: its value against its target (at least, or ``at_most``)."""
    ok = value is not None and (value <= target if at_most else value >= target)
    return {"figure": figure, "value": value, "target": target, "unit": unit, "at_most": at_most, "pass": ok}


def acceptance_line(a: dict) -> str:
    """One acceptance figure as a PASS/FAIL line with its value and target."""
    value = "not measured" if a["value"] is None else f"{a['value']:.3g}{a['unit']}"
    sign = "<=" if a["at_most"] else ">="
    return f"{'PASS' if a['pass'] else 'FAIL'}  {a['figure']}: {value} (target {sign} {a['target']:.3g}{a['unit']})"
