"""The detector of modules 6 and 7: building it from settings, freezing parts, checkpoints.

Seven architectures (:data:`~matchplant.detection.architectures.ARCHITECTURES`), one target format (COCO
boxes, labels 1..N) and one checkpoint format: the two-stage Faster R-CNN ``fasterrcnn_resnet50_fpn`` (the
paper's), ``fasterrcnn_resnet50_fpn_v2``, ``fasterrcnn_mobilenet_v3_large_fpn`` (fast on a CPU) and MatchPlant's
own ``fasterrcnn_resnet18_fpn_lite`` (learns from random weights in a CPU's minutes,
:mod:`matchplant.detection.lite`), and torchvision's one-stage ``retinanet_resnet50_fpn``,
``retinanet_resnet50_fpn_v2`` and ``fcos_resnet50_fpn`` (anchor-free). Every setting of
:class:`ModelConfig` is passed to the model (anchors, RPN and ROI sampling and thresholds, image size,
detections per image); the RPN and ROI sampling settings concern Faster R-CNN only, ``roi.nms_thresh``
and ``roi.detections_per_img`` every architecture. ``anchor_sizes: auto`` is computed from the training
boxes (:func:`resolve_auto_anchors`, :mod:`matchplant.detection.objects`). What differs between
architectures is read from their records (:mod:`matchplant.detection.architectures`).

One-stage models have no ``rpn`` and their ``head`` is the part called ``roi_heads`` (freezing, learning
rates); they get a ``roi_heads.score_thresh`` too (:class:`ScoreThreshold`), so that code written for
Faster R-CNN sets their score threshold the same way (:func:`set_score_threshold` is the direct call).

A checkpoint (docs/DESIGN.md §2) is one ``.pt`` file holding everything needed to rebuild the model with no
other file: the model settings, class names, the weights, and for training runs the epoch, optimizer,
scheduler and scaler state, random states, history and metrics. :func:`load_detector` rebuilds it.
"""

from __future__ import annotations

import dataclasses
import socket
import threading
import types
import urllib.error
import urllib.parse
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Literal

import numpy as np

from matchplant.core.formats.coco import read_dataset
from matchplant.core.runtime.config import from_dict, param, section
from matchplant.core.runtime.errors import ConfigError, DependencyError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.detection import lite
from matchplant.detection.architectures import ARCHITECTURES, Architecture, get_architecture
from matchplant.detection.objects import auto_anchor_sizes, box_sizes

log = get_logger("detector")

PRETRAINED = ("auto", "coco", "imagenet", "none")
WEIGHTS_HOST_TIMEOUT = 3.0  # seconds to wait for the weights' download host before counting it unreachable
AUTO = "auto"  # model.architecture chosen by module 6 (matchplant.model_train.choose)
PARTS = ("backbone", "fpn", "rpn", "roi_heads")


@dataclass
class RPNConfig:
    """Region proposal network: anchor sampling, IoU thresholds and proposal counts."""

    fg_iou_thresh: float = param(0.7, "anchors with IoU >= this to a plant are positives", min=0, max=1)
    bg_iou_thresh: float = param(0.3, "anchors with IoU < this to every plant are negatives", min=0, max=1)
    batch_size_per_image: int = param(256, "anchors sampled per image for the RPN loss", min=1)
    positive_fraction: float = param(0.5, "largest share of positives among the sampled anchors", min=0, max=1)
    pre_nms_top_n_train: int = param(2000, "proposals per FPN level kept before NMS (training)", min=1)
    post_nms_top_n_train: int = param(2000, "proposals kept after NMS (training)", min=1)
    pre_nms_top_n_test: int = param(1000, "proposals per FPN level kept before NMS (inference)", min=1)
    post_nms_top_n_test: int = param(1000, "proposals kept after NMS (inference); raise it for very dense tiles", min=1)
    nms_thresh: float = param(0.7, "NMS IoU threshold between proposals", min=0, max=1)
    score_thresh: float = param(0.0, "drop proposals with an objectness below this", min=0, max=1)

    def check(self) -> None:
        """Reject a background IoU threshold above the foreground one."""
        if self.bg_iou_thresh > self.fg_iou_thresh:
            raise ConfigError(
                f"model.rpn.bg_iou_thresh ({self.bg_iou_thresh}) is above model.rpn.fg_iou_thresh "
                f"({self.fg_iou_thresh})",
                fix="make bg_iou_thresh <= fg_iou_thresh (defaults 0.3, 0.7)",
            )


