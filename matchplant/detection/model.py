"""The Faster R-CNN detector of modules 6 and 7: building it from settings, freezing parts, checkpoints.

Three torchvision architectures: ``fasterrcnn_resnet50_fpn`` (the paper's), ``fasterrcnn_resnet50_fpn_v2``
and ``fasterrcnn_mobilenet_v3_large_fpn`` (fast on a CPU). Every setting of :class:`ModelConfig` is
passed to the model (anchors, RPN and ROI sampling and thresholds, image size, detections per image).

A checkpoint (docs/DESIGN.md §2) is one ``.pt`` file holding everything needed to rebuild the model with no
other file: the model settings, class names, the weights, and for training runs the epoch, optimizer,
scheduler and scaler state, random states, history and metrics. :func:`load_detector` rebuilds it.
"""

from __future__ import annotations

import dataclasses
import urllib.error
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from matchplant.core.config import from_dict, param, section, to_dict
from matchplant.core.errors import ConfigError, DependencyError, InputError
from matchplant.core.io import atomic_path
from matchplant.core.log import get_logger

log = get_logger("detector")

ARCHITECTURES = ("fasterrcnn_resnet50_fpn", "fasterrcnn_resnet50_fpn_v2", "fasterrcnn_mobilenet_v3_large_fpn")
PRETRAINED = ("coco", "imagenet", "none")
PARTS = ("backbone", "fpn", "rpn", "roi_heads")
CHECKPOINT_FORMAT = "matchplant-detector"
CHECKPOINT_VERSION = 1

# the torchvision defaults of each architecture (FPN levels and anchors)
DEFAULT_ANCHORS = {
    "fasterrcnn_resnet50_fpn": [[32], [64], [128], [256], [512]],
    "fasterrcnn_resnet50_fpn_v2": [[32], [64], [128], [256], [512]],
    "fasterrcnn_mobilenet_v3_large_fpn": [[32, 64, 128, 256, 512]] * 3,
}


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
    post_nms_top_n_test: int = param(1000, "proposals kept after NMS (inference); raise it for very dense "
                                           "tiles", min=1)
    nms_thresh: float = param(0.7, "NMS IoU threshold between proposals", min=0, max=1)
    score_thresh: float = param(0.0, "drop proposals with an objectness below this", min=0, max=1)

    def check(self) -> None:
        if self.bg_iou_thresh > self.fg_iou_thresh:
            raise ConfigError(f"model.rpn.bg_iou_thresh ({self.bg_iou_thresh}) is above model.rpn.fg_iou_thresh "
                              f"({self.fg_iou_thresh})", fix="make bg_iou_thresh <= fg_iou_thresh (defaults 0.3, 0.7)")


@dataclass
class ROIConfig:
    """Box head: proposal sampling and IoU thresholds for training, NMS and box count for inference."""

    fg_iou_thresh: float = param(0.5, "proposals with IoU >= this to a plant are positives", min=0, max=1)
    bg_iou_thresh: float = param(0.5, "proposals with IoU < this are background", min=0, max=1)
    batch_size_per_image: int = param(512, "proposals sampled per image for the box loss", min=1)
    positive_fraction: float = param(0.25, "largest share of positives among the sampled proposals", min=0, max=1)
    nms_thresh: float = param(0.5, "NMS IoU threshold between final boxes of one class", min=0, max=1)
    detections_per_img: int = param(300, "most boxes returned per image (torchvision's 100 loses plants on "
                                         "dense tiles)", min=1)

    def check(self) -> None:
        if self.bg_iou_thresh > self.fg_iou_thresh:
            raise ConfigError(f"model.roi.bg_iou_thresh ({self.bg_iou_thresh}) is above model.roi.fg_iou_thresh "
                              f"({self.fg_iou_thresh})", fix="make bg_iou_thresh <= fg_iou_thresh (defaults 0.5, 0.5)")


