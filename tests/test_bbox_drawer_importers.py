"""Module 4's importers: every format round-trips its shipped sample to COCO with exact boxes.

Samples in tests/data/importers (README there): DeepForest's real CSV and Pascal VOC of the same 61
tree crowns, CVAT XML, CVAT COCO and Label Studio COCO layouts of those boxes, an instance mask and a
binary mask. The reference is the DeepForest CSV read with the csv module (or the masks' pixels).
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.run import run
from matchplant.core.formats.masks import mask_boxes
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import InputError

DATA = Path(__file__).resolve().parent / "data" / "importers"


def _reference() -> list[list[float]]:
    with open(DATA / "OSBS_029.csv", newline="") as fh:
        return sorted([float(r[k]) for k in ("xmin", "ymin", "xmax", "ymax")] for r in csv.DictReader(fh))


@pytest.fixture
def photo(tmp_path) -> Path:
    d = tmp_path / "photos"
    d.mkdir()
    cv2.imwrite(str(d / "OSBS_029.tif"), np.zeros((400, 400, 3), np.uint8))
    return d


def _exported(photo: Path, out: Path, *sets: str) -> dict:
    cfg = load_config(
        BboxDrawerConfig,
        None,
        [
            f"images={photo}",
            f"output_dir={out}",
            "categories=[Tree]",
            "export_yolo=false",
            "include_unseen=true",
            *sets,
        ],
    )
    return json.loads(run(cfg)["coco"].read_text())


def _xyxy(ds: dict) -> list[list[float]]:
    return sorted([x, y, round(x + w, 2), round(y + h, 2)] for x, y, w, h in (a["bbox"] for a in ds["annotations"]))


@pytest.mark.parametrize(
    "key, sample",
    [
        ("import_deepforest", "OSBS_029.csv"),
        ("import_voc", "OSBS_029.xml"),
        ("import_cvat", "cvat_for_images_1.1.xml"),
        ("import_coco", "cvat_coco_1.0.json"),
        ("import_coco", "label_studio_coco.json"),
    ],
)
def test_box_formats_round_trip_to_coco_exactly(photo, tmp_path, key, sample):
    ds = _exported(photo, tmp_path / "out", f"{key}={DATA / sample}")
    assert _xyxy(ds) == _reference()  # all 61 boxes, to the pixel (the CVAT polygon skipped)
    assert [c["name"] for c in ds["categories"]] == ["Tree"] and ds["images"][0]["file_name"] == "OSBS_029.tif"


def test_voc_folder_and_deepforest_scores(photo, tmp_path):
    voc = tmp_path / "voc"
    voc.mkdir()
    shutil.copy(DATA / "OSBS_029.xml", voc)
    assert _xyxy(_exported(photo, tmp_path / "a", f"import_voc={voc}")) == _reference()
    scored = tmp_path / "pred.csv"
    scored.write_text("image_path,xmin,ymin,xmax,ymax,score,label\nOSBS_029.tif,1.5,2,30.25,40,0.61,Tree\n")
    ds = _exported(photo, tmp_path / "b", f"import_deepforest={scored}")
    assert _xyxy(ds) == [[1.5, 2.0, 30.25, 40.0]] and ds["annotations"][0]["score"] == 0.61


def test_instance_mask_gives_each_id_its_pixel_extent(photo, tmp_path):
    masks = tmp_path / "masks"
    masks.mkdir()
    shutil.copy(DATA / "OSBS_029_instances.png", masks / "OSBS_029.png")
    ids = cv2.imread(str(masks / "OSBS_029.png"), cv2.IMREAD_UNCHANGED)
    expected = []
    for v in np.unique(ids[ids > 0]):
        rows, cols = np.nonzero(ids == v)
        if len(rows) >= 10:  # the 6-pixel speck is dropped
            expected.append([float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)])
    ds = _exported(photo, tmp_path / "out", f"import_masks={masks}", "mask_min_area=10")
    assert _xyxy(ds) == sorted(expected) and len(expected) == 12
    assert all(b in _reference() for b in expected)  # the mask was filled from CSV boxes


def test_binary_mask_connected_components_with_minimum_area():
    m = cv2.imread(str(DATA / "binary_mask.png"), cv2.IMREAD_UNCHANGED)
    boxes = sorted(b.xyxy for b in mask_boxes(m, min_area=5))
    assert boxes == [[12.0, 10.0, 32.0, 30.0], [85.0, 45.0, 116.0, 76.0], [130.0, 90.0, 150.0, 110.0]]
    assert len(mask_boxes(m, min_area=1)) == 4  # the speck is a component of its own


def test_bad_import_files_are_clear_errors(photo, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("file,x,y\nOSBS_029.tif,1,2\n")
    with pytest.raises(InputError, match="lacks the column"):
        _exported(photo, tmp_path / "a", f"import_deepforest={bad}")
    broken = tmp_path / "broken.xml"
    broken.write_text(
        "<annotation><filename>OSBS_029.tif</filename><object><bndbox><xmin>x</xmin></bndbox></object></annotation>"
    )
    with pytest.raises(InputError, match="not a number"):
        _exported(photo, tmp_path / "b", f"import_voc={broken}")
    with pytest.raises(InputError, match="CVAT for images"):
        _exported(photo, tmp_path / "c", f"import_cvat={DATA / 'OSBS_029.xml'}")


def test_image_names_resolve_exactly_then_loosely_with_did_you_mean():
    from matchplant.core.formats.box_files import resolve_image_names

    files = ["SIM_0001.JPG.tif", "SIM_0002.JPG.tif", "IMG_7.png"]
    matched, unmatched = resolve_image_names(
        ["SIM_0001.JPG", "a/b/SIM_0002.JPG.tif", "3f2a1b7c-IMG_7.png", "sim_0001.jpg", "SIM_0003.JPG", "p0.png"], files
    )
    assert matched == {
        "SIM_0001.JPG": "SIM_0001.JPG.tif",
        "a/b/SIM_0002.JPG.tif": "SIM_0002.JPG.tif",
        "3f2a1b7c-IMG_7.png": "IMG_7.png",
        "sim_0001.jpg": "SIM_0001.JPG.tif",
    }
    assert unmatched["p0.png"] == "" and unmatched["SIM_0003.JPG"] in (
        "did you mean 'SIM_0001.JPG.tif'?",
        "did you mean 'SIM_0002.JPG.tif'?",
    )


def test_yolo_lines_left_out_are_listed_and_malformed_lines_are_errors(tmp_path):
    from matchplant.core.formats.coco import DropLog
    from matchplant.core.formats.yolo import read_yolo

    labels = tmp_path / "labels"
    labels.mkdir()
    (labels / "classes.txt").write_bytes(b"\xef\xbb\xbfplant\r\nweed\r\n")  # BOM + CRLF
    (labels / "a.txt").write_bytes(b"\xef\xbb\xbf1 0.5 0.5 0.2 0.2\r\n0 1.5 0.5 0.1 0.1\r\n0 0.5 0.5 0 0.1\r\n")
    (labels / "ghost.txt").write_text("0 0.5 0.5 0.1 0.1\n")
    drops = DropLog()
    classes, boxes = read_yolo(labels, {"a.png": (200, 100)}, drops)
    assert classes == ["plant", "weed"] and boxes == {"a.png": [([80.0, 40.0, 120.0, 60.0], "weed")]}
    assert [(r["where"], r["reason"]) for r in drops.rows] == [
        ("line 2", "YOLO value outside [0, 1]"),
        ("line 3", "zero or negative size"),
        ("line 1", "label file matches no image"),
    ]
    drops.write_csv(tmp_path / "dropped.csv")
    assert (tmp_path / "dropped.csv").read_text().count("\n") == 4
    (labels / "a.txt").write_text("0 0.5 0.5 0.2\n")
    with pytest.raises(InputError, match="line 1 has 4 values"):
        read_yolo(labels, {"a.png": (200, 100)})


DF = Path(__file__).resolve().parent / "data" / "deepforest-samples"


def _csv_boxes(path: Path, score: str | None = None) -> list[list[float]]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return sorted(
        [round(float(r[k]), 2) for k in ("xmin", "ymin", "xmax", "ymax")] + ([float(r[score])] if score else [])
        for r in rows
    )


def _blank(tmp_path: Path, name: str, size: int) -> Path:
    d = tmp_path / "photos"
    d.mkdir(exist_ok=True)
    cv2.imwrite(str(d / name), np.zeros((size, size, 3), np.uint8))
    return d


def test_deepforest_labels_must_be_categories_or_mapped_and_scores_are_read(tmp_path):
    """DeepForest's real CSVs: an older release's 'scores' and numeric label 0; 1.x's 'Tree' with geometry."""
    sjer = DF / "2018_SJER_3_252000_4107000_image_477.csv"
    photos = _blank(tmp_path, "2018_SJER_3_252000_4107000_image_477.tif", 400)
    with pytest.raises(InputError, match=r"label\(s\) '0' \(7 boxes\) are not among the categories \[plant\]") as e:
        _exported(photos, tmp_path / "a", f"import_deepforest={sjer}", "categories=[plant]")
    assert "label_map: {'0': plant}" in e.value.fix and not (tmp_path / "a" / "annotations.json").exists()
    ds = _exported(photos, tmp_path / "b", f"import_deepforest={sjer}", "categories=[plant]", "label_map={'0': plant}")
    got = sorted(
        [x, y, round(x + w, 2), round(y + h, 2), a["score"]] for a in ds["annotations"] for x, y, w, h in [a["bbox"]]
    )
    ref = _csv_boxes(sjer, "scores")
    assert [g[:4] for g in got] == [r[:4] for r in ref] and len(got) == 7
    assert [round(g[4], 4) for g in got] == [round(r[4], 4) for r in ref]
    assert [c["name"] for c in ds["categories"]] == ["plant"]  # no empty class, no new one
    truth = DF / "2018_SJER_3_252000_4107000_image_477_truth.csv"  # columns xmin,xmax,ymin,ymax
    ds = _exported(photos, tmp_path / "c", f"import_deepforest={truth}", "categories=[plant]", "label_map={'0': plant}")
    assert _xyxy(ds) == _csv_boxes(truth)

    blan = DF / "2019_BLAN_3_751000_4330000_image_crop_bbox.csv"
    photos = _blank(tmp_path, "2019_BLAN_3_751000_4330000_image_crop.jpg", 1024)
    with pytest.raises(InputError, match="'Tree' .* not among the categories"):
        _exported(photos, tmp_path / "d", f"import_deepforest={blan}", "categories=[plant]")
    ds = _exported(photos, tmp_path / "e", f"import_deepforest={blan}", "categories=[plant]", "label_map={Tree: plant}")
    assert _xyxy(ds) == _csv_boxes(blan) and all(0.9 < a["score"] < 1 for a in ds["annotations"])
    ds = _exported(photos, tmp_path / "f", f"import_deepforest={blan}", "categories=[tree]")  # up to case
    assert len(ds["annotations"]) == 4 and [c["name"] for c in ds["categories"]] == ["tree"]