@dataclass
class ROIConfig:
    """Box head: proposal sampling and IoU thresholds for training, NMS and box count for inference."""

    fg_iou_thresh: float = param(0.5, "proposals with IoU >= this to a plant are positives", min=0, max=1)
    bg_iou_thresh: float = param(0.5, "proposals with IoU < this are background", min=0, max=1)
    batch_size_per_image: int = param(512, "proposals sampled per image for the box loss", min=1)
    positive_fraction: float = param(0.25, "largest share of positives among the sampled proposals", min=0, max=1)
    nms_thresh: float = param(0.5, "NMS IoU threshold between final boxes of one class", min=0, max=1)
    detections_per_img: int = param(
        300, "most boxes returned per image (torchvision's 100 loses plants on dense tiles)", min=1
    )

    def check(self) -> None:
        """Reject a background IoU threshold above the foreground one."""
        if self.bg_iou_thresh > self.fg_iou_thresh:
            raise ConfigError(
                f"model.roi.bg_iou_thresh ({self.bg_iou_thresh}) is above model.roi.fg_iou_thresh "
                f"({self.fg_iou_thresh})",
                fix="make bg_iou_thresh <= fg_iou_thresh (defaults 0.5, 0.5)",
            )


@dataclass
class ModelConfig:
    """The detector: architecture, starting weights, input size, anchors, RPN and ROI settings."""

    architecture: str = param(
        AUTO,
        "torchvision detector: auto (module 6: the paper's ResNet-50 FPN on a GPU; "
        "on a CPU from random weights the light ResNet-18 FPN, from pretrained ones what a "
        "measured probe shows can train in the time budget; logged with the reason), Faster "
        "R-CNN (the paper used ResNet-50 FPN; MobileNetV3 is much faster on a CPU), or the "
        "one-stage RetinaNet and FCOS",
        choices=(AUTO, *ARCHITECTURES),
    )
    pretrained: str = param(
        AUTO,
        "starting weights: auto (module 6: coco when the COCO weights are in the torch cache or downloadable now, "
        "else none and the from-scratch recipe; logged with the reason), coco (whole detector, downloaded "
        "once), imagenet (backbone only), none (random)",
        choices=PRETRAINED,
    )
    checkpoint: Path | None = param(
        None,
        "start from this MatchPlant checkpoint instead (transfer learning; "
        "matching layers are loaded, a different class count is fine)",
        path="file",
    )
    min_size: int = param(800, "images are resized so their short side is this many pixels", min=32)
    max_size: int = param(1333, "... and their long side at most this many pixels", min=32)
    anchor_sizes: list[list[int]] | Literal["auto"] | None = param(
        None,
        "anchor sizes in detector input pixels (after the min_size resize), one list per FPN level "
        "(ResNet-50: 5 levels, MobileNetV3: 3; FCOS: one size per level); 'auto' = from the training "
        "boxes (see 'matchplant inspect'); null = the architecture's default",
        min=1,
    )
    aspect_ratios: list[float] = param(
        [0.5, 1.0, 2.0], "anchor height/width ratios (the same at every level)", min=0.01
    )
    rpn: RPNConfig = section(RPNConfig)
    roi: ROIConfig = section(ROIConfig)

    def check(self) -> None:
        """Reject a max_size below min_size and anchor sizes that do not fit the architecture's FPN levels."""
        if self.max_size < self.min_size:
            raise ConfigError(
                f"model.max_size ({self.max_size}) is below model.min_size ({self.min_size})",
                fix="set max_size >= min_size",
            )
        if isinstance(self.anchor_sizes, list) and self.architecture != AUTO:  # auto: module 6 picks a fitting one
            arch = get_architecture(self.architecture)
            levels = arch.anchors.levels
            if len(self.anchor_sizes) != levels:
                raise ConfigError(
                    f"model.anchor_sizes has {len(self.anchor_sizes)} level(s) but "
                    f"{self.architecture} has {levels} FPN levels",
                    fix=f"give {levels} lists, e.g. {[list(s) for s in arch.default_anchors]}",
                )
            if any(s <= 0 for level in self.anchor_sizes for s in level):
                raise ConfigError("model.anchor_sizes must be positive pixel sizes", fix="correct model.anchor_sizes")
            if len({len(s) for s in self.anchor_sizes}) != 1:
                raise ConfigError(
                    "model.anchor_sizes: every level needs the same number of sizes (one RPN head serves all levels)",
                    fix="give each level's list the same length",
                )
            if arch.anchor_free and any(len(level) != 1 for level in self.anchor_sizes):
                raise ConfigError(
                    "model.anchor_sizes: FCOS is anchor-free and takes one size per level (it sets "
                    "the object sizes each level learns)",
                    fix="e.g. [[8], [16], [32], [64], [128]]",
                )


