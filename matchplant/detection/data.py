"""COCO tiles as a torch dataset for the detector, with augmentation that moves the boxes with the image.

Image files are found relative to ``images_dir`` (by default the folder of the COCO JSON; module 5's
``<split>.json`` with ``<split>/images/`` beside it is found as it is). Tiles without
plants stay in the dataset as negatives. Augmentation uses torchvision's ``transforms.v2``, which flips
the boxes together with the pixels.

Before anything is trained or scored, :class:`CocoDetection` checks the dataset against the files on
disk (:func:`~matchplant.detection.dataset_checks.check_dataset`: categories, boxes, every image file present
and whole, the JSON's sizes against the files). :func:`check_disjoint` refuses a validation split that is, or
shares tile files with, the training split.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.formats.coco import annotations_by_image, read_dataset
from matchplant.core.formats.images import read_rgb8
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.validate import did_you_mean
from matchplant.detection.crops import crop_steps
from matchplant.detection.dataset_checks import check_dataset


@dataclass
class AugmentConfig:
    """Training augmentation (boxes move with the image); set a value to 0 to switch it off."""

    hflip: float = param(0.5, "probability of a left-right flip", min=0, max=1)
    vflip: float = param(0.5, "probability of an up-down flip (nadir images have no 'up')", min=0, max=1)
    brightness: float = param(0.2, "random brightness change, as a fraction", min=0, max=1)
    contrast: float = param(0.2, "random contrast change, as a fraction", min=0, max=1)
    saturation: float = param(0.2, "random saturation change, as a fraction", min=0, max=1)
    hue: float = param(
        0.0, "random hue shift (0..0.5 of the colour circle); plant green matters, keep it small", min=0, max=0.5
    )
    crop: int | None = param(
        None,
        "train on random crop x crop windows of each tile at the detector's scale "
        "(detector input pixels): a step then costs the crop, not the tile; 0 = whole tiles; "
        "null = auto (module 6: 256 with model.architecture auto from random weights on a CPU, see "
        "its README)",
        min=0,
    )
    crop_on_plant: float = param(
        0.0,
        "probability that a training crop holds a random plant of the tile (else it "
        "lies anywhere; anywhere did as well or better on dense and on sparse plants, see "
        "module 6's README)",
        min=0,
        max=1,
    )


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
        steps.append(
            T.ColorJitter(
                brightness=cfg.brightness or None,
                contrast=cfg.contrast or None,
                saturation=cfg.saturation or None,
                hue=cfg.hue or None,
            )
        )
    return T.Compose(steps) if steps else None


def _same_bytes(a: Path, b: Path) -> bool:
    return hashlib.sha1(a.read_bytes()).digest() == hashlib.sha1(b.read_bytes()).digest()


def check_disjoint(train: CocoDetection, val: CocoDetection) -> None:
    """Refuse a validation split that is the training split's file, or shares tiles with it (the same files,
    or copies of them: same name, same bytes): its scores would measure memory, not detection. Tiles of
    photos that share a name (DJI_0001.JPG of two flights) are told apart by their bytes."""
    try:
        same = os.path.samefile(train.json_path, val.json_path)
    except OSError:
        same = False
    if same:
        raise ConfigError(
            "val_json is the same file as train_json: validation would score the model on the tiles it learns from",
            path=val.json_path,
            fix="set val_json to the validation split (module 5 writes val.json beside train.json), "
            "or leave it empty (null) for no validation",
        )
    by_key: dict[tuple[str, int], list[Path]] = {}
    for p in train.paths:
        by_key.setdefault((p.name, p.stat().st_size), []).append(p)
    train_real = {os.path.realpath(p) for p in train.paths}
    shared = [
        im["file_name"]
        for im, p in zip(val.images, val.paths)
        if os.path.realpath(p) in train_real
        or any(_same_bytes(p, q) for q in by_key.get((p.name, p.stat().st_size), []))
    ]
    if shared:
        raise InputError(
            f"{len(shared)} of the {len(val)} validation tiles are also training tiles (e.g. "
            f"{', '.join(shared[:3])}): validation would score the model on tiles it learns from",
            path=val.json_path,
            fix="split the tiles again with module 5 (it keeps each photo's tiles "
            "in one split), or give a val_json with other images",
        )


class TileReadError(InputError):
    """A tile that cannot be read while batches load. A DataLoader worker's error comes back as
    ``type(exc)(message=worker's text)`` for classes with a ``message`` attribute; this one rebuilds itself
    from that text, so the user sees the message, not the worker's traceback."""

    message = "a tile could not be read"

    def __init__(
        self, problem: str = "", *, path: str | Path | None = None, fix: str | None = None, message: str | None = None
    ):
        if message is not None:
            lines = message.rsplit(f"{type(self).__name__}: ", 1)[-1].strip("\n").split("\n")
            problem = lines[0] + " (in a data-loading worker)"
            for line in lines[1:]:
                if line.startswith("  file: "):
                    path = line[len("  file: ") :]
                elif line.startswith("  fix:  "):
                    fix = line[len("  fix:  ") :]
        super().__init__(problem, path=path, fix=fix)


class CocoDetection:
    """A COCO dataset of tiles as ``(image float CHW 0..1, target dict)`` pairs for torchvision detectors.

    ``class_names`` fixes the label numbering (labels 1..N in that order) so that a validation set uses
    the training set's labels; by default it is this dataset's categories in id order (``classes_from``
    says where given names come from, for the messages). The dataset is checked against its files first
    (:func:`check_dataset`; ``require_boxes``: at least one box).
    """

    def __init__(
        self,
        json_path: str | Path,
        images_dir: str | Path | None = None,
        *,
        augment: AugmentConfig | None = None,
        class_names: list[str] | None = None,
        classes_from: str | None = None,
        require_boxes: bool = True,
    ):
        self.json_path = Path(json_path)
        self.data = read_dataset(self.json_path, validate=False)
        self.images_dir = Path(images_dir) if images_dir else self.json_path.parent
        self.paths = check_dataset(self.data, self.json_path, self.images_dir, require_boxes=require_boxes)
        cats = sorted(self.data["categories"], key=lambda c: c["id"])
        names = [str(c["name"]) for c in cats]
        if class_names is None:
            class_names = names
        unknown = [n for n in names if n not in class_names]
        if unknown:
            hint = did_you_mean(unknown[0], class_names)
            raise InputError(
                f"categories {unknown} of this dataset are not among the model's classes {class_names}"
                f"{f' (from {classes_from})' if classes_from else ''}{'; ' + hint if hint else ''}",
                path=self.json_path,
                fix="use the model's category names in this JSON (or a dataset of "
                "the same classes), or a model trained on these categories",
            )
        self.class_names = list(class_names)
        self.category_ids = [
            next((c["id"] for c in cats if str(c["name"]) == n), i + 1) for i, n in enumerate(self.class_names)
        ]
        self.label_of = {c["id"]: self.class_names.index(str(c["name"])) + 1 for c in cats}
        self.images = list(self.data["images"])
        self.anns = annotations_by_image(self.data)
        self.transform = build_augmentation(augment)
        self.crop: int | None = None  # set by crop_windows
        self.seed: int | None = None  # set per epoch by training: augmentation then depends on (seed, index) only

    def set_seed(self, seed: int | None) -> None:
        """Make each tile's augmentation a function of ``(seed, index)``, drawn from its own random stream (not
        the process's): a run resumed mid-epoch augments the remaining tiles exactly as the first run would."""
        self.seed = seed

    def crop_windows(self, crop: int, min_size: int, max_size: int, on_plant: float = 0.0) -> None:
        """Serve random ``crop`` x ``crop`` windows of the tiles resized as the detector does
        (:mod:`matchplant.detection.crops`; the model must skip its own training resize)."""
        from torchvision.transforms import v2 as T  # lazy: PyTorch is heavy; configs load without it

        steps = ([self.transform] if self.transform is not None else []) + crop_steps(
            crop, min_size, max_size, on_plant
        )
        self.transform, self.crop = T.Compose(steps), crop

    def __len__(self) -> int:
        return len(self.images)

    def plain_image(self, index: int):
        """Tile ``index`` as the detector's float tensor, without augmentation or crop."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        return torch.from_numpy(read_rgb8(self.paths[index])).permute(2, 0, 1).float().div_(255.0)

    def target(self, index: int) -> dict:
        """Tile ``index``'s plants as torchvision wants them: ``boxes`` (x1, y1, x2, y2), ``labels``, ``image_id``."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        im = self.images[index]
        anns = [a for a in self.anns.get(im["id"], []) if not a.get("iscrowd", 0)]
        if anns:
            b = np.asarray([a["bbox"] for a in anns], dtype=np.float32)
            boxes = np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], axis=1)
        else:  # a negative tile
            boxes = np.zeros((0, 4), dtype=np.float32)
        labels = np.asarray([self.label_of[a["category_id"]] for a in anns], dtype=np.int64)
        return {"boxes": torch.from_numpy(boxes), "labels": torch.from_numpy(labels), "image_id": int(im["id"])}

    def __getitem__(self, index: int | tuple[int, int]):
        """Tile ``index``; ``(index, seed)``: augmented with that seed (:class:`EpochSampler`'s ``item_seed``)."""
        import torch  # lazy: PyTorch is heavy; configs load without it
        from torchvision import tv_tensors

        index, seed = index if isinstance(index, tuple) else (index, self.seed)
        try:
            img = read_rgb8(self.paths[index])
        except InputError as exc:  # passed up from a loader worker whole (see TileReadError)
            raise TileReadError(exc.problem, path=exc.path, fix=exc.fix) from exc
        image = tv_tensors.Image(torch.from_numpy(img).permute(2, 0, 1))
        target = self.target(index)
        target["boxes"] = tv_tensors.BoundingBoxes(target["boxes"], format="XYXY", canvas_size=img.shape[:2])
        if self.transform is not None and seed is not None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed((seed * 1_000_003 + index) % 2**63)
                image, target = self.transform(image, target)
        elif self.transform is not None:
            image, target = self.transform(image, target)
        target["boxes"] = target["boxes"].as_subclass(torch.Tensor)
        return image.as_subclass(torch.Tensor).float().div_(255.0), target


