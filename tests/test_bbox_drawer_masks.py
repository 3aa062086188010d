"""Module 4's mask import on masks as real tools save them, against the label image they were made from.

A clean label image (ellipses, one id each, drawn at 3x and reduced) is the truth. From it: binary masks
anti-aliased by resizing (OpenCV INTER_AREA, PIL Lanczos), saved through JPEG and GIF; colour instance masks
(RGB, RGBA, palette PNG); a one-colour binary mask. Binary masks must give the true object count within 7 %,
colour instance masks exactly one box per plant at its pixel extent.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from PIL import Image

from matchplant.bbox_drawer.importers import read_mask_boxes
from matchplant.core.formats.masks import mask_objects, read_mask
from matchplant.core.runtime.errors import ConfigError, InputError

H, W, S = 300, 400, 3
MIN_AREA = 20


@pytest.fixture(scope="module")
def labels() -> np.ndarray:
    """A (3H, 3W) uint16 label image of separate ellipses (ids 1..N), the truth."""
    rng = np.random.default_rng(7)
    big = np.zeros((H * S, W * S), np.uint16)
    centres: list[tuple[float, float]] = []
    while len(centres) < 260:
        cx, cy = rng.uniform(10, W - 10), rng.uniform(10, H - 10)
        if centres and np.min(np.hypot(*(np.array(centres) - (cx, cy)).T)) < 15:
            continue
        centres.append((cx, cy))
        axes = (int(rng.uniform(4, 7) * S), int(rng.uniform(2.5, 4) * S))
        cv2.ellipse(big, (int(cx * S), int(cy * S)), axes, float(rng.uniform(0, 180)), 0, 360, len(centres), -1)
    return big


def _ids(labels: np.ndarray) -> np.ndarray:
    return cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)


def _binary_variants(labels: np.ndarray) -> dict[str, np.ndarray]:
    fg = (labels > 0).astype(np.float32) * 255
    area = np.round(cv2.resize(fg, (W, H), interpolation=cv2.INTER_AREA)).astype(np.uint8)
    lanczos = np.asarray(Image.fromarray((labels > 0).astype(np.uint8) * 255).resize((W, H), Image.LANCZOS))
    jpeg = cv2.imdecode(cv2.imencode(".jpg", area, [cv2.IMWRITE_JPEG_QUALITY, 75])[1], cv2.IMREAD_GRAYSCALE)
    return {"area": area, "lanczos": lanczos, "jpeg": jpeg}


def _truth_count(labels: np.ndarray) -> int:
    """Objects of at least MIN_AREA px at the photo's size (numpy over the clean label image)."""
    areas = np.bincount(labels.ravel())[1:] / (S * S)
    return int((areas >= MIN_AREA).sum())


def test_antialiased_binary_masks_are_binary_and_give_the_true_count(labels, tmp_path, caplog):
    truth = _truth_count(labels)
    masks = tmp_path / "masks"
    masks.mkdir()
    variants = _binary_variants(labels)
    cv2.imwrite(str(masks / "area.png"), variants["area"])
    cv2.imwrite(str(masks / "lanczos.png"), variants["lanczos"])
    cv2.imwrite(str(masks / "jpeg.jpg"), variants["area"], [cv2.IMWRITE_JPEG_QUALITY, 75])
    Image.fromarray(variants["area"]).save(masks / "gif.gif")  # GIF through PIL
    for path in masks.iterdir():
        assert len(np.unique(read_mask(path))) > 8  # anti-aliased: many grey levels
    names = ["area.JPG", "lanczos.JPG", "jpeg.JPG", "gif.JPG"]
    with caplog.at_level(logging.INFO, logger="matchplant"):
        out = read_mask_boxes(masks, names, MIN_AREA, sizes={n: (W, H) for n in names})
    assert sorted(out) == sorted(names)
    for name, boxes in out.items():
        assert abs(len(boxes) - truth) <= 0.07 * truth, (name, len(boxes), truth)
    assert "4 mask(s) read as binary (decided from the pixels" in caplog.text and "instance" not in caplog.text
    assert "peak at the same value" in caplog.text


def test_binary_boxes_match_the_objects_extent(labels):
    """Each box of the resized mask lies within 1 px of its object's box in the clean label image."""
    ids = labels
    m = _binary_variants(labels)["area"]
    got = np.array(sorted(b.xyxy for b in mask_objects(m, MIN_AREA).boxes))
    objs = [s for s in __import__("scipy.ndimage", fromlist=["find_objects"]).find_objects(ids) if s is not None]
    ref = np.array(sorted([s[1].start / S, s[0].start / S, s[1].stop / S, s[0].stop / S] for s in objs))
    # nearest reference box for each found box
    d = np.abs(got[:, None, :] - ref[None, :, :]).max(axis=2).min(axis=1)
    assert np.median(d) <= 1.0 and np.mean(d <= 1.5) >= 0.93