def model_config_from_dict(data: dict) -> ModelConfig:
    """Rebuild a :class:`ModelConfig` from a checkpoint's plain dict."""
    data = {k: v for k, v in data.items() if k != "checkpoint"}
    return from_dict(ModelConfig, data, prefix="model.", source="checkpoint", base=Path.cwd())


# --------------------------------------------------------------------------------------------------
# building


def _weights(arch: Architecture, pretrained: str):
    """torchvision weight enums (detector, backbone) for a ``pretrained`` choice."""
    from torchvision.models import get_weight  # lazy: PyTorch is heavy; configs load without it

    if pretrained == "coco":
        if arch.coco_weights is None:
            raise ConfigError(
                f"{arch.name} has no COCO weights (model.pretrained: coco)",
                fix="set model.pretrained: imagenet (its backbone's weights) or none",
            )
        return get_weight(arch.coco_weights), None
    if pretrained == "imagenet":
        return None, get_weight(arch.backbone.imagenet_weights)
    return None, None


def _frozen_bn_structure(arch: Architecture, pretrained: str) -> bool:
    return pretrained != "none" and arch.frozen_backbone_norms


def _check_resolved(cfg: ModelConfig, num_classes: int, load_weights: bool) -> None:
    """Refuse to build from settings that module 6 resolves first (``auto``), or for a dataset without categories."""
    if num_classes < 2:
        raise InputError("the dataset has no categories", fix="give a COCO dataset with at least one category")
    if cfg.anchor_sizes == "auto":
        raise ConfigError(
            "model.anchor_sizes is 'auto' but was not computed from the training boxes",
            fix="call resolve_auto_anchors(cfg, train_dataset) first (module 6 does)",
        )
    if cfg.architecture == AUTO:
        raise ConfigError(
            "model.architecture is 'auto', which module 6 resolves before it builds a model",
            fix="set model.architecture to one of " + ", ".join(ARCHITECTURES),
        )
    if cfg.pretrained == AUTO and load_weights:
        raise ConfigError(
            "model.pretrained is 'auto', which module 6 resolves before it builds a model",
            fix="set model.pretrained to one of " + ", ".join(p for p in PRETRAINED if p != AUTO),
        )


def _builder_kwargs(cfg: ModelConfig, arch: Architecture) -> dict:
    """The torchvision builder's keywords from ``cfg``: input size and box settings; the RPN's and the box head's
    for a two-stage detector."""
    return (
        dict(
            min_size=cfg.min_size,
            max_size=cfg.max_size,
            nms_thresh=cfg.roi.nms_thresh,
            detections_per_img=cfg.roi.detections_per_img,
        )
        if not arch.two_stage
        else dict(
            min_size=cfg.min_size,
            max_size=cfg.max_size,
            rpn_pre_nms_top_n_train=cfg.rpn.pre_nms_top_n_train,
            rpn_pre_nms_top_n_test=cfg.rpn.pre_nms_top_n_test,
            rpn_post_nms_top_n_train=cfg.rpn.post_nms_top_n_train,
            rpn_post_nms_top_n_test=cfg.rpn.post_nms_top_n_test,
            rpn_nms_thresh=cfg.rpn.nms_thresh,
            rpn_fg_iou_thresh=cfg.rpn.fg_iou_thresh,
            rpn_bg_iou_thresh=cfg.rpn.bg_iou_thresh,
            rpn_batch_size_per_image=cfg.rpn.batch_size_per_image,
            rpn_positive_fraction=cfg.rpn.positive_fraction,
            rpn_score_thresh=cfg.rpn.score_thresh,
            box_nms_thresh=cfg.roi.nms_thresh,
            box_detections_per_img=cfg.roi.detections_per_img,
            box_fg_iou_thresh=cfg.roi.fg_iou_thresh,
            box_bg_iou_thresh=cfg.roi.bg_iou_thresh,
            box_batch_size_per_image=cfg.roi.batch_size_per_image,
            box_positive_fraction=cfg.roi.positive_fraction,
        )
    )


