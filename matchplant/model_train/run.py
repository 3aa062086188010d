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

Transfer learning: ``model.checkpoint`` starts from an earlier MatchPlant model (a different number of
classes is fine), ``freeze`` and ``trainable_backbone_layers`` freeze parts, ``lr`` sets a rate per part.
"""

from __future__ import annotations

import dataclasses
import math
import random
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.detection.data import CocoDetection, check_disjoint, collate
from matchplant.detection.device import select_device
from matchplant.detection.distributed import Shard, join, world_size
from matchplant.detection.evaluate import coco_evaluate, predict_dataset, summarise_stats
from matchplant.detection.geometry import training_geometry
from matchplant.detection.model import (
    ModelConfig,
    apply_freezing,
    backbone_stages,
    build_detector,
    keep_frozen_norms_fixed,
    load_matching_weights,
    model_config_from_dict,
    parameter_groups,
    read_checkpoint,
    resolve_auto_anchors,
    save_checkpoint,
)
from matchplant.model_train.budget import Plan, fit_plan, stop_status, validation_report
from matchplant.model_train.config import ModelTrainConfig

log = get_logger("model_train")

# --------------------------------------------------------------------------------------------------
# optimisation


def build_optimizer(cfg: ModelTrainConfig, model):
    import torch  # lazy: PyTorch is heavy; configs load without it

    groups = parameter_groups(model, dataclasses.asdict(cfg.lr))
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(groups, lr=groups[0]["lr"], momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    return torch.optim.AdamW(groups, lr=groups[0]["lr"], weight_decay=cfg.weight_decay)


def lr_factor(cfg: ModelTrainConfig, iteration: int, iters_per_epoch: int, planned_epochs: int | None = None) -> float:
    """The learning-rate multiplier at a (0-based) iteration: warm-up times the epoch schedule.

    ``planned_epochs`` (fewer than ``epochs`` when ``max_minutes`` is short) shortens the schedule in
    proportion: epoch ``e`` of the plan is at epoch ``e * epochs / planned_epochs`` of the configured one
    (the warm-up, in iterations, is kept)."""
    planned = planned_epochs or cfg.epochs
    epoch = (iteration // max(iters_per_epoch, 1)) * cfg.epochs / planned
    if cfg.schedule == "step":
        f = cfg.gamma ** math.floor(epoch / cfg.step_size + 1e-9)
    elif cfg.schedule == "multistep":
        f = cfg.gamma ** sum(epoch >= m - 1e-9 for m in cfg.milestones)
    elif cfg.schedule == "cosine":
        total = max(planned * iters_per_epoch, 1)
        f = cfg.min_lr_factor + (1 - cfg.min_lr_factor) * 0.5 * (1 + math.cos(math.pi * min(iteration / total, 1)))
    else:
        f = 1.0
    if iteration < cfg.warmup_iters:
        alpha = iteration / cfg.warmup_iters
        f *= cfg.warmup_factor * (1 - alpha) + alpha
    return f


def build_scheduler(cfg: ModelTrainConfig, optimizer, iters_per_epoch: int, plan: Plan | None = None):
    """A per-iteration LambdaLR (its state is the iteration count, so a resumed run continues exactly);
    it follows ``plan.epochs`` when the time budget shortens the run."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda it: lr_factor(cfg, it, iters_per_epoch, plan.epochs if plan else None))


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
        src = read_checkpoint(cfg.model.checkpoint)
        src_cfg = src["model_config"]
        if src_cfg["architecture"] != cfg.model.architecture:
            raise ConfigError(f"model.checkpoint is a {src_cfg['architecture']} but model.architecture is "
                              f"{cfg.model.architecture}", path=cfg.model.checkpoint,
                              fix=f"set model.architecture: {src_cfg['architecture']}")
        mcfg = dataclasses.replace(cfg.model, pretrained=src_cfg["pretrained"], checkpoint=None)
        mcfg = resolve_auto_anchors(mcfg, cfg.train_json)  # anchor_sizes: auto -> from the training boxes
        model = build_detector(mcfg, len(class_names) + 1, load_weights=False)
        loaded, skipped = load_matching_weights(model, src["model_state"])
        log.info("transfer learning from %s: %d tensors loaded, %d new (%s)", cfg.model.checkpoint, len(loaded),
                 len(skipped), ", ".join(sorted({k.rsplit(".", 2)[0] for k in skipped})) or "none")
        return model, mcfg
    mcfg = resolve_auto_anchors(dataclasses.replace(cfg.model, checkpoint=None), cfg.train_json)
    return build_detector(mcfg, len(class_names) + 1), mcfg


