"""Which torch device to use, said out loud: CUDA, then Apple MPS, then CPU, unless the user says otherwise.

:func:`select_device` logs the device and why it was chosen (a GPU found; CUDA not usable and the reason:
a CPU-only PyTorch build, no NVIDIA driver, a driver too old for this build, a GPU this build was not
compiled for; MPS; CPU). :func:`choose_threads` picks torch's CPU thread count from the cores this
process may use (its affinity and cgroup quota) less those other work keeps busy (the load average), and
:func:`configure_threads` applies and logs it (modules 6 and 7 and the demo; a ``threads`` key overrules it).
:func:`measure_cpu_rates` measures each architecture's ``cpu_seconds_per_megapixel`` (docs/performance.md,
"How long will it take?"). Module 7 estimates a detection run from a probe of the real model on the user's machine
(:mod:`matchplant.model_test.estimate`), not from these rates.
"""

from __future__ import annotations

import os
import shutil
import warnings

from matchplant.core.runtime.cores import usable_cores
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.architectures import ARCHITECTURES, Architecture
from matchplant.detection.model import ModelConfig, build_detector

DEVICE_CHOICES = ("auto", "cuda", "mps", "cpu")
log = get_logger("device")


def cuda_unusable_reason(torch) -> str:
    """Why ``torch.cuda`` cannot be used here, in words a user can act on."""
    if torch.version.cuda is None:
        return (
            "this PyTorch build has no CUDA support (a CPU-only wheel); install a CUDA build from "
            "https://pytorch.org/get-started/locally/ to use an NVIDIA GPU"
        )
    has_driver = shutil.which("nvidia-smi") is not None or os.path.exists("/proc/driver/nvidia/version")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.is_available()
    said = " ".join(str(caught[-1].message).split()) if caught else ""
    if not has_driver and not said:
        return f"no NVIDIA GPU driver found (PyTorch is built for CUDA {torch.version.cuda})"
    if said:
        return f"PyTorch (CUDA {torch.version.cuda}) cannot use the GPU: {said}"
    return (
        f"an NVIDIA driver is installed but PyTorch (CUDA {torch.version.cuda}) sees no usable GPU; "
        "check `nvidia-smi` and CUDA_VISIBLE_DEVICES"
    )


def _cuda_works(torch, dev) -> str | None:
    """None when a small computation runs on ``dev``, else the error (e.g. a GPU too new for this build)."""
    try:
        (torch.ones(8, device=dev) * 2).sum().item()
        return None
    except Exception as exc:  # noqa: BLE001 - any failure means "not usable", reported to the user
        return " ".join(str(exc).split())[:300]


def _describe_cuda(torch, dev) -> str:
    index = dev.index if dev.index is not None else torch.cuda.current_device()
    props = torch.cuda.get_device_properties(index)
    return (
        f"{props.name}, {props.total_memory / 2**30:.0f} GiB, compute capability {props.major}.{props.minor}; "
        f"PyTorch {torch.__version__} built for CUDA {torch.version.cuda}"
    )


