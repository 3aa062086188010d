"""Module 6: train a plant detector (Faster R-CNN, RetinaNet or FCOS) on COCO tiles (module 5's splits).

``train(cfg)`` runs the whole job: by default the paper's optimisation (SGD, a learning rate per part,
momentum 0.9, weight decay 5e-4, x0.1 every 10 epochs, linear warm-up), which ``optimizer`` and ``schedule``
change (AdamW; step, multistep, cosine or constant decay); from random weights with ``model.architecture: auto``
on a CPU or within ``max_minutes``, the light ResNet-18 FPN with AdamW at 1e-3 and cosine decay instead
(:mod:`~matchplant.model_train.choose`). Augmentation that moves the boxes, the device chosen automatically,
mixed precision on CUDA, several GPUs under ``torchrun``. Each epoch it
logs the losses, scores the validation split with COCOeval (AP, AP50) and writes into ``output_dir``:

- ``checkpoints/last.pt`` (every epoch; ``--resume`` continues from it), ``best.pt`` (best validation
  metric) and ``epoch_NNN.pt`` every ``save_every`` epochs: self-contained (docs/DESIGN.md §2);
- ``training_summary.json`` (settings, per-epoch history, best epoch, speed; whether it finished or was
  stopped by ``max_minutes``, and the validation set's size: :mod:`matchplant.model_train.budget`) and
  ``training_curves.png``. Every checkpoint also carries the training geometry module 7 detects with
  (:mod:`matchplant.detection.geometry`).

Before the first step a short probe measures the speed on this device and logs the estimate with advice
(:mod:`~matchplant.model_train.probe`); ``max_minutes`` plans the iterations that fit and stops inside an
epoch when the budget ends (:mod:`~matchplant.model_train.budget`); the learning-rate schedule is laid over the
planned iterations (:mod:`~matchplant.model_train.schedule`); Ctrl-C and the budget write a checkpoint that
``--resume`` continues from exactly (:mod:`~matchplant.model_train.resume`); ``model.architecture: auto`` picks
the detector for the device (:mod:`~matchplant.model_train.choose`); the CPU thread count follows the free
cores (:func:`matchplant.detection.device.configure_threads`, ``threads`` overrules it).

The job as an engine (after torchvision's references/detection/engine.py): :func:`train` is set up
(:mod:`~matchplant.model_train.setup`), plan (:mod:`~matchplant.model_train.plan`), loop and finish
(:mod:`~matchplant.model_train.engine`: one step, one epoch, validation), over the checkpoints
(:mod:`~matchplant.model_train.checkpoint`) and one :class:`~matchplant.model_train.budget.Budget`, the record of
``max_minutes`` built here once and passed down.

Transfer learning: ``model.checkpoint`` starts from an earlier MatchPlant model (a different number of
classes is fine), ``freeze`` and ``trainable_backbone_layers`` freeze parts, ``lr`` sets a rate per part.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from matchplant.model_train.budget import Budget
from matchplant.model_train.checkpoint import restore
from matchplant.model_train.choose import SCRATCH_EPOCHS
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.engine import finish, loop
from matchplant.model_train.plan import describe, probe_and_plan
from matchplant.model_train.resume import StopOnInterrupt
from matchplant.model_train.schedule import lr_factor
from matchplant.model_train.setup import build_optimizer, build_scheduler, set_up

__all__ = ["build_optimizer", "build_scheduler", "lr_factor", "run", "train"]


def train(
    cfg: ModelTrainConfig,
    *,
    on_epoch_end: Callable[[int, dict], Any] | None = None,
    on_iteration: Callable[[int], Any] | None = None,
) -> dict:
    """Train as configured; returns the training summary (also written as training_summary.json).

    ``on_epoch_end(epoch, record)`` is called after each epoch's checkpoints are written,
    ``on_iteration(iterations_done)`` after each training iteration.
    """
    budget = Budget.from_config(cfg)  # max_minutes counts the data checks, the probe and the set-up too
    job, resume, chosen = set_up(cfg, budget)
    # the recipe's ceiling of epochs (choose.scratch_budget, or a resumed run of it): the budget ends the run
    budget.sets_length = budget.limited and job.cfg.epochs == SCRATCH_EPOCHS
    job.on_epoch_end, job.on_iteration = on_epoch_end, on_iteration
    state = restore(job, resume)
    estimate = probe_and_plan(
        job,
        state,
        resume is not None and budget.plan.fitted,
        probe=chosen["probe"],
        size_validation=chosen["size_validation"],
    )
    describe(job, estimate, chosen["reason"])
    budget.stop_flag = StopOnInterrupt()
    reason = loop(job, state)
    return finish(job, state, reason)


def run(cfg: ModelTrainConfig) -> dict:
    """Train the detector as configured: module 6's entry point (``matchplant model_train``).

    Parameters
    ----------
    cfg : ModelTrainConfig
        The step's settings (``6_model_train/config.yaml``, checked).

    Returns
    -------
    dict
        The training summary, also written as ``training_summary.json`` in ``output_dir``.
    """
    return train(cfg)
