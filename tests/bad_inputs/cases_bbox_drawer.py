"""Module 4 (bbox_drawer, run without the GUI): importing boxes made elsewhere. Files whose boxes cannot all be
used (negative sizes, boxes outside the image, unknown categories, repeated boxes, YOLO values outside
[0, 1], image names that match no photo) import what is valid, warn with counts and list every box left out
in ``import_dropped.csv``; files of which nothing can be used, ambiguous or malformed files, boxes drawn on
resized photos, broken photos and an output folder that is an input are errors. Must work: BOM/CRLF files,
non-ASCII paths, junk files in the image folder, names that match loosely.

The reference is the tiny field's truth (``truth/boxes_undistorted.json``: 339 boxes on 9 photos of 400x300
px, all inside their image): what a case breaks is known, so the exported and the dropped boxes are too.
"""

from __future__ import annotations

import copy
import csv
import json
from collections import Counter
from pathlib import Path

from harness import Case, Work
from harness import write_text_file as write

from matchplant.core.formats.yolo import coco_to_yolo

IMAGES = "field/opensfm/undistorted/images"


def truth(w: Work) -> dict:
    return json.loads((w.artifacts / "field" / "truth" / "boxes_undistorted.json").read_text())


def coco(w: Work, ds: dict, name: str = "boxes.json", **kw) -> Path:
    return write(w.inputs / name, json.dumps(ds, indent=1), **kw)


def args(w: Work, images: Path, *sets: str) -> list[str]:
    out = ["--set", f"images={images}", "--set", f"output_dir={w.out}"]
    for s in sets:
        out += ["--set", s]
    return out


def yolo_labels(w: Work, name: str = "labels") -> Path:
    folder = w.inputs / name
    coco_to_yolo(truth(w), folder)
    return folder


# -- checks --------------------------------------------------------------------------------------------------


def exported(w: Work) -> dict:
    return json.loads((w.out / "annotations.json").read_text())


def dropped(w: Work) -> list[dict]:
    path = w.out / "import_dropped.csv"
    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def exports(n_boxes: int, reasons: dict[str, int] | None = None):
    """The export holds ``n_boxes`` boxes and import_dropped.csv lists exactly ``reasons`` (reason -> count)."""

    def check(w: Work) -> None:
        ds = exported(w)
        assert len(ds["annotations"]) == n_boxes, (len(ds["annotations"]), n_boxes)
        got = Counter(r["reason"] for r in dropped(w))
        assert got == Counter(reasons or {}), got

    return check


def exports_truth_boxes(w: Work) -> None:
    """Every truth box, at its place (to 0.01 px: the session rounds), on the photo it belongs to."""
    t = truth(w)
    names = {im["id"]: im["file_name"] for im in t["images"]}
    want = sorted((names[a["image_id"]], *(round(v, 1) for v in a["bbox"])) for a in t["annotations"])
    ds = exported(w)
    got_names = {im["id"]: im["file_name"] for im in ds["images"]}
    got = sorted((got_names[a["image_id"]], *(round(v, 1) for v in a["bbox"])) for a in ds["annotations"])
    assert len(got) == len(want) == 339 and all(
        g[0] == x[0] and max(abs(a - b) for a, b in zip(g[1:], x[1:])) <= 0.11 for g, x in zip(got, want)
    ), (got[:3], want[:3])
    assert not dropped(w)


# -- COCO: partly usable files work, with the rest listed -----------------------------------------------------


def coco_some_boxes_broken(w: Work) -> list[str]:
    ds = truth(w)
    a = ds["annotations"]
    a[0]["bbox"][2] = -a[0]["bbox"][2]  # negative width
    a[1]["bbox"][3] = 0.0  # zero height
    a[2]["bbox"] = [450.0, 20.0, 30.0, 30.0]  # right of the 400 px wide photo
    a[3]["bbox"] = [10.0, -80.0, 20.0, 30.0]  # above it
    a[4]["category_id"] = 7  # no such category
    a[5]["bbox"] = [1.0, "x", 3.0, 4.0]  # not a number
    a.append(copy.deepcopy(a[10]))  # the same box twice (same id)
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds)}")


def coco_duplicate_ids_different_boxes(w: Work) -> list[str]:
    """Two exports merged: annotation ids restart at 1, every box is a different plant and must be kept."""
    ds = truth(w)
    for i, a in enumerate(ds["annotations"]):
        a["id"] = i % 100 + 1
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds)}")


def coco_some_images_missing(w: Work) -> list[str]:
    images = w.copy(IMAGES, "images")
    for name in ("SIM_0002.JPG.tif", "SIM_0005.JPG.tif"):
        (images / name).unlink()
    return args(w, images, f"import_coco={w.copy('field/truth/boxes_undistorted.json')}")


