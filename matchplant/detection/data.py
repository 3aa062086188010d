"""COCO tiles as a torch dataset for the detector, with augmentation that moves the boxes with the image.

Image files are found relative to ``images_dir`` (by default the folder of the COCO JSON; module 5's
``<split>.json`` with ``<split>/images/`` beside it is found as it is). Tiles without
plants stay in the dataset as negatives. Augmentation uses torchvision's ``transforms.v2``, which flips
the boxes together with the pixels.

Before anything is trained or scored, :class:`CocoDetection` checks the dataset against the files on
disk (:func:`check_dataset`): categories that the annotations use, at least one box, every image file
present and whole (header and length, :func:`image_size`), the JSON's width/height against the files
(a warning with counts when the boxes still fit, an error when they fall outside the real images).
:func:`check_disjoint` refuses a validation split that is, or shares tile files with, the training split.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from matchplant.core.formats.coco import annotations_by_image, bbox_values, read_dataset, validate_dataset
from matchplant.core.formats.images import read_image, read_rgb8
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.core.runtime.validate import did_you_mean, name_key
from matchplant.detection.crops import crop_steps

log = get_logger("data")


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


def find_image(file_name: str, images_dir: Path, split: str | None = None) -> Path | None:
    """The file for a COCO ``file_name`` under ``images_dir``: as given, in ``images/``, in module 5's
    ``<split>/images/`` (``split`` = the JSON's stem), or by its base name (Windows ``\\`` separators too)."""
    name = str(file_name).replace("\\", "/")
    candidates = []
    for n in dict.fromkeys([name, Path(name).name]):
        candidates += [images_dir / n, images_dir / "images" / n]
        if split:
            candidates.append(images_dir / split / "images" / n)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


# --------------------------------------------------------------------------------------------------
# checks of a dataset against its files


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, checked cheaply for completeness: its header, and the end of its
    data against the file's length (TIFF strips, JPEG's end marker, PNG's IEND); a file that looks cut off is
    decoded in full before it is called truncated. Files PIL cannot parse are decoded with OpenCV instead.
    Raises an InputError naming the file."""
    path = Path(path)
    fix = "copy the file again, or regenerate the tiles with module 5 (or remove the image from the JSON)"
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"image cannot be read: {exc.strerror}", path=path, fix=fix) from exc
    if size == 0:
        raise InputError("image file is empty (0 bytes)", path=path, fix=fix)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            warnings.simplefilter("ignore", UserWarning)  # PIL on a cut-off file ("Corrupt EXIF data"): said below
            with Image.open(path) as im:
                width, height = im.size
                cut = _looks_cut(im, path, size)
                if cut:
                    try:
                        im.load()
                    except (OSError, SyntaxError, ValueError) as exc:
                        raise InputError(f"image is truncated ({cut})", path=path, fix=fix) from exc
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        cut = _cut_header(path, size)
        if cut:
            raise InputError(f"image is truncated ({cut})", path=path, fix=fix) from exc
        img = read_image(path)  # formats PIL does not know; an InputError naming the file if OpenCV fails too
        return int(img.shape[1]), int(img.shape[0])
    return int(width), int(height)


def _cut_header(path: Path, size: int) -> str:
    """Why a file PIL cannot open looks like a cut-off TIFF, JPEG or PNG ("" when it does not)."""
    with open(path, "rb") as fh:
        head = fh.read(16)
        fh.seek(max(0, size - 64))
        tail = fh.read()
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        ifd = int.from_bytes(head[4:8], "little" if head[:2] == b"II" else "big")
        return f"{size} bytes, its TIFF directory at byte {ifd} is missing" if ifd >= size else ""
    if head.startswith(b"\xff\xd8") and not tail.rstrip(b"\x00").endswith(b"\xff\xd9"):
        return f"{size} bytes, no end-of-image marker"
    if head.startswith(b"\x89PNG") and b"IEND" not in tail:
        return f"{size} bytes, no end chunk"
    return ""


def _looks_cut(im, path: Path, size: int) -> str:
    """Why the file may be cut off ("" when it looks whole)."""
    if im.format == "TIFF":
        for offsets_tag, counts_tag in ((273, 279), (324, 325)):  # strips, tiles
            offsets, counts = im.tag_v2.get(offsets_tag), im.tag_v2.get(counts_tag)
            if offsets is not None and counts is not None:
                offsets = offsets if isinstance(offsets, tuple) else (offsets,)
                counts = counts if isinstance(counts, tuple) else (counts,)
                end = max(int(o) + int(c) for o, c in zip(offsets, counts))
                return f"{size} bytes, its pixel data ends at byte {end}" if end > size else ""
        return ""
    if im.format in ("JPEG", "MPO", "PNG"):
        with open(path, "rb") as fh:
            fh.seek(max(0, size - 4096))
            tail = fh.read()
        if im.format == "PNG":
            return "" if b"IEND" in tail[-64:] else f"{size} bytes, no end chunk"
        return "" if tail.rstrip(b"\x00").endswith(b"\xff\xd9") else f"{size} bytes, no end-of-image marker"
    return ""


def _check_ids(data: dict, path: Path) -> None:
    """Every image, annotation and category id (and an annotation's image_id, category_id) an integer, as
    COCO and its tools have them."""
    for kind, key, names in (
        ("image", "images", ("id",)),
        ("annotation", "annotations", ("id", "image_id", "category_id")),
        ("category", "categories", ("id",)),
    ):
        for i, item in enumerate(data[key]):
            for name in names:
                value = item.get(name)
                if not isinstance(value, int) or isinstance(value, bool):
                    raise InputError(
                        f"{kind} number {i + 1} of '{key}' has {name} = {value!r}, not an integer",
                        path=path,
                        fix=f"give every {kind} its integer '{name}' (or regenerate the file with module 4 or 5)",
                    )


def _check_categories(data: dict, path: Path) -> None:
    """Categories with an id and a unique name, and every annotation's category_id among them."""
    cats, anns = data["categories"], data["annotations"]
    example = '"categories": [{"id": 1, "name": "plant"}]'
    if not cats:
        if anns:
            raise InputError(
                f"the COCO file has {len(anns)} annotation(s) but no 'categories'",
                path=path,
                fix=f"add the categories, e.g. {example} (modules 4 and 5 write them)",
            )
        return
    for c in cats:
        if not isinstance(c.get("id"), int) or isinstance(c.get("id"), bool) or not str(c.get("name") or "").strip():
            raise InputError(
                f"category {c!r} needs an integer 'id' and a 'name'",
                path=path,
                fix=f"write each category as in {example}",
            )
    names = Counter(str(c["name"]) for c in cats)
    twice = [n for n, k in names.items() if k > 1]
    if twice:
        raise InputError(
            f"category name '{twice[0]}' is used by {names[twice[0]]} categories (ids "
            f"{[c['id'] for c in cats if str(c['name']) == twice[0]]})",
            path=path,
            fix="give each category its own name, or merge them into one id",
        )
    ids = {c["id"]: str(c["name"]) for c in cats}
    unknown = Counter(repr(a.get("category_id")) for a in anns if a.get("category_id") not in ids)
    if unknown:
        n = sum(unknown.values())
        shown = ", ".join(f"{k} ({v} annotation{'s' * (v > 1)})" for k, v in unknown.most_common(5))
        values = [a.get("category_id") for a in anns if a.get("category_id") not in ids]
        zero_based = all(isinstance(v, int) and v + 1 in ids for v in values)
        hint = "; numbered from 0? COCO category ids here start at " + str(min(ids)) if zero_based else ""
        raise InputError(
            f"{n} of {len(anns)} annotations have a category_id that is not a category: {shown}; "
            f"the categories are {', '.join(f'{i} {nm!r}' for i, nm in sorted(ids.items()))}{hint}",
            path=path,
            fix="give each annotation the id of one of the 'categories' (or add the missing categories)",
        )


def _find_files(images: list[dict], json_path: Path, images_dir: Path) -> list[Path]:
    for im in images:
        if not isinstance(im.get("file_name"), str) or not im["file_name"].strip():
            raise InputError(
                f"image id {im.get('id')!r} has no file_name",
                path=json_path,
                fix="give every image entry the name of its file",
            )
    paths = [find_image(im["file_name"], images_dir, json_path.stem) for im in images]
    missing = [im["file_name"] for im, p in zip(images, paths) if p is None]
    if not missing:
        return paths  # type: ignore[return-value]
    looked = f"{images_dir}, {images_dir / 'images'}, {images_dir / json_path.stem / 'images'}"
    folder = (
        images_dir / json_path.stem / "images"
        if (images_dir / json_path.stem / "images").is_dir()
        else images_dir / "images"
        if (images_dir / "images").is_dir()
        else images_dir
    )
    present = {name_key(p.name): p.name for p in folder.iterdir()} if folder.is_dir() else {}
    close = present.get(name_key(missing[0]))  # the same name but for case or extension; tiles all look alike
    hint = f"did you mean '{close}' (in {folder})?" if close else ""
    what = (
        f"none of the {len(images)} image files of {json_path.name} was found"
        if len(missing) == len(images)
        else f"{len(missing)} of the {len(images)} image files of {json_path.name} are missing"
    )
    raise InputError(
        f"{what} (looked in {looked}): "
        f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}{'; ' + hint if hint else ''}",
        path=json_path,
        fix="set the images folder of this dataset (train_images, val_images or "
        "evaluate.images), copy the missing files, or regenerate the tiles "
        "with module 5",
    )


def check_image_files(paths: list[Path], source: str) -> list[tuple[int, int]]:
    """``(width, height)`` of every file (:func:`image_size`); one error naming every broken file of ``source``
    (a JSON's name, a config key)."""
    sizes, bad = [], []
    for p in progress(paths, desc=f"checking the images of {source}", unit="image"):
        try:
            sizes.append(image_size(p))
        except InputError as exc:
            bad.append((p, exc.problem))
            sizes.append((0, 0))
    if bad:
        raise InputError(
            f"{len(bad)} image file(s) of {source} cannot be used: "
            f"{'; '.join(f'{p.name} ({why})' for p, why in bad[:5])}{' ...' if len(bad) > 5 else ''}",
            path=bad[0][0] if len(bad) == 1 else bad[0][0].parent,
            fix="copy those files again, regenerate them (module 5 for tiles), or remove them",
        )
    return sizes


def _use_file_sizes(data: dict, sizes: list[tuple[int, int]], json_path: Path, tolerance: float = 1.0) -> None:
    """Where the JSON's width/height differ from the file's: an error when boxes fall outside the real image,
    else a warning with counts; the files' sizes replace the JSON's (in memory)."""
    differ = {im["id"]: (im, wh) for im, wh in zip(data["images"], sizes) if (im.get("width"), im.get("height")) != wh}
    if not differ:
        return
    outside = []
    for a in data["annotations"]:
        if a.get("image_id") not in differ:
            continue
        im, (w, h) = differ[a["image_id"]]
        box = bbox_values(a.get("bbox"))
        if box and (
            box[0] < -tolerance
            or box[1] < -tolerance
            or box[0] + box[2] > w + tolerance
            or box[1] + box[3] > h + tolerance
        ):
            outside.append((a, im, (w, h)))
    named = [(im, wh) for im, wh in differ.values() if im.get("width") is not None or im.get("height") is not None]
    if outside:
        a, im, (w, h) = outside[0]
        raise InputError(
            f"{len(outside)} box(es) fall outside their image files: the JSON gives "
            f"{im['file_name']} as {im.get('width')}x{im.get('height')} px but the file is {w}x{h} "
            f"(annotation {a.get('id')}, box {a.get('bbox')}); {len(differ)} of {len(sizes)} images "
            f"differ in size",
            path=json_path,
            fix="the boxes were drawn on other (larger) images: point the images folder at those, "
            "or annotate and tile again (modules 4 and 5)",
        )
    if named:
        im, (w, h) = named[0]
        log.warning(
            "%d of %d images of %s have another width/height in the JSON than on disk (e.g. %s: %sx%s in "
            "the JSON, %dx%d file); every box lies inside the real images, so the files' sizes are used "
            "(correct the JSON, or regenerate it with module 5, to silence this)",
            len(named),
            len(sizes),
            json_path,
            im["file_name"],
            im.get("width"),
            im.get("height"),
            w,
            h,
        )
    for im, (w, h) in differ.values():
        im["width"], im["height"] = w, h


def check_dataset(data: dict, json_path: Path, images_dir: Path, *, require_boxes: bool = True) -> list[Path]:
    """Check a COCO dataset (read from ``json_path``) against its image files; returns each image's file.

    Errors: no images, a predictions file instead of a dataset, categories missing or not matching the
    annotations, no box at all (``require_boxes``), image files missing, truncated or unreadable, boxes
    outside the real images; and everything :func:`~matchplant.core.formats.coco.validate_dataset` finds.
    """
    if not data["images"]:
        raise InputError(
            "the COCO file lists no images",
            path=json_path,
            fix="give the COCO JSON of the tiles (module 5 writes train.json, val.json, test.json)",
        )
    if "predictions" in data and not data["annotations"]:
        raise InputError(
            "this is a predictions file (module 7's output), not an annotated dataset",
            path=json_path,
            fix="give the COCO JSON with the true boxes (module 5's train/val/test.json)",
        )
    _check_ids(data, json_path)
    _check_categories(data, json_path)
    if require_boxes and not any(not a.get("iscrowd", 0) for a in data["annotations"]):
        raise InputError(
            f"the COCO file has no annotations (0 boxes on {len(data['images'])} images): nothing to "
            "learn from or to score against",
            path=json_path,
            fix="tile the images together with their annotations (module 5's 'annotations' key), "
            "or point the config at the split that has the boxes",
        )
    paths = _find_files(data["images"], json_path, images_dir)
    _use_file_sizes(data, check_image_files(paths, json_path.name), json_path)
    problems = validate_dataset(data)
    if problems:
        shown = "\n".join(f"  - {p}" for p in problems[:10])
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        raise InputError(
            f"the COCO dataset has {len(problems)} problem(s):\n{shown}{more}",
            path=json_path,
            fix="correct the annotations (module 4 can open and fix them)",
        )
    return paths


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
        self.epoch, self.start = epoch, start

    def order(self) -> list[int]:
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
