"""Honest training reports: the time plan (``max_minutes``) and the size of the validation set.

The plan: a short probe (:mod:`matchplant.model_train.probe`) measures seconds per iteration and the
validation's cost before training; :func:`plan_iterations` then gives how many iterations of the configured
``epochs`` x iterations fit in the budget, counting each validation and checkpoint on the way (binary search
over :func:`run_seconds`). The learning-rate schedule is laid over that many iterations
(:mod:`matchplant.model_train.schedule`), so a budget-limited run still ends at the small learning rates
instead of being cut while they are high. The plan is refitted from the measured speed of the real
iterations (after the first epoch or a tenth of the plan, whichever comes first), and once more half way from
the pace since then, validations and checkpoints included (:meth:`Budget.refit_from_pace`); the clock is read after
every iteration: when the next one would leave too little time to validate and save, training stops inside
the epoch, validates, and writes a checkpoint ``--resume`` continues from. The summary then says "stopped by
max_minutes after 412 of 1500 iterations", not "finished".

:class:`Budget` is ``max_minutes`` as one record, built once from the config (:meth:`Budget.from_config`, the one place
the key is read) and passed down: the limit (in seconds here and nowhere else), the session's clock, the plan, its
refits from the measured speed and the decision to stop.

Validation: best.pt is the epoch with the best validation metric; on a handful of plants that choice is
noise (one plant moves AP50 by 1/N), so fewer than ``MIN_VAL_OBJECTS`` distinct plants give a warning
in the log and in the summary.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration
from matchplant.detection.tile_objects import distinct_objects

log = get_logger("model_train")

MIN_VAL_OBJECTS = 20
LONG_RUN_S = 3 * 3600.0  # "a few hours": without a budget, a longer estimate gets the advice too


@dataclass
class Costs:
    """Measured seconds: one training iteration, one validation pass, one epoch's checkpoints."""

    iteration: float
    validation: float = 0.0
    checkpoint: float = 0.0


@dataclass
class Plan:
    """The iterations the run is planned for (``epochs`` x per epoch, or fewer when the budget is short)."""

    iters: int
    iters_per_epoch: int
    fitted: bool = False  # refitted from the real iterations' speed (once per run)
    source: str = "configured"  # configured, probe, measured

    @property
    def epochs(self) -> int:
        """Epochs the planned iterations reach, the last one possibly partial."""
        return math.ceil(self.iters / max(self.iters_per_epoch, 1))


