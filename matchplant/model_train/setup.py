"""Module 6's set-up: the processes and device, the data, the settings auto chooses, the model, the loader and the
optimisation, in that order (the order the random state is drawn in: a run repeats with its seed)."""

from __future__ import annotations

import dataclasses
import math
import random
from pathlib import Path

import numpy as np

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.checkpoint import load_matching_weights
from matchplant.detection.crops import skip_training_resize
from matchplant.detection.data import CocoDetection, EpochSampler, check_disjoint, collate
from matchplant.detection.device import configure_threads, select_device
from matchplant.detection.distributed import Shard, check_environment, join
from matchplant.detection.foreign import read_any_checkpoint
from matchplant.detection.geometry import training_geometry
from matchplant.detection.gpu import as_runtime, choose_runtime
from matchplant.detection.model import (
    AUTO,
    apply_freezing,
    backbone_stages,
    build_detector,
    model_config_from_dict,
    parameter_groups,
    resolve_auto_anchors,
)
from matchplant.model_train.budget import Budget, Plan, validation_report
from matchplant.model_train.choose import (
    budget_recipe,
    choose_architecture,
    cpu_proposals,
    resolve_pretrained,
    resumed_recipe,
    scratch_recipe,
    scratch_settings,
    where,
)
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.gpu import fused_ok, loader_settings, prepare_model
from matchplant.model_train.resume import ignore_sigint, open_resume
from matchplant.model_train.schedule import lr_factor
from matchplant.model_train.state import Job

log = get_logger("model_train")


def build_optimizer(cfg: ModelTrainConfig, model, device=None):
    """SGD or AdamW over the per-part groups; on CUDA its step fused into one kernel (model_train/gpu.py)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    groups = parameter_groups(model, dataclasses.asdict(cfg.lr))
    fused = {"fused": True} if fused_ok([p for g in groups for p in g["params"]], device) else {}
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(
            groups, lr=groups[0]["lr"], momentum=cfg.momentum, weight_decay=cfg.weight_decay, **fused
        )
    return torch.optim.AdamW(groups, lr=groups[0]["lr"], weight_decay=cfg.weight_decay, **fused)


def build_scheduler(cfg: ModelTrainConfig, optimizer, iters_per_epoch: int, plan: Plan | None = None):
    """A per-iteration LambdaLR (its state is the iteration count, so a resumed run continues exactly);
    it follows ``plan.iters`` (read at every step: a refitted plan moves the schedule)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda it: lr_factor(cfg, it, iters_per_epoch, plan.iters if plan else None)
    )