def _check_resumable(cfg: ModelTrainConfig, ck: dict, class_names: list[str], path: Path) -> None:
    if ck.get("class_names") != class_names:
        raise ConfigError(f"cannot resume: the checkpoint's classes {ck.get('class_names')} differ from the "
                          f"dataset's {class_names}", path=path,
                          fix="resume with the same dataset, or start a new run in another output_dir")
    if ck.get("epoch", 0) >= cfg.epochs:
        log.warning("the run in %s already finished its %d epochs; raise 'epochs' to train longer",
                    cfg.output_dir, ck["epoch"])


def _rank0_value(value: float, dist_info, device) -> float:
    """Rank 0's value on every process under torchrun (one broadcast; a clock-based decision must agree)."""
    if dist_info.world <= 1:
        return value
    import torch  # lazy: PyTorch is heavy; configs load without it

    t = torch.tensor([float(value)], device=device)
    torch.distributed.broadcast(t, src=0)
    return float(t.item())


def _out_of_time(cfg: ModelTrainConfig, run_start: float, epoch_time: float, dist_info, device) -> bool:
    """Whether another epoch (as long as the last: training, validation, checkpoints) would end past
    ``max_minutes``; one answer for all processes under torchrun (rank 0's clock)."""
    if not cfg.max_minutes:
        return False
    over = (time.perf_counter() - run_start) + epoch_time > cfg.max_minutes * 60.0
    return bool(_rank0_value(1.0 if over else 0.0, dist_info, device))