def run_seconds(n: int, iters_per_epoch: int, costs: Costs, val_every: int, validated: bool) -> float:
    """Seconds for ``n`` iterations: training, a validation every ``val_every`` epochs and after the last
    iteration, checkpoints after each epoch and at the end."""
    epochs_done = n // max(iters_per_epoch, 1)
    vals = (epochs_done // val_every + (n % iters_per_epoch != 0 or epochs_done % val_every != 0)) if validated else 0
    saves = epochs_done + (n % iters_per_epoch != 0)
    return n * costs.iteration + vals * costs.validation + saves * costs.checkpoint


def plan_iterations(
    total: int, done: int, iters_per_epoch: int, costs: Costs, budget_s: float, val_every: int, validated: bool
) -> int:
    """The most iterations (at least ``done``, at most ``total``) whose remaining work fits ``budget_s``."""

    def fits(n: int) -> bool:
        return (
            run_seconds(n, iters_per_epoch, costs, val_every, validated)
            - run_seconds(done, iters_per_epoch, costs, val_every, validated)
            <= budget_s
        )

    lo, hi = done, total
    if fits(hi):
        return hi
    while lo < hi - 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def validation_report(val_data: dict | None) -> dict:
    """Tiles, boxes and distinct plants of the validation set, with a warning when it is too small to pick
    best.pt (also logged)."""
    if val_data is None:
        msg = "no validation set (val_json): best.pt is simply the last epoch"
        log.warning(msg)
        return {"tiles": 0, "boxes": 0, "plants": 0, "warning": msg}
    _, plants = distinct_objects(val_data)
    report = {"tiles": len(val_data.get("images", [])), "boxes": len(val_data.get("annotations", [])), "plants": plants}
    if plants < MIN_VAL_OBJECTS:
        report["warning"] = (
            f"the validation set holds only {plants} distinct plant(s) (fewer than "
            f"{MIN_VAL_OBJECTS}): best.pt is chosen on a noisy metric (one plant moves AP50 by "
            f"{1 / max(plants, 1):.2f}); give module 5 a larger val share or more annotated images"
        )
        log.warning(report["warning"])
    return report


def rank0_value(value: float, dist_info, device) -> float:
    """Rank 0's value on every process under torchrun (one broadcast; a clock-based decision must agree)."""
    if dist_info is None or dist_info.world <= 1:
        return value
    import torch  # lazy: PyTorch is heavy; configs load without it

    t = torch.tensor([float(value)], device=device)
    torch.distributed.broadcast(t, src=0)
    return float(t.item())


@dataclass
class Budget:
    """``max_minutes`` of one training session: the limit, the clock (from the session's start: set-up and probe
    count), the plan, its refits from the real speed and the stop decision. 0 minutes: no budget (the plan is the
    configured run, the clock still times the session). The costs, the validation interval and the processes
    (``dist_info``, ``device``: clock decisions agree across them) are attached when known."""

    minutes: float = 0.0
    start: float = field(default_factory=lambda: time.perf_counter())
    plan: Plan | None = None
    total: int = 0
    costs: Costs | None = None
    val_every: int = 1
    validated: bool = False
    stop_flag: Any = None  # resume.StopOnInterrupt: Ctrl-C asks to stop
    dist_info: Any = None
    device: Any = None
    step_times: list[float] = field(default_factory=list)
    fitted_at: tuple[float, int] | None = None  # (elapsed s, iterations) at this session's first refit
    # the epochs are a ceiling the recipe set (choose.scratch_budget): max_minutes, not epochs, ends the run, so the
    # messages speak of the budget only, and its fitting the plan is information, not a warning
    sets_length: bool = False

    @classmethod
    def from_config(cls, cfg) -> Budget:
        """The one place the config's ``max_minutes`` is read; the clock starts now."""
        return cls(minutes=cfg.max_minutes)

    # -- the limit -------------------------------------------------------------------------------------------------
    @property
    def limited(self) -> bool:
        """Whether ``max_minutes`` limits the session (0: no budget)."""
        return bool(self.minutes)

    @property
    def seconds(self) -> float:
        """The limit in seconds (0: none)."""
        return self.minutes * 60.0

    @property
    def horizon_s(self) -> float:
        """The limit, or without one ``LONG_RUN_S`` ("a few hours"): what the advice and the choice of detector
        measure a run against."""
        return self.seconds if self.limited else LONG_RUN_S

    def horizon_words(self) -> str:
        """The time the run must fit in, for messages: ``max_minutes = N``, or a few hours without a budget."""
        return f"max_minutes = {self.minutes:g}" if self.limited else f"{duration(LONG_RUN_S)} (no max_minutes)"

    # -- the clock -------------------------------------------------------------------------------------------------
    def elapsed(self) -> float:
        """Seconds since the session started (set-up and probe included)."""
        return time.perf_counter() - self.start

    def left(self) -> float:
        """Seconds of the limit not yet spent."""
        return self.seconds - self.elapsed()

    def reserve(self) -> float:
        """Seconds kept for the last validation and checkpoints."""
        return (self.costs.validation if self.validated else 0.0) + self.costs.checkpoint

    def iteration_s(self) -> float:
        """Seconds per training iteration: mean of the last 20 steps timed (the first left out), else the estimate."""
        recent = self.step_times[1:][-20:] or self.step_times or [self.costs.iteration]
        return float(np.mean(recent))

    def _agree(self, value: float) -> float:
        return rank0_value(value, self.dist_info, self.device)

    # -- the plan --------------------------------------------------------------------------------------------------
    def plan_for(self, total: int, iters_per_epoch: int) -> Plan:
        """The plan of the configured run (``total`` iterations), to be fitted to the limit."""
        self.plan, self.total = Plan(total, iters_per_epoch), total
        return self.plan

    def fit(self, done: int, costs: Costs, budget_s: float, source: str) -> None:
        """Set ``plan.iters`` to what fits in ``budget_s`` (seconds left), with a log line when it is shorter than
        configured."""
        plan, total = self.plan, self.total
        before = plan.iters
        plan.iters = max(
            plan_iterations(total, done, plan.iters_per_epoch, costs, budget_s, self.val_every, self.validated), done, 1
        )
        plan.source = source
        if plan.iters < total and plan.iters != before and self.sets_length:
            log.info(
                "max_minutes = %g sets the run's length: at %.2f s per iteration (%s), about %d iterations "
                "(%.1f epochs) fit; the learning-rate schedule is laid over them",
                self.minutes,
                costs.iteration,
                source,
                plan.iters,
                plan.iters / plan.iters_per_epoch,
            )
        elif plan.iters < total and plan.iters != before:
            log.warning(
                "max_minutes = %g: at %.2f s per iteration (%s), %d of the %d iterations (%.1f of %d epochs) "
                "fit; the learning-rate schedule is laid over %d iterations (raise max_minutes, or lower "
                "epochs, to train as set)",
                self.minutes,
                costs.iteration,
                source,
                plan.iters,
                total,
                plan.iters / plan.iters_per_epoch,
                math.ceil(total / plan.iters_per_epoch),
                plan.iters,
            )

    # -- the stop decision -----------------------------------------------------------------------------------------
    def after_step(self, done: int, step_s: float) -> str | None:
        """After an iteration: refit the plan once from the real speed; then why to stop (None: go on)."""
        self.step_times.append(step_s)
        plan = self.plan
        if (
            self.limited
            and not plan.fitted
            and len(self.step_times) >= max(3, min(plan.iters_per_epoch, plan.iters // 10))
        ):
            plan.fitted = True
            measured = dataclasses.replace(self.costs, iteration=self.iteration_s())
            self.fit(done, measured, self.left(), "measured on the first iterations")
            plan.iters = int(self._agree(plan.iters))
            self.fitted_at = (self.elapsed(), done)
        elif (
            self.limited
            and self.fitted_at is not None
            and done - self.fitted_at[1] >= max(3, (plan.iters - self.fitted_at[1]) // 2)
        ):
            self.refit_from_pace(done)
        reason = 0.0
        if self.stop_flag.requested:
            reason = 2.0
        elif self.limited and done < plan.iters and self.elapsed() + self.iteration_s() + self.reserve() > self.seconds:
            reason = 1.0
        reason = self._agree(reason)
        return {0.0: None, 1.0: "budget", 2.0: "interrupt"}[reason]

    def refit_from_pace(self, done: int) -> None:
        """Once, half way: the iterations that fit at the pace measured since the first refit, validations and
        checkpoints included (the planned per-epoch costs of many short epochs, or a machine that sped up or slowed
        down, otherwise end the plan well before the budget or cut it)."""
        t0, n0 = self.fitted_at
        self.fitted_at = None
        pace = (self.elapsed() - t0) / max(done - n0, 1)
        left = self.left() - self.reserve()
        iters = int(self._agree(min(self.total, done + max(int(left / pace), 0))))
        if iters != self.plan.iters:
            log.info(
                "max_minutes = %g: at the pace of the last %d iterations (%.2f s each, validations and "
                "checkpoints included) %d iterations fit, not %d; the schedule is laid over them",
                self.minutes,
                done - n0,
                pace,
                iters,
                self.plan.iters,
            )
            self.plan.iters = max(iters, done)

    def out_of_time_for(self, seconds: float) -> bool:
        """Whether ``seconds`` more work (an epoch's validation) leaves too little for the rest."""
        if not self.limited:
            return False
        over = self.elapsed() + seconds + self.iteration_s() + self.reserve() > self.seconds
        return bool(self._agree(1.0 if over else 0.0))

    def epoch_label(self, epoch: int) -> str:
        """``epoch N/M`` of the configured epochs, or ``epoch N`` when the budget sets the run's length (the
        number of epochs that fit changes as the pace is measured; the user set none)."""
        if self.sets_length:
            return f"epoch {epoch + 1}"
        return f"epoch {epoch + 1}/{math.ceil(self.total / max(self.plan.iters_per_epoch, 1))}"

    def status(self, done_iters: int, interrupted: bool = False) -> tuple[str, str]:
        """``(status, message)`` for the summary of a run that ended after ``done_iters`` iterations."""
        total, iters_per_epoch = self.total, self.plan.iters_per_epoch
        planned = None if interrupted else self.plan.iters
        epochs = f"{done_iters / iters_per_epoch:.2f}".rstrip("0").rstrip(".")
        if self.sets_length:  # the user set no epochs: the recipe's ceiling is not theirs to read
            where = f"after {done_iters} iterations ({epochs} epochs)"
        else:
            where = (
                f"after {done_iters} of {total} iterations ({epochs} of {math.ceil(total / iters_per_epoch)} epochs)"
            )
        if interrupted:
            return "interrupted", f"interrupted (Ctrl-C) {where}; --resume continues exactly there"
        over = self.limited and self.elapsed() > self.seconds
        if done_iters >= total and over:  # the one iteration every run makes already took longer than the budget
            return (
                "finished_over_max_minutes",
                f"finished all {math.ceil(total / iters_per_epoch)} epochs ({total} iterations) in "
                f"{self.elapsed():.1f} s, past max_minutes = {self.minutes:g} ({self.seconds:.1f} s): the budget is "
                "shorter than the run's least work (one iteration, validation and checkpoints); raise max_minutes "
                "or set it to 0",
            )
        if done_iters >= total:
            return "finished", f"finished all {math.ceil(total / iters_per_epoch)} epochs ({total} iterations)"
        if over:  # an iteration is never cut: the last one may end a little after the budget
            where += (
                f", in {self.elapsed():.1f} s ({self.elapsed() - self.seconds:.1f} s past max_minutes: the iteration, "
                "validation and checkpoints under way are finished, never cut)"
            )
        if done_iters >= planned:
            return (
                "stopped_by_max_minutes",
                (
                    f"stopped by max_minutes ({self.minutes:g}) {where}, the end of the "
                    "plan fitted to the budget (the learning-rate schedule ran its course)"
                ),
            )
        return (
            "stopped_by_max_minutes",
            f"stopped by max_minutes ({self.minutes:g}) {where}, before the end of the plan fitted to it "
            f"({planned} iterations at the pace measured before: training ran slower); --resume trains the "
            f"{planned - done_iters} left"
            if planned
            else f"stopped by max_minutes {where}",
        )