@dataclass
class ModelConfig:
    """The detector: architecture, starting weights, input size, anchors, RPN and ROI settings."""

    architecture: str = param("fasterrcnn_resnet50_fpn", "torchvision detector (the paper used ResNet-50 FPN; "
                              "MobileNetV3 is much faster on a CPU)", choices=ARCHITECTURES)
    pretrained: str = param("coco", "starting weights: coco (whole detector, downloaded once), imagenet "
                            "(backbone only), none (random)", choices=PRETRAINED)
    checkpoint: Path | None = param(None, "start from this MatchPlant checkpoint instead (transfer learning; "
                                    "matching layers are loaded, a different class count is fine)", path="file")
    min_size: int = param(800, "images are resized so their short side is this many pixels", min=32)
    max_size: int = param(1333, "... and their long side at most this many pixels", min=32)
    anchor_sizes: list[list[int]] | None = param(None, "anchor sizes in pixels, one list per FPN level "
                                                 "(ResNet-50: 5 levels, MobileNetV3: 3); null = the "
                                                 "architecture's default", min=1)
    aspect_ratios: list[float] = param([0.5, 1.0, 2.0], "anchor height/width ratios (the same at every level)",
                                       min=0.01)
    rpn: RPNConfig = section(RPNConfig)
    roi: ROIConfig = section(ROIConfig)

    def check(self) -> None:
        if self.max_size < self.min_size:
            raise ConfigError(f"model.max_size ({self.max_size}) is below model.min_size ({self.min_size})",
                              fix="set max_size >= min_size")
        if self.anchor_sizes is not None:
            levels = len(DEFAULT_ANCHORS[self.architecture])
            if len(self.anchor_sizes) != levels:
                raise ConfigError(f"model.anchor_sizes has {len(self.anchor_sizes)} level(s) but "
                                  f"{self.architecture} has {levels} FPN levels",
                                  fix=f"give {levels} lists, e.g. {DEFAULT_ANCHORS[self.architecture]}")
            if any(s <= 0 for level in self.anchor_sizes for s in level):
                raise ConfigError("model.anchor_sizes must be positive pixel sizes", fix="correct model.anchor_sizes")
            if len({len(s) for s in self.anchor_sizes}) != 1:
                raise ConfigError("model.anchor_sizes: every level needs the same number of sizes (one RPN head "
                                  "serves all levels)", fix="give each level's list the same length")


def model_config_from_dict(data: dict) -> ModelConfig:
    """Rebuild a :class:`ModelConfig` from a checkpoint's plain dict."""
    data = {k: v for k, v in data.items() if k != "checkpoint"}
    return from_dict(ModelConfig, data, prefix="model.", source="checkpoint", base=Path.cwd())


# --------------------------------------------------------------------------------------------------
# building


def _weights(arch: str, pretrained: str):
    """torchvision weight enums (detector, backbone) for a ``pretrained`` choice."""
    # lazy: PyTorch is heavy; configs load without it
    from torchvision.models import MobileNet_V3_Large_Weights, ResNet50_Weights
    from torchvision.models import detection as d

    detector = {"fasterrcnn_resnet50_fpn": d.FasterRCNN_ResNet50_FPN_Weights.COCO_V1,
                "fasterrcnn_resnet50_fpn_v2": d.FasterRCNN_ResNet50_FPN_V2_Weights.COCO_V1,
                "fasterrcnn_mobilenet_v3_large_fpn": d.FasterRCNN_MobileNet_V3_Large_FPN_Weights.COCO_V1}[arch]
    backbone = (MobileNet_V3_Large_Weights.IMAGENET1K_V1 if "mobilenet" in arch else ResNet50_Weights.IMAGENET1K_V1)
    if pretrained == "coco":
        return detector, None
    if pretrained == "imagenet":
        return None, backbone
    return None, None


def _frozen_bn_structure(arch: str, pretrained: str) -> bool:
    # torchvision freezes the backbone's batch norms of pretrained ResNet-50 FPN and MobileNetV3 models
    return pretrained != "none" and arch != "fasterrcnn_resnet50_fpn_v2"