def train(cfg: ModelTrainConfig, *, on_epoch_end: Callable[[int, dict], Any] | None = None) -> dict:
    """Train as configured; returns the training summary (also written as training_summary.json).

    ``on_epoch_end(epoch, record)`` is called after each epoch's checkpoints are written.
    """
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torch.utils.data import DataLoader, DistributedSampler, RandomSampler

    dist_info, device = _init_distributed(cfg)
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

    resume = None
    if cfg.resume:
        last = ck_dir / "last.pt"
        if not last.is_file():
            raise InputError("nothing to resume: no checkpoint of an earlier run here", path=last,
                             fix="set output_dir to the crashed run's folder, or start without --resume")
        resume = read_checkpoint(last)
        _check_resumable(cfg, resume, class_names, last)
        log.info("resuming %s after epoch %d", last, resume["epoch"])

    model, model_cfg = _initial_model(cfg, class_names, resume)
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

    generator = torch.Generator()
    sampler = (DistributedSampler(train_ds, dist_info.world, dist_info.rank, shuffle=True, seed=cfg.seed)
               if dist_info.world > 1 else RandomSampler(train_ds, generator=generator))
    loader = DataLoader(train_ds, batch_size=cfg.batch_size, sampler=sampler, num_workers=cfg.num_workers,
                        collate_fn=collate, generator=generator, pin_memory=device.type == "cuda")
    iters = len(loader)
    optimizer = build_optimizer(cfg, core)
    plan = Plan(cfg.epochs)
    scheduler = build_scheduler(cfg, optimizer, iters, plan)
    amp = cfg.amp and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=amp)

    start_epoch, history, best = 0, [], {"epoch": None, "value": None}
    if resume is not None:
        optimizer.load_state_dict(resume["optimizer_state"])
        scheduler.load_state_dict(resume["scheduler_state"])
        if resume.get("scaler_state"):
            scaler.load_state_dict(resume["scaler_state"])
        start_epoch, history, best = resume["epoch"], list(resume["history"]), dict(resume["best"])
        if cfg.max_minutes and resume.get("planned_epochs"):  # the budget's plan of the run resumed
            plan.epochs, plan.fitted = min(int(resume["planned_epochs"]), cfg.epochs), True

    log.info("device %s%s, %s, %d trainable parameters, %d iterations per epoch", device,
             " (mixed precision)" if amp else "", model_cfg.architecture,
             sum(p.numel() for p in core.parameters() if p.requires_grad), iters)
    run_start = time.perf_counter()
    epoch_time = None  # wall time of the last whole epoch (training, validation, checkpoints)
    for epoch in range(start_epoch, cfg.epochs):
        if epoch >= plan.epochs:  # a resumed run whose budget plan is done
            break
        # each epoch's randomness depends only on (seed, epoch): a resumed run repeats it exactly
        seed_everything(cfg.seed * 100003 + epoch)
        generator.manual_seed(cfg.seed * 100003 + epoch)
        if dist_info.world > 1:
            sampler.set_epoch(epoch)
        t0 = time.perf_counter()
        losses = _train_one_epoch(model, loader, optimizer, scheduler, scaler, device, amp,
                                  f"epoch {epoch + 1}/{plan.epochs}", dist_info)
        train_time = time.perf_counter() - t0
        record = {"epoch": epoch + 1, "lr": {g["name"]: g["lr"] for g in optimizer.param_groups},
                  "losses": losses, "train_time_s": round(train_time, 3),
                  "train_images_per_s": round(len(train_ds) / max(train_time, 1e-9), 3)}
        out_of_time = _out_of_time(cfg, run_start, epoch_time or train_time, dist_info, device)
        last = epoch + 1 >= plan.epochs or out_of_time
        validate = val_ds is not None and ((epoch + 1) % cfg.val_every == 0 or last)
        if validate and dist_info.main:
            record["val"] = validate_model(core, val_ds, model_cfg, cfg, device, amp)
        history.append(record)
        value = record.get("val", {}).get(cfg.best_metric) if val_ds is not None else float(epoch)
        improved = value is not None and (best["value"] is None or value > best["value"])
        if improved:
            best = {"epoch": epoch + 1, "value": value, "metric": cfg.best_metric if val_ds else "last epoch"}
        log.info("epoch %d/%d: loss %.4f%s (%.1f s)", epoch + 1, plan.epochs, losses["loss"],
                 f"; validation {summarise_stats(record['val'])}" if "val" in record else "", train_time)
        if dist_info.main:
            state = dict(epoch=epoch + 1, optimizer_state=optimizer.state_dict(),
                         scheduler_state=scheduler.state_dict(), scaler_state=scaler.state_dict() if amp else None,
                         history=history, best=best, metrics=record.get("val"), train_config=to_dict(cfg),
                         iters_per_epoch=iters, training_geometry=geometry,
                         planned_epochs=plan.epochs if plan.epochs < cfg.epochs else None)
            save_checkpoint(ck_dir / "last.pt", core, model_cfg, class_names, train_ds.category_ids, **state)
            if improved:
                save_checkpoint(ck_dir / "best.pt", core, model_cfg, class_names, train_ds.category_ids, **state)
            if cfg.save_every and (epoch + 1) % cfg.save_every == 0:
                save_checkpoint(ck_dir / f"epoch_{epoch + 1:03d}.pt", core, model_cfg, class_names,
                                train_ds.category_ids, **state)
            write_summary(out, cfg, history, best, class_names, device, "running",
                          time.perf_counter() - run_start, validation=validation, plan=plan)
            plot_curves(history, out / "training_curves.png")
        dist_info.barrier()
        epoch_time = time.perf_counter() - t0
        if cfg.max_minutes and not plan.fitted:  # the first epoch's time says how many epochs fit (rank 0's)
            fit_plan(plan, cfg.epochs, epoch + 1, cfg.max_minutes, time.perf_counter() - run_start, epoch_time)
            plan.epochs = int(_rank0_value(plan.epochs, dist_info, device))
        if on_epoch_end is not None:
            on_epoch_end(epoch + 1, record)
        if epoch + 1 < cfg.epochs and (out_of_time or epoch + 1 >= plan.epochs):
            log.info("stopping after epoch %d of %d: the next would pass max_minutes = %g", epoch + 1, cfg.epochs,
                     cfg.max_minutes)
            break
    summary = {}
    if dist_info.main:
        status, message = stop_status(len(history), cfg.epochs, cfg.max_minutes)
        summary = write_summary(out, cfg, history, best, class_names, device, status, time.perf_counter() - run_start,
                                validation=validation, plan=plan, message=message)
        log.info("training %s", message)
    if dist_info.main and best["epoch"] is not None:
        log.info("best epoch %d (%s %.4f); model: %s", best["epoch"], best.get("metric"), best["value"],
                 ck_dir / "best.pt")
    if dist_info.world > 1:
        torch.distributed.destroy_process_group()
    return summary


