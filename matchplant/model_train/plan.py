"""Before the first step: the probe's measured estimate, logged with advice, and the plan fitted to the budget
(:class:`~matchplant.model_train.budget.Budget`); then the schedule's warning and the run's one-line description."""

from __future__ import annotations

from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration
from matchplant.model_train.budget import run_seconds
from matchplant.model_train.choose import sized_validation
from matchplant.model_train.probe import (
    PROBE_CAP_S,
    advice,
    costs_from_probe,
    estimate_lines,
    heartbeat,
    log_estimate,
    probe_speed,
)
from matchplant.model_train.schedule import schedule_warning, warmup_length
from matchplant.model_train.state import Job, TrainState

log = get_logger("model_train")


def measure(job: Job, state: TrainState, probe=None):
    """The probe (``probe``: one made already, for the choice of architecture) within its cap of the budget."""
    budget, cfg = job.budget, job.cfg
    cap = min(PROBE_CAP_S, 0.05 * budget.seconds) if budget.limited else PROBE_CAP_S
    if probe is None:
        log.info(
            "measuring the training speed: %d tile(s) per batch at the config's input size on %s",
            cfg.batch_size,
            job.device,
        )
        with heartbeat("measuring the training speed (the first batch on a CPU can take minutes)"):
            probe = probe_speed(
                job.core,
                job.train_ds,
                cfg.batch_size,
                job.runtime,
                job.amp,
                cap_s=cap,
                num_workers=cfg.num_workers,
                run_iters=budget.total - state.done,
            )
    return probe


def probe_and_plan(job: Job, state: TrainState, resumed_plan: bool, probe=None, size_validation: bool = False) -> dict:
    """The measured estimate before training, logged with advice; the plan fitted to the budget; ``job.cfg`` with
    ``val_every`` sized to the measured costs when ``size_validation`` (choose.scratch_budget). Returns the
    estimate (for the summary)."""
    budget, plan, done, total = job.budget, job.budget.plan, state.done, job.budget.total
    probe = measure(job, state, probe)
    n_params = sum(p.numel() for p in job.core.parameters())
    costs = costs_from_probe(probe, len(job.val_ds) if job.val_ds is not None else 0, n_params)
    budget.costs, budget.validated = costs, job.val_ds is not None
    if size_validation and budget.validated:
        job.cfg = sized_validation(job.cfg, costs.validation, plan.iters_per_epoch * costs.iteration)
    cfg = job.cfg
    budget.val_every = cfg.val_every
    lines, total_s = estimate_lines(
        probe,
        costs,
        iters_per_epoch=plan.iters_per_epoch,
        epochs=cfg.epochs,
        architecture=job.model_cfg.architecture,
        device=job.device,
        val_every=cfg.val_every,
        validated=budget.validated,
    )
    spent = budget.elapsed()
    if budget.limited and not resumed_plan:  # set-up and probe count too
        budget.fit(done, costs, budget.seconds - spent - 2.0, "measured by the probe")
    # a from-scratch CPU run's epochs are set for the budget to end it (choose.scratch_budget): no advice then
    hint = (
        None if size_validation else advice(total_s, budget, job.runtime, job.model_cfg.architecture, plan.iters, total)
    )
    planned_s = run_seconds(plan.iters, plan.iters_per_epoch, costs, cfg.val_every, budget.validated) - run_seconds(
        done, plan.iters_per_epoch, costs, cfg.val_every, budget.validated
    )
    if plan.iters < total and budget.sets_length:
        lines.append(
            f"planned: about {plan.iters} iterations ({plan.iters / plan.iters_per_epoch:.1f} epochs) fit in "
            f"max_minutes = {budget.minutes:g}: about {duration(planned_s)} of training and validation from here, "
            f"{duration(spent + planned_s)} in all"
        )
    elif plan.iters < total:
        lines.append(
            f"planned: {plan.iters} of {total} iterations ({plan.iters / plan.iters_per_epoch:.1f} of "
            f"{cfg.epochs} epochs) in max_minutes = {budget.minutes:g}: about {duration(planned_s)} of "
            f"training and validation from here, {duration(spent + planned_s)} in all"
        )
    log_estimate(lines, hint)
    return {
        "probe": probe.as_dict(),
        "seconds_per_iteration": round(costs.iteration, 4),
        "validation_s": round(costs.validation, 2),
        "checkpoint_s": round(costs.checkpoint, 2),
        "run_as_configured_s": round(total_s, 1),
        "planned_s": round(spent + planned_s, 1),
        "advice": hint,
    }


def describe(job: Job, estimate: dict, reason: str | None) -> None:
    """The schedule's warning and the run's line in the log; the summary's extras."""
    cfg, plan = job.cfg, job.budget.plan
    warning = schedule_warning(cfg, job.iters, plan.iters)
    if warning:
        log.warning(warning)
    log.info(
        "device %s%s, %s, %d trainable parameters, %d iterations per epoch, %d planned (warm-up %d)",
        job.device,
        " (mixed precision)" if job.amp else "",
        job.model_cfg.architecture,
        sum(p.numel() for p in job.core.parameters() if p.requires_grad),
        job.iters,
        plan.iters,
        warmup_length(cfg, plan.iters),
    )
    job.extras.update(
        estimate=estimate,
        schedule_warning=warning,
        architecture={"chosen": job.model_cfg.architecture, "reason": reason or "as set"},
    )
