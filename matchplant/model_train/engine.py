"""Module 6's training engine, after torchvision's references/detection/engine.py: small parts over the two records
of :mod:`~matchplant.model_train.state`.

- :func:`train_step`: one optimisation step on one batch (forward, loss check, backward, optimizer, schedule);
- :func:`train_one_epoch`: the steps of one epoch (or of its rest, resumed), asking after each whether to stop;
- :func:`evaluate`: COCOeval of the detector on the validation tiles;
- :func:`run_epoch`: one epoch with its seeding, its record, validation, checkpoints and summary;
- :func:`loop`: epochs until the plan is done, the budget ends or Ctrl-C; :func:`finish`: the summary.

Each epoch's order and augmentation depend only on (seed, epoch); a resumed epoch restores the random state the
interrupted run had, so a resumed run repeats the uninterrupted one exactly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from contextlib import nullcontext

from matchplant.core.runtime.errors import MatchPlantError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.detection.data import CocoDetection
from matchplant.detection.evaluate import coco_evaluate, predict_dataset, summarise_stats
from matchplant.detection.gpu import as_runtime
from matchplant.detection.model import ModelConfig, keep_frozen_norms_fixed
from matchplant.model_train.checkpoint import save, save_numbered
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.gpu import READ_EVERY
from matchplant.model_train.probe import HEARTBEAT_S, heartbeat
from matchplant.model_train.report import plot_curves, write_summary
from matchplant.model_train.resume import random_state, set_random_state
from matchplant.model_train.setup import seed_everything
from matchplant.model_train.state import Job, TrainState

log = get_logger("model_train")


def check_loss(value: float, desc: str) -> None:
    """A loss that is not finite stops training with what to change."""
    if not math.isfinite(value):
        raise MatchPlantError(
            f"the training loss became {value} ({desc})",
            fix="lower the learning rates (lr.*) or raise warmup_iters; check the boxes",
        )


def train_step(model, images, targets, optimizer, scheduler, scaler, device, amp: bool, desc: str, dtype=None):
    """One step on a batch: ``(loss names, their values and the total's)``. On a CPU the values come as floats,
    checked here (one transfer per step, free there); on CUDA as one tensor left on the device, read and checked by
    :class:`LossTally` every few steps (a read waits for the GPU: model_train/gpu.py)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    runtime = as_runtime(device)
    device = runtime.device
    images = [im.to(device, non_blocking=True) for im in images]
    targets = [
        {"boxes": t["boxes"].to(device, non_blocking=True), "labels": t["labels"].to(device, non_blocking=True)}
        for t in targets
    ]
    with torch.autocast(device_type=runtime.kind, enabled=amp, dtype=dtype):
        loss_dict = model(images, targets)
        loss = sum(loss_dict.values())
    values = torch.stack([*(v.detach().float() for v in loss_dict.values()), loss.detach().float()])
    if not runtime.losses_on_device:
        values = values.tolist()
        check_loss(values[-1], desc)
    optimizer.zero_grad(set_to_none=True)
    scaler.scale(loss).backward()
    scaler.step(optimizer)
    scaler.update()
    scheduler.step()
    return (*loss_dict, "loss"), values


class LossTally:
    """The epoch's loss sums: added at once from floats (a CPU), or summed on the device and read every
    :data:`~matchplant.model_train.gpu.READ_EVERY` steps and at the end (CUDA), where the loss is checked."""

    def __init__(self, sums: dict[str, float], desc: str):
        self.sums, self.desc = sums, desc
        self.names, self.pending, self.count = None, None, 0

    def add(self, names, values) -> bool:
        """Add a step's losses; True when the sums are up to date (the progress bar may show them)."""
        if isinstance(values, list):
            for k, v in zip(names, values):
                self.sums[k] = self.sums.get(k, 0.0) + v
            return True
        self.names = names
        self.pending = values if self.pending is None else self.pending + values
        self.count += 1
        return self.flush() if self.count >= READ_EVERY else False

    def flush(self) -> bool:
        """Read the losses summed on the device into the sums, checking the loss; True (the sums are up to date)."""
        if self.pending is not None:
            values = self.pending.tolist()  # the one host-device sync of READ_EVERY steps
            check_loss(values[-1], self.desc)
            for k, v in zip(self.names, values):
                self.sums[k] = self.sums.get(k, 0.0) + v
        self.pending, self.count = None, 0
        return True


def train_one_epoch(
    model,
    loader,
    optimizer,
    scheduler,
    scaler,
    device,
    amp: bool,
    desc: str,
    sums: dict[str, float],
    batches: int,
    after: Callable[[float], str | None],
    *,
    slow: bool,
    limit: int,
    dtype=None,
) -> tuple[str | None, int]:
    """Train on the loader's batches (at most ``limit``), adding the losses into ``sums``; ``after(step_s)`` after
    each iteration says whether to stop. Returns ``(why it stopped or None, batches done in this epoch)``. A
    heartbeat line shows life during slow iterations (the first one, or all when the probe found them slow)."""
    model.train()
    keep_frozen_norms_fixed(model)
    bar = progress(loader, desc=desc, unit="batch", total=min(len(loader), limit))
    batch_iter = iter(bar)
    reason, first, tally = None, True, LossTally(sums, desc)
    try:
        for _ in range(limit):
            t0 = time.perf_counter()
            with heartbeat(f"{desc}, batch {batches + 1}") if (slow or first) else nullcontext():
                try:
                    images, targets = next(batch_iter)
                except StopIteration:
                    break
                step = train_step(model, images, targets, optimizer, scheduler, scaler, device, amp, desc, dtype)
            first = False
            batches += 1
            if tally.add(*step) and hasattr(bar, "set_postfix"):
                bar.set_postfix(loss=f"{sums['loss'] / batches:.3f}")
            reason = after(time.perf_counter() - t0)
            if reason is not None:
                break
        tally.flush()
    finally:
        if hasattr(bar, "close"):
            bar.close()
    return reason, batches


def evaluate(model, val_ds: CocoDetection, model_cfg: ModelConfig, cfg: ModelTrainConfig, device, amp: bool) -> dict:
    """COCOeval of the model on the validation tiles, boxes above ``val_score_threshold``."""
    heads = model.roi_heads
    saved = heads.score_thresh
    heads.score_thresh = cfg.val_score_threshold
    try:
        results = predict_dataset(
            model, val_ds, device, batch_size=cfg.batch_size, num_workers=cfg.num_workers, amp=amp, desc="validating"
        )
    finally:
        heads.score_thresh = saved
    stats, _ = coco_evaluate(val_ds.data, results, max_dets=model_cfg.roi.detections_per_img)
    stats["detections"] = len(results)
    return stats


def after_iteration(job: Job, state: TrainState, step_s: float) -> str | None:
    """Count the iteration, tell the caller, and ask the budget whether to stop."""
    state.done += 1
    if job.on_iteration is not None:
        job.on_iteration(state.done)
    return job.budget.after_step(state.done, step_s)


def begin_epoch(job: Job, state: TrainState, epoch: int, start: int) -> tuple[dict, int]:
    """Seed the epoch (and mid-epoch, the interrupted run's random state); ``(loss sums, batches done)``."""
    cfg = job.cfg
    seed_everything(cfg.seed * 100003 + epoch)
    if start and state.rng is not None:
        set_random_state(state.rng, job.runtime)
    job.train_ds.set_seed(cfg.seed * 100003 + epoch)
    if getattr(job.loader, "persistent_workers", False):  # workers kept from the last epoch: the seed goes with
        job.sampler.item_seed = cfg.seed * 100003 + epoch  # each index (detection/data.py EpochSampler)
    job.sampler.set_epoch(epoch, start * cfg.batch_size)
    sums = dict(state.progress["sums"]) if start and state.progress else {}
    batches = int(state.progress["batches"]) if start and state.progress else 0
    state.progress, state.rng = None, None
    return sums, batches


def epoch_record(
    job: Job, state: TrainState, epoch: int, start: int, sums: dict, batches: int, train_time: float
) -> dict:
    """The epoch's line of the history: iterations, learning rates, mean losses (over every process), speed."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    dist_info, iters = job.dist_info, job.iters
    means = {k: v / max(batches, 1) for k, v in sums.items()}
    if dist_info.world > 1:  # the mean over every process
        keys = sorted(means)
        t = torch.tensor([means[k] for k in keys], device=job.device)
        torch.distributed.all_reduce(t)
        means = dict(zip(keys, (t / dist_info.world).tolist()))
    record = {
        "epoch": epoch + 1,
        "iterations": state.done,
        "lr": {g["name"]: g["lr"] for g in job.optimizer.param_groups},
        "losses": means,
        "train_time_s": round(train_time, 3),
        "train_images_per_s": round(
            (state.done - epoch * iters - start) * job.cfg.batch_size * dist_info.world / max(train_time, 1e-9), 3
        ),
    }
    if batches < iters:
        record.update(partial=True, batches=batches)
    return record


def stop_interrupted(job: Job, state: TrainState, epoch: int, record: dict, sums: dict, batches: int) -> None:
    """Ctrl-C: no validation (the user wants out); the checkpoint continues exactly here."""
    if job.dist_info.main:
        save(job, state, "last.pt", epoch, record, {"batches": batches, "sums": sums})
        write_summary(
            job.out,
            job.cfg,
            state.history + [record],
            state.best,
            job.class_names,
            job.device,
            "interrupted",
            job.budget,
            validation=job.validation,
            extras=job.extras,
            message=job.budget.status(state.done, interrupted=True)[1],
        )
    log.debug(  # the command's own line says it (one line on Ctrl-C)
        "interrupted after %d of %d planned iterations: %s written; --resume continues there",
        state.done,
        job.budget.plan.iters,
        job.ck_dir / "last.pt",
    )
    raise KeyboardInterrupt


def run_epoch(job: Job, state: TrainState) -> str | None:
    """One epoch (or its rest), its validation and checkpoints; why training stops after it, or None."""
    cfg, budget, iters = job.cfg, job.budget, job.iters
    plan = budget.plan
    epoch, start = divmod(state.done, iters)
    sums, batches = begin_epoch(job, state, epoch, start)
    t0 = time.perf_counter()
    reason, batches = train_one_epoch(
        job.model,
        job.loader,
        job.optimizer,
        job.scheduler,
        job.scaler,
        job.runtime,
        job.amp,
        budget.epoch_label(epoch),
        sums,
        batches,
        lambda step_s: after_iteration(job, state, step_s),
        slow=budget.costs.iteration >= HEARTBEAT_S / 2 or not budget.step_times,
        limit=min(iters, plan.iters - epoch * iters) - start,
        dtype=job.amp_dtype,
    )
    train_time = time.perf_counter() - t0
    # the random state where training stopped (validation draws from it too; a resumed run starts here)
    state.stop_rng = random_state(job.runtime) if batches < iters else None
    record = epoch_record(job, state, epoch, start, sums, batches, train_time)
    if reason == "interrupt":
        stop_interrupted(job, state, epoch, record, sums, batches)
    if (
        reason is None
        and state.done < plan.iters
        and budget.out_of_time_for(
            budget.costs.validation if (epoch + 1) % cfg.val_every == 0 and job.val_ds is not None else 0.0
        )
    ):
        reason = "budget"
    end_epoch(job, state, record, sums, batches, train_time, last=state.done >= plan.iters or reason is not None)
    return reason


def end_epoch(
    job: Job, state: TrainState, record: dict, sums: dict, batches: int, train_time: float, *, last: bool
) -> None:
    """Validate (every ``val_every`` epochs and at the end), keep the best, log the epoch, write its checkpoints
    and the summary, then tell the caller."""
    cfg, epoch, complete = job.cfg, record["epoch"] - 1, batches >= job.iters
    if job.val_ds is not None and ((complete and (epoch + 1) % cfg.val_every == 0) or last) and job.dist_info.main:
        record["val"] = evaluate(job.core, job.val_ds, job.model_cfg, cfg, job.device, job.amp)
    state.history.append(record)
    value = record.get("val", {}).get(cfg.best_metric) if job.val_ds is not None else float(state.done)
    improved = value is not None and (state.best["value"] is None or value > state.best["value"])
    if improved:
        state.best = {
            "epoch": epoch + 1,
            "iterations": state.done,
            "value": value,
            "metric": cfg.best_metric if job.val_ds else "last epoch",
        }
    log.info(
        "%s%s: loss %.4f%s (%.1f s)",
        job.budget.epoch_label(epoch),
        "" if complete else f" (stopped after {batches} of {job.iters} batches)",
        record["losses"].get("loss", math.nan),
        f"; validation {summarise_stats(record['val'])}" if "val" in record else "",
        train_time,
    )
    if job.dist_info.main:
        save_epoch(job, state, record, None if complete else {"batches": batches, "sums": sums}, improved)
    job.dist_info.barrier()
    if job.on_epoch_end is not None and complete:
        job.on_epoch_end(epoch + 1, record)


def save_epoch(job: Job, state: TrainState, record: dict, partial: dict | None, improved: bool) -> None:
    """last.pt, best.pt when the epoch improved, epoch_NNN.pt as ``save_every`` asks; the summary, the curves."""
    epoch, complete = record["epoch"] - 1, partial is None
    save(job, state, "last.pt", epoch + complete, record, partial)
    if improved:
        save(job, state, "best.pt", epoch + complete, record, partial)
    if complete:
        save_numbered(job, state, epoch + 1, record)
    write_summary(
        job.out,
        job.cfg,
        state.history,
        state.best,
        job.class_names,
        job.device,
        "running",
        job.budget,
        validation=job.validation,
        extras=job.extras,
    )
    plot_curves(state.history, job.out / "training_curves.png")


def loop(job: Job, state: TrainState) -> str | None:
    """Epochs until the plan is done or training must stop; returns why it stopped ("budget") or None."""
    reason = None
    with job.budget.stop_flag:
        while state.done < job.budget.plan.iters and reason is None:
            reason = run_epoch(job, state)
    return reason


def finish(job: Job, state: TrainState, reason: str | None) -> dict:
    """The final summary and log lines; returns the summary (empty on other processes than rank 0)."""

    budget, done, main = job.budget, state.done, job.dist_info.main
    if reason == "budget" or (done >= budget.plan.iters and budget.plan.iters < budget.total):
        of = "" if budget.sets_length else f" of {budget.total}"
        log.info("stopping after %d%s iterations: max_minutes = %g", done, of, budget.minutes)
    summary = {}
    if main:
        status, message = budget.status(done)
        summary = write_summary(
            job.out,
            job.cfg,
            state.history,
            state.best,
            job.class_names,
            job.device,
            status,
            budget,
            validation=job.validation,
            message=message,
            extras=job.extras,
        )
        over = status == "finished_over_max_minutes"  # a budget shorter than the least run: said, not buried
        (log.warning if over else log.info)("training %s (%s)", message, clock_words(budget.elapsed()))
    if main and state.best["epoch"] is not None:
        log.info(
            "best epoch %d (%s %.4f); model: %s",
            state.best["epoch"],
            state.best.get("metric"),
            state.best["value"],
            job.ck_dir / "best.pt",
        )
    job.dist_info.leave()
    return summary


def clock_words(seconds: float) -> str:
    """A duration for the log: minutes with one decimal from a minute up, whole seconds below."""
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"