def coco_bom_crlf_unicode_junk(w: Work) -> list[str]:
    images = w.copy(IMAGES, "photos ñandú 1")
    (images / "Thumbs.db").write_bytes(b"\x00junk")
    (images / "._SIM_0001.JPG.tif").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (images / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    text = (w.artifacts / "field" / "truth" / "boxes_undistorted.json").read_text()
    return args(w, images, f"import_coco={write(w.inputs / 'cajas é.json', text, bom=True, crlf=True)}")


def coco_names_match_loosely(w: Work) -> list[str]:
    """A tool that wrote the photos' names (lower case, .jpg) for ODM's undistorted .tif copies."""
    ds = truth(w)
    for im in ds["images"]:
        im["file_name"] = "uploads/" + im["file_name"].replace(".JPG.tif", ".jpg").lower()
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds)}")


# -- COCO: errors ---------------------------------------------------------------------------------------------


def coco_other_photos(w: Work) -> list[str]:
    ds = truth(w)
    for im in ds["images"]:
        im["file_name"] = im["file_name"].replace("SIM_", "DJI_")
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'other_flight.json')}")


def coco_resized_photos(w: Work) -> list[str]:
    ds = truth(w)
    for im in ds["images"]:
        im["width"], im["height"] = 800, 600
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'big.json')}")


def coco_duplicate_image_ids(w: Work) -> list[str]:
    ds = truth(w)
    ds["images"][1]["id"] = ds["images"][0]["id"]
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds)}")


def coco_categories_off_by_one(w: Work) -> list[str]:
    ds = truth(w)
    ds["categories"][0]["id"] = 0  # annotations still say 1
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'zero_based.json')}")


def coco_no_categories(w: Work) -> list[str]:
    ds = truth(w)
    ds["categories"] = []
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'nocats.json')}")


def coco_truncated(w: Work) -> list[str]:
    text = json.dumps(truth(w))
    return args(w, w.copy(IMAGES, "images"), f"import_coco={write(w.inputs / 'cut.json', text[: len(text) // 3])}")


def coco_every_box_negative(w: Work) -> list[str]:
    ds = truth(w)
    for a in ds["annotations"]:
        x, y, bw, bh = a["bbox"]
        a["bbox"] = [x + bw, y + bh, -bw, -bh]  # corners written as x2, y2, -w, -h
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'flipped.json')}")


def coco_without_boxes(w: Work) -> list[str]:
    ds = truth(w)
    ds["annotations"] = []
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'empty.json')}")


# -- YOLO -----------------------------------------------------------------------------------------------------


def yolo_bom_crlf(w: Work) -> list[str]:
    labels = yolo_labels(w)
    for p in labels.glob("*.txt"):
        write(p, p.read_text(), bom=True, crlf=True)
    (labels / "._SIM_0001.JPG.txt").write_bytes(b"\x00\x05\x16\x07 resource fork")
    return args(w, w.copy(IMAGES, "imágenes"), f"import_yolo={labels}")


def yolo_one_value_out_of_range(w: Work) -> list[str]:
    labels = yolo_labels(w)
    path = labels / "SIM_0003.JPG.txt"
    lines = path.read_text().splitlines()
    lines[0] = "0 1.4 0.5 0.1 0.1"  # a centre right of the image
    lines[1] = "0 0.5 0.5 -0.1 0.1"  # a negative width
    path.write_text("\n".join(lines) + "\n")
    return args(w, w.copy(IMAGES, "images"), f"import_yolo={labels}")


def yolo_label_for_no_image(w: Work) -> list[str]:
    labels = yolo_labels(w)
    (labels / "SIM_0004.JPG.txt").rename(labels / "SIM_004.JPG.txt")
    return args(w, w.copy(IMAGES, "images"), f"import_yolo={labels}")


def yolo_in_pixels(w: Work) -> list[str]:
    labels = w.inputs / "labels"
    write(labels / "classes.txt", "plant\n")
    t = truth(w)
    for im in t["images"]:
        rows = [
            f"0 {x + bw / 2:.2f} {y + bh / 2:.2f} {bw:.2f} {bh:.2f}"
            for x, y, bw, bh in (a["bbox"] for a in t["annotations"] if a["image_id"] == im["id"])
        ]
        write(labels / (Path(im["file_name"]).stem + ".txt"), "\n".join(rows) + "\n")
    return args(w, w.copy(IMAGES, "images"), f"import_yolo={labels}")


def yolo_six_columns(w: Work) -> list[str]:
    labels = yolo_labels(w)
    path = labels / "SIM_0006.JPG.txt"
    lines = path.read_text().splitlines()
    lines[2] += " 0.87"  # a confidence left in
    path.write_text("\n".join(lines) + "\n")
    return args(w, w.copy(IMAGES, "images"), f"import_yolo={labels}")


