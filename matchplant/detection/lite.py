"""A light Faster R-CNN for training from random weights on a CPU, built from torchvision's own parts.

torchvision's detectors are sized for COCO on a GPU: a 256-channel feature pyramid and a box head whose first
layer maps 256 x 7 x 7 pooled values to 1024. From random weights nothing ties a model to those widths, and on a
CPU they are most of a training step once the backbone is small. ``fasterrcnn_resnet18_fpn_lite`` is:

- a ResNet-18 (torchvision's, trainable batch norms) cut after ``layer3``: features at strides 8 and 16, the
  ones small plants (15-80 px) need, plus torchvision's max-pool level at stride 32 for the large ones;
- a feature pyramid of ``FPN_CHANNELS`` channels and a two-layer box head of ``HEAD_WIDTH`` (torchvision's
  ``TwoMLPHead``), pooling from the stride-8 and stride-16 levels.

The builder takes the arguments of torchvision's builders (``weights``, ``weights_backbone``, ``num_classes``,
``trainable_backbone_layers`` and the Faster R-CNN keywords), so :func:`matchplant.detection.model.build_detector`
builds it like the others. There are no COCO weights for it; ImageNet weights of the ResNet-18 can start it.
"""

from __future__ import annotations

from matchplant.core.runtime.errors import ConfigError

FPN_CHANNELS = 64
HEAD_WIDTH = 256
RETURNED_LAYERS = (2, 3)  # ResNet stages kept: strides 8 and 16
LAYER_CHANNELS = {1: 64, 2: 128, 3: 256, 4: 512}  # ResNet-18's output channels per stage
DEFAULT_ANCHORS = ((32, 40, 50), (64, 80, 101), (128, 161, 203))  # octaves at strides 8, 16, 32


def fasterrcnn_resnet18_fpn_lite(
    *,
    weights=None,
    weights_backbone=None,
    num_classes: int | None = None,
    trainable_backbone_layers: int | None = None,
    **kwargs,
):
    """The light detector (see the module's text); ``weights`` (COCO) do not exist for it."""
    from torch import nn  # lazy: PyTorch is heavy; configs load without it
    from torchvision.models import resnet18
    from torchvision.models.detection import FasterRCNN
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
    from torchvision.models.detection.rpn import RPNHead
    from torchvision.ops import MultiScaleRoIAlign
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool
    from torchvision.ops.misc import FrozenBatchNorm2d

    if weights is not None:
        raise ConfigError(
            "fasterrcnn_resnet18_fpn_lite has no COCO weights",
            fix="set model.pretrained: imagenet (its ResNet-18) or none",
        )
    # as torchvision does: pretrained batch norms are frozen, random ones trained (module 6 freezes stages)
    body = resnet18(weights=weights_backbone, norm_layer=FrozenBatchNorm2d if weights_backbone else nn.BatchNorm2d)
    backbone = BackboneWithFPN(
        body,
        {f"layer{k}": str(i) for i, k in enumerate(RETURNED_LAYERS)},
        [LAYER_CHANNELS[k] for k in RETURNED_LAYERS],
        FPN_CHANNELS,
        extra_blocks=LastLevelMaxPool(),
    )
    levels = len(RETURNED_LAYERS) + 1
    anchors = AnchorGenerator(DEFAULT_ANCHORS, ((0.5, 1.0, 2.0),) * levels)
    return FasterRCNN(
        backbone,
        num_classes=None,
        rpn_anchor_generator=anchors,
        rpn_head=RPNHead(FPN_CHANNELS, anchors.num_anchors_per_location()[0]),
        box_roi_pool=MultiScaleRoIAlign([str(i) for i in range(len(RETURNED_LAYERS))], 7, 2),
        box_head=TwoMLPHead(FPN_CHANNELS * 7 * 7, HEAD_WIDTH),
        box_predictor=FastRCNNPredictor(HEAD_WIDTH, num_classes),
        **kwargs,
    )