def build_detector(cfg: ModelConfig, num_classes: int, *, load_weights: bool = True):
    """A torchvision Faster R-CNN with ``num_classes`` outputs (background included) built from ``cfg``.

    ``load_weights=False`` builds the same structure without downloading anything (the weights then
    come from a checkpoint).
    """
    import torch.nn as nn  # lazy: PyTorch is heavy; configs load without it
    from torchvision.models import detection as d
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.faster_rcnn import FastRCNNPredictor
    from torchvision.models.detection.rpn import RPNHead

    if num_classes < 2:
        raise InputError("the dataset has no categories", fix="give a COCO dataset with at least one category")
    weights, weights_backbone = _weights(cfg.architecture, cfg.pretrained) if load_weights else (None, None)
    kwargs = dict(
        min_size=cfg.min_size, max_size=cfg.max_size,
        rpn_pre_nms_top_n_train=cfg.rpn.pre_nms_top_n_train, rpn_pre_nms_top_n_test=cfg.rpn.pre_nms_top_n_test,
        rpn_post_nms_top_n_train=cfg.rpn.post_nms_top_n_train, rpn_post_nms_top_n_test=cfg.rpn.post_nms_top_n_test,
        rpn_nms_thresh=cfg.rpn.nms_thresh, rpn_fg_iou_thresh=cfg.rpn.fg_iou_thresh,
        rpn_bg_iou_thresh=cfg.rpn.bg_iou_thresh, rpn_batch_size_per_image=cfg.rpn.batch_size_per_image,
        rpn_positive_fraction=cfg.rpn.positive_fraction, rpn_score_thresh=cfg.rpn.score_thresh,
        box_nms_thresh=cfg.roi.nms_thresh,
        box_detections_per_img=cfg.roi.detections_per_img, box_fg_iou_thresh=cfg.roi.fg_iou_thresh,
        box_bg_iou_thresh=cfg.roi.bg_iou_thresh, box_batch_size_per_image=cfg.roi.batch_size_per_image,
        box_positive_fraction=cfg.roi.positive_fraction)
    builder = getattr(d, cfg.architecture)
    # all stages trainable here; train.apply_freezing decides (the same on every rebuild)
    trainable = 6 if "mobilenet" in cfg.architecture else 5
    try:
        model = builder(weights=weights, weights_backbone=weights_backbone,
                        num_classes=91 if weights is not None else num_classes,
                        trainable_backbone_layers=trainable if (weights or weights_backbone) else None, **kwargs)
    except (urllib.error.URLError, OSError, ConnectionError) as exc:
        from torch.hub import get_dir  # lazy: PyTorch is heavy; configs load without it
        name = (weights or weights_backbone).url.rsplit("/", 1)[-1]
        raise DependencyError(f"could not download the {cfg.pretrained.upper()} weights of {cfg.architecture} "
                              f"({type(exc).__name__}: {exc})", path=Path(get_dir()) / "checkpoints" / name,
                              fix="connect to the internet once (the file is then cached), or copy the file to "
                                  "that path, or set model.pretrained: none, or start from model.checkpoint") from exc
    if weights is not None:  # COCO has 91 classes: a new box predictor for ours
        in_features = model.roi_heads.box_predictor.cls_score.in_features
        model.roi_heads.box_predictor = FastRCNNPredictor(in_features, num_classes)
    elif not load_weights and _frozen_bn_structure(cfg.architecture, cfg.pretrained):
        _freeze_batchnorm(model.backbone.body)
    if cfg.anchor_sizes is not None or list(cfg.aspect_ratios) != [0.5, 1.0, 2.0]:
        sizes = cfg.anchor_sizes or DEFAULT_ANCHORS[cfg.architecture]
        ratios = tuple(float(r) for r in cfg.aspect_ratios)
        gen = AnchorGenerator(tuple(tuple(int(s) for s in level) for level in sizes), (ratios,) * len(sizes))
        model.rpn.anchor_generator = gen
        n = gen.num_anchors_per_location()[0]
        if n != model.rpn.head.cls_logits.out_channels:  # a head with one output per anchor shape
            depth = len(model.rpn.head.conv)
            model.rpn.head = RPNHead(model.backbone.out_channels, n, conv_depth=depth)
            if weights is not None:
                log.info("the RPN head was re-initialised for %d anchors per position", n)
    assert isinstance(model, nn.Module)
    return model


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
    """The four parts that can be frozen and given their own learning rate."""
    return {"backbone": model.backbone.body, "fpn": model.backbone.fpn, "rpn": model.rpn,
            "roi_heads": model.roi_heads}