def yolo_without_classes(w: Work) -> list[str]:
    labels = yolo_labels(w)
    (labels / "classes.txt").unlink()
    return args(w, w.copy(IMAGES, "images"), f"import_yolo={labels}")


# -- other formats, the folders ------------------------------------------------------------------------------


def deepforest_text_coordinate(w: Work) -> list[str]:
    csv_path = write(
        w.inputs / "trees.csv",
        "image_path,xmin,ymin,xmax,ymax,label\n"
        "SIM_0001.JPG.tif,10,10,40,40,plant\n"
        "SIM_0001.JPG.tif,10,n/a,40,40,plant\n",
    )
    return args(w, w.copy(IMAGES, "images"), f"import_deepforest={csv_path}")


def deepforest_bom_crlf_swapped_corners(w: Work) -> list[str]:
    """A BOM/CRLF DeepForest CSV with one box whose corners are swapped (negative size): 2 of 3 boxes import."""
    text = (
        "image_path,xmin,ymin,xmax,ymax,label\nSIM_0001.JPG.tif,10,10,40,40,plant\n"
        "SIM_0001.JPG.tif,80,80,50,95,plant\nSIM_0002.JPG.tif,100,100,130,120,plant\n"
    )
    path = write(w.inputs / "trees.csv", text, bom=True, crlf=True)
    return args(w, w.copy(IMAGES, "images"), f"import_deepforest={path}")


def predictions_below_min_score(w: Work) -> list[str]:
    pred = json.loads((w.artifacts / "predictions.json").read_text())
    for p in pred["predictions"]:
        p["score"] = 0.3
    return args(w, w.copy(IMAGES, "images"), f"import_predictions={coco(w, pred, 'predictions.json')}")


