"""Module 7's predictions JSON read and checked in one place, for every step that reads it (docs/DESIGN.md §2).

``{"images": [...], "categories": [...], "predictions": [{"image_id", "category_id", "bbox", "score"}, ...]}``;
each image entry carries ``file_name``, ``width``, ``height`` and, for tiles, ``source_image``, ``x0``, ``y0``.
A plain COCO results list plus a dataset for the image entries (``images_from``) is accepted too. Each problem
names the file, the prediction (its index and image) and the fix; a COCO dataset or a plain results list given
where predictions are expected is recognised and said in those words.
"""

from __future__ import annotations

import math
from pathlib import Path

from matchplant.core.formats.coco import read_dataset, source_name
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.validate import did_you_mean, read_json

FIX_PREDICTIONS = "give the predictions JSON written by module 7 (model_test), or regenerate it"


def read_predictions(path: str | Path, images_from: str | Path | None = None, *, every_box: bool = False) -> dict:
    """Read predictions as ``{"images", "categories", "predictions"}``: MatchPlant's predictions file, or a plain
    COCO results list with ``images_from`` (a COCO dataset providing the image entries).

    ``every_box``: also the right kind of file (said in the words of module 8's keys), at least one detection,
    every image entry named with sizes and offsets >= 0, and every box four finite numbers of positive size with
    a score in [0, 1] - what module 8 needs before casting a ray. Without it (module 4, which leaves out and
    lists the boxes it cannot use) only the file's structure is checked.
    """
    path = Path(path)
    data = read_json(path, what="predictions file")
    if every_box:
        _check_kind(data, path, images_from)
    data = _structure(data, path, images_from)
    if every_box:
        _check_entries(data, path)
    return data


def _structure(data, path: Path, images_from) -> dict:
    """The file as images, categories and predictions, each a list of objects, every prediction on a listed
    image."""
    if isinstance(data, list):
        if images_from is None:
            raise InputError(
                "this is a plain COCO results list; it has no image names",
                path=path,
                fix="also give the COCO dataset the predictions were made on",
            )
        ds = read_dataset(images_from, validate=False)
        data = {"images": ds["images"], "categories": ds["categories"], "predictions": data}
    if not isinstance(data, dict) or "predictions" not in data or "images" not in data:
        raise InputError(
            "not a predictions file (needs 'images' and 'predictions')",
            path=path,
            fix="give the predictions JSON written by module 7",
        )
    if (
        not isinstance(data["images"], list)
        or not all(isinstance(im, dict) and "id" in im for im in data["images"])
        or not isinstance(data["predictions"], list)
        or not all(isinstance(p, dict) for p in data["predictions"])
    ):
        raise InputError(
            "'images' and 'predictions' must be lists of objects (images with an 'id')",
            path=path,
            fix="give the predictions JSON written by module 7",
        )
    known = {im["id"] for im in data["images"]}
    orphans = [p for p in data["predictions"] if p.get("image_id") not in known]
    if orphans:
        raise InputError(
            f"{len(orphans)} prediction(s) refer to images not listed in the file",
            path=path,
            fix="regenerate the predictions with module 7",
        )
    data.setdefault("categories", [{"id": 1, "name": "plant"}])
    return data


def _check_kind(data, path: Path, images_from) -> None:
    """A COCO dataset, a results list without its images, or a file of another kind, said in those words."""
    if isinstance(data, list):
        if images_from is None:
            raise ConfigError(
                f"the predictions file is a plain COCO results list ({len(data)} boxes) without image names",
                path=path,
                fix="set 'images_from' to the COCO dataset the predictions were made on (it names "
                "the images), or give module 7's predictions.json",
            )
        if not all(isinstance(p, dict) for p in data):
            raise InputError(
                "the predictions file is a list, but not of detections {image_id, bbox, score}",
                path=path,
                fix=FIX_PREDICTIONS,
            )
        return
    if not isinstance(data, dict):
        raise InputError(
            f"the predictions file holds a {type(data).__name__}, not predictions", path=path, fix=FIX_PREDICTIONS
        )
    if "predictions" not in data and "annotations" in data:
        raise InputError(
            "this is a COCO dataset ('images' and 'annotations': labelled boxes), not predictions",
            path=path,
            fix="give module 7's predictions JSON; to project labelled boxes, rename "
            "their 'annotations' key to 'predictions'",
        )
    if "predictions" not in data:
        hint = did_you_mean("predictions", data)
        raise InputError(
            f"the predictions file has no 'predictions'{'; ' + hint if hint else ''} (keys: "
            f"{', '.join(map(str, data)) or 'none'})",
            path=path,
            fix=FIX_PREDICTIONS,
        )
    if "images" not in data:
        raise InputError(
            "the predictions file has 'predictions' but no 'images' (the image names)", path=path, fix=FIX_PREDICTIONS
        )


