"""``model.architecture: auto``: the detector that fits the device and the time budget, with the reason logged.

On a CUDA or Apple GPU: the paper's Faster R-CNN ResNet-50 FPN, except from random weights with ``max_minutes``,
where the budget recipe below applies on every device (:func:`budget_recipe`: ResNet-50 FPN from random weights
stopped at 14 % test AP50 in 3 GPU minutes on the real-photo bench, where this recipe reached 53 % in 15 minutes of
one CPU core). On a CPU from random weights (``model.pretrained: none``): the light ResNet-18 FPN
(:mod:`matchplant.detection.lite`), trained on ``CPU_CROP`` px crops at the detector's scale (:func:`cpu_crop`) for
as long as ``max_minutes`` allows (:func:`scratch_budget`); measured on real photos in the module's README ("15
minutes of one CPU core"). On a CPU from pretrained weights: a probe of the fast MobileNetV3-Large
FPN at the config's input size and batch (:func:`matchplant.model_train.probe.probe_speed`) gives its seconds per
iteration; ResNet-50 FPN costs ``RESNET_TRAIN_COST`` times as much per training iteration (measured, see below).
ResNet-50 is chosen when the whole run as configured fits in ``max_minutes`` (or in a few hours when there is
no budget), MobileNetV3 otherwise. An ``anchor_sizes`` list fixes the number of FPN levels, and so the
candidates (ResNet-50 FPN: 5, MobileNetV3 FPN: 3).

On a CPU, auto also sizes the proposals (:func:`cpu_proposals`): torchvision's counts (2000 proposals, 512 of
them sampled per image for the box head) are sized for a GPU; on a CPU the box head on those samples is most of
a training step. Counts left at their defaults are lowered to what the training tiles' plant counts need.
From random weights (``model.pretrained: none``) on a CPU it also sets the optimisation (:func:`scratch_recipe`):
the paper's rates are for fine-tuning pretrained weights and decay at a third of the run; a budget of minutes
allows a few hundred iterations, too few for that.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration
from matchplant.detection.architectures import get_architecture
from matchplant.detection.crops import skip_training_resize
from matchplant.detection.gpu import as_runtime
from matchplant.detection.model import (
    AUTO,
    PRETRAINED,
    ROIConfig,
    RPNConfig,
    apply_freezing,
    backbone_stages,
    build_detector,
    coco_weights_at_hand,
    resolve_auto_anchors,
)
from matchplant.model_train.budget import Budget
from matchplant.model_train.config import LearningRates
from matchplant.model_train.probe import Probe, heartbeat, probe_speed

log = get_logger("model_train")

MOBILE = "fasterrcnn_mobilenet_v3_large_fpn"
PAPER = "fasterrcnn_resnet50_fpn"
LITE = "fasterrcnn_resnet18_fpn_lite"
# ResNet-50 FPN / MobileNetV3-Large FPN seconds per training iteration on one CPU core of this project's
# shared 2-core machine (batch 2, 512 px input, random weights, every stage trained, SGD step included):
# 44 s against 4.9 s, 9x (3.8x for one inference pass). Measured under load: indicative.
RESNET_TRAIN_COST = 9.0
# Box-head samples and proposals on a CPU. MobileNetV3 FPN at 448 px, batch 4 of 400 px photos with ~20 plants:
# 7.0 s of CPU per training step with torchvision's counts, 3.6 s with these (192 samples for those photos), and
# 0.82 against 0.35 s per photo to detect (python -m bench.bench_model_train_step)
CPU_ROI_SAMPLES = 128  # per image; 32 positives at positive_fraction 0.25
CPU_PROPOSALS_TRAIN = 500  # after NMS (1000 before)
CPU_PROPOSALS_TEST = 300  # after NMS (500 before), = detections_per_img's default


# From random weights on a CPU: AdamW at 1e-3 for every part, cosine decay over the planned iterations. On the
# real-photo bench (python -m bench.bench_model_train_real --minutes 0 --set epochs=10 --set ..., MobileNetV3 at
# 448 px, 27 iterations) the RPN objectness loss was 0.46 against 0.56 (SGD 0.02, cosine) and 0.62 (the paper's
# SGD rates, decays at 1/3 and 2/3); validation AP50 stayed below 2 % in all three (SGD 0.02: 1.3 % at 90)
SCRATCH = {"optimizer": "adamw", "lr": 0.001, "schedule": "cosine"}
CPU_CROP = 256  # augment.crop from random weights on a CPU (detector input pixels)
SCRATCH_EPOCHS = 1000  # with max_minutes, from random weights on a CPU: the budget ends the run
VAL_SHARE = 0.1  # ... and validation takes about this share of the training time
LITE_WHY = (
    "random weights on a CPU: the light ResNet-18 FPN (matchplant/detection/lite.py) learns from scratch "
    "in the iterations a CPU budget allows, where MobileNetV3-Large FPN does not"
)

LITE_WHY_GPU = (
    "random weights within {}: the budget recipe of the light ResNet-18 FPN (matchplant/detection/lite.py), "
    "which learns from scratch in minutes, where ResNet-50 FPN from random weights does not"
)


def resolve_pretrained(cfg, resume: dict | None) -> object:
    """``model.pretrained: auto`` made concrete, logged with the reason: a resumed run keeps its weights' kind (the
    detector's structure depends on it); from a checkpoint, none (the weights come from it); else coco when the
    COCO weights of the architecture (for ``architecture: auto``, of both the paper's and MobileNetV3) are in the
    torch cache or downloadable now, none otherwise, which on a CPU picks the from-scratch recipe. Checked
    before any model is built, so an offline run does not time MobileNetV3 only to fail on the download."""
    model = cfg.model
    if model.pretrained != AUTO:
        return cfg
    saved = ((resume or {}).get("model_config") or {}).get("pretrained")
    if saved in PRETRAINED and saved != AUTO:
        choice, why = saved, "the resumed run's"
    elif model.checkpoint is not None:
        choice, why = "none", f"the weights come from model.checkpoint ({model.checkpoint})"
    else:
        at_hand, why = coco_weights_at_hand([PAPER, MOBILE] if model.architecture == AUTO else [model.architecture])
        choice = "coco" if at_hand else "none"
    log.info("model.pretrained: auto -> %s (%s)", choice, why)
    return dataclasses.replace(cfg, model=dataclasses.replace(model, pretrained=choice))


def from_scratch_on_cpu(cfg, device) -> bool:
    """``model.architecture: auto`` from random weights (no checkpoint) on a CPU: the case the CPU recipe is for (a
    config naming its architecture, as the demo's, keeps its own training as set)."""
    return as_runtime(device).on_cpu and from_scratch(cfg)


def from_scratch(cfg) -> bool:
    """``model.architecture: auto`` from random weights and no checkpoint, on any device."""
    return cfg.model.architecture == AUTO and cfg.model.pretrained == "none" and cfg.model.checkpoint is None


def budget_recipe(cfg, device, budget: Budget | None) -> bool:
    """Whether the recipe for random weights applies (the light detector, crops, AdamW, epochs ended by the
    budget): from scratch on a CPU, or on any device with ``max_minutes`` (a GPU without a budget has the hours
    the paper's detector needs)."""
    return from_scratch(cfg) and (as_runtime(device).on_cpu or (budget is not None and budget.limited))


def where(device) -> str:
    """Where the recipe for random weights applies, in words (``device``: the run's Runtime or a bare device)."""
    runtime = as_runtime(device)
    return "on a CPU" if runtime.on_cpu else f"on {runtime.kind.upper()} within max_minutes"


def cpu_crop(cfg, device, budget: Budget | None = None) -> tuple[object, str | None]:
    """``augment.crop: null`` (auto) resolved: ``CPU_CROP`` where :func:`budget_recipe` applies and the detector's
    input is larger, whole tiles otherwise; the reason, or None when whole tiles are kept."""
    if cfg.augment.crop is not None:
        return cfg, None
    crop = CPU_CROP if budget_recipe(cfg, device, budget) and cfg.model.min_size > CPU_CROP else 0
    cfg = dataclasses.replace(cfg, augment=dataclasses.replace(cfg.augment, crop=crop))
    if not crop:
        return cfg, None
    return cfg, (
        f"augment.crop: {crop} (random weights {where(device)}: training steps on {crop} px windows of the "
        f"{cfg.model.min_size} px detector input cost a fraction of whole tiles, so many more fit the "
        "budget; detection still sees whole tiles)"
    )


def scratch_budget(cfg, device, budget: Budget) -> tuple[object, bool, str | None]:
    """From random weights with ``max_minutes`` (any device) and ``epochs``/``val_every`` at their defaults: the
    budget, not the 30 epochs, ends the run (``SCRATCH_EPOCHS``), and the validation interval is sized after the
    probe (:func:`validation_interval`). Returns ``(cfg, whether to size val_every, the reason or None)``."""
    defaults = type(cfg)(train_json=cfg.train_json)
    if not (
        from_scratch(cfg) and budget.limited and cfg.epochs == defaults.epochs and cfg.val_every == defaults.val_every
    ):
        return cfg, False, None
    cfg = dataclasses.replace(cfg, epochs=SCRATCH_EPOCHS)
    return (
        cfg,
        True,
        (
            f"epochs: {SCRATCH_EPOCHS} (random weights {where(device)}: a detector learning from scratch "
            f"gains from every iteration max_minutes = {budget.minutes:g} allows, and 30 epochs of a "
            "small dataset end long before it); val_every: sized so that validation takes about "
            f"{100 * VAL_SHARE:.0f} % of the time"
        ),
    )


def validation_interval(validation_s: float, epoch_s: float) -> int:
    """Epochs between validations so that validating costs about ``VAL_SHARE`` of the training time."""
    return max(1, math.ceil(validation_s / max(VAL_SHARE * epoch_s, 1e-9)))


def sized_validation(cfg, validation_s: float, epoch_s: float):
    """``cfg`` with ``val_every`` from :func:`validation_interval` (logged when it changes)."""
    every = validation_interval(validation_s, epoch_s)
    if every == cfg.val_every:
        return cfg
    log.info(
        "val_every: %d (validation %.1f s, an epoch %.1f s of training: validating takes about %.0f %% of the time)",
        every,
        validation_s,
        epoch_s,
        100 * VAL_SHARE,
    )
    return dataclasses.replace(cfg, val_every=every)


def scratch_settings(cfg, device, budget: Budget) -> tuple[object, bool, list[str]]:
    """:func:`cpu_crop` and :func:`scratch_budget` together, logged: ``(cfg, size val_every, reasons)``."""
    cfg, crop_why = cpu_crop(cfg, device, budget)
    cfg, size_validation, budget_why = scratch_budget(cfg, device, budget)
    reasons = [w for w in (crop_why, budget_why) if w]
    for why in reasons:
        log.info("%s from random weights -> %s", where(device), why)
    return cfg, size_validation, reasons


def scratch_recipe(cfg, device=None) -> tuple[object, str | None]:
    """``cfg`` (module 6's) with the optimisation for random weights, when the optimizer, the learning rates and
    the schedule are all at their defaults (a user who set one keeps all three); the reason, or None."""
    if cfg.model.pretrained != "none" or cfg.model.checkpoint is not None:
        return cfg, None
    defaults = type(cfg)(train_json=cfg.train_json)
    if (cfg.optimizer, cfg.lr, cfg.schedule) != (defaults.optimizer, defaults.lr, defaults.schedule):
        return cfg, None
    lr = SCRATCH["lr"]
    cfg = dataclasses.replace(
        cfg,
        optimizer=SCRATCH["optimizer"],
        schedule=SCRATCH["schedule"],
        lr=LearningRates(backbone=lr, fpn=lr, rpn=lr, roi_heads=lr),
    )
    return cfg, (
        f"optimizer: {cfg.optimizer}, lr.*: {lr:g}, schedule: {cfg.schedule} (random weights "
        f"{where(device) if device is not None else 'on a CPU'}: "
        "the paper's SGD rates, made for fine-tuning pretrained weights, learn too slowly in the few "
        "hundred iterations a budget of minutes allows)"
    )


def resumed_recipe(cfg, saved: dict) -> object:
    """On resume: the optimizer, learning rates and schedule the run had (a recipe auto chose) when the config
    leaves them at their defaults, so the saved optimizer state and schedule continue as they were; so too the
    crop, the epochs and the validation interval auto chose."""
    defaults = type(cfg)(train_json=cfg.train_json)
    if cfg.augment.crop is None and isinstance(saved.get("augment", {}).get("crop"), int):
        cfg = dataclasses.replace(cfg, augment=dataclasses.replace(cfg.augment, crop=saved["augment"]["crop"]))
    if (
        (cfg.epochs, cfg.val_every) == (defaults.epochs, defaults.val_every)
        and isinstance(saved.get("epochs"), int)
        and isinstance(saved.get("val_every"), int)
        and (saved["epochs"], saved["val_every"]) != (cfg.epochs, cfg.val_every)
    ):
        cfg = dataclasses.replace(cfg, epochs=saved["epochs"], val_every=saved["val_every"])
    if (cfg.optimizer, cfg.lr, cfg.schedule) != (defaults.optimizer, defaults.lr, defaults.schedule) or not isinstance(
        saved.get("lr"), dict
    ):
        return cfg
    return dataclasses.replace(
        cfg,
        optimizer=saved.get("optimizer", cfg.optimizer),
        schedule=saved.get("schedule", cfg.schedule),
        lr=LearningRates(**saved["lr"]),
    )


def cpu_proposals(model_cfg, objects_per_image: list[int]) -> tuple[object, str | None]:
    """``model_cfg`` with the box head's samples and the proposal counts sized for a CPU, where they are at
    their (GPU-sized) defaults: enough for every plant of the densest tiles (the most plants in a training
    tile; the 90th percentile of them fits the positive share of the samples). Returns the reason logged, or
    None when nothing changed."""
    most = max(objects_per_image, default=0)
    dense = float(np.percentile(objects_per_image, 90)) if objects_per_image else 0.0
    samples = max(CPU_ROI_SAMPLES, 64 * math.ceil(dense / model_cfg.roi.positive_fraction / 64))
    train, test = max(CPU_PROPOSALS_TRAIN, 4 * most), max(CPU_PROPOSALS_TEST, 3 * most)
    want = {
        ("roi", "batch_size_per_image"): samples,
        ("rpn", "pre_nms_top_n_train"): 2 * train,
        ("rpn", "post_nms_top_n_train"): train,
        ("rpn", "pre_nms_top_n_test"): 2 * test,
        ("rpn", "post_nms_top_n_test"): test,
    }
    defaults = {"roi": ROIConfig(), "rpn": RPNConfig()}
    parts = {"roi": model_cfg.roi, "rpn": model_cfg.rpn}
    changed = {}
    for (part, key), value in want.items():
        default = getattr(defaults[part], key)
        if getattr(parts[part], key) == default and value < default:
            changed[f"model.{part}.{key}"] = value
            parts[part] = dataclasses.replace(parts[part], **{key: value})
    if not changed:
        return model_cfg, None
    why = (
        ", ".join(f"{k}: {v}" for k, v in changed.items()) + f" (on a CPU the box head's samples dominate a "
        f"training step; the training tiles hold at most {most} plants, 90 % of them at most {dense:.0f})"
    )
    return dataclasses.replace(model_cfg, roi=parts["roi"], rpn=parts["rpn"]), why


def choose_architecture(
    cfg, model_cfg, device, train_ds, n_classes: int, total_iters: int, train_json, budget: Budget
) -> tuple[str, str, Probe | None]:
    """``(architecture, reason, probe of MobileNetV3 or None)`` for ``model.architecture: auto``."""
    levels = len(model_cfg.anchor_sizes) if isinstance(model_cfg.anchor_sizes, list) else None
    candidates = [a for a in (PAPER, MOBILE, LITE) if levels is None or get_architecture(a).anchors.levels == levels]
    if not candidates:
        candidates = [PAPER]  # the anchors' check then names the mismatch
    runtime = as_runtime(device)
    light = model_cfg.pretrained == "none" and (runtime.on_cpu or budget.limited)  # the budget recipe's
    if not light:
        candidates = [a for a in candidates if a != LITE] or [PAPER]
    if len(candidates) == 1:
        return candidates[0], f"model.anchor_sizes lists {levels} FPN levels, which only {candidates[0]} has", None
    if light and LITE in candidates:
        return LITE, LITE_WHY if runtime.on_cpu else LITE_WHY_GPU.format(budget.horizon_words()), None
    if not runtime.on_cpu:
        return PAPER, f"the paper's detector, on a GPU ({runtime.device})", None
    mcfg = resolve_auto_anchors(dataclasses.replace(model_cfg, architecture=MOBILE, checkpoint=None), train_json)
    model = build_detector(mcfg, n_classes + 1, load_weights=False)
    stages = len(backbone_stages(model, MOBILE))
    trainable = stages if mcfg.pretrained == "none" else min(cfg.trainable_backbone_layers, stages)
    apply_freezing(model, MOBILE, trainable, cfg.freeze)
    if getattr(train_ds, "crop", None):  # the training crops come at the detector's scale
        skip_training_resize(model)
    log.info("model.architecture: auto on the CPU: timing %s at the config's input size and batch", MOBILE)
    with heartbeat("timing MobileNetV3 for model.architecture: auto"):
        probe = probe_speed(
            model, train_ds, cfg.batch_size, runtime, amp=False, num_workers=cfg.num_workers, run_iters=total_iters
        )
    mobile_s = total_iters * probe.iteration_s
    resnet_s = mobile_s * RESNET_TRAIN_COST
    limit, what = budget.horizon_s, budget.horizon_words()
    measured = (
        f"{total_iters} iterations at {probe.iteration_s:.2f} s ({MOBILE}, measured) or about "
        f"{probe.iteration_s * RESNET_TRAIN_COST:.2f} s ({PAPER}, {RESNET_TRAIN_COST:g}x)"
    )
    if resnet_s <= limit:
        return PAPER, f"the paper's detector fits the CPU budget: {measured} take {duration(resnet_s)} <= {what}", None
    return (
        MOBILE,
        (
            f"on this CPU {PAPER} would take about {duration(resnet_s)} ({measured}), more than {what}; "
            f"{MOBILE} takes about {duration(mobile_s)}"
        ),
        probe,
    )
