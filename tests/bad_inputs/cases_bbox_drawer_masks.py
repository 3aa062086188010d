"""Module 4 (bbox_drawer): masks and box files as other tools save them. Must work: anti-aliased binary masks
saved as GIF or JPEG (binary, not one object per grey level), colour instance masks (one RGB colour per plant),
a Label Studio COCO export whose image names carry its upload prefix and an extra suffix, DeepForest labels
mapped by ``label_map``. Errors: masks in a format that is not read (named for the suffix, not the names), two
masks for one photo, ``mask_threshold`` with ``mask_mode: instance``, imported labels that are not categories,
``label_map`` onto no category, two image names for one photo.

The reference is the tiny field's truth: its instance masks (``truth/masks_undistorted``, uint16 plant ids) and
boxes; binary masks are counted against the connected components of the clean mask (numpy/OpenCV over it).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from cases_bbox_drawer import IMAGES, args, coco, exported, exports_truth_boxes, truth
from harness import Case, Work
from PIL import Image

MASKS = "field/truth/masks_undistorted"
MIN_AREA = 20


def _instances(w: Work) -> dict[str, np.ndarray]:
    folder = w.artifacts / MASKS
    return {p.name[: -len(".png")]: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(folder.glob("*.png"))}


def _antialiased(ids: np.ndarray) -> np.ndarray:
    """The plants as a white-on-black mask drawn at 3x and reduced (anti-aliased edges, as resizing gives)."""
    h, w = ids.shape
    big = cv2.resize((ids > 0).astype(np.float32) * 255, (3 * w, 3 * h), interpolation=cv2.INTER_NEAREST)
    big = cv2.GaussianBlur(big, (5, 5), 1.2)  # soft edges at the fine scale
    return np.round(cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)).astype(np.uint8)


def _components(ids: np.ndarray) -> int:
    _n, _, stats, _ = cv2.connectedComponentsWithStats((ids > 0).astype(np.uint8), connectivity=8)
    return int((stats[1:, 4] >= MIN_AREA).sum())


def antialiased_masks(fmt: str):
    def prepare(w: Work) -> list[str]:
        folder = w.inputs / "masks"
        folder.mkdir()
        for photo, ids in _instances(w).items():
            m = _antialiased(ids)
            if fmt == "gif":
                Image.fromarray(m).save(folder / f"{Path(photo).stem}.gif")
            else:
                cv2.imwrite(str(folder / f"{Path(photo).stem}.jpg"), m, [cv2.IMWRITE_JPEG_QUALITY, 80])
        return args(w, w.copy(IMAGES, "images"), f"import_masks={folder}", f"mask_min_area={MIN_AREA}")

    return prepare


def counts_within_7_percent(w: Work) -> None:
    ds = exported(w)
    names = {im["id"]: im["file_name"] for im in ds["images"]}
    got: dict[str, int] = {}
    for a in ds["annotations"]:
        got[names[a["image_id"]]] = got.get(names[a["image_id"]], 0) + 1
    want = {f"{photo}.tif": _components(ids) for photo, ids in _instances(w).items()}
    total_got, total_want = sum(got.values()), sum(want.values())
    assert abs(total_got - total_want) <= 0.07 * total_want, (total_got, total_want)
    assert all(abs(got.get(k, 0) - v) <= max(2, 0.1 * v) for k, v in want.items()), (got, want)


def colour_masks(w: Work) -> list[str]:
    folder = w.inputs / "masks"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for photo, ids in _instances(w).items():
        palette = np.unique(rng.integers(30, 256, (int(ids.max()) + 50, 3)), axis=0)
        rng.shuffle(palette)
        palette = palette[: int(ids.max()) + 1].astype(np.uint8)
        palette[0] = 0
        cv2.imwrite(str(folder / f"{photo}.png"), palette[ids][..., ::-1])  # RGB written as OpenCV's BGR
    return args(w, w.copy(IMAGES, "images"), f"import_masks={folder}", "mask_min_area=1")


def one_box_per_plant(w: Work) -> None:
    ds = exported(w)
    names = {im["id"]: im["file_name"] for im in ds["images"]}
    got = sorted((names[a["image_id"]], *a["bbox"]) for a in ds["annotations"])
    want = []
    for photo, ids in _instances(w).items():  # numpy over the truth ids, one plant at a time
        for v in np.unique(ids[ids > 0]):
            rows, cols = np.nonzero(ids == v)
            want.append(
                (
                    f"{photo}.tif",
                    float(cols.min()),
                    float(rows.min()),
                    float(cols.max() + 1 - cols.min()),
                    float(rows.max() + 1 - rows.min()),
                )
            )
    assert got == sorted(want), (len(got), len(want))


def masks_as_npy(w: Work) -> list[str]:
    folder = w.inputs / "masks"
    folder.mkdir()
    for photo, ids in _instances(w).items():
        np.save(folder / f"{photo}.npy", ids)
    return args(w, w.copy(IMAGES, "images"), f"import_masks={folder}")


def two_masks_for_one_photo(w: Work) -> list[str]:
    masks = w.copy(MASKS, "masks")
    ids = cv2.imread(str(masks / "SIM_0004.JPG.png"), cv2.IMREAD_UNCHANGED)
    Image.fromarray((ids > 0).astype(np.uint8) * 255).save(masks / "SIM_0004.gif")
    return args(w, w.copy(IMAGES, "images"), f"import_masks={masks}")


def threshold_with_instance_mode(w: Work) -> list[str]:
    return args(
        w,
        w.copy(IMAGES, "images"),
        f"import_masks={w.copy(MASKS, 'masks')}",
        "mask_mode=instance",
        "mask_threshold=128",
    )


def large_ids(w: Work) -> list[str]:
    """The truth's instance masks with ids from 1001 (16-bit, as some tools number them): every id lies within
    4 % of the top value, which the mode test read as one binary foreground (touching plants merged)."""
    folder = w.inputs / "masks"
    folder.mkdir()
    for photo, ids in _instances(w).items():
        cv2.imwrite(str(folder / f"{photo}.png"), np.where(ids > 0, ids.astype(np.uint16) + 1000, 0).astype(np.uint16))
    return args(w, w.copy(IMAGES, "images"), f"import_masks={folder}", "mask_min_area=1")


def threshold_above_values(w: Work) -> list[str]:
    """Anti-aliased binary masks (values 0-255) with mask_threshold 300: no pixel reaches it."""
    folder = w.inputs / "masks"
    folder.mkdir()
    for photo, ids in _instances(w).items():
        cv2.imwrite(str(folder / f"{Path(photo).stem}.png"), _antialiased(ids))
    return args(w, w.copy(IMAGES, "images"), f"import_masks={folder}", "mask_threshold=300")


def deepforest_csv(w: Work, label: str = "Tree") -> Path:
    t = truth(w)
    names = {im["id"]: im["file_name"] for im in t["images"]}
    lines = ["image_path,xmin,ymin,xmax,ymax,label,scores"]
    for a in t["annotations"]:
        x, y, bw, bh = a["bbox"]
        lines.append(f"{names[a['image_id']]},{x},{y},{x + bw},{y + bh},{label},0.9")
    path = w.inputs / "deepforest.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def labels_not_categories(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), f"import_deepforest={deepforest_csv(w)}")


def labels_mapped(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), f"import_deepforest={deepforest_csv(w)}", "label_map={Tree: plant}")


def mapped_and_scored(w: Work) -> None:
    exports_truth_boxes(w)
    ds = exported(w)
    assert [c["name"] for c in ds["categories"]] == ["plant"] and {a["score"] for a in ds["annotations"]} == {0.9}


def label_map_onto_nothing(w: Work) -> list[str]:
    return args(w, w.copy(IMAGES, "images"), f"import_deepforest={deepforest_csv(w)}", "label_map={Tree: shrub}")


def label_studio_names(w: Work) -> list[str]:
    ds = truth(w)
    for k, im in enumerate(ds["images"]):
        photo = im["file_name"].removesuffix(".tif")
        im["file_name"] = f"images/{k:07x}a-{photo}.png"  # images/<8 hex>-SIM_0001.JPG.png
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'label_studio.json')}")


def two_names_one_photo(w: Work) -> list[str]:
    ds = truth(w)
    ds["images"][0]["file_name"] = "100MEDIA/" + ds["images"][1]["file_name"]
    ds["images"][1]["file_name"] = "101MEDIA/" + ds["images"][1]["file_name"]
    return args(w, w.copy(IMAGES, "images"), f"import_coco={coco(w, ds, 'two_folders.json')}")


CASES = [
    Case(
        "m4-masks-antialiased-gif", "bbox_drawer", antialiased_masks("gif"), expect="ok", check=counts_within_7_percent
    ),
    Case(
        "m4-masks-antialiased-jpeg",
        "bbox_drawer",
        antialiased_masks("jpeg"),
        expect="ok",
        check=counts_within_7_percent,
    ),
    Case("m4-masks-colour-instances", "bbox_drawer", colour_masks, expect="ok", check=one_box_per_plant),
    Case("m4-masks-npy", "bbox_drawer", masks_as_npy, mentions=("masks", ".npy", "png")),
    Case(
        "m4-masks-two-for-one-photo",
        "bbox_drawer",
        two_masks_for_one_photo,
        mentions=("SIM_0004.JPG", "SIM_0004.gif", "one mask per photo"),
    ),
    Case(
        "m4-mask-threshold-with-instance-mode",
        "bbox_drawer",
        threshold_with_instance_mode,
        mentions=("mask_threshold", "mask_mode"),
    ),
    Case("m4-masks-16bit-large-ids", "bbox_drawer", large_ids, expect="ok", check=one_box_per_plant),
    Case(
        "m4-mask-threshold-above-values",
        "bbox_drawer",
        threshold_above_values,
        mentions=("mask_threshold = 300", "255", "masks"),
    ),
    Case(
        "m4-deepforest-labels-not-categories",
        "bbox_drawer",
        labels_not_categories,
        mentions=("deepforest.csv", "'Tree' (339 boxes)", "label_map", "categories"),
    ),
    Case("m4-deepforest-labels-mapped", "bbox_drawer", labels_mapped, expect="ok", check=mapped_and_scored),
    Case("m4-label-map-onto-no-category", "bbox_drawer", label_map_onto_nothing, mentions=("label_map", "shrub")),
    Case(
        "m4-label-studio-prefix-and-suffix", "bbox_drawer", label_studio_names, expect="ok", check=exports_truth_boxes
    ),
    Case(
        "m4-two-image-names-one-photo",
        "bbox_drawer",
        two_names_one_photo,
        mentions=("two_folders.json", "more than one image", "101MEDIA"),
    ),
]
