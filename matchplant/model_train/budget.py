"""Honest training reports: the time budget (``max_minutes``) and the size of the validation set.

``max_minutes``: after the first epoch of a session its wall time (training, validation, checkpoints)
gives how many epochs fit in the budget; when fewer than ``epochs`` fit, the run is planned for that many
and the learning-rate schedule is shortened in proportion (:func:`matchplant.model_train.run.lr_factor`:
a step every ``step_size`` epochs of a 30-epoch plan becomes one every ``step_size * planned / 30``), so
a budget-limited run still ends at the small learning rates instead of being cut while they are high.
Each later epoch is still checked against the clock (an epoch that would end past the budget is not
started). The summary then says "stopped by max_minutes after 6 of 30 epochs", not "finished".

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


@dataclass
class Plan:
    """The number of epochs the run is planned for (``epochs``, or fewer when the budget is short)."""

    epochs: int
    fitted: bool = False        # the budget has been taken into account in this run
    first_epoch_s: float | None = None


def epochs_that_fit(total_epochs: int, done: int, max_minutes: float, elapsed_s: float, epoch_s: float) -> int:
    """Epochs the run can complete within ``max_minutes``: those done plus whole epochs of ``epoch_s``
    in the time left (at least the ones done, at most ``total_epochs``)."""
    left = max_minutes * 60.0 - elapsed_s
    more = math.floor(left / epoch_s) if epoch_s > 0 else total_epochs
    return int(min(total_epochs, max(done, done + more)))


def fit_plan(plan: Plan, total_epochs: int, done: int, max_minutes: float, elapsed_s: float, epoch_s: float) -> None:
    """Shorten ``plan`` to the epochs that fit (once per run), with a log line saying so."""
    plan.fitted, plan.first_epoch_s = True, round(epoch_s, 3)
    fit = epochs_that_fit(total_epochs, done, max_minutes, elapsed_s, epoch_s)
    if fit < plan.epochs:
        plan.epochs = max(fit, done)
        log.warning("max_minutes = %g: an epoch takes %.0f s, so %d of the %d epochs fit; the learning-rate "
                    "schedule is shortened to %d epochs (raise max_minutes, or lower epochs, to train as set)",
                    max_minutes, epoch_s, plan.epochs, total_epochs, plan.epochs)


def stop_status(done: int, total_epochs: int, max_minutes: float) -> tuple[str, str]:
    """``(status, message)`` for the summary of a run that ended after ``done`` epochs."""
    if done >= total_epochs:
        return "finished", f"finished all {total_epochs} epochs"
    return ("stopped_by_max_minutes",
            f"stopped by max_minutes ({max_minutes:g}) after {done} of {total_epochs} epochs (the learning-rate "
            f"schedule was fitted to the epochs that fit)")


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