def explain_device(preference: str = "auto"):
    """``(torch.device, reason)`` for ``preference`` (auto, cpu, mps, cuda or cuda:N)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    pref = (preference or "auto").lower()
    mps = getattr(torch.backends, "mps", None)
    mps_ok = mps is not None and mps.is_available()
    if pref == "cpu":
        return torch.device("cpu"), "asked for (device: cpu)"
    if pref == "auto":
        if torch.cuda.is_available():
            dev = torch.device("cuda")
            broken = _cuda_works(torch, dev)
            if broken is None:
                return dev, f"CUDA GPU found: {_describe_cuda(torch, dev)}"
            why = f"a CUDA GPU is present but a test computation failed: {broken}"
        else:
            why = cuda_unusable_reason(torch)
        if mps_ok:
            return torch.device("mps"), f"Apple Metal (MPS) GPU; no CUDA: {why}"
        return torch.device("cpu"), f"no GPU: {why}"
    if pref.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(
                f"device '{preference}' was asked for but CUDA cannot be used: {cuda_unusable_reason(torch)}",
                fix="set device: auto (or cpu)",
            )
        dev = torch.device(pref)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(
                f"device '{preference}' does not exist: {torch.cuda.device_count()} GPU(s) found",
                fix="use cuda:0 .. cuda:N-1, or device: auto",
            )
        broken = _cuda_works(torch, dev)
        if broken is not None:
            raise ConfigError(
                f"device '{preference}' fails a test computation: {broken}",
                fix="install a PyTorch build for this GPU and driver, or set device: cpu",
            )
        return dev, f"asked for: {_describe_cuda(torch, dev)}"
    if pref == "mps":
        if not mps_ok:
            raise ConfigError(
                "device 'mps' was asked for but Apple Metal is not available", fix="set device: auto (or cpu)"
            )
        return torch.device("mps"), "asked for: Apple Metal (MPS)"
    raise ConfigError(f"unknown device '{preference}'", fix="use auto, cuda, cuda:N, mps or cpu")


def select_device(preference: str = "auto"):
    """Return a ``torch.device`` and log which one and why."""
    dev, why = explain_device(preference)
    log.info("device: %s (%s)", dev, why)
    return dev


def choose_threads(
    requested: int | None = None, *, load: float | None = None, cores: int | None = None
) -> tuple[int, str]:
    """``(threads, reason)`` for torch on the CPU. ``requested`` (a ``threads`` key > 0) is used as given;
    otherwise the usable cores less the busy ones: the 1-minute load average (other processes' runnable
    work, ``os.getloadavg``) is subtracted, rounded, and at least one thread is kept. On a shared 2-core
    machine PyTorch's default (every core) ran small training steps 5-10x slower than one thread,
    because its threads wait for cores that other work holds (issue 29)."""
    if requested:
        return int(requested), f"threads: {requested} (set in the config)"
    n, source = (cores, "given") if cores else usable_cores()
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (OSError, AttributeError):  # Windows: no load average
            load = 0.0
    busy = min(n - 1, round(max(load, 0.0)))
    threads = max(1, n - busy)
    why = f"{n} usable core(s) ({source}), load average {load:.1f}"
    if busy:
        why += f": {busy} busy, so {threads}"
    return threads, f"{why} (set 'threads' to overrule)"


def configure_threads(requested: int | None = None) -> int:
    """Set torch's CPU thread count (:func:`choose_threads`) and log it with the reason; returns it."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    threads, why = choose_threads(requested)
    torch.set_num_threads(threads)
    log.info("CPU threads: %d (%s)", threads, why)
    return threads


def _measured() -> list[Architecture]:
    return [a for a in ARCHITECTURES.values() if a.cpu_seconds_per_megapixel is not None]


def measure_cpu_rates(architectures=None, tile: int = 1024, repeats: int = 2) -> dict[str, float]:
    """Seconds per megapixel of one detection pass on the CPU, per architecture: a ``tile`` x ``tile`` image
    (module 7's default tile, resized by the model to its ``min_size``), random weights, best of ``repeats``."""
    import time

    import torch  # lazy: PyTorch is heavy; configs load without it

    rates = {}
    for arch in architectures or [a.name for a in _measured()]:
        model = build_detector(ModelConfig(architecture=arch, pretrained="none"), 2, load_weights=False).eval()
        image = torch.rand(3, tile, tile)
        best = float("inf")
        with torch.inference_mode():
            model([image])  # warm-up
            for _ in range(repeats):
                t0 = time.perf_counter()
                model([image])
                best = min(best, time.perf_counter() - t0)
        rates[arch] = best / (tile * tile / 1e6)
    return rates


if (
    __name__ == "__main__"
):  # python -m matchplant.detection.device [--measure [ARCH ...]]: the device and why; CPU rates
    import sys

    from matchplant.core.runtime.log import setup_console

    setup_console()
    select_device("auto")
    if "--measure" in sys.argv:
        import torch  # lazy: PyTorch is heavy; configs load without it

        configure_threads()  # as module 7 does: PyTorch's default took every core, also under taskset -c 1
        print(f"CPU seconds per megapixel (one detection pass, {torch.get_num_threads()} threads):")
        names = [a for a in sys.argv[sys.argv.index("--measure") + 1 :] if not a.startswith("-")]  # or every one
        for name, value in measure_cpu_rates(names or None).items():
            print(f"  {name:<36} {value:.2f}")