def _train_one_epoch(model, loader, optimizer, scheduler, scaler, device, amp: bool, desc: str,
                     dist_info: Shard) -> dict[str, float]:
    import torch  # lazy: PyTorch is heavy; configs load without it

    model.train()
    keep_frozen_norms_fixed(model)
    sums: dict[str, float] = {}
    n = 0
    bar = progress(loader, desc=desc, unit="batch")
    for images, targets in bar:
        images = [im.to(device, non_blocking=True) for im in images]
        targets = [{"boxes": t["boxes"].to(device), "labels": t["labels"].to(device)} for t in targets]
        with torch.autocast(device_type=device.type, enabled=amp):
            loss_dict = model(images, targets)
            loss = sum(loss_dict.values())
        # every loss to the host in one transfer: one device sync per step, not one per value
        values = torch.stack([*(v.detach().float() for v in loss_dict.values()), loss.detach().float()]).tolist()
        if not math.isfinite(values[-1]):
            raise MatchPlantError(f"the training loss became {values[-1]} ({desc})",
                                  fix="lower the learning rates (lr.*) or raise warmup_iters; check the boxes")
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
        scheduler.step()
        for k, v in zip((*loss_dict, "loss"), values):
            sums[k] = sums.get(k, 0.0) + v
        n += 1
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{sums['loss'] / n:.3f}")
    means = {k: v / max(n, 1) for k, v in sums.items()}
    if dist_info.world > 1:  # the mean over every process
        keys = sorted(means)
        t = torch.tensor([means[k] for k in keys], device=device)
        torch.distributed.all_reduce(t)
        means = dict(zip(keys, (t / dist_info.world).tolist()))
    return means


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


# --------------------------------------------------------------------------------------------------
# reporting


def write_summary(out: Path, cfg: ModelTrainConfig, history: list[dict], best: dict, class_names: list[str],
                  device, status: str, seconds: float, *, validation: dict | None = None, plan: Plan | None = None,
                  message: str | None = None) -> dict:
    """training_summary.json. ``status``: running, finished, or stopped_by_max_minutes (``message`` says
    after how many of how many epochs); ``validation``: tiles, boxes and distinct plants, with a warning
    when too few; metrics are fractions 0..1."""
    times = [h["train_time_s"] for h in history]
    warnings = [validation["warning"]] if validation and validation.get("warning") else []
    if plan is not None and plan.epochs < cfg.epochs:
        warnings.append(f"max_minutes ({cfg.max_minutes:g}) fits {plan.epochs} of {cfg.epochs} epochs (first epoch "
                        f"{plan.first_epoch_s} s): the learning-rate schedule was shortened to {plan.epochs} epochs")
    summary = {
        "status": status, "message": message or status, "epochs_done": len(history), "epochs": cfg.epochs,
        "epochs_planned": plan.epochs if plan is not None else cfg.epochs, "max_minutes": cfg.max_minutes,
        "warnings": warnings, "validation": validation, "units": "AP, AP50 and the other metrics are fractions 0..1",
        "class_names": class_names, "best": best, "device": str(device),
        "checkpoints": {"best": str(out / "checkpoints" / "best.pt"), "last": str(out / "checkpoints" / "last.pt")},
        "mean_train_images_per_s": (float(np.mean([h["train_images_per_s"] for h in history]))
                                    if history else None),
        "train_time_s": float(sum(times)), "this_session_s": round(seconds, 3),
        "history": history, "config": to_dict(cfg),
    }
    write_json(out / "training_summary.json", summary)
    return summary


def plot_curves(history: list[dict], path: Path) -> Path:
    """Loss components and validation AP / AP50 per epoch."""
    fig = figure(headless=True, figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    epochs = [h["epoch"] for h in history]
    for key in history[0]["losses"]:
        ax1.plot(epochs, [h["losses"][key] for h in history], marker=".", lw=2 if key == "loss" else 1,
                 label=key.replace("loss_", ""))
    ax1.set(xlabel="epoch", ylabel="training loss", title="losses")
    ax1.legend(fontsize=8)
    val = [h for h in history if "val" in h]
    for key in ("AP50", "AP"):
        ax2.plot([h["epoch"] for h in val], [100 * (h["val"][key] or 0) for h in val], marker="o", label=key)
    ax2.set(xlabel="epoch", ylabel="%", title="validation", ylim=(0, 100))
    if val:
        ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path


def run(cfg: ModelTrainConfig) -> dict:
    return train(cfg)
