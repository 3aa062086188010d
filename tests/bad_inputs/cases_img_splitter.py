"""Module 5 (img_splitter): annotations without boxes (no silent negatives-only tiles), split shares that do not
add up to 1, tiles larger than the photos, an overlap as large as a tile, annotations whose image sizes or
names disagree with the folder, broken photos, malformed boxes and YOLO lines, an output folder that is an
input, a failed re-run over earlier tiles; and what must work: BOM/CRLF COCO and YOLO files, non-ASCII paths,
junk files, a positions CSV from Excel, photos missing from the folder (skipped, listed in dropped.csv).

The reference is the tiny field's truth (``truth/boxes_undistorted.json``: 339 boxes on 9 photos of 400x300
px) and module 5's own geometry rule, recomputed here independently for the checks (tiles of 128 px with 32
px overlap; a box is in a tile when >= 30 % of it and >= 10 px of each side are inside).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from harness import Case, Work
from harness import write_text_file as write

from matchplant.cli import run_module
from matchplant.core.formats.yolo import coco_to_yolo

IMAGES = "field/opensfm/undistorted/images"
TRUTH = "field/truth/boxes_undistorted.json"
GRID = ("tile_size=128", "overlap=32", "workers=1")


def truth(w: Work) -> dict:
    return json.loads((w.artifacts / TRUTH).read_text())


def coco(w: Work, ds: dict, name: str = "annotations.json", **kw) -> Path:
    return write(w.inputs / name, json.dumps(ds), **kw)


def args(w: Work, images: Path, annotations: Path, *sets: str, grid: tuple[str, ...] = GRID) -> list[str]:
    out = ["--set", f"images={images}", "--set", f"annotations={annotations}", "--set", f"output_dir={w.out}"]
    for s in (*grid, *sets):
        out += ["--set", s]
    return out


# -- checks: the boxes in the tiles against the truth --------------------------------------------------------


def _origins(length: int, tile: int = 128, overlap: int = 32) -> list[int]:
    starts = list(range(0, length - tile, tile - overlap))
    return starts + [length - tile]


def expected_boxes(ds: dict, skip: set[str] = frozenset()) -> int:
    """How many (tile, box) pairs the rule gives, counted here box by box (not vectorised like module 5)."""
    n = 0
    sizes = {im["id"]: (im["file_name"], im["width"], im["height"]) for im in ds["images"]}
    for a in ds["annotations"]:
        name, width, height = sizes[a["image_id"]]
        if name in skip:
            continue
        x, y, bw, bh = a["bbox"]
        for y0 in _origins(height):
            for x0 in _origins(width):
                iw = min(x + bw, x0 + 128) - max(x, x0)
                ih = min(y + bh, y0 + 128) - max(y, y0)
                if iw >= 10 and ih >= 10 and iw * ih >= 0.3 * bw * bh:
                    n += 1
    return n


def tiles_like_truth(skip: tuple[str, ...] = (), dropped_images: int = 0):
    def check(w: Work) -> None:
        t = truth(w)
        got = sum(len(json.loads((w.out / f"{k}.json").read_text())["annotations"]) for k in ("train", "val", "test"))
        assert got == expected_boxes(t, set(skip)), (got, expected_boxes(t, set(skip)))
        sources = {
            im["source_image"]
            for k in ("train", "val", "test")
            for im in json.loads((w.out / f"{k}.json").read_text())["images"]
        }
        assert sources == {im["file_name"] for im in t["images"]} - set(skip), sources
        n_tiles = sum(1 for _ in w.out.glob("*/images/*"))
        assert n_tiles == json.loads((w.out / "summary.json").read_text())["tiles"] and n_tiles > 0
        rows = []
        if (w.out / "dropped.csv").is_file():
            with open(w.out / "dropped.csv", newline="", encoding="utf-8") as fh:
                rows = [r for r in csv.DictReader(fh) if r["reason"] == "image not in the image folder"]
        ids = {im["id"] for im in t["images"] if im["file_name"] in skip}
        assert len(rows) == sum(a["image_id"] in ids for a in t["annotations"]) == dropped_images, len(rows)

    return check


# -- must work -------------------------------------------------------------------------------------------------


def bom_crlf_coco_unicode_junk(w: Work) -> list[str]:
    images = w.copy(IMAGES, "fotos ñandú")
    (images / "Thumbs.db").write_bytes(b"\x00junk")
    (images / "._SIM_0001.JPG.tif").write_bytes(b"\x00\x05\x16\x07 resource fork")
    text = (w.artifacts / TRUTH).read_text()
    return args(w, images, write(w.inputs / "anotación é.json", text, bom=True, crlf=True))


def yolo_bom_crlf(w: Work) -> list[str]:
    labels = w.inputs / "labels"
    coco_to_yolo(truth(w), labels)
    for p in labels.glob("*.txt"):
        write(p, p.read_text(), bom=True, crlf=True)
    return args(w, w.copy(IMAGES, "images"), labels)


def some_photos_missing(w: Work) -> list[str]:
    images = w.copy(IMAGES, "images")
    (images / "SIM_0007.JPG.tif").unlink()
    return args(w, images, w.copy(TRUTH))


def positions_csv_from_excel(w: Work) -> list[str]:
    rows = "".join(f"{im['file_name']};{10 * i},{5};{i * 3},5\n" for i, im in enumerate(truth(w)["images"]))
    pos = write(w.inputs / "positions.csv", "image;x;y\n" + rows, bom=True, crlf=True)
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), "split_mode=spatial", f"positions={pos}")


def rerun_over_earlier_tiles(w: Work) -> list[str]:
    """A second run with another grid replaces the first run's tiles (none of them stale)."""
    a = args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), grid=("tile_size=200", "overlap=20", "workers=1"))
    assert run_module("img_splitter", [*a, "--quiet"]) == 0
    return args(w, w.inputs / "images", w.inputs / "boxes_undistorted.json")