def collate(batch):
    """Detection batches are lists: images may differ in size."""
    return tuple(zip(*batch))


class EpochSampler:
    """The training order: a shuffle that depends only on ``(seed, epoch)``, split between ``world`` processes
    (padded to a multiple of it, as DistributedSampler does), and resumable: ``set_epoch(epoch, start)`` skips
    the first ``start`` indices of this process's share, so a run resumed mid-epoch sees exactly the samples
    the interrupted one had left, in the same order (``len(loader)`` then counts the remaining batches).
    With ``item_seed`` it yields ``(index, item_seed)``: the epoch's augmentation seed reaches loader workers kept
    across epochs (``persistent_workers``), which a seed set on the dataset in the main process would not."""

    def __init__(self, n: int, seed: int, rank: int = 0, world: int = 1):
        self.n, self.seed, self.rank, self.world = n, seed, rank, world
        self.epoch, self.start = 0, 0
        self.item_seed: int | None = None

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Start ``epoch`` at the ``start``-th index of this process's share (a resumed epoch skips what it did)."""
        self.epoch, self.start = epoch, start

    def order(self) -> list[int]:
        """This process's share of the epoch's shuffle, whole (from index 0)."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        g = torch.Generator()
        g.manual_seed(self.seed * 100003 + self.epoch)
        perm = torch.randperm(self.n, generator=g).tolist()
        total = -(-self.n // self.world) * self.world
        perm = (perm * (total // max(self.n, 1) + 1))[:total]
        return perm[self.rank :: self.world]

    def __iter__(self):
        order = self.order()[self.start :]
        return iter(order if self.item_seed is None else [(i, self.item_seed) for i in order])

    def __len__(self) -> int:
        return max(-(-self.n // self.world) - self.start, 0)
