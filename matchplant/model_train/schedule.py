"""The learning-rate schedule of module 6, planned in iterations so that it scales with the dataset and the budget.

A run is planned for ``planned`` iterations (``epochs`` x iterations per epoch, or fewer when ``max_minutes``
fits fewer: :mod:`matchplant.model_train.budget`). Every schedule reads its position as the fraction of that
plan done, so a 9-iteration-per-epoch dataset and a 900-iteration one decay at the same points of their run:

- ``step``: x ``gamma`` every ``step_size`` of the configured ``epochs`` (10 of 30: at 1/3 and 2/3 of the plan);
- ``multistep``: x ``gamma`` at each of ``milestone_fractions`` of the plan, or at ``milestones`` epochs of the
  configured ``epochs`` (moved in proportion when the plan is shorter);
- ``cosine`` from 1 to ``min_lr_factor`` over the plan; ``constant``.

The linear warm-up lasts ``warmup_iters`` iterations when set (the absolute key, still accepted), otherwise
``warmup_fraction`` of the plan. :func:`schedule_warning` says when a run's settings never reach the nominal
rate (a warm-up longer than the plan or than the first decay), the failure of a fixed 500-iteration warm-up
on a 9-iteration-per-epoch dataset (issue 28).
"""

from __future__ import annotations

import math

import numpy as np


def warmup_length(cfg, planned: int) -> int:
    """Warm-up iterations: ``warmup_iters`` when set, else ``warmup_fraction`` of the planned iterations."""
    if cfg.warmup_iters is not None:
        return int(cfg.warmup_iters)
    return round(cfg.warmup_fraction * planned)


def planned_iterations(cfg, iters_per_epoch: int, planned: int | None) -> int:
    """Iterations the schedule spans: ``planned`` when given, else ``epochs`` x ``iters_per_epoch`` (at least 1)."""
    return max(int(planned if planned is not None else cfg.epochs * iters_per_epoch), 1)


def lr_factor(cfg, iteration: int, iters_per_epoch: int, planned: int | None = None) -> float:
    """The learning-rate multiplier at a (0-based) iteration of a run planned for ``planned`` iterations
    (default: ``epochs`` x ``iters_per_epoch``): warm-up times the schedule."""
    planned = planned_iterations(cfg, iters_per_epoch, planned)
    p = iteration / planned  # the fraction of the plan done
    epoch = p * cfg.epochs  # ... as an epoch of the configured run
    if cfg.schedule == "step":
        f = cfg.gamma ** math.floor(epoch / cfg.step_size + 1e-9)
    elif cfg.schedule == "multistep":
        if cfg.milestone_fractions:
            f = cfg.gamma ** sum(p >= m - 1e-9 for m in cfg.milestone_fractions)
        else:
            f = cfg.gamma ** sum(epoch >= m - 1e-9 for m in cfg.milestones)
    elif cfg.schedule == "cosine":
        f = cfg.min_lr_factor + (1 - cfg.min_lr_factor) * 0.5 * (1 + math.cos(math.pi * min(p, 1.0)))
    else:
        f = 1.0
    warmup = warmup_length(cfg, planned)
    if iteration < warmup:
        alpha = iteration / warmup
        f *= cfg.warmup_factor * (1 - alpha) + alpha
    return f


def peak_factor(cfg, iters_per_epoch: int, planned: int | None = None) -> float:
    """The highest multiplier the planned run reaches (the warm-up's end and a sample of the plan)."""
    planned = planned_iterations(cfg, iters_per_epoch, planned)
    points = set(np.linspace(0, planned - 1, min(planned, 2000)).astype(int).tolist())
    warmup = warmup_length(cfg, planned)
    points |= {min(warmup, planned - 1), max(min(warmup, planned - 1) - 1, 0)}
    return max(lr_factor(cfg, i, iters_per_epoch, planned) for i in points)


def schedule_warning(cfg, iters_per_epoch: int, planned: int | None = None) -> str | None:
    """A warning when the planned run never reaches the nominal learning rates (peak below 99 %), else None."""
    planned = planned_iterations(cfg, iters_per_epoch, planned)
    peak = peak_factor(cfg, iters_per_epoch, planned)
    if peak >= 0.99:
        return None
    warmup = warmup_length(cfg, planned)
    return (
        f"the learning rate never reaches its nominal value: it peaks at {100 * peak:.1f} % of lr.* over the "
        f"{planned} planned iterations ({iters_per_epoch} per epoch; warm-up {warmup} iterations"
        f"{', longer than the run' if warmup >= planned else ''}); set warmup_iters: null to scale the "
        f"warm-up with the run (warmup_fraction {cfg.warmup_fraction:g}), or lower warmup_iters"
    )
