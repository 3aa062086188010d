"""``model.architecture: auto``: the detector that fits the device and the time budget, with the reason logged.

On a CUDA or Apple GPU: the paper's Faster R-CNN ResNet-50 FPN. On a CPU: a probe of the fast MobileNetV3-Large
FPN at the config's input size and batch (:func:`matchplant.model_train.probe.probe_speed`) gives its seconds per
iteration; ResNet-50 FPN costs ``RESNET_TRAIN_COST`` times as much per training iteration (measured, see below).
ResNet-50 is chosen when the whole run as configured fits in ``max_minutes`` (or in a few hours when there is
no budget), MobileNetV3 otherwise. An ``anchor_sizes`` list fixes the number of FPN levels, and so the
candidates (ResNet-50 FPN: 5, MobileNetV3 FPN: 3).
"""

from __future__ import annotations

import dataclasses

from matchplant.core.runtime.log import get_logger
from matchplant.detection.architectures import get_architecture
from matchplant.detection.model import (
    apply_freezing,
    backbone_stages,
    build_detector,
    resolve_auto_anchors,
)
from matchplant.core.runtime.progress import duration
from matchplant.model_train.budget import LONG_RUN_S
from matchplant.model_train.probe import Probe, heartbeat, probe_speed

log = get_logger("model_train")

MOBILE = "fasterrcnn_mobilenet_v3_large_fpn"
PAPER = "fasterrcnn_resnet50_fpn"
# ResNet-50 FPN / MobileNetV3-Large FPN seconds per training iteration on one CPU core of this project's
# shared 2-core machine (batch 2, 512 px input, random weights, every stage trained, SGD step included):
# 44 s against 4.9 s, 9x (3.8x for one inference pass). Measured under load: indicative.
RESNET_TRAIN_COST = 9.0


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
