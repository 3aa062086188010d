"""A short measured probe before training: seconds per iteration at the config's input size and batch on the
user's device, the validation's cost and the peak memory, and the estimate and advice logged from them.

:func:`probe_speed` trains a copy of the model (the real one is not touched, so the run is the same with or
without the probe) on one batch of real training tiles: the first iteration is timed on its own (memory
allocation, lazy initialisation: often slower), then up to ``MORE`` more while the probe stays within its time
cap; one inference pass times the validation. :func:`heartbeat` logs a line every few seconds while a single
long step (the first batch on a slow CPU can take minutes) gives no other sign of life.
"""

from __future__ import annotations

import copy
import resource
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass

from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration
from matchplant.detection.data import collate
from matchplant.detection.gpu import as_runtime
from matchplant.detection.model import keep_frozen_norms_fixed
from matchplant.model_train.budget import Budget, Costs

log = get_logger("model_train")

MORE = 3  # iterations timed after the first
PROBE_CAP_S = 60.0  # the probe stops adding iterations after this long (or 5 % of the budget)
HEARTBEAT_S = 10.0


@dataclass
class Probe:
    """One detector's speed measured on this device: an iteration, loading a batch, inference, peak memory."""

    first_s: float  # the first iteration (allocation, warm-up)
    iteration_s: float  # a steady iteration (median of the later ones; the first when it was alone)
    iterations: int  # timed
    load_s: float  # reading and augmenting one batch (main process)
    inference_s_per_image: float
    peak_memory_mb: float
    batch: int
    input_px: tuple[int, int]  # the network input of the probe batch (after the model's resize)

    def as_dict(self) -> dict:
        """The measurements for training_summary.json, floats rounded to 4 decimals."""
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


@contextmanager
def heartbeat(what: str, every: float = HEARTBEAT_S):
    """Log ``what: still working (N s)`` every ``every`` seconds until the block ends."""
    stop = threading.Event()
    t0 = time.perf_counter()

    def beat():
        while not stop.wait(every):
            log.info("%s: still working (%s so far)", what, duration(time.perf_counter() - t0))

    thread = threading.Thread(target=beat, daemon=True, name="heartbeat")
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=1.0)


def _peak_memory_mb(runtime) -> float:
    """The peak memory of the probe: the GPU's (CUDA), else the process's."""
    if runtime.asynchronous:
        import torch  # lazy: PyTorch is heavy; configs load without it

        return torch.cuda.max_memory_allocated(runtime.device) / 2**20
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


def probe_speed(
    model,
    dataset,
    batch_size: int,
    device,
    amp: bool,
    *,
    cap_s: float = PROBE_CAP_S,
    num_workers: int = 0,
    run_iters: int | None = None,
) -> Probe:
    """Time training iterations of a copy of ``model`` on the first ``batch_size`` tiles of ``dataset``: the
    first, a second (the steady speed; not when the first took over ``cap_s``), then up to ``MORE`` in all while
    the probe stays under ``cap_s`` and 5 % of the run (``run_iters`` iterations as long as the first)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    runtime = as_runtime(device)
    device = runtime.device
    if runtime.asynchronous:
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]):  # the run's random state is not consumed by the probe
        images, targets = collate([dataset[i % len(dataset)] for i in range(batch_size)])
        load_s = time.perf_counter() - t0
        images = [im.to(device) for im in images]
        targets = [{"boxes": t["boxes"].to(device), "labels": t["labels"].to(device)} for t in targets]
        twin = copy.deepcopy(model).to(device).train()
        keep_frozen_norms_fixed(twin)
        input_px = tuple(twin.transform(images[:1])[0].tensors.shape[-2:])
        times = _time_iterations(twin, images, targets, runtime, amp, cap_s, run_iters)
        if getattr(dataset, "crop", None):  # training on crops: detection (validation) sees whole tiles
            images = [dataset.plain_image(i % len(dataset)).to(device) for i in range(batch_size)]
        inference = _time_inference(twin, images, runtime, amp)
    later = sorted(times[1:])
    steady = later[len(later) // 2] if later else times[0]
    if num_workers == 0:  # loading happens between the steps, in this process
        steady += load_s
    peak = _peak_memory_mb(runtime)
    del twin
    return Probe(
        first_s=times[0],
        iteration_s=steady,
        iterations=len(times),
        load_s=load_s,
        inference_s_per_image=inference,
        peak_memory_mb=peak,
        batch=batch_size,
        input_px=(int(input_px[1]), int(input_px[0])),
    )


def _time_iterations(twin, images, targets, runtime, amp: bool, cap_s: float, run_iters: int | None) -> list[float]:
    """Seconds of each timed training iteration of ``twin`` (a copy of the model, at learning rate 0)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    opt = torch.optim.SGD([p for p in twin.parameters() if p.requires_grad], lr=0.0, momentum=0.9)
    times: list[float] = []
    started = time.perf_counter()
    # a second iteration always, unless the first took longer than the cap: the first pays the warm-up, and
    # taken as the steady speed it made a 30-iteration run's estimate 1.5x the run (1.7x for 6 iterations)
    while len(times) < 1 + MORE and (
        len(times) < 1
        or (len(times) < 2 and times[0] <= cap_s)
        or time.perf_counter() - started + times[-1] <= min(cap_s, 0.05 * times[0] * (run_iters or 10**9))
    ):
        t = time.perf_counter()
        with torch.autocast(device_type=runtime.kind, enabled=amp):
            loss = sum(twin(images, targets).values())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if runtime.asynchronous:
            torch.cuda.synchronize(runtime.device)
        times.append(time.perf_counter() - t)
    return times