def test_label_studio_and_cvat_names_match_the_photos(tmp_path, caplog):
    photos = tmp_path / "photos"
    photos.mkdir()
    for n in ("SIM_0001.JPG", "SIM_0002.JPG", "SIM_0003.JPG"):
        cv2.imwrite(str(photos / n), np.zeros((100, 120, 3), np.uint8))
    names = [
        "images/3f2a1b7c-SIM_0001.JPG.png",  # Label Studio: folder, upload prefix, extra suffix
        "/data/local-files/?d=field%20a/SIM_0002.JPG",  # Label Studio local storage, URL-encoded
        "task_7/job_1/SIM_0003.JPG",
    ]  # CVAT: the task's folders
    ds = {
        "images": [{"id": i, "file_name": n, "width": 120, "height": 100} for i, n in enumerate(names)],
        "categories": [{"id": 0, "name": "plant"}],
        "annotations": [{"id": i, "image_id": i, "category_id": 0, "bbox": [10 + i, 10, 20, 30]} for i in range(3)],
    }
    (tmp_path / "ls.json").write_text(json.dumps(ds))
    with caplog.at_level(logging.INFO, logger="matchplant"):
        out = _exported(photos, tmp_path / "a", f"import_coco={tmp_path / 'ls.json'}", "categories=[plant]")
    files = {im["id"]: im["file_name"] for im in out["images"]}
    assert sorted((files[a["image_id"]], a["bbox"][0]) for a in out["annotations"]) == [
        ("SIM_0001.JPG", 10),
        ("SIM_0002.JPG", 11),
        ("SIM_0003.JPG", 12),
    ]
    assert "matched 1 image name(s) by stripping Label Studio's upload prefix" in caplog.text
    assert "matched 2 image name(s) without the folder" in caplog.text
    assert "not added" not in caplog.text

    # two images of the file name one photo (DJI folders 100MEDIA, 101MEDIA): an error, nothing written
    ds["images"][0]["file_name"], ds["images"][1]["file_name"] = "100MEDIA/SIM_0001.JPG", "101MEDIA/SIM_0001.JPG"
    (tmp_path / "twice.json").write_text(json.dumps(ds))
    with pytest.raises(InputError, match="named by more than one image of the file, e.g. SIM_0001.JPG"):
        _exported(photos, tmp_path / "b", f"import_coco={tmp_path / 'twice.json'}", "categories=[plant]")
    # one name that fits two photos loosely
    cv2.imwrite(str(photos / "SIM_0003.png"), np.zeros((100, 120, 3), np.uint8))
    ds["images"][0]["file_name"], ds["images"][1]["file_name"] = "sim_0003.tif", "SIM_0002.JPG"
    (tmp_path / "loose.json").write_text(json.dumps(ds))
    with pytest.raises(InputError, match="fit more than one photo, e.g. 'sim_0003.tif'"):
        _exported(photos, tmp_path / "c", f"import_coco={tmp_path / 'loose.json'}", "categories=[plant]")
    assert not (tmp_path / "b" / "annotations.json").exists() and not (tmp_path / "c" / "annotations.json").exists()


