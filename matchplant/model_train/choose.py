"""``model.architecture: auto``: the detector that fits the device and the time budget, with the reason logged.

On a CUDA or Apple GPU: the paper's Faster R-CNN ResNet-50 FPN. On a CPU: a probe of the fast MobileNetV3-Large
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
from matchplant.detection.model import (
    ROIConfig,
    RPNConfig,
    apply_freezing,
    backbone_stages,
    build_detector,
    resolve_auto_anchors,
)
from matchplant.model_train.budget import LONG_RUN_S
from matchplant.model_train.config import LearningRates
from matchplant.model_train.probe import Probe, heartbeat, probe_speed

log = get_logger("model_train")

MOBILE = "fasterrcnn_mobilenet_v3_large_fpn"
PAPER = "fasterrcnn_resnet50_fpn"
# ResNet-50 FPN / MobileNetV3-Large FPN seconds per training iteration on one CPU core of this project's
# shared 2-core machine (batch 2, 512 px input, random weights, every stage trained, SGD step included):
# 44 s against 4.9 s, 9x (3.8x for one inference pass). Measured under load: indicative.
RESNET_TRAIN_COST = 9.0
# Box-head samples and proposals on a CPU. MobileNetV3 FPN at 448 px, batch 4 of 400 px photos with ~20 plants:
# 7.0 s of CPU per training step with torchvision's counts, 3.6 s with these (192 samples for those photos), and
# 0.82 against 0.35 s per photo to detect (python -m bench.bench_model_train_step)
CPU_ROI_SAMPLES = 128       # per image; 32 positives at positive_fraction 0.25
CPU_PROPOSALS_TRAIN = 500   # after NMS (1000 before)
CPU_PROPOSALS_TEST = 300    # after NMS (500 before), = detections_per_img's default


# From random weights on a CPU: AdamW at 1e-3 for every part, cosine decay over the planned iterations. On the
# real-photo bench (python -m bench.bench_model_train_real --minutes 0 --set epochs=10 --set ..., MobileNetV3 at
# 448 px, 27 iterations) the RPN objectness loss was 0.46 against 0.56 (SGD 0.02, cosine) and 0.62 (the paper's
# SGD rates, decays at 1/3 and 2/3); validation AP50 stayed below 2 % in all three (SGD 0.02: 1.3 % at 90)
SCRATCH = {"optimizer": "adamw", "lr": 0.001, "schedule": "cosine"}


def scratch_recipe(cfg) -> tuple[object, str | None]:
    """``cfg`` (module 6's) with the optimisation for random weights, when the optimizer, the learning rates and
    the schedule are all at their defaults (a user who set one keeps all three); the reason, or None."""
    if cfg.model.pretrained != "none" or cfg.model.checkpoint is not None:
        return cfg, None
    defaults = type(cfg)(train_json=cfg.train_json)
    if (cfg.optimizer, cfg.lr, cfg.schedule) != (defaults.optimizer, defaults.lr, defaults.schedule):
        return cfg, None
    lr = SCRATCH["lr"]
    cfg = dataclasses.replace(cfg, optimizer=SCRATCH["optimizer"], schedule=SCRATCH["schedule"],
                              lr=LearningRates(backbone=lr, fpn=lr, rpn=lr, roi_heads=lr))
    return cfg, (f"optimizer: {cfg.optimizer}, lr.*: {lr:g}, schedule: {cfg.schedule} (random weights on a CPU: "
                 "the paper's SGD rates, made for fine-tuning pretrained weights, learn too slowly in the few "
                 "hundred iterations a budget of minutes allows)")


def resumed_recipe(cfg, saved: dict) -> object:
    """On resume: the optimizer, learning rates and schedule the run had (a recipe auto chose) when the config
    leaves them at their defaults, so the saved optimizer state and schedule continue as they were."""
    defaults = type(cfg)(train_json=cfg.train_json)
    if (cfg.optimizer, cfg.lr, cfg.schedule) != (defaults.optimizer, defaults.lr, defaults.schedule) or \
            not isinstance(saved.get("lr"), dict):
        return cfg
    return dataclasses.replace(cfg, optimizer=saved.get("optimizer", cfg.optimizer),
                               schedule=saved.get("schedule", cfg.schedule), lr=LearningRates(**saved["lr"]))


def cpu_proposals(model_cfg, objects_per_image: list[int]) -> tuple[object, str | None]:
    """``model_cfg`` with the box head's samples and the proposal counts sized for a CPU, where they are at
    their (GPU-sized) defaults: enough for every plant of the densest tiles (the most plants in a training
    tile; the 90th percentile of them fits the positive share of the samples). Returns the reason logged, or
    None when nothing changed."""
    most = max(objects_per_image, default=0)
    dense = float(np.percentile(objects_per_image, 90)) if objects_per_image else 0.0
    samples = max(CPU_ROI_SAMPLES, 64 * math.ceil(dense / model_cfg.roi.positive_fraction / 64))
    train, test = max(CPU_PROPOSALS_TRAIN, 4 * most), max(CPU_PROPOSALS_TEST, 3 * most)
    want = {("roi", "batch_size_per_image"): samples, ("rpn", "pre_nms_top_n_train"): 2 * train,
            ("rpn", "post_nms_top_n_train"): train, ("rpn", "pre_nms_top_n_test"): 2 * test,
            ("rpn", "post_nms_top_n_test"): test}
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
    why = (", ".join(f"{k}: {v}" for k, v in changed.items()) + f" (on a CPU the box head's samples dominate a "
           f"training step; the training tiles hold at most {most} plants, 90 % of them at most {dense:.0f})")
    return dataclasses.replace(model_cfg, roi=parts["roi"], rpn=parts["rpn"]), why


def choose_architecture(cfg, model_cfg, device, train_ds, n_classes: int, total_iters: int,
                        train_json) -> tuple[str, str, Probe | None]:
    """``(architecture, reason, probe of MobileNetV3 or None)`` for ``model.architecture: auto``."""
    levels = len(model_cfg.anchor_sizes) if isinstance(model_cfg.anchor_sizes, list) else None
    candidates = [a for a in (PAPER, MOBILE) if levels is None or get_architecture(a).anchors.levels == levels]
    if not candidates:
        candidates = [PAPER]  # the anchors' check then names the mismatch
    if len(candidates) == 1:
        return candidates[0], f"model.anchor_sizes lists {levels} FPN levels, which only {candidates[0]} has", None
    if device.type != "cpu":
        return PAPER, f"the paper's detector, on a GPU ({device})", None
    mcfg = resolve_auto_anchors(dataclasses.replace(model_cfg, architecture=MOBILE, checkpoint=None), train_json)
    model = build_detector(mcfg, n_classes + 1, load_weights=False)
    stages = len(backbone_stages(model, MOBILE))
    trainable = stages if mcfg.pretrained == "none" else min(cfg.trainable_backbone_layers, stages)
    apply_freezing(model, MOBILE, trainable, cfg.freeze)
    log.info("model.architecture: auto on the CPU: timing %s at the config's input size and batch", MOBILE)
    with heartbeat("timing MobileNetV3 for model.architecture: auto"):
        probe = probe_speed(model, train_ds, cfg.batch_size, device, amp=False, num_workers=cfg.num_workers,
                            run_iters=total_iters)
    mobile_s = total_iters * probe.iteration_s
    resnet_s = mobile_s * RESNET_TRAIN_COST
    limit = cfg.max_minutes * 60.0 if cfg.max_minutes else LONG_RUN_S
    what = f"max_minutes = {cfg.max_minutes:g}" if cfg.max_minutes else f"{duration(LONG_RUN_S)} (no max_minutes)"
    measured = (f"{total_iters} iterations at {probe.iteration_s:.2f} s ({MOBILE}, measured) or about "
                f"{probe.iteration_s * RESNET_TRAIN_COST:.2f} s ({PAPER}, {RESNET_TRAIN_COST:g}x)")
    if resnet_s <= limit:
        return PAPER, f"the paper's detector fits the CPU budget: {measured} take {duration(resnet_s)} <= {what}", None
    return MOBILE, (f"on this CPU {PAPER} would take about {duration(resnet_s)} ({measured}), more than {what}; "
                    f"{MOBILE} takes about {duration(mobile_s)}"), probe