def build_detector(cfg: ModelConfig, num_classes: int, *, load_weights: bool = True):
    """A detector with ``num_classes`` outputs (background included) built from ``cfg``.

    ``load_weights=False`` builds the same structure without downloading anything (the weights then
    come from a checkpoint).

    Parameters
    ----------
    cfg : ModelConfig
        The model settings, with ``architecture``, ``pretrained`` and ``anchor_sizes`` resolved (not "auto").
    num_classes : int
        Categories + 1 (background).
    load_weights : bool
        Load the ``pretrained`` weights (COCO or ImageNet, downloaded when not in the torch cache).

    Returns
    -------
    torch.nn.Module
        The torchvision detector (or MatchPlant's lite one) with the settings of ``cfg``, every backbone stage
        trainable (:func:`apply_freezing` freezes parts).
    """
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it
    from torchvision.models import detection as d
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.faster_rcnn import FastRCNNPredictor
    from torchvision.models.detection.rpn import RPNHead

    _check_resolved(cfg, num_classes, load_weights)
    arch = get_architecture(cfg.architecture)
    weights, weights_backbone = _weights(arch, cfg.pretrained) if load_weights else (None, None)
    kwargs = _builder_kwargs(cfg, arch)
    builder = getattr(lite, arch.builder, None) or getattr(d, arch.builder)
    # all stages trainable here; train.apply_freezing decides (the same on every rebuild)
    trainable = arch.backbone.stage_count
    try:
        model = builder(
            weights=weights,
            weights_backbone=weights_backbone,
            num_classes=91 if weights is not None else num_classes,
            trainable_backbone_layers=trainable if (weights or weights_backbone) else None,
            **kwargs,
        )
    except (urllib.error.URLError, OSError, ConnectionError) as exc:
        _download_failed(cfg, weights or weights_backbone, exc)
    assert isinstance(model, nn.Module)
    if not arch.two_stage:
        _adapt_one_stage(model, cfg, arch, num_classes, coco_head=weights is not None, load_weights=load_weights)
        return model
    if weights is not None:  # COCO has 91 classes: a new box predictor for ours
        in_features = model.roi_heads.box_predictor.cls_score.in_features
        model.roi_heads.box_predictor = FastRCNNPredictor(in_features, num_classes)
    elif not load_weights and _frozen_bn_structure(arch, cfg.pretrained):
        _freeze_batchnorm(model.backbone.body)
    if cfg.anchor_sizes is not None or list(cfg.aspect_ratios) != [0.5, 1.0, 2.0]:
        sizes = cfg.anchor_sizes or arch.default_anchors
        ratios = tuple(float(r) for r in cfg.aspect_ratios)
        gen = AnchorGenerator(tuple(tuple(int(s) for s in level) for level in sizes), (ratios,) * len(sizes))
        model.rpn.anchor_generator = gen
        n = gen.num_anchors_per_location()[0]
        if n != model.rpn.head.cls_logits.out_channels:  # a head with one output per anchor shape
            depth = len(model.rpn.head.conv)
            model.rpn.head = RPNHead(model.backbone.out_channels, n, conv_depth=depth)
            if weights is not None:
                log.info("the RPN head was re-initialised for %d anchors per position", n)
    return model


def coco_weights_at_hand(architectures: list[str], timeout: float = WEIGHTS_HOST_TIMEOUT) -> tuple[bool, str]:
    """Whether the COCO weights of every one of ``architectures`` can be loaded now, and why: in torch's cache, or
    else their download host answers within ``timeout`` seconds. Costs milliseconds offline (no model is built,
    nothing is downloaded here)."""
    from torch.hub import get_dir  # lazy: PyTorch is heavy; configs load without it
    from torchvision.models import get_weight

    cache = Path(get_dir()) / "checkpoints"
    urls = []
    for name in architectures:
        arch = get_architecture(name)
        if arch.coco_weights is None:
            return False, f"{name} has no COCO weights"
        url = get_weight(arch.coco_weights).url
        if not (cache / url.rsplit("/", 1)[-1]).is_file():
            urls.append(url)
    if not urls:
        return True, f"the COCO weights are in the torch cache ({cache})"
    host = urllib.parse.urlparse(urls[0]).hostname
    answered: list[bool] = []

    def connect() -> None:  # in a thread: a name lookup can outlast any socket timeout
        try:
            socket.create_connection((host, 443), timeout=timeout).close()
            answered.append(True)
        except OSError:
            pass

    worker = threading.Thread(target=connect, daemon=True)
    worker.start()
    worker.join(timeout)
    if answered:
        return True, f"the COCO weights are not in the torch cache ({cache}) but {host} answers: downloaded once"
    return False, f"the COCO weights are not in the torch cache ({cache}) and {host} does not answer (offline?)"


