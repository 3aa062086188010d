"""Module 6's checkpoints: :func:`save` writes one (self-contained: the detector, the optimisation's state, the
history, the plan, and inside an epoch its progress and random state); :func:`save_numbered` keeps the
``epoch_NNN.pt`` that ``save_every`` asks for (bounded when the budget sets the run's length) and logs the disk they
use; :func:`restore` puts a resumed run's state back (:mod:`~matchplant.model_train.resume` finds and checks the
checkpoint)."""

from __future__ import annotations

import re

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.readers import read_record
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.model_train.state import Job, TrainState

log = get_logger("model_train")

AUTO_EVERY = 5  # save_every: auto keeps epoch_NNN.pt every AUTO_EVERY epochs ...
AUTO_KEEP = 3  # ... and, when max_minutes sets the run's length, only the last AUTO_KEEP of them
NUMBERED = re.compile(r"epoch_(\d+)\.pt")
AUTO_RECORD = "auto_checkpoints.json"  # the epoch_NNN.pt that save_every: auto wrote and may delete
AUTO_RECORD_TEXT = (
    "the epoch_NNN.pt files that module 6's save_every: auto wrote and will delete (it keeps the last 3): "
    "no other file of this folder is ever deleted"
)
RECORD_FIX = "delete it: then no epoch_NNN.pt is deleted by save_every: auto (each is kept)"


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


def save_numbered(job: Job, state: TrainState, epoch: int, record: dict) -> None:
    """``epoch_NNN.pt`` after whole epoch ``epoch`` when ``save_every`` asks for it. With ``save_every: auto`` and a
    budget that sets the length (``max_minutes``: the epochs are a ceiling, 1000 for a CPU recipe) only the last
    AUTO_KEEP are kept; a number set by the user keeps them all. The checkpoints' disk use is logged and kept in the
    summary (``checkpoint_disk``)."""
    every = AUTO_EVERY if job.cfg.save_every == "auto" else job.cfg.save_every
    if not every or epoch % every:
        return
    name = f"epoch_{epoch:03d}.pt"
    deletable = auto_written(job.ck_dir)
    save(job, state, name, epoch, record, None)
    removed = []
    if job.cfg.save_every == "auto" and job.budget.limited:
        # only the files a save_every: auto session wrote (this one or an earlier one, recorded): never one that
        # a session with save_every: N kept, nor one the user put there
        mine = sorted({*deletable, name}, key=lambda n: int(NUMBERED.fullmatch(n)[1]))
        mine = [n for n in mine if (job.ck_dir / n).is_file()]
        for old in mine[:-AUTO_KEEP]:
            (job.ck_dir / old).unlink(missing_ok=True)
            removed.append(old)
        write_json(job.ck_dir / AUTO_RECORD, {"description": AUTO_RECORD_TEXT, "files": mine[-AUTO_KEEP:]})
    elif name in deletable:  # written again by a session that keeps it: no longer auto's to delete
        write_json(job.ck_dir / AUTO_RECORD, {"description": AUTO_RECORD_TEXT, "files": sorted(deletable - {name})})
    files = [p for p in job.ck_dir.iterdir() if p.suffix == ".pt" and p.is_file()]
    size = sum(p.stat().st_size for p in files)
    job.extras["checkpoint_disk"] = {"files": len(files), "bytes": size, "folder": str(job.ck_dir)}
    log.info(
        "checkpoints: %d file(s), %.1f MB in %s%s",
        len(files),
        size / 1e6,
        job.ck_dir,
        f" (removed {', '.join(removed)}: save_every: auto keeps the last {AUTO_KEEP} epoch_NNN.pt when "
        "max_minutes sets the run's length; set save_every: N to keep every N-th)"
        if removed
        else "",
    )


def auto_written(ck_dir) -> set[str]:
    """The ``epoch_NNN.pt`` names that ``save_every: auto`` wrote in ``ck_dir`` (its record; none without one)."""
    record = read_record(ck_dir / AUTO_RECORD, what="module 6's list of its deletable checkpoints", fix=RECORD_FIX)
    files = (record or {}).get("files", [])
    return {n for n in files if isinstance(n, str) and NUMBERED.fullmatch(n)} if isinstance(files, list) else set()


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