# -- errors ----------------------------------------------------------------------------------------------------


def no_annotations(w: Work) -> list[str]:
    ds = truth(w)
    ds["annotations"] = []
    return args(w, w.copy(IMAGES, "images"), coco(w, ds, "unlabelled.json"))


def annotations_key_missing(w: Work) -> list[str]:
    ds = truth(w)
    del ds["annotations"]
    return args(w, w.copy(IMAGES, "images"), coco(w, ds, "images_only.json"))


def predictions_as_annotations(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy("predictions.json"))


def split_not_one(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), "split=[0.7, 0.2, 0.2]")


def split_percentages(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), "split=[70, 15, 15]")


def tile_larger_than_photos(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), grid=("tile_size=1024", "overlap=100", "workers=1"))


def whole_photos(w: Work) -> None:
    """Every tile is a whole 400 x 300 photo, and every photo with boxes is one."""
    tiles = [
        im
        for split in ("train", "val", "test")
        if (w.out / f"{split}.json").is_file()
        for im in json.loads((w.out / f"{split}.json").read_text())["images"]
    ]
    assert tiles and all((t["x0"], t["y0"], t["width"], t["height"]) == (0, 0, 400, 300) for t in tiles), tiles[:3]
    assert len({t["source_image"] for t in tiles}) == len(tiles)
    assert len(tiles) == len({im["file_name"] for im in truth(w)["images"]})


def overlap_equals_tile(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), grid=("tile_size=128", "overlap=128", "workers=1"))


def sizes_disagree(w: Work) -> list[str]:
    ds = truth(w)
    ds["images"][3]["width"], ds["images"][3]["height"] = 800, 600
    return args(w, w.copy(IMAGES, "images"), coco(w, ds))


