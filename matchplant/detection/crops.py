"""Training on random crops at the detector's scale: a training step's cost set by the crop, not by the photo.

A detector resizes each tile so its short side is ``min_size`` (long side at most ``max_size``), and a training
step costs in proportion to those pixels. On a CPU a 1024 px photo costs about five times a 448 px one per step,
so a budget of minutes allows only a few dozen steps: too few to learn anything from random weights. Cut from the
photo after the same resize, a ``crop`` x ``crop`` window keeps every plant at the size the detector sees at
inference (the network is convolutional: it learns the same per pixel), and a step costs what the crop costs,
whatever the photo size. Each epoch sees another window of each photo.

:func:`crop_steps` gives the ``transforms.v2`` steps (scale as the detector would, a random window padded with
black where the photo is smaller, boxes clipped to it, boxes left under 2 px dropped); the model must then skip
its own resize while training (:func:`skip_training_resize`); inference resizes whole tiles as before. With
``augment.crop_on_plant`` the window holds a random plant's centre that share of the time (meant for sparse plants,
where a window placed anywhere often holds none; placed anywhere did as well or better on the real crowns and on
sparse synthetic plants, so it is off by default).
"""

from __future__ import annotations

from typing import Any

MIN_BOX_PX = 2.0  # a box cut to a thinner sliver than this by the window's edge is dropped


def detector_scale(height: int, width: int, min_size: int, max_size: int) -> float:
    """The factor torchvision's ``GeneralizedRCNNTransform`` resizes a ``height`` x ``width`` image by."""
    return min(min_size / min(height, width), max_size / max(height, width))


def crop_steps(crop: int, min_size: int, max_size: int, on_plant: float = 0.0) -> list[Any]:
    """``transforms.v2`` steps: resize as the detector does, then a random ``crop`` x ``crop`` window, which holds
    the centre of a random plant of the tile with probability ``on_plant`` (else lies anywhere)."""
    import torch  # lazy: PyTorch is heavy; configs load without it
    from torch import nn
    from torchvision.transforms import v2 as T

    def uniform(lo: int, hi: int) -> int:
        return int(torch.randint(lo, hi + 1, ()).item()) if hi > lo else lo

    class DetectorScale(nn.Module):
        """Resize image and boxes as the detector would (the model's own resize is then skipped)."""

        def forward(self, image, target):
            h, w = image.shape[-2:]
            s = detector_scale(h, w, min_size, max_size)
            size = [max(round(h * s), 1), max(round(w * s), 1)]
            return T.functional.resize(image, size, antialias=True), {
                **target,
                "boxes": T.functional.resize(target["boxes"], size),
            }

    class Window(nn.Module):
        """The window, padded with black below and right where the tile is smaller; with probability ``on_plant``
        it holds a random plant's centre (on sparse plants a window anywhere would mostly hold none)."""

        def forward(self, image, target):
            h, w = image.shape[-2:]
            if h < crop or w < crop:
                pad = [0, 0, max(crop - w, 0), max(crop - h, 0)]
                image, target = (
                    T.functional.pad(image, pad),
                    {**target, "boxes": T.functional.pad(target["boxes"], pad)},
                )
                h, w = image.shape[-2:]
            boxes = target["boxes"]
            if len(boxes) and float(torch.rand(())) < on_plant:
                b = boxes[int(torch.randint(len(boxes), ()).item())]
                cx, cy = int((b[0] + b[2]) / 2), int((b[1] + b[3]) / 2)
                x0, y0 = (
                    uniform(max(cx - crop + 1, 0), min(cx, w - crop)),
                    uniform(max(cy - crop + 1, 0), min(cy, h - crop)),
                )
            else:
                x0, y0 = uniform(0, w - crop), uniform(0, h - crop)
            return T.functional.crop(image, y0, x0, crop, crop), {
                **target,
                "boxes": T.functional.crop(boxes, y0, x0, crop, crop),
            }

    return [DetectorScale(), Window(), T.SanitizeBoundingBoxes(min_size=MIN_BOX_PX)]


def skip_training_resize(model, skip: bool = True) -> None:
    """Make the model take training images as they come (already at its scale: :func:`crop_steps`)."""
    model = getattr(model, "module", model)  # DistributedDataParallel
    if not hasattr(model.transform, "_skip_resize"):  # torchvision >= 0.13 has it
        raise RuntimeError(
            "this torchvision's detection transform cannot skip its resize (augment.crop needs torchvision >= 0.13)"
        )
    model.transform._skip_resize = skip