def truncated_photo(w: Work) -> list[str]:
    images = w.copy("field/images", "photos")
    photo = images / "SIM_0004.JPG"
    photo.write_bytes(photo.read_bytes()[: photo.stat().st_size // 2])
    return args(w, images, f"import_coco={w.copy('field/truth/boxes_undistorted.json')}")


def voc_of_resized_photos(w: Work) -> list[str]:
    voc = w.inputs / "voc"
    t = truth(w)
    for im in t["images"][:2]:
        objects = "".join(
            f"<object><name>plant</name><bndbox><xmin>{x:.1f}</xmin><ymin>{y:.1f}</ymin>"
            f"<xmax>{x + bw:.1f}</xmax><ymax>{y + bh:.1f}</ymax></bndbox></object>"
            for x, y, bw, bh in (a["bbox"] for a in t["annotations"] if a["image_id"] == im["id"])
        )
        write(
            voc / (Path(im["file_name"]).stem + ".xml"),
            f"<annotation><filename>{im['file_name']}</filename><size><width>200</width><height>150</height>"
            f"<depth>3</depth></size>{objects}</annotation>",
        )
    return args(w, w.copy(IMAGES, "images"), f"import_voc={voc}")


def mask_of_other_size(w: Work) -> list[str]:
    import cv2

    masks = w.copy("field/truth/masks_undistorted", "masks")
    m = cv2.imread(str(masks / "SIM_0003.JPG.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(masks / "SIM_0003.JPG.png"), cv2.resize(m, (200, 150), interpolation=cv2.INTER_NEAREST))
    return args(w, w.copy(IMAGES, "images"), f"import_masks={masks}")


def damaged_session(w: Work) -> list[str]:
    a = args(w, w.copy(IMAGES, "images"), f"import_coco={w.copy('field/truth/boxes_undistorted.json')}")
    w.out.mkdir(parents=True)
    (w.out / "session.json").write_text('{"format": "matchplant-annotation-session", "images": {"SIM_0')
    return a


def output_is_image_folder(w: Work) -> list[str]:
    images = w.copy(IMAGES, "images")
    return [
        "--set",
        f"images={images}",
        "--set",
        f"output_dir={images}",
        "--set",
        f"import_coco={w.copy('field/truth/boxes_undistorted.json')}",
    ]


def output_is_labels_folder(w: Work) -> list[str]:
    labels = yolo_labels(w)
    return [
        "--set",
        f"images={w.copy(IMAGES, 'images')}",
        "--set",
        f"output_dir={labels}",
        "--set",
        f"import_yolo={labels}",
    ]


def nothing_to_export(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"))


CASES = [
    # must work: partly usable files import the rest, warn and list what was left out
    Case(
        "m4-coco-some-boxes-broken",
        "bbox_drawer",
        coco_some_boxes_broken,
        expect="ok",
        check=exports(
            339 - 6,
            {
                "zero or negative size": 2,
                "outside the image": 2,
                "unknown category id": 1,
                "bbox is not [x, y, w, h] numbers": 1,
                "duplicate box": 1,
            },
        ),
    ),
    Case(
        "m4-coco-duplicate-ids-different-boxes",
        "bbox_drawer",
        coco_duplicate_ids_different_boxes,
        expect="ok",
        check=exports_truth_boxes,
    ),
    Case(
        "m4-coco-some-images-missing",
        "bbox_drawer",
        coco_some_images_missing,
        expect="ok",
        check=exports(339 - 40 - 44, {"image not in the image folder": 40 + 44}),
    ),
    Case(
        "m4-coco-bom-crlf-unicode-junk",
        "bbox_drawer",
        coco_bom_crlf_unicode_junk,
        expect="ok",
        check=exports_truth_boxes,
    ),
    Case(
        "m4-coco-names-match-loosely", "bbox_drawer", coco_names_match_loosely, expect="ok", check=exports_truth_boxes
    ),
    Case("m4-yolo-bom-crlf-unicode", "bbox_drawer", yolo_bom_crlf, expect="ok", check=exports_truth_boxes),
    Case(
        "m4-yolo-one-value-out-of-range",
        "bbox_drawer",
        yolo_one_value_out_of_range,
        expect="ok",
        check=exports(339 - 2, {"YOLO value outside [0, 1]": 1, "zero or negative size": 1}),
    ),
    Case(
        "m4-yolo-label-for-no-image",
        "bbox_drawer",
        yolo_label_for_no_image,
        expect="ok",
        check=exports(339 - 40, {"label file matches no image": 40}),
    ),
    Case(
        "m4-deepforest-bom-crlf-swapped-corners",
        "bbox_drawer",
        deepforest_bom_crlf_swapped_corners,
        expect="ok",
        check=exports(2, {"zero or negative size": 1}),
    ),
    # errors
    Case(
        "m4-coco-other-photos",
        "bbox_drawer",
        coco_other_photos,
        mentions=("other_flight.json", "image folder"),
        outputs_allowed=("import_dropped.csv",),
    ),
    Case("m4-coco-resized-photos", "bbox_drawer", coco_resized_photos, mentions=("big.json", "800x600", "400x300")),
    Case("m4-coco-duplicate-image-ids", "bbox_drawer", coco_duplicate_image_ids, mentions=("boxes.json", "image id")),
    Case(
        "m4-coco-categories-off-by-one",
        "bbox_drawer",
        coco_categories_off_by_one,
        mentions=("zero_based.json", "unknown category"),
        outputs_allowed=("import_dropped.csv",),
    ),
    Case("m4-coco-no-categories", "bbox_drawer", coco_no_categories, mentions=("nocats.json", "categories")),
    Case("m4-coco-truncated", "bbox_drawer", coco_truncated, mentions=("cut.json", "truncated")),
    Case(
        "m4-coco-every-box-negative",
        "bbox_drawer",
        coco_every_box_negative,
        mentions=("flipped.json", "negative size"),
        outputs_allowed=("import_dropped.csv",),
    ),
    Case("m4-coco-without-boxes", "bbox_drawer", coco_without_boxes, mentions=("empty.json", "no boxes")),
    Case("m4-yolo-in-pixels", "bbox_drawer", yolo_in_pixels, mentions=("labels", "outside [0, 1]")),
    Case("m4-yolo-six-columns", "bbox_drawer", yolo_six_columns, mentions=("SIM_0006.JPG.txt", "line 3")),
    Case("m4-yolo-without-classes", "bbox_drawer", yolo_without_classes, mentions=("classes.txt",)),
    Case("m4-deepforest-text-coordinate", "bbox_drawer", deepforest_text_coordinate, mentions=("trees.csv", "line 3")),
    Case(
        "m4-predictions-below-min-score",
        "bbox_drawer",
        predictions_below_min_score,
        mentions=("predictions.json", "min_score"),
    ),
    Case("m4-voc-of-resized-photos", "bbox_drawer", voc_of_resized_photos, mentions=("voc", "200x150", "400x300")),
    Case("m4-mask-of-other-size", "bbox_drawer", mask_of_other_size, mentions=("SIM_0003.JPG.png", "200x150")),
    Case("m4-damaged-session", "bbox_drawer", damaged_session, mentions=("session.json",)),
    Case("m4-truncated-photo", "bbox_drawer", truncated_photo, mentions=("SIM_0004.JPG", "truncated")),
    Case("m4-output-is-image-folder", "bbox_drawer", output_is_image_folder, mentions=("output_dir", "images")),
    Case("m4-output-is-labels-folder", "bbox_drawer", output_is_labels_folder, mentions=("output_dir", "import_yolo")),
    Case("m4-nothing-to-export", "bbox_drawer", nothing_to_export, mentions=("no boxes", "session.json")),
]
