"""Module 6: train a Faster R-CNN plant detector on COCO tiles (module 5's splits).

``train(cfg)`` runs the whole job: the paper's optimisation (SGD, a learning rate per part, momentum
0.9, weight decay 5e-4, x0.1 every 10 epochs, linear warm-up), augmentation that moves the boxes, the
device chosen automatically, mixed precision on CUDA, several GPUs under ``torchrun``. Each epoch it
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

Transfer learning: ``model.checkpoint`` starts from an earlier MatchPlant model (a different number of
classes is fine), ``freeze`` and ``trainable_backbone_layers`` freeze parts, ``lr`` sets a rate per part.
"""

from __future__ import annotations

import dataclasses
import math
import random
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable

import numpy as np

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration, progress
from matchplant.detection.data import CocoDetection, EpochSampler, check_disjoint, collate
from matchplant.detection.crops import skip_training_resize
from matchplant.detection.device import configure_threads, select_device
from matchplant.detection.foreign import read_any_checkpoint
from matchplant.detection.distributed import Shard, join, world_size
from matchplant.detection.evaluate import coco_evaluate, predict_dataset, summarise_stats
from matchplant.detection.geometry import training_geometry
from matchplant.detection.model import AUTO, ModelConfig, apply_freezing, backbone_stages, build_detector, keep_frozen_norms_fixed, model_config_from_dict, parameter_groups, resolve_auto_anchors
from matchplant.detection.checkpoint import load_matching_weights, save_checkpoint
from matchplant.model_train.budget import Costs, Plan, fit_plan, run_seconds, stop_status, validation_report
from matchplant.model_train.choose import (
    choose_architecture, cpu_proposals, resumed_recipe, scratch_recipe, scratch_settings, sized_validation)
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.probe import (
    HEARTBEAT_S, PROBE_CAP_S, advice, costs_from_probe, estimate_lines, heartbeat, log_estimate, probe_speed)
from matchplant.model_train.report import plot_curves, write_summary
from matchplant.model_train.resume import StopOnInterrupt, ignore_sigint, open_resume, random_state, set_random_state
from matchplant.model_train.schedule import lr_factor, schedule_warning, warmup_length

log = get_logger("model_train")
__all__ = ["build_optimizer", "build_scheduler", "lr_factor", "run", "train"]

# --------------------------------------------------------------------------------------------------
# optimisation