def test_boxes_of_photos_module_3_did_not_select_are_info_not_a_warning(tmp_path, caplog):
    """Annotating module 3's selection with boxes made for the whole flight: the others are expected."""
    project = tmp_path / "odm"
    (project / "opensfm" / "undistorted" / "images").mkdir(parents=True)
    sel = tmp_path / "min_images"
    (sel / "images").mkdir(parents=True)
    for n in ("A.JPG", "B.JPG", "C.JPG"):
        cv2.imwrite(str(project / "opensfm" / "undistorted" / "images" / f"{n}.tif"), np.zeros((50, 60, 3), np.uint8))
    cv2.imwrite(str(sel / "images" / "A.JPG.tif"), np.zeros((50, 60, 3), np.uint8))
    (sel / "selected_images.csv").write_text("order,image,file\n1,A.JPG,A.JPG.tif\n")
    (sel / "selection.json").write_text(json.dumps({"project_dir": str(project), "selected": ["A.JPG"]}))
    ds = {
        "images": [{"id": i, "file_name": n} for i, n in enumerate(["A.JPG", "B.JPG", "C.JPG", "TYPO.JPG"])],
        "categories": [{"id": 1, "name": "plant"}],
        "annotations": [{"id": i, "image_id": i, "category_id": 1, "bbox": [1, 1, 5, 5]} for i in range(4)],
    }
    (tmp_path / "all.json").write_text(json.dumps(ds))
    with caplog.at_level(logging.INFO, logger="matchplant"):
        out = _exported(sel / "images", tmp_path / "out", f"import_coco={tmp_path / 'all.json'}", "categories=[plant]")
    assert len(out["annotations"]) == 1
    info = [r for r in caplog.records if "module 3 did not select" in r.getMessage()]
    assert (
        len(info) == 1
        and info[0].levelno == logging.INFO
        and "2 imported box(es) on 2 photo(s)" in info[0].getMessage()
    )
    warn = [r for r in caplog.records if r.levelno == logging.WARNING and "not added" in r.getMessage()]
    assert len(warn) == 1 and warn[0].getMessage().startswith("1 imported box(es) were not added (1 image not in")
    with open(tmp_path / "out" / "import_dropped.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted((r["image"], r["reason"]) for r in rows) == [
        ("B.JPG", "photo not in module 3's selection"),
        ("C.JPG", "photo not in module 3's selection"),
        ("TYPO.JPG", "image not in the image folder"),
    ]
