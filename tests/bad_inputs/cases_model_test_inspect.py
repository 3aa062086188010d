"""``matchplant inspect`` on COCO files of broken structure (issue 27): annotations without ``bbox``, a ``bbox``
written as text, images without ``width``/``height``: each a clear message naming the file and the first broken
entry; and module 5's tiles of the tiny field, which must give the advice of the photos they were cut from."""

from __future__ import annotations

import json

from harness import Case, Work

from matchplant.detection.objects import InspectConfig, inspect_dataset


def broken(edit, name: str = "train.json"):
    def prepare(w: Work) -> list[str]:
        data = json.loads((w.artifacts / "tiles" / "train.json").read_text())
        edit(data)
        path = w.inputs / name
        path.write_text(json.dumps(data))
        return [str(path), "--report", str(w.out / "report.json")]

    return prepare


def _no_bbox(d):
    d["annotations"][3].pop("bbox")


def _text_bbox(d):
    d["annotations"][0]["bbox"] = ", ".join(str(v) for v in d["annotations"][0]["bbox"])


def _no_size(d):
    for im in d["images"][:2]:
        im.pop("width")


def tiles(w: Work) -> list[str]:
    return [str(w.copy("tiles/train.json")), "--report", str(w.out / "report.json")]


def same_advice_as_the_photos(w: Work) -> None:
    tiled = json.loads((w.out / "report.json").read_text())
    photos = inspect_dataset(InspectConfig(annotations=w.artifacts / "field" / "truth" / "boxes_undistorted.json"))
    for key in ("tile_size", "overlap", "min_size"):
        assert tiled["recommended"][key] == photos["recommended"][key], (key, tiled["recommended"], photos)


CASES = [
    Case(
        "inspect-annotation-without-bbox",
        "inspect",
        broken(_no_bbox),
        mentions=("train.json", "no 'bbox'", "annotation"),
    ),
    Case("inspect-bbox-as-text", "inspect", broken(_text_bbox), mentions=("train.json", "(str)", "bbox")),
    Case("inspect-images-without-size", "inspect", broken(_no_size), mentions=("train.json", "width", "height")),
    Case("inspect-tiles-advice-of-the-photos", "inspect", tiles, expect="ok", check=same_advice_as_the_photos),
]