@pytest.mark.parametrize("layout", ["rgb", "rgba", "palette"])
def test_colour_instance_masks_give_one_box_per_plant(labels, tmp_path, layout, caplog):
    ids = _ids(labels)
    if layout == "palette":
        ids = np.where(ids <= 200, ids, 0)  # a palette holds at most 255 colours
    rng = np.random.default_rng(1)
    palette = np.unique(rng.integers(40, 256, (400, 3)), axis=0)[: ids.max() + 1].astype(np.uint8)
    palette[0] = 0
    rgb = palette[ids]
    path = tmp_path / "m" / "IMG_1.png"
    path.parent.mkdir()
    if layout == "rgb":
        Image.fromarray(rgb).save(path)
    elif layout == "rgba":
        Image.fromarray(np.dstack([rgb, np.where(ids > 0, 255, 0).astype(np.uint8)])).save(path)
    else:
        im = Image.fromarray(ids.astype(np.uint8), mode="L").convert("P")
        im.putpalette(palette.ravel().tolist() + [0] * (768 - palette.size))
        im.save(path)
    assert read_mask(path).ndim == 3  # read as its colours
    with caplog.at_level(logging.INFO, logger="matchplant"):
        boxes = read_mask_boxes(path.parent, ["IMG_1.JPG"], 1)["IMG_1.JPG"]
    assert "read as instance" in caplog.text and "one object per colour" in caplog.text
    ref = []
    for v in np.unique(ids[ids > 0]):  # numpy over the same pixels, one id at a time
        rows, cols = np.nonzero(ids == v)
        ref.append([float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)])
    assert sorted(b.xyxy for b in boxes) == sorted(ref)


