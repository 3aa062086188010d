"""Module 6's checkpoints: :func:`save` writes one (self-contained: the detector, the optimisation's state, the
history, the plan, and inside an epoch its progress and random state); :func:`restore` puts a resumed run's
state back (:mod:`~matchplant.model_train.resume` finds and checks the checkpoint)."""

from __future__ import annotations

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.model_train.state import Job, TrainState

log = get_logger("model_train")


def save(job: Job, state: TrainState, name: str, epoch_done: int, record: dict | None, partial: dict | None) -> None:
    """``checkpoints/<name>`` after ``epoch_done`` whole epochs; ``partial``: the stopped epoch's progress."""
    content = dict(
        epoch=epoch_done,
        iteration=state.done,
        optimizer_state=job.optimizer.state_dict(),
        scheduler_state=job.scheduler.state_dict(),
        scaler_state=job.scaler.state_dict() if job.amp else None,
        history=state.history,
        best=state.best,
        metrics=(record or {}).get("val"),
        train_config=to_dict(job.cfg),
        iters_per_epoch=job.iters,
        training_geometry=job.geometry,
        planned_iters=job.budget.plan.iters,
        epoch_progress=partial,
        random_state=state.stop_rng if partial else None,
    )
    save_checkpoint(job.ck_dir / name, job.core, job.model_cfg, job.class_names, job.train_ds.category_ids, **content)


def restore(job: Job, resume: dict | None) -> TrainState:
    """The state to train from: a new one, or the resumed run's (optimizer, schedule, scaler, history, plan)."""
    state = TrainState()
    if resume is None:
        return state
    iters = job.iters
    if resume.get("iters_per_epoch", iters) != iters and resume.get("epoch_progress"):
        raise ConfigError(
            f"cannot resume inside epoch {resume['epoch'] + 1}: the run had "
            f"{resume['iters_per_epoch']} iterations per epoch, this config gives {iters} "
            "(batch_size or the training set changed)",
            path=job.ck_dir / "last.pt",
            fix="resume with the run's batch_size and training set, or start with --fresh",
        )
    job.optimizer.load_state_dict(resume["optimizer_state"])
    job.scheduler.load_state_dict(resume["scheduler_state"])
    if resume.get("scaler_state"):
        job.scaler.load_state_dict(resume["scaler_state"])
    state.done = int(resume.get("iteration", resume["epoch"] * iters))
    state.history = [h for h in resume["history"] if not h.get("partial")]
    state.best = dict(resume["best"])
    state.progress, state.rng = resume.get("epoch_progress"), resume.get("random_state")
    restore_plan(job.budget, resume, state.done)
    return state


def restore_plan(budget, resume: dict, done: int) -> None:
    """The resumed run's plan; when it is done, this session plans the rest with its own budget."""
    plan, total, iters = budget.plan, budget.total, budget.plan.iters_per_epoch
    if resume.get("planned_iters"):
        plan.iters, plan.fitted, plan.source = min(int(resume["planned_iters"]), total), True, "resumed"
    elif budget.limited and resume.get("planned_epochs"):  # a checkpoint of the epoch-based budget
        plan.iters, plan.fitted = min(int(resume["planned_epochs"]) * iters, total), True
    if not resume.get("planned_iters") and not budget.limited:
        plan.fitted = True
    if plan.iters <= done < total:  # the budget's plan is done: this session plans the rest with its budget
        log.info(
            "the run's plan of %d iterations (fitted to its max_minutes) is done; the remaining %d of %d "
            "are planned now%s (the learning-rate schedule is laid over the longer run)",
            plan.iters,
            total - done,
            total,
            f" with max_minutes = {budget.minutes:g}" if budget.limited else "",
        )
        plan.iters, plan.fitted, plan.source = total, False, "configured"