def truncated_photo(w: Work) -> list[str]:
    images = w.copy(IMAGES, "images")
    photo = images / "SIM_0005.JPG.tif"
    photo.write_bytes(photo.read_bytes()[: photo.stat().st_size * 2 // 3])
    return args(w, images, w.copy(TRUTH))


def truncated_jpeg_photo(w: Work) -> list[str]:
    images = w.copy("field/images", "photos")
    photo = images / "SIM_0002.JPG"
    photo.write_bytes(photo.read_bytes()[: photo.stat().st_size // 2])
    return args(w, images, w.copy(TRUTH))


def wrong_image_folder(w: Work) -> list[str]:
    """'images' set to another folder of the field (it holds one .tif, named like no annotated photo)."""
    return args(w, w.copy("field/multispectral", "multispectral"), w.copy(TRUTH))


def box_not_numbers(w: Work) -> list[str]:
    ds = truth(w)
    ds["annotations"][12]["bbox"] = [10, 20, "wide", 30]
    return args(w, w.copy(IMAGES, "images"), coco(w, ds))


def duplicate_annotation_ids(w: Work) -> list[str]:
    ds = truth(w)
    ds["annotations"][5]["id"] = ds["annotations"][4]["id"]
    return args(w, w.copy(IMAGES, "images"), coco(w, ds))


def yolo_polygon_line(w: Work) -> list[str]:
    labels = w.inputs / "labels"
    coco_to_yolo(truth(w), labels)
    with open(labels / "SIM_0008.JPG.txt", "a") as fh:
        fh.write("0 0.1 0.1 0.2 0.1 0.2 0.2 0.1 0.2\n")
    return args(w, w.copy(IMAGES, "images"), labels)


def boxes_too_small_for_any_tile(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), w.copy(TRUTH), "min_box_side=200")


def output_is_image_folder(w: Work) -> list[str]:
    images = w.copy(IMAGES, "images")
    a = args(w, images, w.copy(TRUTH))
    return [x if not x.startswith("output_dir=") else f"output_dir={images}" for x in a]


def failed_rerun_keeps_earlier_tiles(w: Work) -> list[str]:
    a = args(w, w.copy(IMAGES, "images"), w.copy(TRUTH))
    assert run_module("img_splitter", [*a, "--quiet"]) == 0
    photo = w.inputs / "images" / "SIM_0003.JPG.tif"
    photo.write_bytes(photo.read_bytes()[:1000])
    return a


CASES = [
    Case(
        "m5-bom-crlf-coco-unicode-junk",
        "img_splitter",
        bom_crlf_coco_unicode_junk,
        expect="ok",
        check=tiles_like_truth(),
    ),
    Case("m5-yolo-bom-crlf", "img_splitter", yolo_bom_crlf, expect="ok", check=tiles_like_truth()),
    Case(
        "m5-some-photos-missing",
        "img_splitter",
        some_photos_missing,
        expect="ok",
        check=tiles_like_truth(("SIM_0007.JPG.tif",), dropped_images=33),
    ),
    Case(
        "m5-positions-csv-from-excel", "img_splitter", positions_csv_from_excel, expect="ok", check=tiles_like_truth()
    ),
    Case(
        "m5-rerun-over-earlier-tiles", "img_splitter", rerun_over_earlier_tiles, expect="ok", check=tiles_like_truth()
    ),
    Case("m5-no-annotations", "img_splitter", no_annotations, mentions=("unlabelled.json", "no box")),
    Case(
        "m5-annotations-key-missing", "img_splitter", annotations_key_missing, mentions=("images_only.json", "no box")
    ),
    Case(
        "m5-predictions-as-annotations",
        "img_splitter",
        predictions_as_annotations,
        mentions=("predictions.json", "predictions"),
    ),
    Case("m5-split-not-one", "img_splitter", split_not_one, mentions=("split", "1.1")),
    Case("m5-split-percentages", "img_splitter", split_percentages, mentions=("split", "percentages")),
    # a tile at least the photo's size: no tiling, each photo one whole tile (inspect's advice for large plants)
    Case("m5-tile-larger-than-photos", "img_splitter", tile_larger_than_photos, expect="ok", check=whole_photos),
    Case("m5-overlap-equals-tile", "img_splitter", overlap_equals_tile, mentions=("overlap", "tile_size")),
    Case("m5-sizes-disagree", "img_splitter", sizes_disagree, mentions=("SIM_0004.JPG.tif", "800x600")),
    Case("m5-truncated-tif", "img_splitter", truncated_photo, mentions=("SIM_0005.JPG.tif",)),
    Case("m5-truncated-jpeg", "img_splitter", truncated_jpeg_photo, mentions=("SIM_0002.JPG", "truncated")),
    Case("m5-wrong-image-folder", "img_splitter", wrong_image_folder, mentions=("multispectral", "images")),
    Case("m5-box-not-numbers", "img_splitter", box_not_numbers, mentions=("annotations.json", "annotation 13")),
    Case(
        "m5-duplicate-annotation-ids",
        "img_splitter",
        duplicate_annotation_ids,
        mentions=("annotations.json", "duplicate annotation ids"),
    ),
    Case("m5-yolo-polygon-line", "img_splitter", yolo_polygon_line, mentions=("SIM_0008.JPG.txt", "polygon")),
    Case(
        "m5-boxes-too-small-for-any-tile",
        "img_splitter",
        boxes_too_small_for_any_tile,
        mentions=("min_box_side", "boxes_undistorted.json"),
    ),
    Case(
        "m5-failed-rerun-keeps-earlier-tiles",
        "img_splitter",
        failed_rerun_keeps_earlier_tiles,
        mentions=("SIM_0003.JPG.tif",),
    ),
    Case("m5-output-is-image-folder", "img_splitter", output_is_image_folder, mentions=("output_dir",)),
]