def build_optimizer(cfg: ModelTrainConfig, model):
    import torch  # lazy: PyTorch is heavy; configs load without it

    groups = parameter_groups(model, dataclasses.asdict(cfg.lr))
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(groups, lr=groups[0]["lr"], momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    return torch.optim.AdamW(groups, lr=groups[0]["lr"], weight_decay=cfg.weight_decay)


def build_scheduler(cfg: ModelTrainConfig, optimizer, iters_per_epoch: int, plan: Plan | None = None):
    """A per-iteration LambdaLR (its state is the iteration count, so a resumed run continues exactly);
    it follows ``plan.iters`` (read at every step: a refitted plan moves the schedule)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda it: lr_factor(cfg, it, iters_per_epoch, plan.iters if plan else None))


# --------------------------------------------------------------------------------------------------
# the run


def _init_distributed(cfg: ModelTrainConfig):
    """Join a torchrun job (WORLD_SIZE > 1) and pick this process's device."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    if world_size() <= 1:
        return Shard(), select_device(cfg.device)
    if torch.cuda.is_available() and cfg.device in ("auto", "cuda"):
        return join(torch.device("cuda"))  # join makes it this process's GPU
    return join(select_device("cpu" if cfg.device == "auto" else cfg.device))


def seed_everything(seed: int) -> None:
    import torch  # lazy: PyTorch is heavy; configs load without it

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _initial_model(cfg: ModelTrainConfig, class_names: list[str], resume: dict | None):
    """The model and the settings that rebuild it (stored in every checkpoint)."""
    if resume is not None:  # the run's own settings, so the same structure is rebuilt
        mcfg = model_config_from_dict(resume["model_config"])
        model = build_detector(mcfg, len(class_names) + 1, load_weights=False)
        model.load_state_dict(resume["model_state"])
        return model, mcfg
    if cfg.model.checkpoint is not None:
        # a MatchPlant checkpoint, the paper's layout or a bare torchvision state_dict (detection/foreign.py)
        src = read_any_checkpoint(cfg.model.checkpoint, architecture=cfg.model.architecture, fit_classes=False)
        src_cfg = src["model_config"]
        if cfg.model.architecture == AUTO:
            log.info("model.architecture: auto -> %s, the architecture of model.checkpoint", src_cfg["architecture"])
        elif src_cfg["architecture"] != cfg.model.architecture:
            raise ConfigError(f"model.checkpoint is a {src_cfg['architecture']} but model.architecture is "
                              f"{cfg.model.architecture}", path=cfg.model.checkpoint,
                              fix=f"set model.architecture: {src_cfg['architecture']} (or auto)")
        mcfg = dataclasses.replace(cfg.model, architecture=src_cfg["architecture"], pretrained=src_cfg["pretrained"],
                                   checkpoint=None)
        mcfg = resolve_auto_anchors(mcfg, cfg.train_json)  # anchor_sizes: auto -> from the training boxes
        model = build_detector(mcfg, len(class_names) + 1, load_weights=False)
        loaded, skipped = load_matching_weights(model, src["model_state"])
        log.info("transfer learning from %s: %d tensors loaded, %d new (%s)", cfg.model.checkpoint, len(loaded),
                 len(skipped), ", ".join(sorted({k.rsplit(".", 2)[0] for k in skipped})) or "none")
        return model, mcfg
    mcfg = resolve_auto_anchors(dataclasses.replace(cfg.model, checkpoint=None), cfg.train_json)
    return build_detector(mcfg, len(class_names) + 1), mcfg


def _rank0_value(value: float, dist_info, device) -> float:
    """Rank 0's value on every process under torchrun (one broadcast; a clock-based decision must agree)."""
    if dist_info.world <= 1:
        return value
    import torch  # lazy: PyTorch is heavy; configs load without it

    t = torch.tensor([float(value)], device=device)
    torch.distributed.broadcast(t, src=0)
    return float(t.item())


class _Session:
    """The clock and the stop decisions of one training session (``max_minutes`` counts from its start)."""

    def __init__(self, cfg: ModelTrainConfig, plan: Plan, total: int, costs: Costs, dist_info, device, stop_flag,
                 validated: bool):
        self.cfg, self.plan, self.total, self.costs = cfg, plan, total, costs
        self.dist_info, self.device, self.stop_flag, self.validated = dist_info, device, stop_flag, validated
        self.start = time.perf_counter()
        self.step_times: list[float] = []
        self.fitted_at: tuple[float, int] | None = None  # (elapsed s, iterations) at this session's first refit

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def reserve(self) -> float:
        """Seconds kept for the last validation and checkpoints."""
        return (self.costs.validation if self.validated else 0.0) + self.costs.checkpoint

    def iteration_s(self) -> float:
        recent = self.step_times[1:][-20:] or self.step_times or [self.costs.iteration]
        return float(np.mean(recent))

    def after_step(self, done: int, step_s: float) -> str | None:
        """After an iteration: refit the plan once from the real speed; then why to stop (None: go on)."""
        self.step_times.append(step_s)
        cfg, plan = self.cfg, self.plan
        if cfg.max_minutes and not plan.fitted and len(self.step_times) >= max(3, min(plan.iters_per_epoch,
                                                                                    plan.iters // 10)):
            plan.fitted = True
            measured = dataclasses.replace(self.costs, iteration=self.iteration_s())
            fit_plan(plan, self.total, done, measured, cfg.max_minutes * 60.0 - self.elapsed(), cfg.val_every,
                     self.validated, "measured on the first iterations", cfg.max_minutes)
            plan.iters = int(_rank0_value(plan.iters, self.dist_info, self.device))
            self.fitted_at = (self.elapsed(), done)
        elif cfg.max_minutes and self.fitted_at is not None and \
                done - self.fitted_at[1] >= max(3, (plan.iters - self.fitted_at[1]) // 2):
            self.refit_from_pace(done)
        reason = 0.0
        if self.stop_flag.requested:
            reason = 2.0
        elif cfg.max_minutes and done < plan.iters and \
                self.elapsed() + self.iteration_s() + self.reserve() > cfg.max_minutes * 60.0:
            reason = 1.0
        reason = _rank0_value(reason, self.dist_info, self.device)
        return {0.0: None, 1.0: "budget", 2.0: "interrupt"}[reason]

    def refit_from_pace(self, done: int) -> None:
        """Once, half way: the iterations that fit at the pace measured since the first refit, validations and
        checkpoints included (the planned per-epoch costs of many short epochs, or a machine that sped up or slowed
        down, otherwise end the plan well before the budget or cut it)."""
        t0, n0 = self.fitted_at
        self.fitted_at = None
        pace = (self.elapsed() - t0) / max(done - n0, 1)
        left = self.cfg.max_minutes * 60.0 - self.elapsed() - self.reserve()
        iters = int(_rank0_value(min(self.total, done + max(int(left / pace), 0)), self.dist_info, self.device))
        if iters != self.plan.iters:
            log.info("max_minutes = %g: at the pace of the last %d iterations (%.2f s each, validations and "
                     "checkpoints included) %d iterations fit, not %d; the schedule is laid over them",
                     self.cfg.max_minutes, done - n0, pace, iters, self.plan.iters)
            self.plan.iters = max(iters, done)

    def out_of_time_for(self, seconds: float) -> bool:
        """Whether ``seconds`` more work (an epoch's validation) leaves too little for the rest."""
        if not self.cfg.max_minutes:
            return False
        over = self.elapsed() + seconds + self.iteration_s() + self.reserve() > self.cfg.max_minutes * 60.0
        return bool(_rank0_value(1.0 if over else 0.0, self.dist_info, self.device))


def _probe_and_plan(cfg, core, train_ds, val_ds, model_cfg, device, amp, plan: Plan, total: int, done: int,
                    resumed_plan: bool, probe=None, started: float | None = None,
                    size_validation: bool = False) -> tuple[ModelTrainConfig, Costs, dict]:
    """The measured estimate before training, logged with advice; the plan fitted to the budget; ``cfg`` with
    ``val_every`` sized to the measured costs when ``size_validation`` (choose.scratch_budget)."""
    budget_s = cfg.max_minutes * 60.0
    cap = min(PROBE_CAP_S, 0.05 * budget_s) if budget_s else PROBE_CAP_S
    if probe is None:
        log.info("measuring the training speed: %d tile(s) per batch at the config's input size on %s", cfg.batch_size,
                 device)
        with heartbeat("measuring the training speed (the first batch on a CPU can take minutes)"):
            probe = probe_speed(core, train_ds, cfg.batch_size, device, amp, cap_s=cap, num_workers=cfg.num_workers,
                                run_iters=total - done)
    n_params = sum(p.numel() for p in core.parameters())
    costs = costs_from_probe(probe, len(val_ds) if val_ds is not None else 0, n_params)
    validated = val_ds is not None
    if size_validation and validated:
        cfg = sized_validation(cfg, costs.validation, plan.iters_per_epoch * costs.iteration)
    lines, total_s = estimate_lines(probe, costs, iters_per_epoch=plan.iters_per_epoch, epochs=cfg.epochs,
                                    architecture=model_cfg.architecture, device=device, val_every=cfg.val_every,
                                    validated=validated, max_minutes=cfg.max_minutes)
    spent = time.perf_counter() - started if started is not None else 0.0
    if budget_s and not resumed_plan:  # set-up and probe count too
        fit_plan(plan, total, done, costs, budget_s - spent - 2.0, cfg.val_every, validated, "measured by the probe",
                 cfg.max_minutes)
    # a from-scratch CPU run's epochs are set for the budget to end it (choose.scratch_budget): no advice then
    hint = None if size_validation else advice(total_s, cfg.max_minutes, device, model_cfg.architecture, plan.iters,
                                               total)
    planned_s = run_seconds(plan.iters, plan.iters_per_epoch, costs, cfg.val_every, validated) - \
        run_seconds(done, plan.iters_per_epoch, costs, cfg.val_every, validated)
    if plan.iters < total:
        lines.append(f"planned: {plan.iters} of {total} iterations ({plan.iters / plan.iters_per_epoch:.1f} of "
                     f"{cfg.epochs} epochs) in max_minutes = {cfg.max_minutes:g}: about {duration(planned_s)} of "
                     f"training and validation from here, {duration(spent + planned_s)} in all")
    log_estimate(lines, hint)
    estimate = {"probe": probe.as_dict(), "seconds_per_iteration": round(costs.iteration, 4),
                "validation_s": round(costs.validation, 2), "checkpoint_s": round(costs.checkpoint, 2),
                "run_as_configured_s": round(total_s, 1), "planned_s": round(spent + planned_s, 1), "advice": hint}
    return cfg, costs, estimate


def _choose_model_config(cfg: ModelTrainConfig, device, train_ds, total: int):
    """``cfg`` with ``model.architecture: auto`` resolved (logged with the reason), and the probe it made."""
    if cfg.model.architecture != AUTO or cfg.model.checkpoint is not None:
        return cfg, None, None
    model_cfg, sized = cfg.model, None
    if device.type == "cpu":
        model_cfg, sized = cpu_proposals(cfg.model, [len(train_ds.anns.get(im["id"], [])) for im in train_ds.images])
        cfg, recipe = scratch_recipe(cfg)
        sized = "; ".join(filter(None, (sized, recipe))) or None
        if sized:
            log.info("model.architecture: auto on the CPU -> %s", sized)
    arch, why, probe = choose_architecture(cfg, model_cfg, device, train_ds, len(train_ds.class_names), total,
                                           cfg.train_json)
    log.info("model.architecture: auto -> %s (%s)", arch, why)
    why = f"{why}; {sized}" if sized else why
    return dataclasses.replace(cfg, model=dataclasses.replace(model_cfg, architecture=arch)), probe, why


def train(cfg: ModelTrainConfig, *, on_epoch_end: Callable[[int, dict], Any] | None = None,
          on_iteration: Callable[[int], Any] | None = None) -> dict:
    """Train as configured; returns the training summary (also written as training_summary.json).

    ``on_epoch_end(epoch, record)`` is called after each epoch's checkpoints are written,
    ``on_iteration(iterations_done)`` after each training iteration.
    """
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torch.utils.data import DataLoader

    session_start = time.perf_counter()  # max_minutes counts the data checks, the probe and the set-up too
    dist_info, device = _init_distributed(cfg)
    threads = configure_threads(cfg.threads or None)
    out = Path(cfg.output_dir)
    ck_dir = out / "checkpoints"
    seed_everything(cfg.seed)

    train_ds = CocoDetection(cfg.train_json, cfg.train_images, augment=cfg.augment)
    class_names = train_ds.class_names
    val_ds = CocoDetection(cfg.val_json, cfg.val_images, class_names=class_names,
                           classes_from=f"the training set {cfg.train_json}") if cfg.val_json else None
    if val_ds is not None:
        check_disjoint(train_ds, val_ds)  # validation on training tiles would measure memory, not skill
    n_neg = sum(1 for im in train_ds.images if not train_ds.anns.get(im["id"]))
    log.info("training tiles: %d (%d without plants, kept as negatives); validation tiles: %s; classes: %s",
             len(train_ds), n_neg, len(val_ds) if val_ds else "none", ", ".join(class_names))
    validation = validation_report(val_ds.data if val_ds is not None else None)

    sampler = EpochSampler(len(train_ds), cfg.seed, dist_info.rank, dist_info.world)
    iters = math.ceil(len(sampler) / cfg.batch_size)
    resume = open_resume(cfg, ck_dir, class_names)
    if resume is not None:
        log.info("resuming %s after %d iteration(s) (epoch %d%s)", ck_dir / "last.pt",
                 resume.get("iteration", resume["epoch"] * iters), resume["epoch"],
                 f", {resume['epoch_progress']['batches']} batch(es) into epoch {resume['epoch'] + 1}"
                 if resume.get("epoch_progress") else " done")
    choice_probe, choice_reason, size_validation, scratch = None, None, False, []
    if resume is not None:
        cfg = resumed_recipe(cfg, resume.get("train_config") or {})
    else:  # random weights on a CPU: training crops and a run as long as the budget
        cfg, size_validation, scratch = scratch_settings(cfg, device)
    if cfg.augment.crop:
        train_ds.crop_windows(cfg.augment.crop, cfg.model.min_size, cfg.model.max_size, cfg.augment.crop_on_plant)
    total = cfg.epochs * iters
    if resume is None:
        cfg, choice_probe, choice_reason = _choose_model_config(cfg, device, train_ds, total)
        choice_reason = "; ".join(filter(None, (choice_reason, *scratch))) or None

    model, model_cfg = _initial_model(cfg, class_names, resume)
    if cfg.augment.crop:  # the crops come at the detector's scale
        skip_training_resize(model)
    # what module 7 needs to detect as trained: tile size, input scale, classes, plant sizes
    geometry = training_geometry(train_ds.data, model_cfg.min_size, model_cfg.max_size, class_names)
    log.info("training geometry: %s px tiles, detector input x%s, median plant %s px in the detector's input",
             geometry["tile_size"], geometry["input_scale"], geometry["objects_input_px"])
    trainable = cfg.trainable_backbone_layers
    n_stages = len(backbone_stages(model, model_cfg.architecture))
    if model_cfg.pretrained == "none" and cfg.model.checkpoint is None and trainable < n_stages:
        # as torchvision does: freezing random weights makes no sense
        log.warning("model.pretrained is none: all %d backbone stages are trained (trainable_backbone_layers "
                    "applies to pretrained weights)", n_stages)
        trainable = n_stages
    apply_freezing(model, model_cfg.architecture, trainable, cfg.freeze)
    model.to(device)
    core = model
    if dist_info.world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)

    # the loader's own generator: the workers' seeds do not draw from the process's random state
    generator = torch.Generator()
    generator.manual_seed(cfg.seed)
    loader = DataLoader(train_ds, batch_size=cfg.batch_size, sampler=sampler, num_workers=cfg.num_workers,
                        collate_fn=collate, generator=generator, pin_memory=device.type == "cuda",
                        worker_init_fn=ignore_sigint if cfg.num_workers else None)
    optimizer = build_optimizer(cfg, core)
    plan = Plan(total, iters)
    scheduler = build_scheduler(cfg, optimizer, iters, plan)
    amp = cfg.amp and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=amp)

    done, history, best, progress_state, rng = 0, [], {"epoch": None, "value": None}, None, None
    if resume is not None:
        if resume.get("iters_per_epoch", iters) != iters and resume.get("epoch_progress"):
            raise ConfigError(f"cannot resume inside epoch {resume['epoch'] + 1}: the run had "
                              f"{resume['iters_per_epoch']} iterations per epoch, this config gives {iters} "
                              "(batch_size or the training set changed)", path=ck_dir / "last.pt",
                              fix="resume with the run's batch_size and training set, or start with --fresh")
        optimizer.load_state_dict(resume["optimizer_state"])
        scheduler.load_state_dict(resume["scheduler_state"])
        if resume.get("scaler_state"):
            scaler.load_state_dict(resume["scaler_state"])
        done = int(resume.get("iteration", resume["epoch"] * iters))
        history = [h for h in resume["history"] if not h.get("partial")]
        best = dict(resume["best"])
        progress_state, rng = resume.get("epoch_progress"), resume.get("random_state")
        if resume.get("planned_iters"):
            plan.iters, plan.fitted, plan.source = min(int(resume["planned_iters"]), total), True, "resumed"
        elif cfg.max_minutes and resume.get("planned_epochs"):  # a checkpoint of the epoch-based budget
            plan.iters, plan.fitted = min(int(resume["planned_epochs"]) * iters, total), True
        if not resume.get("planned_iters") and not cfg.max_minutes:
            plan.fitted = True
        if plan.iters <= done < total:  # the budget's plan is done: this session plans the rest with its budget
            log.info("the run's plan of %d iterations (fitted to its max_minutes) is done; the remaining %d of %d "
                     "are planned now%s (the learning-rate schedule is laid over the longer run)", plan.iters,
                     total - done, total, f" with max_minutes = {cfg.max_minutes:g}" if cfg.max_minutes else "")
            plan.iters, plan.fitted, plan.source = total, False, "configured"

    cfg, costs, estimate = _probe_and_plan(cfg, core, train_ds, val_ds, model_cfg, device, amp, plan, total, done,
                                           resume is not None and plan.fitted, probe=choice_probe,
                                           started=session_start, size_validation=size_validation)
    warning = schedule_warning(cfg, iters, plan.iters)
    if warning:
        log.warning(warning)
    log.info("device %s%s, %s, %d trainable parameters, %d iterations per epoch, %d planned (warm-up %d)", device,
             " (mixed precision)" if amp else "", model_cfg.architecture,
             sum(p.numel() for p in core.parameters() if p.requires_grad), iters, plan.iters,
             warmup_length(cfg, plan.iters))
    extras = {"threads": threads, "estimate": estimate, "schedule_warning": warning,
              "architecture": {"chosen": model_cfg.architecture, "reason": choice_reason or "as set"}}

    stop_rng = None

    def save(name: str, epoch_done: int, record: dict | None, partial: dict | None) -> None:
        state = dict(epoch=epoch_done, iteration=done, optimizer_state=optimizer.state_dict(),
                     scheduler_state=scheduler.state_dict(), scaler_state=scaler.state_dict() if amp else None,
                     history=history, best=best, metrics=(record or {}).get("val"), train_config=to_dict(cfg),
                     iters_per_epoch=iters, training_geometry=geometry, planned_iters=plan.iters,
                     epoch_progress=partial, random_state=stop_rng if partial else None)
        save_checkpoint(ck_dir / name, core, model_cfg, class_names, train_ds.category_ids, **state)

    stop_flag = StopOnInterrupt()
    session = _Session(cfg, plan, total, costs, dist_info, device, stop_flag, val_ds is not None)
    session.start = session_start  # the budget counts the probe and the model's set-up
    reason = None
    with stop_flag:
        while done < plan.iters and reason is None:
            epoch, start = divmod(done, iters)
            # each epoch's order and augmentation depend only on (seed, epoch); mid-epoch, the random state
            # the interrupted run had is restored too: a resumed run repeats the uninterrupted one exactly
            seed_everything(cfg.seed * 100003 + epoch)
            if start and rng is not None:
                set_random_state(rng, device)
            train_ds.set_seed(cfg.seed * 100003 + epoch)
            sampler.set_epoch(epoch, start * cfg.batch_size)
            sums = dict(progress_state["sums"]) if start and progress_state else {}
            batches = int(progress_state["batches"]) if start and progress_state else 0
            progress_state, rng = None, None
            t0 = time.perf_counter()
            epoch_iters = min(iters, plan.iters - epoch * iters)

            def after(step_s: float) -> str | None:
                nonlocal done
                done += 1
                if on_iteration is not None:
                    on_iteration(done)
                return session.after_step(done, step_s)

            reason, batches = _train_epoch(model, loader, optimizer, scheduler, scaler, device, amp,
                                           f"epoch {epoch + 1}/{plan.epochs}", sums, batches, after,
                                           slow=costs.iteration >= HEARTBEAT_S / 2 or not session.step_times,
                                           limit=epoch_iters - start)
            train_time = time.perf_counter() - t0
            # the random state where training stopped (validation draws from it too; a resumed run starts here)
            stop_rng = random_state(device) if batches < iters else None
            means = {k: v / max(batches, 1) for k, v in sums.items()}
            if dist_info.world > 1:  # the mean over every process
                keys = sorted(means)
                t = torch.tensor([means[k] for k in keys], device=device)
                torch.distributed.all_reduce(t)
                means = dict(zip(keys, (t / dist_info.world).tolist()))
            complete = batches >= iters
            record = {"epoch": epoch + 1, "iterations": done, "lr": {g["name"]: g["lr"] for g in optimizer.param_groups},
                      "losses": means, "train_time_s": round(train_time, 3),
                      "train_images_per_s": round((done - epoch * iters - start) * cfg.batch_size * dist_info.world
                                                  / max(train_time, 1e-9), 3)}
            if not complete:
                record.update(partial=True, batches=batches)
            if reason == "interrupt":  # no validation: the user wants out; the checkpoint continues exactly here
                if dist_info.main:
                    save("last.pt", epoch, record, {"batches": batches, "sums": sums})
                    write_summary(out, cfg, history + [record], best, class_names, device, "interrupted",
                                  session.elapsed(), validation=validation, plan=plan, extras=extras,
                                  message=stop_status(done, total, iters, cfg.max_minutes, True)[1])
                log.warning("interrupted after %d of %d planned iterations: %s written; --resume continues there",
                            done, plan.iters, ck_dir / "last.pt")
                raise KeyboardInterrupt
            if reason is None and done < plan.iters and session.out_of_time_for(
                    costs.validation if (epoch + 1) % cfg.val_every == 0 and val_ds is not None else 0.0):
                reason = "budget"
            last = done >= plan.iters or reason is not None
            validate = val_ds is not None and ((complete and (epoch + 1) % cfg.val_every == 0) or last)
            if validate and dist_info.main:
                record["val"] = validate_model(core, val_ds, model_cfg, cfg, device, amp)
            history.append(record)
            value = record.get("val", {}).get(cfg.best_metric) if val_ds is not None else float(done)
            improved = value is not None and (best["value"] is None or value > best["value"])
            if improved:
                best = {"epoch": epoch + 1, "iterations": done, "value": value,
                        "metric": cfg.best_metric if val_ds else "last epoch"}
            log.info("epoch %d/%d%s: loss %.4f%s (%.1f s)", epoch + 1, plan.epochs,
                     "" if complete else f" (stopped after {batches} of {iters} batches)", means.get("loss", math.nan),
                     f"; validation {summarise_stats(record['val'])}" if "val" in record else "", train_time)
            if dist_info.main:
                partial = None if complete else {"batches": batches, "sums": sums}
                save("last.pt", epoch + complete, record, partial)
                if improved:
                    save("best.pt", epoch + complete, record, partial)
                if complete and cfg.save_every and (epoch + 1) % cfg.save_every == 0:
                    save(f"epoch_{epoch + 1:03d}.pt", epoch + 1, record, None)
                write_summary(out, cfg, history, best, class_names, device, "running", session.elapsed(),
                              validation=validation, plan=plan, extras=extras)
                plot_curves(history, out / "training_curves.png")
            dist_info.barrier()
            if on_epoch_end is not None and complete:
                on_epoch_end(epoch + 1, record)
    if reason == "budget" or (done >= plan.iters and plan.iters < total):
        log.info("stopping after %d of %d iterations: max_minutes = %g", done, total, cfg.max_minutes)
    summary = {}
    if dist_info.main:
        status, message = stop_status(done, total, iters, cfg.max_minutes, planned=plan.iters)
        summary = write_summary(out, cfg, history, best, class_names, device, status, session.elapsed(),
                                validation=validation, plan=plan, message=message, extras=extras)
        log.info("training %s (%s)", message, _clock_words(session.elapsed()))
    if dist_info.main and best["epoch"] is not None:
        log.info("best epoch %d (%s %.4f); model: %s", best["epoch"], best.get("metric"), best["value"],
                 ck_dir / "best.pt")
    if dist_info.world > 1:
        torch.distributed.destroy_process_group()
    return summary


def _clock_words(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _train_epoch(model, loader, optimizer, scheduler, scaler, device, amp: bool, desc: str, sums: dict[str, float],
                 batches: int, after: Callable[[float], str | None], *, slow: bool, limit: int) -> tuple[str | None, int]:
    """Train on the loader's batches (at most ``limit``), adding the losses into ``sums``; ``after(step_s)`` after
    each iteration says whether to stop. Returns ``(why it stopped or None, batches done in this epoch)``. A
    heartbeat line shows life during slow iterations (the first one, or all when the probe found them slow)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    model.train()
    keep_frozen_norms_fixed(model)
    bar = progress(loader, desc=desc, unit="batch", total=min(len(loader), limit))
    batch_iter = iter(bar)
    reason = None
    first = True
    try:
        for _ in range(limit):
            t0 = time.perf_counter()
            with heartbeat(f"{desc}, batch {batches + 1}") if (slow or first) else nullcontext():
                try:
                    images, targets = next(batch_iter)
                except StopIteration:
                    break
                images = [im.to(device, non_blocking=True) for im in images]
                targets = [{"boxes": t["boxes"].to(device), "labels": t["labels"].to(device)} for t in targets]
                with torch.autocast(device_type=device.type, enabled=amp):
                    loss_dict = model(images, targets)
                    loss = sum(loss_dict.values())
                # every loss to the host in one transfer: one device sync per step, not one per value
                values = torch.stack([*(v.detach().float() for v in loss_dict.values()),
                                      loss.detach().float()]).tolist()
                if not math.isfinite(values[-1]):
                    raise MatchPlantError(f"the training loss became {values[-1]} ({desc})",
                                          fix="lower the learning rates (lr.*) or raise warmup_iters; check the boxes")
                optimizer.zero_grad(set_to_none=True)
                scaler.scale(loss).backward()
                scaler.step(optimizer)
                scaler.update()
                scheduler.step()
            first = False
            for k, v in zip((*loss_dict, "loss"), values):
                sums[k] = sums.get(k, 0.0) + v
            batches += 1
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(loss=f"{sums['loss'] / batches:.3f}")
            reason = after(time.perf_counter() - t0)
            if reason is not None:
                break
    finally:
        if hasattr(bar, "close"):
            bar.close()
    return reason, batches


def validate_model(model, val_ds: CocoDetection, model_cfg: ModelConfig, cfg: ModelTrainConfig, device,
                   amp: bool) -> dict:
    """COCOeval of the model on the validation tiles, boxes above ``val_score_threshold``."""
    heads = model.roi_heads
    saved = heads.score_thresh
    heads.score_thresh = cfg.val_score_threshold
    try:
        results = predict_dataset(model, val_ds, device, batch_size=cfg.batch_size, num_workers=cfg.num_workers,
                                  amp=amp, desc="validating")
    finally:
        heads.score_thresh = saved
    stats, _ = coco_evaluate(val_ds.data, results, max_dets=model_cfg.roi.detections_per_img)
    stats["detections"] = len(results)
    return stats


def run(cfg: ModelTrainConfig) -> dict:
    return train(cfg)
