"""A COCO dataset checked against its files before anything is trained or scored (:func:`check_dataset`):
categories that the annotations use, at least one box, every image file present (:func:`find_image`) and whole
(header and length, :func:`image_size`), the JSON's width/height against the files (a warning with counts when
the boxes still fit, an error when they fall outside the real images). :class:`~matchplant.detection.data.CocoDetection`
runs them; module 7 checks its photos with :func:`check_image_files`."""

from __future__ import annotations

import warnings
from collections import Counter
from pathlib import Path

from PIL import Image

from matchplant.core.formats.coco import bbox_values, raise_problems
from matchplant.core.formats.images import read_image
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.core.runtime.validate import name_key

log = get_logger("data")


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
    raise_problems(data, json_path, "correct the annotations (module 4 can open and fix them)")
    return paths
