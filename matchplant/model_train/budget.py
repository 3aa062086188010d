"""Honest training reports: the time plan (``max_minutes``) and the size of the validation set.

The plan: a short probe (:mod:`matchplant.model_train.probe`) measures seconds per iteration and the
validation's cost before training; :func:`plan_iterations` then gives how many iterations of the configured
``epochs`` x iterations fit in the budget, counting each validation and checkpoint on the way (binary search
over :func:`run_seconds`). The learning-rate schedule is laid over that many iterations
(:mod:`matchplant.model_train.schedule`), so a budget-limited run still ends at the small learning rates
instead of being cut while they are high. The plan is refitted from the measured speed of the real
iterations (after the first epoch or a tenth of the plan, whichever comes first), and once more half way from
the pace since then, validations and checkpoints included (``run._Session.refit_from_pace``); the clock is read after
every iteration: when the next one would leave too little time to validate and save, training stops inside
the epoch, validates, and writes a checkpoint ``--resume`` continues from. The summary then says "stopped by
max_minutes after 412 of 1500 iterations", not "finished".

Validation: best.pt is the epoch with the best validation metric; on a handful of plants that choice is
noise (one plant moves AP50 by 1/N), so fewer than ``MIN_VAL_OBJECTS`` distinct plants give a warning
in the log and in the summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from matchplant.core.runtime.log import get_logger
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
    fitted: bool = False          # refitted from the real iterations' speed (once per run)
    source: str = "configured"    # configured, probe, measured

    @property
    def epochs(self) -> int:
        return math.ceil(self.iters / max(self.iters_per_epoch, 1))


def run_seconds(n: int, iters_per_epoch: int, costs: Costs, val_every: int, validated: bool) -> float:
    """Seconds for ``n`` iterations: training, a validation every ``val_every`` epochs and after the last
    iteration, checkpoints after each epoch and at the end."""
    epochs_done = n // max(iters_per_epoch, 1)
    vals = (epochs_done // val_every + (n % iters_per_epoch != 0 or epochs_done % val_every != 0)) if validated else 0
    saves = epochs_done + (n % iters_per_epoch != 0)
    return n * costs.iteration + vals * costs.validation + saves * costs.checkpoint


def plan_iterations(total: int, done: int, iters_per_epoch: int, costs: Costs, budget_s: float, val_every: int,
                    validated: bool) -> int:
    """The most iterations (at least ``done``, at most ``total``) whose remaining work fits ``budget_s``."""
    def fits(n: int) -> bool:
        return run_seconds(n, iters_per_epoch, costs, val_every, validated) - \
            run_seconds(done, iters_per_epoch, costs, val_every, validated) <= budget_s

    lo, hi = done, total
    if fits(hi):
        return hi
    while lo < hi - 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def fit_plan(plan: Plan, total: int, done: int, costs: Costs, budget_s: float, val_every: int, validated: bool,
             source: str, max_minutes: float) -> None:
    """Set ``plan.iters`` to what fits in ``budget_s`` (seconds left), with a log line when it is shorter than
    configured."""
    before = plan.iters
    plan.iters = max(plan_iterations(total, done, plan.iters_per_epoch, costs, budget_s, val_every, validated),
                     done, 1)
    plan.source = source
    if plan.iters < total and plan.iters != before:
        log.warning("max_minutes = %g: at %.2f s per iteration (%s), %d of the %d iterations (%.1f of %d epochs) "
                    "fit; the learning-rate schedule is laid over %d iterations (raise max_minutes, or lower "
                    "epochs, to train as set)", max_minutes, costs.iteration, source, plan.iters, total,
                    plan.iters / plan.iters_per_epoch, math.ceil(total / plan.iters_per_epoch), plan.iters)


def stop_status(done_iters: int, total: int, iters_per_epoch: int, max_minutes: float, interrupted: bool = False,
                planned: int | None = None) -> tuple[str, str]:
    """``(status, message)`` for the summary of a run that ended after ``done_iters`` iterations."""
    epochs = f"{done_iters / iters_per_epoch:.2f}".rstrip("0").rstrip(".")
    where = f"after {done_iters} of {total} iterations ({epochs} of {math.ceil(total / iters_per_epoch)} epochs)"
    if interrupted:
        return "interrupted", f"interrupted (Ctrl-C) {where}; --resume continues exactly there"
    if done_iters >= total:
        return "finished", f"finished all {math.ceil(total / iters_per_epoch)} epochs ({total} iterations)"
    if planned is not None and done_iters >= planned:
        return ("stopped_by_max_minutes", (f"stopped by max_minutes ({max_minutes:g}) {where}, the end of the plan "
                                           "fitted to the budget (the learning-rate schedule ran its course)"))
    return ("stopped_by_max_minutes", f"stopped by max_minutes ({max_minutes:g}) {where}; --resume continues "
            f"the planned {planned} iterations" if planned else f"stopped by max_minutes {where}")


def validation_report(val_data: dict | None) -> dict:
    """Tiles, boxes and distinct plants of the validation set, with a warning when it is too small to pick
    best.pt (also logged)."""
    if val_data is None:
        msg = "no validation set (val_json): best.pt is simply the last epoch"
        log.warning(msg)
        return {"tiles": 0, "boxes": 0, "plants": 0, "warning": msg}
    _, plants = distinct_objects(val_data)
    report = {"tiles": len(val_data.get("images", [])), "boxes": len(val_data.get("annotations", [])),
              "plants": plants}
    if plants < MIN_VAL_OBJECTS:
        report["warning"] = (f"the validation set holds only {plants} distinct plant(s) (fewer than "
                             f"{MIN_VAL_OBJECTS}): best.pt is chosen on a noisy metric (one plant moves AP50 by "
                             f"{1 / max(plants, 1):.2f}); give module 5 a larger val share or more annotated images")
        log.warning(report["warning"])
    return report
