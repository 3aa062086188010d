"""COCO tiles as a torch dataset for the detector, with augmentation that moves the boxes with the image.

Image files are found relative to ``images_dir`` (by default the folder of the COCO JSON; module 5's
``<split>.json`` with ``<split>/images/`` beside it is found as it is). Tiles without
plants stay in the dataset as negatives. Augmentation uses torchvision's ``transforms.v2``, which flips
the boxes together with the pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.coco import annotations_by_image, read_dataset
from matchplant.core.config import param
from matchplant.core.errors import InputError
from matchplant.core.images import read_rgb8


@dataclass
class AugmentConfig:
    """Training augmentation (boxes move with the image); set a value to 0 to switch it off."""

    hflip: float = param(0.5, "probability of a left-right flip", min=0, max=1)
    vflip: float = param(0.5, "probability of an up-down flip (nadir images have no 'up')", min=0, max=1)
    brightness: float = param(0.2, "random brightness change, as a fraction", min=0, max=1)
    contrast: float = param(0.2, "random contrast change, as a fraction", min=0, max=1)
    saturation: float = param(0.2, "random saturation change, as a fraction", min=0, max=1)
    hue: float = param(0.0, "random hue shift (0..0.5 of the colour circle); plant green matters, keep it "
                            "small", min=0, max=0.5)


def find_image(file_name: str, images_dir: Path, split: str | None = None) -> Path | None:
    """The file for a COCO ``file_name`` under ``images_dir``: as given, in ``images/``, in module 5's
    ``<split>/images/`` (``split`` = the JSON's stem), or by its base name."""
    candidates = [images_dir / file_name, images_dir / "images" / file_name]
    if split:
        candidates.append(images_dir / split / "images" / file_name)
    candidates.append(images_dir / Path(file_name).name)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


def build_augmentation(cfg: AugmentConfig | None):
    """A ``transforms.v2`` pipeline for ``(image, target)``, or None for no augmentation."""
    if cfg is None:
        return None
    from torchvision.transforms import v2 as T  # lazy: PyTorch is heavy; configs load without it

    steps = []
    if cfg.hflip > 0:
        steps.append(T.RandomHorizontalFlip(cfg.hflip))
    if cfg.vflip > 0:
        steps.append(T.RandomVerticalFlip(cfg.vflip))
    if max(cfg.brightness, cfg.contrast, cfg.saturation, cfg.hue) > 0:
        steps.append(T.ColorJitter(brightness=cfg.brightness or None, contrast=cfg.contrast or None,
                                   saturation=cfg.saturation or None, hue=cfg.hue or None))
    return T.Compose(steps) if steps else None


class CocoDetection:
    """A COCO dataset of tiles as ``(image float CHW 0..1, target dict)`` pairs for torchvision detectors.

    ``class_names`` fixes the label numbering (labels 1..N in that order) so that a validation set uses
    the training set's labels; by default it is this dataset's categories in id order.
    """

    def __init__(self, json_path: str | Path, images_dir: str | Path | None = None, *,
                 augment: AugmentConfig | None = None, class_names: list[str] | None = None):
        self.json_path = Path(json_path)
        self.data = read_dataset(self.json_path)
        self.images_dir = Path(images_dir) if images_dir else self.json_path.parent
        cats = sorted(self.data["categories"], key=lambda c: c["id"])
        names = [str(c["name"]) for c in cats]
        if class_names is None:
            class_names = names
        unknown = [n for n in names if n not in class_names]
        if unknown:
            raise InputError(f"categories {unknown} are not among the model's classes {class_names}",
                             path=self.json_path, fix="use the same category names in every split")
        self.class_names = list(class_names)
        self.category_ids = [next((c["id"] for c in cats if c["name"] == n), i + 1)
                             for i, n in enumerate(self.class_names)]
        self.label_of = {c["id"]: self.class_names.index(str(c["name"])) + 1 for c in cats}
        self.images = list(self.data["images"])
        if not self.images:
            raise InputError("the dataset lists no images", path=self.json_path, fix="give a COCO JSON with tiles")
        self.anns = annotations_by_image(self.data)
        self.paths = [find_image(im["file_name"], self.images_dir, self.json_path.stem) for im in self.images]
        missing = [im["file_name"] for im, p in zip(self.images, self.paths) if p is None]
        if missing:
            raise InputError(f"{len(missing)} image(s) of the dataset are missing, e.g. {missing[:3]}",
                             path=self.images_dir, fix="set the images folder of this dataset, or regenerate "
                                                       "the tiles with module 5")
        self.transform = build_augmentation(augment)

    def __len__(self) -> int:
        return len(self.images)

    def target(self, index: int) -> dict:
        import torch  # lazy: PyTorch is heavy; configs load without it

        im = self.images[index]
        anns = [a for a in self.anns.get(im["id"], []) if not a.get("iscrowd", 0)]
        if anns:
            b = np.asarray([a["bbox"] for a in anns], dtype=np.float32)
            boxes = np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], axis=1)
        else:  # a negative tile
            boxes = np.zeros((0, 4), dtype=np.float32)
        labels = np.asarray([self.label_of[a["category_id"]] for a in anns], dtype=np.int64)
        return {"boxes": torch.from_numpy(boxes), "labels": torch.from_numpy(labels),
                "image_id": int(im["id"])}

    def __getitem__(self, index: int):
        import torch  # lazy: PyTorch is heavy; configs load without it
        from torchvision import tv_tensors

        img = read_rgb8(self.paths[index])
        image = tv_tensors.Image(torch.from_numpy(img).permute(2, 0, 1))
        target = self.target(index)
        target["boxes"] = tv_tensors.BoundingBoxes(target["boxes"], format="XYXY", canvas_size=img.shape[:2])
        if self.transform is not None:
            image, target = self.transform(image, target)
        target["boxes"] = target["boxes"].as_subclass(torch.Tensor)
        return image.as_subclass(torch.Tensor).float().div_(255.0), target


def collate(batch):
    """Detection batches are lists: images may differ in size."""
    return tuple(zip(*batch))