def _download_failed(cfg: ModelConfig, weights, exc: Exception):
    from torch.hub import get_dir  # lazy: PyTorch is heavy; configs load without it

    name = weights.url.rsplit("/", 1)[-1]
    raise DependencyError(
        f"could not download the {cfg.pretrained.upper()} weights of {cfg.architecture} ({type(exc).__name__}: {exc})",
        path=Path(get_dir()) / "checkpoints" / name,
        fix="connect to the internet once (the file is then cached), or copy the file to "
        "that path, or set model.pretrained: none, or start from model.checkpoint",
    ) from exc


def _adapt_one_stage(
    model, cfg: ModelConfig, arch: Architecture, num_classes: int, *, coco_head: bool, load_weights: bool
) -> None:
    """RetinaNet / FCOS: our classes, anchors, frozen norms and the score-threshold handle."""
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.retinanet import RetinaNetHead

    norm = partial(nn.GroupNorm, arch.head_norm_groups) if arch.head_norm_groups else None
    if cfg.anchor_sizes is not None or (not arch.anchor_free and list(cfg.aspect_ratios) != [0.5, 1.0, 2.0]):
        sizes = cfg.anchor_sizes or arch.default_anchors
        ratios = (1.0,) if arch.anchor_free else tuple(float(r) for r in cfg.aspect_ratios)
        model.anchor_generator = AnchorGenerator(
            tuple(tuple(int(s) for s in level) for level in sizes), (ratios,) * len(sizes)
        )
    n = model.anchor_generator.num_anchors_per_location()[0]
    channels = model.backbone.out_channels
    if not arch.anchor_free and n != model.head.classification_head.num_anchors:  # one output per anchor shape
        model.head = RetinaNetHead(channels, n, num_classes, norm_layer=norm)
        if coco_head:
            log.info("the RetinaNet head was re-initialised for %d anchors per position", n)
    elif coco_head:  # COCO has 91 classes: new class scores for ours (the conv tower is kept)
        _new_class_scores(model.head.classification_head, n, num_classes)
    if not load_weights and _frozen_bn_structure(arch, cfg.pretrained):
        _freeze_batchnorm(model.backbone.body)
    model.roi_heads = ScoreThreshold(model)
    # label 0 is the background of our label convention (1..N), a real class to a one-stage head
    model.postprocess_detections = types.MethodType(_without_background, model)


def _new_class_scores(head, num_anchors: int, num_classes: int) -> None:
    """Replace a RetinaNet/FCOS classification head's last layer, initialised as torchvision does."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    old = head.cls_logits
    layer = torch.nn.Conv2d(old.in_channels, num_anchors * num_classes, kernel_size=3, stride=1, padding=1)
    torch.nn.init.normal_(layer.weight, std=0.01)
    torch.nn.init.constant_(layer.bias, -np.log((1 - 0.01) / 0.01))  # prior probability 0.01
    head.cls_logits = layer
    head.num_classes = num_classes


def _without_background(model, *args, **kwargs):
    """The one-stage model's own postprocessing, less any box of label 0."""
    out = type(model).postprocess_detections(model, *args, **kwargs)
    for det in out:
        keep = det["labels"] > 0
        for key in det:
            det[key] = det[key][keep]
    return out


class ScoreThreshold:
    """``model.roi_heads.score_thresh`` for one-stage models (a plain attribute, not a module: no
    weights): reads and sets the model's own ``score_thresh``."""

    def __init__(self, model):
        self._model = model

    @property
    def score_thresh(self) -> float:
        """The one-stage model's score threshold: boxes scoring below it are dropped."""
        return self._model.score_thresh

    @score_thresh.setter
    def score_thresh(self, value: float) -> None:
        self._model.score_thresh = float(value)