def backbone_stages(model, arch: str) -> list[list[Any]]:
    """The backbone's stages from the input on (ResNet-50: 5, MobileNetV3: 6), as torchvision counts them."""
    body = model.backbone.body
    if "mobilenet" in arch:
        blocks = list(body.children())
        starts = [0] + [i for i, b in enumerate(blocks) if getattr(b, "_is_cn", False)] + [len(blocks) - 1]
        starts = sorted(set(starts))
        return [blocks[a:b] for a, b in zip(starts, starts[1:] + [len(blocks)])]
    return [[body.conv1, body.bn1], [body.layer1], [body.layer2], [body.layer3], [body.layer4]]


def apply_freezing(model, arch: str, trainable_backbone_layers: int, freeze: list[str]) -> None:
    """Make everything trainable, then freeze the backbone's first stages and the named parts."""
    stages = backbone_stages(model, arch)
    if trainable_backbone_layers > len(stages):
        raise ConfigError(f"trainable_backbone_layers = {trainable_backbone_layers} but {arch} has only "
                          f"{len(stages)} backbone stages", fix=f"use 0 to {len(stages)}")
    for p in model.parameters():
        p.requires_grad_(True)
    for stage in stages[:len(stages) - trainable_backbone_layers]:
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
        raise ConfigError("every part of the model is frozen: nothing to train",
                          fix="remove a part from 'freeze' or raise 'trainable_backbone_layers'")
    return groups


# --------------------------------------------------------------------------------------------------
# checkpoints


def save_checkpoint(path: str | Path, model, model_cfg: ModelConfig, class_names: list[str],
                    category_ids: list[int], **extra) -> Path:
    """Write a self-contained checkpoint atomically (``extra``: epoch, optimizer state, metrics, ...)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    model = getattr(model, "module", model)  # DistributedDataParallel
    data = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
            "model_config": to_dict(dataclasses.replace(model_cfg, checkpoint=None)),
            "class_names": list(class_names), "category_ids": [int(c) for c in category_ids],
            "model_state": model.state_dict(), **extra}
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return Path(path)


def read_checkpoint(path: str | Path) -> dict:
    """Load a checkpoint's contents (on the CPU), with a clear error for other files."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint not found", path=path, fix="point 'checkpoint' at a .pt file written by module 6")
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling problem means the same to the user
        raise InputError(f"cannot read this checkpoint ({type(exc).__name__}: {exc})", path=path,
                         fix="give a .pt file written by module 6 (it may be truncated or from another tool)") from exc
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise InputError("not a MatchPlant detector checkpoint", path=path,
                         fix="give a checkpoint written by module 6 (best.pt, last.pt or epoch_NNN.pt)")
    if data.get("version", 0) > CHECKPOINT_VERSION:
        raise InputError(f"checkpoint version {data['version']} is newer than this MatchPlant reads",
                         path=path, fix="update MatchPlant")
    return data


def load_detector(path_or_data: str | Path | dict, device: Any = "cpu", *, overrides: dict | None = None):
    """Rebuild a detector from a checkpoint; returns ``(model, checkpoint_dict)``.

    ``overrides`` replaces settings, e.g. ``{"roi": {"detections_per_img": 500}}``; the score threshold
    is ``model.roi_heads.score_thresh`` (set it before predicting).
    """
    data = path_or_data if isinstance(path_or_data, dict) else read_checkpoint(path_or_data)
    mcfg = dict(data["model_config"])
    for key, value in (overrides or {}).items():
        mcfg[key] = {**mcfg[key], **value} if isinstance(value, dict) else value
    cfg = model_config_from_dict(mcfg)
    model = build_detector(cfg, len(data["class_names"]) + 1, load_weights=False)
    model.load_state_dict(data["model_state"])
    model.to(device).eval()
    return model, data


def load_matching_weights(model, state: dict) -> tuple[list[str], list[str]]:
    """Copy the tensors of ``state`` whose name and shape match ``model`` (transfer learning).

    Returns (loaded, skipped) names; a different class count skips only the box predictor.
    """
    own = model.state_dict()
    loaded = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    skipped = sorted(k for k in own if k not in loaded and not k.endswith("num_batches_tracked"))
    model.load_state_dict(loaded, strict=False)
    return sorted(loaded), skipped