def _time_inference(twin, images, runtime, amp: bool) -> float:
    """Seconds per image of one detection pass of ``twin`` over ``images`` (validation's cost)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    twin.eval()
    t = time.perf_counter()
    with torch.inference_mode(), torch.autocast(device_type=runtime.kind, enabled=amp):
        twin(images)
    if runtime.asynchronous:
        torch.cuda.synchronize(runtime.device)
    return (time.perf_counter() - t) / len(images)


def costs_from_probe(probe: Probe, n_val_images: int, n_params: int) -> Costs:
    """Per-iteration, per-validation and per-epoch checkpoint seconds from the probe. A checkpoint holds the
    weights and the optimizer's momentum (twice the weights), written at about 200 MB/s, and last.pt and
    best.pt may both be written."""
    checkpoint = 2 * (0.3 + 3 * 4 * n_params / 200e6)
    validation = 1.15 * probe.inference_s_per_image * n_val_images  # + COCOeval, a few percent
    return Costs(iteration=probe.iteration_s, validation=validation, checkpoint=checkpoint)


def estimate_lines(
    probe: Probe,
    costs: Costs,
    *,
    iters_per_epoch: int,
    epochs: int,
    architecture: str,
    device,
    val_every: int,
    validated: bool,
) -> tuple[list[str], float]:
    """The estimate logged before training, and the whole run's seconds as configured."""
    epoch_s = iters_per_epoch * costs.iteration + costs.checkpoint
    val_s = costs.validation if validated else 0.0
    total = epochs * epoch_s + (epochs // val_every + (epochs % val_every != 0)) * val_s
    lines = [
        (
            f"estimate ({architecture} on {device}, batch {probe.batch}, network input {probe.input_px[0]} x "
            f"{probe.input_px[1]} px): first iteration {probe.first_s:.2f} s, then {costs.iteration:.2f} s per "
            f"iteration ({probe.iterations} timed); {iters_per_epoch} iterations per epoch = {duration(epoch_s)} per "
            f"epoch{f' + {duration(val_s)} validation' if validated else ''}; {epochs} epochs = {duration(total)}; "
            f"peak memory {probe.peak_memory_mb / 1024:.1f} GiB"
        )
    ]
    return lines, total


def advice(total_s: float, budget: Budget, device, architecture: str, fits_iters: int, total_iters: int) -> str | None:
    """What to change when the run as set would not fit the budget (or would take more than a few hours)."""
    if total_s <= budget.horizon_s:
        return None
    ways = []
    if as_runtime(device).on_cpu:
        ways.append("use a CUDA GPU (device: auto picks it; often 20-50x faster)")
        if architecture not in ("fasterrcnn_mobilenet_v3_large_fpn", "fasterrcnn_resnet18_fpn_lite"):
            ways.append(
                "model.architecture: fasterrcnn_mobilenet_v3_large_fpn (or auto), several times faster on a CPU"
            )
        ways.append(
            "a smaller model.min_size/max_size (time grows with the input's area; keep plants >= 24 px, "
            "see 'matchplant inspect')"
        )
    ways.append("fewer epochs")
    over = (
        f"the run as set takes about {duration(total_s)}, more than max_minutes = {budget.minutes:g}: only "
        f"{fits_iters} of {total_iters} iterations fit (the schedule is fitted to them)"
        if budget.limited
        else f"the run as set takes about {duration(total_s)} (no max_minutes set)"
    )
    return f"{over}; to train more in less time: {'; '.join(ways)}"


def log_estimate(lines: list[str], hint: str | None) -> None:
    """Log the time estimate's lines, and the advice to train faster as a warning."""
    for line in lines:
        log.info(line)
    if hint:
        log.warning(hint)
    sys.stderr.flush()