def _check_entries(preds: dict, path: Path) -> None:
    """At least one detection; every image entry, the categories and every detection usable."""
    if not preds["predictions"]:
        raise InputError(
            "the predictions file holds no detections ('predictions' is empty)",
            path=path,
            fix="run module 7 again (check its score threshold), or point 'predictions' at the right file",
        )
    images = {im["id"]: im for im in preds["images"]}
    for k, im in enumerate(preds["images"]):
        name = im.get("source_image") or im.get("file_name")
        if not isinstance(name, str) or not name.strip():
            raise InputError(f"images[{k}] (id {im['id']!r}) has no 'file_name'", path=path, fix=FIX_PREDICTIONS)
        for key in ("x0", "y0", "width", "height"):  # a tile's place in its photo, and the image size
            if im.get(key) is not None and not (_number(im[key]) and im[key] >= 0):
                raise InputError(
                    f"images[{k}] ('{name}'): '{key}' is {im[key]!r}, not a number >= 0", path=path, fix=FIX_PREDICTIONS
                )
    cats = preds.get("categories")
    if not isinstance(cats, list) or not all(isinstance(c, dict) and "id" in c for c in cats):
        raise InputError("'categories' must be a list of objects with an 'id'", path=path, fix=FIX_PREDICTIONS)
    for i, p in enumerate(preds["predictions"]):
        _check_prediction(i, p, source_name(images[p["image_id"]]), path)


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_prediction(i: int, p: dict, image: str, path: Path) -> None:
    where = f"predictions[{i}] (image '{image}')"
    bbox = p.get("bbox")
    if not (isinstance(bbox, (list, tuple)) and len(bbox) == 4 and all(_number(v) for v in bbox)):
        raise InputError(
            f"{where}: bbox {bbox!r} is not four finite numbers [x, y, width, height]",
            path=path,
            fix="regenerate the predictions (module 7), or remove that box",
        )
    x, y, w, h = (float(v) for v in bbox)
    if w < 0 or h < 0:
        corners = " (it looks like [x1, y1, x2, y2] with the corners swapped)" if w + x >= 0 and h + y >= 0 else ""
        raise InputError(
            f"{where}: bbox {bbox!r} has a negative width or height{corners}",
            path=path,
            fix="COCO boxes are [x, y, width, height] with width, height >= 0; convert the boxes",
        )
    if "score" in p:
        s = p["score"]
        if not _number(s) or not 0.0 <= float(s) <= 1.0:
            pct = " (a percentage? scores are 0..1)" if _number(s) and 1.0 < float(s) <= 100.0 else ""
            raise InputError(
                f"{where}: score {s!r} is not a number in [0, 1]{pct}",
                path=path,
                fix="scores must be probabilities between 0 and 1; divide percentages by 100",
            )
    cat = p.get("category_id", 1)
    if not (_number(cat) and float(cat) == int(cat)):
        raise InputError(f"{where}: category_id {cat!r} is not an integer", path=path, fix=FIX_PREDICTIONS)


def write_predictions(
    path: str | Path, images: list[dict], categories: list[dict], predictions: list[dict], info: dict | None = None
) -> Path:
    """Write a predictions file (images, categories, predictions) as compact JSON, whole or not at all."""
    data = {
        "info": info or {"description": "MatchPlant predictions"},
        "images": images,
        "categories": categories,
        "predictions": predictions,
    }
    return write_json(path, data, indent=None)
