"""The detector architectures of modules 6 and 7: one record each, looked up by name in one place.

Everything MatchPlant knows about an architecture is in its :class:`Architecture` record in
:data:`ARCHITECTURES` (as torchvision and DeepForest pick a model by name from one entry per model):
the torchvision builder and COCO weights, the backbone (ImageNet weights, stages), one or two stages,
anchor-free or not, the anchor rule for ``anchor_sizes: auto``, torchvision's default anchors, whether
the backbone's batch norms are frozen, and the measured CPU cost. **Adding a detector means adding one
record here**; the code that builds, freezes, checks and times a model reads its fields, never its name.
:func:`get_architecture` is the one lookup by name.

torchvision is imported only where a model is built (:mod:`matchplant.detection.model`): the records
name its builders and weights as strings, so configs load without PyTorch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.validate import did_you_mean
from matchplant.detection.lite import DEFAULT_ANCHORS as LITE_ANCHORS


@dataclass(frozen=True)
class AnchorRule:
    """How ``anchor_sizes: auto`` lays anchors on the FPN levels from the small objects' size.

    Level ``i`` starts at ``small * 2**i``, with ``per_level`` sizes spread by 2^(k/per_level)
    (RetinaNet's octaves); ``same_sizes_everywhere`` (MobileNetV3 FPN, whose levels all get every size)
    gives ``levels`` lists of the sizes ``small * 2**k`` for k < per_level.
    """

    levels: int  # FPN levels the model has (and anchor_sizes must list)
    per_level: int  # anchor sizes per level
    same_sizes_everywhere: bool = False

    def sizes(self, small: float) -> list[list[int]]:
        """Anchor sizes (input pixels) for objects whose small ones are ``small`` pixels."""
        base = max(8.0, small)
        if self.same_sizes_everywhere:
            sizes = [int(round(base * 2**k)) for k in range(self.per_level)]
            return [sizes for _ in range(self.levels)]
        return [
            [int(round(base * 2**i * 2 ** (k / self.per_level))) for k in range(self.per_level)]
            for i in range(self.levels)
        ]


def _resnet_stages(body) -> list[list[Any]]:
    # a backbone cut before layer4 (the lite detector) has fewer stages
    return [[body.conv1, body.bn1]] + [[getattr(body, f"layer{i}")] for i in range(1, 5) if hasattr(body, f"layer{i}")]


def _mobilenet_stages(body) -> list[list[Any]]:
    # torchvision marks the blocks that start a stage with ``_is_cn``
    blocks = list(body.children())
    starts = [0] + [i for i, b in enumerate(blocks) if getattr(b, "_is_cn", False)] + [len(blocks) - 1]
    starts = sorted(set(starts))
    return [blocks[a:b] for a, b in zip(starts, starts[1:] + [len(blocks)])]


@dataclass(frozen=True)
class Backbone:
    """A feature extractor: its ImageNet weights (``pretrained: imagenet``) and its stages."""

    name: str
    imagenet_weights: str  # torchvision.models weights, e.g. "ResNet50_Weights.IMAGENET1K_V1"
    stage_count: int  # stages as torchvision's trainable_backbone_layers counts them
    stages: Callable[[Any], list[list[Any]]]  # model.backbone.body -> its stages from the input on


RESNET50 = Backbone("resnet50", "ResNet50_Weights.IMAGENET1K_V1", 5, _resnet_stages)
RESNET18_TO_LAYER3 = Backbone("resnet18", "ResNet18_Weights.IMAGENET1K_V1", 4, _resnet_stages)
MOBILENET_V3_LARGE = Backbone("mobilenet_v3_large", "MobileNet_V3_Large_Weights.IMAGENET1K_V1", 6, _mobilenet_stages)


@dataclass(frozen=True)
class Architecture:
    """One torchvision detector and everything MatchPlant needs to build, train and time it."""

    name: str  # model.architecture
    builder: str  # the torchvision.models.detection function that builds it (or lite.py's)
    coco_weights: str | None  # its torchvision COCO weights (``pretrained: coco``); None: there are none
    backbone: Backbone
    two_stage: bool  # Faster R-CNN (rpn + roi_heads) or one-stage (head)
    anchors: AnchorRule  # anchor_sizes: auto
    default_anchors: tuple[tuple[int, ...], ...]  # torchvision's, one tuple per FPN level
    anchor_free: bool = False  # FCOS: one size per level, which sets the object sizes it learns
    frozen_backbone_norms: bool = True  # torchvision freezes a pretrained backbone's batch norms (not v2)
    head_norm_groups: int | None = None  # GroupNorm groups of a rebuilt RetinaNet head (v2)
    cpu_seconds_per_megapixel: float | None = None  # measured (see ARCHITECTURES); None: not measured

    def __post_init__(self) -> None:
        assert len(self.default_anchors) == self.anchors.levels, self.name


def _octaves(x: int) -> tuple[int, int, int]:
    return x, int(x * 2 ** (1 / 3)), int(x * 2 ** (2 / 3))


_RESNET_LEVELS = ((32,), (64,), (128,), (256,), (512,))
_RETINANET_ANCHORS = tuple(_octaves(x) for x in (32, 64, 128, 256, 512))
_ONE_PER_LEVEL, _OCTAVES = AnchorRule(5, 1), AnchorRule(5, 3)

# cpu_seconds_per_megapixel: one forward pass (detection) of a 1024 px tile on one core with one thread, median of 5
# rounds with the architectures alternating, the other core idle (`taskset -c 1 python bench/bench_detect_cpu_rates.py`,
# docs/performance.md; ranges in the comments). The figures before (15.2, 28.2, 9.2, 2.5) were measured while other
# jobs shared the machine, with PyTorch's two threads on one pinned core. RetinaNet and FCOS: not measured.
ARCHITECTURES: dict[str, Architecture] = {
    a.name: a
    for a in (
        Architecture(
            "fasterrcnn_resnet50_fpn",
            "fasterrcnn_resnet50_fpn",
            "FasterRCNN_ResNet50_FPN_Weights.COCO_V1",
            RESNET50,
            two_stage=True,
            anchors=_ONE_PER_LEVEL,
            default_anchors=_RESNET_LEVELS,
            cpu_seconds_per_megapixel=3.69,  # 3.45-3.77
        ),
        Architecture(
            "fasterrcnn_resnet50_fpn_v2",
            "fasterrcnn_resnet50_fpn_v2",
            "FasterRCNN_ResNet50_FPN_V2_Weights.COCO_V1",
            RESNET50,
            two_stage=True,
            anchors=_ONE_PER_LEVEL,
            default_anchors=_RESNET_LEVELS,
            frozen_backbone_norms=False,
            cpu_seconds_per_megapixel=6.51,  # 6.36-6.56
        ),
        Architecture(
            "fasterrcnn_mobilenet_v3_large_fpn",
            "fasterrcnn_mobilenet_v3_large_fpn",
            "FasterRCNN_MobileNet_V3_Large_FPN_Weights.COCO_V1",
            MOBILENET_V3_LARGE,
            two_stage=True,
            anchors=AnchorRule(3, 3, same_sizes_everywhere=True),
            default_anchors=((32, 64, 128, 256, 512),) * 3,
            cpu_seconds_per_megapixel=0.72,  # 0.70-0.75
        ),
        # from random weights on a CPU (matchplant.detection.lite): ResNet-18 to stride 16, a 64-channel FPN
        Architecture(
            "fasterrcnn_resnet18_fpn_lite",
            "fasterrcnn_resnet18_fpn_lite",
            None,
            RESNET18_TO_LAYER3,
            two_stage=True,
            anchors=AnchorRule(3, 3),
            default_anchors=LITE_ANCHORS,
            cpu_seconds_per_megapixel=0.60,  # 0.58-0.61
        ),
        Architecture(
            "retinanet_resnet50_fpn",
            "retinanet_resnet50_fpn",
            "RetinaNet_ResNet50_FPN_Weights.COCO_V1",
            RESNET50,
            two_stage=False,
            anchors=_OCTAVES,
            default_anchors=_RETINANET_ANCHORS,
        ),
        Architecture(
            "retinanet_resnet50_fpn_v2",
            "retinanet_resnet50_fpn_v2",
            "RetinaNet_ResNet50_FPN_V2_Weights.COCO_V1",
            RESNET50,
            two_stage=False,
            anchors=_OCTAVES,
            default_anchors=_RETINANET_ANCHORS,
            frozen_backbone_norms=False,
            head_norm_groups=32,
        ),
        Architecture(
            "fcos_resnet50_fpn",
            "fcos_resnet50_fpn",
            "FCOS_ResNet50_FPN_Weights.COCO_V1",
            RESNET50,
            two_stage=False,
            anchors=_ONE_PER_LEVEL,
            default_anchors=((8,), (16,), (32,), (64,), (128,)),
            anchor_free=True,
        ),
    )
}


def get_architecture(name: str) -> Architecture:
    """The record of the architecture called ``name`` (a ConfigError naming the closest one otherwise)."""
    try:
        return ARCHITECTURES[name]
    except KeyError:
        hint = did_you_mean(name, ARCHITECTURES)
        raise ConfigError(
            f"unknown detector architecture {name!r}{f' ({hint})' if hint else ''}",
            fix=f"use one of {', '.join(ARCHITECTURES)}",
        ) from None


__all__ = ["AnchorRule", "Architecture", "Backbone", "ARCHITECTURES", "get_architecture"]