def test_one_colour_masks_stay_binary(labels):
    m = _binary_variants(labels)["area"]
    white = np.dstack([m, m, m])
    green = np.dstack([m // 3, m, np.zeros_like(m)])
    n = len(mask_objects(m, MIN_AREA).boxes)
    for rgb in (white, green):
        got = mask_objects(rgb, MIN_AREA)
        assert got.mode == "binary" and len(got.boxes) == n


def test_grey_instance_ids_stay_instances(labels):
    ids = _ids(labels)
    got = mask_objects(ids, 1)
    assert got.mode == "instance" and len(got.boxes) == len(np.unique(ids[ids > 0]))
    few = np.zeros((50, 60), np.uint8)
    few[5:15, 5:15], few[20:30, 30:50] = 1, 7  # two plants, ids 1 and 7
    assert mask_objects(few).mode == "instance" and len(mask_objects(few).boxes) == 2


def test_instance_ids_near_the_top_value_stay_instances(labels, tmp_path, caplog):
    """Issue 39: 16-bit ids 1001-1040 all lie within 4 % of the top value; touching plants (ellipses overlapping
    their neighbours) then merged into one binary object. Read as instances: one box per id at its extent
    (numpy over each id); forced binary, the merge is warned about."""
    m = np.zeros((220, 420), np.uint16)
    for k in range(40):
        r, c = divmod(k, 10)
        cv2.ellipse(m, (20 + 40 * c, 25 + 50 * r), (24, 18), 0, 0, 360, 1001 + k, -1)
    want = []
    for v in range(1001, 1041):
        rows, cols = np.nonzero(m == v)
        want.append([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
    got = mask_objects(m, 1)
    assert got.mode == "instance" and "40 distinct values" in got.reason
    assert sorted(b.xyxy for b in got.boxes) == sorted(map(lambda b: [float(x) for x in b], want))
    assert _blobs_of(m) == 4  # the binary reading: 4 rows of touching plants
    forced = mask_objects(m, 1, mode="binary")
    assert len(forced.boxes) == 4 and any("40 distinct values" in w and "merges" in w for w in forced.warnings)
    # the 260 separate ids of the fixture moved to 1001-1260 (16-bit): one box per id, as ids 1-260
    ids = _ids(labels)
    high = np.where(ids > 0, ids + 1000, 0).astype(np.uint16)
    assert mask_objects(high, 1).mode == "instance"
    assert [b.xyxy for b in mask_objects(high, 1).boxes] == [b.xyxy for b in mask_objects(ids, 1).boxes]
    # through the importer: the mode and why are logged
    (tmp_path / "m").mkdir()
    cv2.imwrite(str(tmp_path / "m" / "a.png"), m)
    with caplog.at_level(logging.INFO, logger="matchplant"):
        boxes = read_mask_boxes(tmp_path / "m", ["a.JPG"], 1)
    assert len(boxes["a.JPG"]) == 40 and "read as instance" in caplog.text and "1001-1040" in caplog.text


def _blobs_of(m: np.ndarray) -> int:
    return cv2.connectedComponents((m > 0).astype(np.uint8), connectivity=8)[0] - 1


def test_a_threshold_above_the_masks_values_names_the_key(labels, tmp_path, caplog):
    """mask_threshold above every value of the masks: a ConfigError naming the key, the values and the fix
    (was: "the file holds no boxes"); above the values of some masks only: a warning naming them."""
    m = _binary_variants(labels)["area"]
    (tmp_path / "k").mkdir()
    cv2.imwrite(str(tmp_path / "k" / "a.png"), m)
    with pytest.raises(ConfigError) as e:
        read_mask_boxes(tmp_path / "k", ["a.JPG"], 1, threshold=300)
    text = str(e.value)
    assert "mask_threshold = 300" in text and "reach 255" in text and "a.png" in text and "remove it" in text
    cv2.imwrite(str(tmp_path / "k" / "b.png"), (m // 2))  # values up to 127
    with caplog.at_level(logging.WARNING, logger="matchplant"):
        boxes = read_mask_boxes(tmp_path / "k", ["a.JPG", "b.JPG"], 1, threshold=200)
    assert len(boxes["a.JPG"]) > 100 and not boxes["b.JPG"]
    assert "mask_threshold = 200 is above every value of 1 mask(s) (b.png" in caplog.text


def test_mode_and_threshold_overrule_and_warnings(labels, tmp_path, caplog):
    m = _binary_variants(labels)["area"]
    forced = mask_objects(m, 1, mode="instance")
    assert forced.mode == "instance" and any("separate pieces" in w for w in forced.warnings)
    assert any("span more than" in w for w in forced.warnings)
    high = mask_objects(m, MIN_AREA, threshold=250)  # a high cut: smaller objects
    auto = mask_objects(m, MIN_AREA)
    assert high.mode == "binary" and high.threshold == 250 and auto.threshold == 127.5
    area_high = sum((b.xyxy[2] - b.xyxy[0]) * (b.xyxy[3] - b.xyxy[1]) for b in high.boxes)
    area_auto = sum((b.xyxy[2] - b.xyxy[0]) * (b.xyxy[3] - b.xyxy[1]) for b in auto.boxes)
    assert area_high < area_auto
    # specks dropped by mask_min_area are counted (numpy: components under the minimum)
    n_all = len(mask_objects(m, 1).boxes)
    big = mask_objects(m, 60)
    assert big.dropped == n_all - len(big.boxes) > 0
    (tmp_path / "k").mkdir()
    cv2.imwrite(str(tmp_path / "k" / "a.png"), m)
    with caplog.at_level(logging.INFO, logger="matchplant"):
        read_mask_boxes(tmp_path / "k", ["a.JPG"], 60)
    assert f"mask_min_area 60: {big.dropped} of the {n_all} mask object(s) were smaller" in caplog.text


def test_mask_names_and_formats(tmp_path):
    d = tmp_path / "masks"
    d.mkdir()
    m = np.zeros((20, 30), np.uint8)
    m[2:8, 3:9] = 255
    (d / "IMG_1.npy").write_bytes(b"\x93NUMPY")  # named after the photo, but no image
    with pytest.raises(InputError, match=r"\.npy files .*not read as images.*GIF"):
        read_mask_boxes(d, ["IMG_1.JPG"])
    Image.fromarray(m).save(d / "3f2a1b7c-IMG_2.JPG_mask.gif")  # upload prefix, photo extension, _mask, GIF
    cv2.imwrite(str(d / "IMG_3.png"), m)
    cv2.imwrite(str(d / "img_3.tif"), m)
    out = read_mask_boxes(d, ["IMG_2.JPG"], 1)
    assert out["IMG_2.JPG"][0].xyxy == [3.0, 2.0, 9.0, 8.0]
    with pytest.raises(InputError, match="2 masks fit the photo IMG_3.JPG"):
        read_mask_boxes(d, ["IMG_3.JPG"])
    with pytest.raises(InputError, match="no mask is named after any of the 1 photos"):
        read_mask_boxes(d, ["OTHER.JPG"])