def init_distributed(cfg: ModelTrainConfig):
    """Join a torchrun job (WORLD_SIZE > 1) and pick this process's device."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    if check_environment() <= 1:  # the torchrun variables checked against each other first, job or not
        return Shard(), select_device(cfg.device)
    if torch.cuda.is_available() and cfg.device in ("auto", "cuda"):
        return join(torch.device("cuda"))  # join makes it this process's GPU
    return join(select_device("cpu" if cfg.device == "auto" else cfg.device))


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's random generators with ``seed``."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def load_data(cfg: ModelTrainConfig):
    """``(training set, validation set or None, the validation set's report)``, logged."""
    train_ds = CocoDetection(cfg.train_json, cfg.train_images, augment=cfg.augment)
    class_names = train_ds.class_names
    val_ds = (
        CocoDetection(
            cfg.val_json, cfg.val_images, class_names=class_names, classes_from=f"the training set {cfg.train_json}"
        )
        if cfg.val_json
        else None
    )
    if val_ds is not None:
        check_disjoint(train_ds, val_ds)  # validation on training tiles would measure memory, not skill
    n_neg = sum(1 for im in train_ds.images if not train_ds.anns.get(im["id"]))
    log.info(
        "training tiles: %d (%d without plants, kept as negatives); validation tiles: %s; classes: %s",
        len(train_ds),
        n_neg,
        len(val_ds) if val_ds else "none",
        ", ".join(class_names),
    )
    return train_ds, val_ds, validation_report(val_ds.data if val_ds is not None else None)


def open_run(cfg: ModelTrainConfig, ck_dir: Path, class_names: list[str], iters: int) -> dict | None:
    """The checkpoint to resume from (logged), or None for a new run."""
    resume = open_resume(cfg, ck_dir, class_names)
    if resume is not None:
        log.info(
            "resuming %s after %d iteration(s) (epoch %d%s)",
            ck_dir / "last.pt",
            resume.get("iteration", resume["epoch"] * iters),
            resume["epoch"],
            f", {resume['epoch_progress']['batches']} batch(es) into epoch {resume['epoch'] + 1}"
            if resume.get("epoch_progress")
            else " done",
        )
    return resume


def settle_config(cfg: ModelTrainConfig, device, train_ds, iters: int, resume: dict | None, budget: Budget):
    """``cfg`` with what auto chooses (or, resumed, what the run chose): the CPU recipe, the crops, the detector.
    Returns ``(cfg, the architecture probe or None, the reason or None, whether to size val_every)``."""
    probe, reason, size_validation, scratch = None, None, False, []
    cfg = resolve_pretrained(cfg, resume)  # model.pretrained: auto -> coco or none, before anything depends on it
    if resume is not None:
        cfg = resumed_recipe(cfg, resume.get("train_config") or {})
    else:  # random weights on a CPU: training crops and a run as long as the budget
        cfg, size_validation, scratch = scratch_settings(cfg, device, budget)
    if cfg.augment.crop:
        train_ds.crop_windows(cfg.augment.crop, cfg.model.min_size, cfg.model.max_size, cfg.augment.crop_on_plant)
    if resume is None:
        cfg, probe, reason = choose_model_config(cfg, device, train_ds, cfg.epochs * iters, budget)
        reason = "; ".join(filter(None, (reason, *scratch))) or None
    return cfg, probe, reason, size_validation


def choose_model_config(cfg: ModelTrainConfig, device, train_ds, total: int, budget: Budget):
    """``cfg`` with ``model.architecture: auto`` resolved (logged with the reason), and the probe it made."""
    if cfg.model.architecture != AUTO or cfg.model.checkpoint is not None:
        return cfg, None, None
    model_cfg, sized = cfg.model, None
    if as_runtime(device).on_cpu:
        model_cfg, sized = cpu_proposals(cfg.model, [len(train_ds.anns.get(im["id"], [])) for im in train_ds.images])
    if budget_recipe(cfg, device, budget):  # from random weights on a CPU, or on any device within max_minutes
        cfg, recipe = scratch_recipe(cfg, device)
        sized = "; ".join(filter(None, (sized, recipe))) or None
    if sized:
        log.info("model.architecture: auto %s -> %s", where(device), sized)
    arch, why, probe = choose_architecture(
        cfg, model_cfg, device, train_ds, len(train_ds.class_names), total, cfg.train_json, budget
    )
    log.info("model.architecture: auto -> %s (%s)", arch, why)
    why = f"{why}; {sized}" if sized else why
    return dataclasses.replace(cfg, model=dataclasses.replace(model_cfg, architecture=arch)), probe, why


def initial_model(cfg: ModelTrainConfig, class_names: list[str], resume: dict | None):
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
            raise ConfigError(
                f"model.checkpoint is a {src_cfg['architecture']} but model.architecture is {cfg.model.architecture}",
                path=cfg.model.checkpoint,
                fix=f"set model.architecture: {src_cfg['architecture']} (or auto)",
            )
        mcfg = dataclasses.replace(
            cfg.model, architecture=src_cfg["architecture"], pretrained=src_cfg["pretrained"], checkpoint=None
        )
        mcfg = resolve_auto_anchors(mcfg, cfg.train_json)  # anchor_sizes: auto -> from the training boxes
        model = build_detector(mcfg, len(class_names) + 1, load_weights=False)
        loaded, skipped = load_matching_weights(model, src["model_state"])
        log.info(
            "transfer learning from %s: %d tensors loaded, %d new (%s)",
            cfg.model.checkpoint,
            len(loaded),
            len(skipped),
            ", ".join(sorted({k.rsplit(".", 2)[0] for k in skipped})) or "none",
        )
        return model, mcfg
    mcfg = resolve_auto_anchors(dataclasses.replace(cfg.model, checkpoint=None), cfg.train_json)
    return build_detector(mcfg, len(class_names) + 1), mcfg


def build_model(cfg: ModelTrainConfig, train_ds, resume: dict | None, device, dist_info):
    """``(model that trains, the detector itself, its settings, the training geometry)``: weights, crops'
    scale, frozen parts, on the device (wrapped for torchrun)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    model, model_cfg = initial_model(cfg, train_ds.class_names, resume)
    if cfg.augment.crop:  # the crops come at the detector's scale
        skip_training_resize(model)
    # what module 7 needs to detect as trained: tile size, input scale, classes, plant sizes
    geometry = training_geometry(train_ds.data, model_cfg.min_size, model_cfg.max_size, train_ds.class_names)
    log.info(
        "training geometry: %s px tiles, detector input x%s, median plant %s px in the detector's input",
        geometry["tile_size"],
        geometry["input_scale"],
        geometry["objects_input_px"],
    )
    trainable = cfg.trainable_backbone_layers
    n_stages = len(backbone_stages(model, model_cfg.architecture))
    if model_cfg.pretrained == "none" and cfg.model.checkpoint is None and trainable < n_stages:
        # as torchvision does: freezing random weights makes no sense. A warning only for a value the user set
        default = ModelTrainConfig.__dataclass_fields__["trainable_backbone_layers"].default
        (log.warning if trainable != default else log.info)(
            "model.pretrained is none: all %d backbone stages are trained (trainable_backbone_layers "
            "applies to pretrained weights)",
            n_stages,
        )
        trainable = n_stages
    apply_freezing(model, model_cfg.architecture, trainable, cfg.freeze)
    runtime = as_runtime(device)
    model.to(runtime.device)
    core = prepare_model(model, runtime)  # channels_last, compiled backbone: where asked, on CUDA
    if dist_info.world > 1:
        ids = runtime.ddp_device_ids
        model = torch.nn.parallel.DistributedDataParallel(model, device_ids=list(ids) if ids else None)
    return model, core, model_cfg, geometry


def build_loader(cfg: ModelTrainConfig, train_ds, sampler, device):
    """The training DataLoader: batches from ``sampler``, seeded by ``cfg.seed``, with workers suited to the device."""
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torch.utils.data import DataLoader

    # the loader's own generator: the workers' seeds do not draw from the process's random state
    generator = torch.Generator()
    generator.manual_seed(cfg.seed)
    feed = loader_settings(cfg.num_workers, device)  # on CUDA: more workers, persistent, pinned, prefetching
    return DataLoader(
        train_ds,
        batch_size=cfg.batch_size,
        sampler=sampler,
        collate_fn=collate,
        generator=generator,
        worker_init_fn=ignore_sigint if feed["num_workers"] else None,
        **feed,
    )


def set_up(cfg: ModelTrainConfig, budget: Budget) -> tuple[Job, dict | None, dict]:
    """Everything before the probe: ``(the job, the checkpoint to resume or None, what auto chose)`` where the
    last holds ``probe`` (the architecture's, reused), ``reason`` and ``size_validation``; the budget gets its
    plan of the configured run."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    dist_info, device = init_distributed(cfg)
    runtime = choose_runtime(device, cfg.amp)  # the device's kind is tested here, once
    budget.dist_info, budget.device = dist_info, device
    threads = configure_threads(cfg.threads or None)
    out = Path(cfg.output_dir)
    seed_everything(cfg.seed)
    train_ds, val_ds, validation = load_data(cfg)
    sampler = EpochSampler(len(train_ds), cfg.seed, dist_info.rank, dist_info.world)
    iters = math.ceil(len(sampler) / cfg.batch_size)
    resume = open_run(cfg, out / "checkpoints", train_ds.class_names, iters)
    cfg, probe, reason, size_validation = settle_config(cfg, runtime, train_ds, iters, resume, budget)
    model, core, model_cfg, geometry = build_model(cfg, train_ds, resume, runtime, dist_info)
    job = Job(
        cfg=cfg,
        budget=budget,
        out=out,
        device=device,
        dist_info=dist_info,
        train_ds=train_ds,
        val_ds=val_ds,
        class_names=train_ds.class_names,
        validation=validation,
        model=model,
        core=core,
        model_cfg=model_cfg,
        geometry=geometry,
        sampler=sampler,
        loader=build_loader(cfg, train_ds, sampler, runtime),
        iters=iters,
        runtime=runtime,
    )
    job.optimizer = build_optimizer(cfg, core, runtime)
    plan = budget.plan_for(cfg.epochs * iters, iters)
    job.scheduler = build_scheduler(cfg, job.optimizer, iters, plan)
    job.amp, job.amp_dtype = runtime.amp, runtime.amp_dtype  # bf16 where supported: no loss scaling needed
    job.scaler = torch.amp.GradScaler("cuda", enabled=job.amp and job.amp_dtype == torch.float16)
    job.extras = {"threads": threads}
    return job, resume, {"probe": probe, "reason": reason, "size_validation": size_validation}