def set_score_threshold(model, value: float) -> None:
    """Boxes scoring below ``value`` are dropped by the model (every architecture)."""
    model = getattr(model, "module", model)  # DistributedDataParallel
    if hasattr(model, "rpn"):
        model.roi_heads.score_thresh = float(value)
    else:
        model.score_thresh = float(value)


def resolve_auto_anchors(cfg: ModelConfig, dataset: dict | str | Path) -> ModelConfig:
    """``cfg`` with ``anchor_sizes: auto`` replaced by sizes computed from the boxes of ``dataset`` (the
    training COCO, a dict or a path), in the detector's input pixels (:mod:`matchplant.detection.objects`)."""
    if cfg.anchor_sizes != "auto":
        return cfg
    data = dataset if isinstance(dataset, dict) else read_dataset(dataset, validate=False)
    w, h = box_sizes(data, cfg.min_size, cfg.max_size)
    if not len(w):
        raise InputError(
            "model.anchor_sizes: auto needs boxes in the training set, and it has none",
            fix="give training tiles with boxes, or set model.anchor_sizes explicitly",
        )
    sizes = auto_anchor_sizes(w, h, get_architecture(cfg.architecture).anchors)
    log.info(
        "anchor_sizes: auto -> %s (from %d training boxes, median %.0f px in the detector's input)",
        sizes,
        len(w),
        float(np.median(np.sqrt(w * h))),
    )
    return dataclasses.replace(cfg, anchor_sizes=sizes)


def _freeze_batchnorm(module) -> None:
    """Replace every BatchNorm2d below ``module`` with torchvision's FrozenBatchNorm2d (same buffers)."""
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it
    from torchvision.ops.misc import FrozenBatchNorm2d

    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d):
            frozen = FrozenBatchNorm2d(child.num_features, eps=child.eps)
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(frozen, key).copy_(getattr(child, key).detach())
            setattr(module, name, frozen)
        else:
            _freeze_batchnorm(child)


# --------------------------------------------------------------------------------------------------
# parts, freezing, learning rates


def model_parts(model) -> dict[str, Any]:
    """The four parts that can be frozen and given their own learning rate; a one-stage model has no
    ``rpn`` (an empty part) and its ``head`` is ``roi_heads``."""
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it

    if not hasattr(model, "rpn"):
        return {
            "backbone": model.backbone.body,
            "fpn": model.backbone.fpn,
            "rpn": nn.ModuleList(),
            "roi_heads": model.head,
        }
    return {"backbone": model.backbone.body, "fpn": model.backbone.fpn, "rpn": model.rpn, "roi_heads": model.roi_heads}


def backbone_stages(model, arch: str) -> list[list[Any]]:
    """The backbone's stages from the input on (ResNet-50: 5, MobileNetV3: 6), as torchvision counts them."""
    return get_architecture(arch).backbone.stages(model.backbone.body)


def apply_freezing(model, arch: str, trainable_backbone_layers: int, freeze: list[str]) -> None:
    """Make everything trainable, then freeze the backbone's first stages and the named parts."""
    stages = backbone_stages(model, arch)
    if trainable_backbone_layers > len(stages):
        raise ConfigError(
            f"trainable_backbone_layers = {trainable_backbone_layers} but {arch} has only "
            f"{len(stages)} backbone stages",
            fix=f"use 0 to {len(stages)}",
        )
    for p in model.parameters():
        p.requires_grad_(True)
    for stage in stages[: len(stages) - trainable_backbone_layers]:
        for block in stage:
            for p in block.parameters():
                p.requires_grad_(False)
    parts = model_parts(model)
    for name in freeze:
        for p in parts[name].parameters():
            p.requires_grad_(False)


def keep_frozen_norms_fixed(model) -> None:
    """Put batch norms whose weights are frozen in eval mode, so their running statistics stay fixed too
    (call after ``model.train()``)."""
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it

    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm) and not any(p.requires_grad for p in m.parameters()):
            m.eval()


def parameter_groups(model, lrs: dict[str, float]) -> list[dict]:
    """Optimizer groups, one per part with its learning rate; frozen parameters are left out."""
    groups = []
    for name, part in model_parts(model).items():
        params = [p for p in part.parameters() if p.requires_grad]
        if params:
            groups.append({"params": params, "lr": float(lrs[name]), "name": name})
    if not groups:
        raise ConfigError(
            "every part of the model is frozen: nothing to train",
            fix="remove a part from 'freeze' or raise 'trainable_backbone_layers'",
        )
    return groups
