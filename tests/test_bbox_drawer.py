"""Module 4 (bbox_drawer): the annotation store, its GUI driven by synthesised events, crash resume,
imports and the COCO/YOLO exports."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.run import open_session, run
from matchplant.bbox_drawer.store import AnnotationStore
from matchplant.core.formats.coco import (
    make_annotation,
    new_dataset,
    validate_dataset,
    write_dataset,
)
from matchplant.core.formats.predictions import write_predictions
from matchplant.core.formats.yolo import read_yolo, yolo_to_coco
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def _write_png(path: Path, w: int, h: int, seed: int = 0) -> None:
    import cv2

    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))


@pytest.fixture
def photos(tmp_path) -> Path:
    """Two images plus files that must be ignored: a text file, a hidden image, junk of Windows and macOS."""
    d = tmp_path / "photos"
    d.mkdir()
    _write_png(d / "a.png", 200, 150, 1)
    _write_png(d / "b.png", 160, 120, 2)
    _write_png(d / ".hidden.png", 50, 50, 3)
    (d / "notes.txt").write_text("not an image")
    (d / "Thumbs.db").write_bytes(b"\x00junk")
    (d / "._a.png").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (d / "sub").mkdir()
    return d


def _gui(store):
    from matchplant.bbox_drawer.gui import BboxDrawerGUI

    return BboxDrawerGUI(store, headless=True, dpi=60)  # small: every synthesised event redraws the figure


def _xyxy(store, name):
    return [b["xyxy"] for b in store.boxes(name)]


# -- folder -------------------------------------------------------------------------------------------------


def test_folder_config_loads_and_help_works():
    cfg = load_config(BboxDrawerConfig, ROOT / "4_bbox_drawer" / "config.yaml", strict=False)
    assert cfg.categories == ["plant"] and cfg.images is None
    r = subprocess.run(
        [sys.executable, str(ROOT / "4_bbox_drawer" / "bbox_drawer.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--gui" in r.stdout


def test_non_images_ignored(photos, tmp_path):
    store = AnnotationStore(photos, tmp_path / "out")
    assert store.images == ["a.png", "b.png"]
    with pytest.raises(InputError, match="no images"):
        AnnotationStore(photos / "sub", tmp_path / "out2")
    # a file named like an image that is not a whole one is named, not skipped or shown half grey
    (photos / "broken.jpg").write_bytes(b"this is no jpeg")
    with pytest.raises(InputError, match="broken.jpg"):
        AnnotationStore(photos, tmp_path / "out3")


# -- the GUI, headless -----------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.gui
def test_gui_events_make_exactly_the_expected_boxes(photos, tmp_path):
    import gui_events

    class ge:  # the events of gui_events, with short drags (each event redraws the figure)
        mouse, click, key = gui_events.mouse, gui_events.click, gui_events.key
        drag = staticmethod(lambda *a: gui_events.drag(*a, steps=1))

    store = AnnotationStore(photos, tmp_path / "out", ["plant", "weed"])
    g = _gui(store)
    fig, ax = g.fig, g.ax
    assert store.current == "a.png"
    ge.drag(fig, ax, 20, 30, 60, 80)  # draw
    assert _xyxy(store, "a.png") == [[20, 30, 60, 80]]
    ge.drag(fig, ax, 150, 100, 260, 190)  # dragged past the image edge: clipped
    assert _xyxy(store, "a.png")[1] == [150, 100, 200, 150]
    ge.click(fig, ax, 100, 20)  # click without drag on empty image: no box
    assert len(store.boxes("a.png")) == 2 and g.selected is None
    ge.click(fig, ax, 40, 50)  # click on a box selects it
    assert g.selected == 1
    ge.drag(fig, ax, 40, 50, 50, 55)  # move it by (10, 5)
    assert _xyxy(store, "a.png")[0] == [30, 35, 70, 85]
    ge.drag(fig, ax, 70, 85, 75, 100)  # drag its bottom-right corner: resize
    assert _xyxy(store, "a.png")[0] == [30, 35, 75, 100]
    ge.drag(fig, ax, 50, 35, 50, 20)  # drag its top edge up: resize top only
    assert _xyxy(store, "a.png")[0] == [30, 20, 75, 100]
    ge.key(fig, "2")  # category of the selected box
    assert store.boxes("a.png")[0]["category_id"] == 2
    ge.key(fig, "ctrl+z")
    assert store.boxes("a.png")[0]["category_id"] == 1
    ge.key(fig, "ctrl+y")
    assert store.boxes("a.png")[0]["category_id"] == 2
    ge.click(fig, ax, 180, 130)  # select the clipped box and delete it
    ge.key(fig, "delete")
    assert _xyxy(store, "a.png") == [[30, 20, 75, 100]]
    ge.key(fig, "z")  # undo the delete
    assert _xyxy(store, "a.png")[1] == [150, 100, 200, 150]
    # new boxes take the current category (2 was chosen above)
    ge.drag(fig, ax, 100, 10, 120, 25)
    assert store.boxes("a.png")[-1]["category_id"] == 2 and _xyxy(store, "a.png")[-1] == [100, 10, 120, 25]

    # zoom and pan: the wheel zooms around the cursor, keys pan and reset
    ge.mouse(fig, ax, "scroll_event", 100, 75, step=1)
    x0, x1 = ax.get_xlim()
    assert x1 - x0 == pytest.approx(200 / 1.25) and (x0 + x1) / 2 == pytest.approx(100, abs=0.5)
    ge.key(fig, "right")
    assert ax.get_xlim()[0] > x0
    ge.drag(fig, ax, 100, 60, 104, 64)  # zoomed in: still exact image pixels
    assert _xyxy(store, "a.png")[-1] == [100, 60, 104, 64]
    ge.key(fig, "0")
    assert ax.get_xlim() == (0, 200)

    # next and previous image
    assert "box added" in g.status.get_text()
    ge.key(fig, "n")
    assert store.current == "b.png" and ax.get_xlim() == (0, 160)
    assert "box added" not in g.status.get_text()  # what happened on a.png is not said on b.png
    ge.drag(fig, ax, 10, 10, 30, 40)
    assert _xyxy(store, "b.png") == [[10, 10, 30, 40]]
    ge.key(fig, "p")
    assert store.current == "a.png"
    ge.key(fig, "h")  # help panel toggles
    assert not g.help_ax.get_visible()
    ge.key(fig, "e")  # export now
    ds = json.loads((tmp_path / "out" / "annotations.json").read_text())
    assert len(ds["annotations"]) == 5 and not validate_dataset(ds)


@pytest.mark.gui
def test_gui_shows_owned_area(photos, tmp_path):
    from matchplant.bbox_drawer.gui import BboxDrawerGUI
    from matchplant.core.formats.owned_areas import read_owned_areas

    owned = tmp_path / "owned.json"
    owned.write_text(json.dumps({"a.png": [[10, 10], [190, 10], [190, 140], [10, 140]]}))
    g = BboxDrawerGUI(AnnotationStore(photos, tmp_path / "out"), read_owned_areas(owned), headless=True)
    polys = [p for p in g.ax.patches if type(p).__name__ == "Polygon"]
    assert len(polys) == 1 and np.allclose(polys[0].get_xy()[:4], [[10, 10], [190, 10], [190, 140], [10, 140]])


@pytest.mark.gui
def test_category_keys_choose_the_next_box_and_relabel_only_a_clicked_box(photos, tmp_path):
    """Issue 17: a category key pressed right after drawing a box sets the NEXT box's category and leaves the
    box just drawn alone (also after fixing its corner); a box the user clicked, or pressed to drag, is relabelled."""
    import gui_events as ge

    store = AnnotationStore(photos, tmp_path / "out", ["plant", "weed", "soil"])
    g = _gui(store)
    fig, ax = g.fig, g.ax

    def cats():
        return [b["category_id"] for b in store.boxes("a.png")]

    ge.drag(fig, ax, 20, 30, 60, 80, steps=1)  # box 1, drawn as plant
    assert g.selected == 1  # it keeps its handles, to fix it at once
    ge.key(fig, "2")
    assert cats() == [1] and g.category == 2 and "next box: 2=weed" in g.status.get_text()
    ge.drag(fig, ax, 60, 80, 70, 90, steps=1)  # its corner dragged: resized, still not relabelled
    assert _xyxy(store, "a.png") == [[20, 30, 70, 90]]
    ge.key(fig, "3")
    assert cats() == [1]
    ge.drag(fig, ax, 100, 20, 140, 60, steps=1)  # box 2 takes the category chosen: soil
    ge.key(fig, "2")
    ge.drag(fig, ax, 150, 100, 180, 140, steps=1)  # box 3: weed; box 2 was not relabelled
    assert cats() == [1, 3, 2]
    assert store.undo() == "a.png" and cats() == [1, 3]  # the last edit was drawing box 3: no relabel in between
    assert store.redo() == "a.png" and cats() == [1, 3, 2]
    ge.click(fig, ax, 40, 50)  # click box 1: picked, the keys relabel it
    ge.key(fig, "3")
    assert cats() == [3, 3, 2] and "keys relabel it" in g.status.get_text()
    ge.key(fig, "1")
    assert cats() == [1, 3, 2]
    ge.drag(fig, ax, 120, 40, 125, 45, steps=1)  # press box 2 (not selected) and drag it: picked too
    assert _xyxy(store, "a.png")[1] == [105, 25, 145, 65]
    ge.key(fig, "2")
    assert cats() == [1, 2, 2]
    ge.key(fig, "escape")  # nothing selected: the key only sets the next box
    ge.key(fig, "3")
    assert cats() == [1, 2, 2] and g.category == 3
    ge.key(fig, "n")  # another image: nothing picked there
    ge.drag(fig, ax, 10, 10, 30, 40, steps=1)
    ge.key(fig, "1")
    assert [b["category_id"] for b in store.boxes("b.png")] == [3]
    ge.key(fig, "q")  # headless: exported (no window to close)
    ds = json.loads((tmp_path / "out" / "annotations.json").read_text())
    names = {c["id"]: c["name"] for c in ds["categories"]}
    files = {im["id"]: im["file_name"] for im in ds["images"]}
    got = sorted((files[a["image_id"]], names[a["category_id"]]) for a in ds["annotations"])
    assert got == [("a.png", "plant"), ("a.png", "weed"), ("a.png", "weed"), ("b.png", "soil")]


# -- never lose work ---------------------------------------------------------------------------------------------


KILLED = textwrap.dedent("""
    import sys
    sys.path.insert(0, {tests!r})
    import gui_events as ge
    from matchplant.bbox_drawer.store import AnnotationStore
    from matchplant.bbox_drawer.gui import BboxDrawerGUI
    g = BboxDrawerGUI(AnnotationStore({photos!r}, {out!r}), headless=True, dpi=60)
    i = 0
    while True:                       # draw boxes until killed; report each one once the GUI returns
        x, y = 16 * (i % 12) + 1, 30 * (i // 12 % 5) + 1
        ge.drag(g.fig, g.ax, x, y, x + 10, y + 20, steps=1)
        print(i, flush=True)
        i += 1
""")


@pytest.mark.slow
def test_killed_session_resumes_with_every_saved_edit(photos, tmp_path):
    out = tmp_path / "out"
    code = KILLED.format(tests=str(TESTS), photos=str(photos), out=str(out))
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=dict(os.environ, MPLBACKEND="Agg")
    )
    done = []
    for line in proc.stdout:
        done.append(int(line))
        if len(done) >= 6:
            break
    os.kill(proc.pid, signal.SIGKILL)  # no clean shutdown
    proc.wait()
    store = AnnotationStore(photos, out)  # resume
    boxes = _xyxy(store, "a.png")
    expected = [
        [16 * (i % 12) + 1, 30 * (i // 12) + 1, 16 * (i % 12) + 11, 30 * (i // 12) + 21] for i in range(len(boxes))
    ]
    assert len(boxes) >= len(done) and boxes == expected  # every reported edit, nothing half-written
    assert store.undo() == "a.png" and len(store.boxes("a.png")) == len(boxes) - 1  # history survived too


def test_store_edits_undo_redo_and_reopen(photos, tmp_path):
    store = AnnotationStore(photos, tmp_path / "out", ["plant"])
    a = store.add("b.png", [30, 40, 10, 5])  # corners in any order
    assert store.box("b.png", a)["xyxy"] == [10, 5, 30, 40]
    assert store.add("b.png", [10, 10, 11, 30]) is None  # thinner than min_box_size
    store.move("b.png", a, 500, -3)  # stops at the right edge
    assert store.box("b.png", a)["xyxy"] == [140, 2, 160, 37]
    store.resize("b.png", a, [100, 2, 170, 37])
    assert store.box("b.png", a)["xyxy"] == [100, 2, 160, 37]
    with pytest.raises(ConfigError, match="category 3"):
        store.set_category("b.png", a, 3)
    store.delete("b.png", a)
    again = AnnotationStore(photos, tmp_path / "out", ["plant"])
    assert again.boxes("b.png") == []
    assert again.undo() == "b.png" and again.box("b.png", a)["xyxy"] == [100, 2, 160, 37]
    again.undo()
    again.redo()
    assert again.box("b.png", a)["xyxy"] == [100, 2, 160, 37]
    assert again.current == "a.png"


# -- imports and exports -------------------------------------------------------------------------------------


def test_coco_yolo_coco_is_lossless(photos, tmp_path):
    store = AnnotationStore(photos, tmp_path / "out", ["plant", "weed"])
    rng = np.random.default_rng(5)
    for name in ("a.png", "b.png"):
        w, h = store.size(name)
        for _ in range(7):
            x, y = rng.uniform(0, w - 30), rng.uniform(0, h - 30)
            store.add(name, [x, y, x + rng.uniform(3, 30), y + rng.uniform(3, 30)], int(rng.integers(1, 3)))
    store.add("a.png", [0, 0, 200, 150])  # the whole image
    paths = store.export(coco=True, yolo=True)
    coco = json.loads(paths["coco"].read_text())
    assert not validate_dataset(coco, tolerance=0)
    assert len({a["id"] for a in coco["annotations"]}) == 15
    for a in coco["annotations"]:
        assert a["area"] == pytest.approx(a["bbox"][2] * a["bbox"][3]) and a["iscrowd"] == 0
    assert (paths["yolo"] / "classes.txt").read_text() == "plant\nweed\n"
    back = yolo_to_coco(paths["yolo"], {im["file_name"]: (im["width"], im["height"]) for im in coco["images"]})
    assert [c["name"] for c in back["categories"]] == ["plant", "weed"]
    assert len(back["annotations"]) == len(coco["annotations"])
    for a, b in zip(coco["annotations"], back["annotations"]):
        assert a["image_id"] == b["image_id"] and a["category_id"] == b["category_id"]
        assert np.allclose(a["bbox"], b["bbox"], atol=1e-5)


def test_imports_coco_yolo_and_predictions(photos, tmp_path):
    # module 7 predictions on two overlapping tiles of a.png: one plant seen twice, one low score
    images = [
        {"id": 1, "file_name": "a_0_0.png", "width": 128, "height": 128, "source_image": "a.png", "x0": 0, "y0": 0},
        {"id": 2, "file_name": "a_72_0.png", "width": 128, "height": 128, "source_image": "a.png", "x0": 72, "y0": 0},
    ]
    preds = [
        {"image_id": 1, "category_id": 1, "bbox": [90, 20, 20, 30], "score": 0.9},
        {"image_id": 2, "category_id": 1, "bbox": [18.5, 20, 20, 30], "score": 0.8},  # same plant
        {"image_id": 2, "category_id": 1, "bbox": [80, 80, 20, 20], "score": 0.2},
    ]  # below min_score
    write_predictions(tmp_path / "pred.json", images, [{"id": 1, "name": "plant"}], preds)
    cfg = load_config(
        BboxDrawerConfig,
        None,
        [f"images={photos}", f"output_dir={tmp_path / 'out'}", f"import_predictions={tmp_path / 'pred.json'}"],
    )
    store = open_session(cfg)
    assert _xyxy(store, "a.png") == [[90, 20, 110, 50]] and store.boxes("a.png")[0]["score"] == 0.9
    assert open_session(cfg).count() == 1  # reopening does not import twice

    # a COCO dataset and YOLO labels, into a fresh session
    ds = new_dataset(["plant"])
    ds["images"] = [{"id": 1, "file_name": "photos/b.png", "width": 160, "height": 120}]
    ds["annotations"] = [make_annotation(1, 1, [5.5, 6, 20, 10])]
    write_dataset(tmp_path / "in.json", ds)
    yolo = tmp_path / "yolo"
    yolo.mkdir()
    (yolo / "classes.txt").write_text("plant\nweed\n")
    (yolo / "a.txt").write_text("1 0.5 0.5 0.1 0.2\n")
    cfg2 = load_config(
        BboxDrawerConfig,
        None,
        [
            f"images={photos}",
            f"output_dir={tmp_path / 'out2'}",
            f"import_coco={tmp_path / 'in.json'}",
            f"import_yolo={yolo}",
            "categories=[plant, weed]",
        ],
    )  # an import's labels must be categories
    store2 = open_session(cfg2)
    assert _xyxy(store2, "b.png") == [[5.5, 6, 25.5, 16]]
    assert _xyxy(store2, "a.png") == [[90, 60, 110, 90]] and store2.categories == ["plant", "weed"]
    assert store2.boxes("a.png")[0]["category_id"] == 2
    (yolo / "a.txt").write_text("7 0.5 0.5 0.1 0.2\n")
    with pytest.raises(InputError, match="line 1"):
        read_yolo(yolo, {"a.png": (200, 150)})


@pytest.fixture
def console_cleanup():
    """The CLI binds a console handler to the (captured) stderr of the test; remove it afterwards."""
    yield
    from matchplant.core.runtime.log import get_logger

    logger = get_logger()
    for h in list(logger.handlers):
        if getattr(h, "_matchplant_console", False):
            logger.removeHandler(h)


def test_cli_run_exports_and_bad_input_is_a_clear_error(photos, tmp_path, capsys, console_cleanup):
    from matchplant.cli import run_module

    out = tmp_path / "out"
    store = AnnotationStore(photos, out)
    store.add("a.png", [1, 2, 30, 40])
    assert run_module("bbox_drawer", ["--set", f"images={photos}", "--set", f"output_dir={out}", "--quiet"]) == 0
    ds = json.loads((out / "annotations.json").read_text())
    assert [a["bbox"] for a in ds["annotations"]] == [[1, 2, 29, 38]]
    assert (out / "yolo" / "a.txt").read_text() == "0 0.07750000 0.14000000 0.14500000 0.25333333\n"
    rc = run_module(
        "bbox_drawer", ["--set", f"images={photos}", "--set", f"output_dir={out}", "--set", "categories=[a,b,c,d,e,f]"]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "categories" in err and "Traceback" not in err
    (tmp_path / "bad.json").write_text("{not json")
    rc = run_module(
        "bbox_drawer",
        ["--set", f"images={photos}", "--set", f"output_dir={out}", "--set", f"import_coco={tmp_path / 'bad.json'}"],
    )
    err = capsys.readouterr().err
    assert rc == 2 and "bad.json" in err and "not valid JSON" in err


def test_tiny_field_truth_round_trip(tiny_field, tmp_path):
    """The synthetic field's undistorted truth boxes imported, exported, and equal to the truth."""
    truth = json.loads(tiny_field.boxes_undistorted.read_text())
    cfg = load_config(
        BboxDrawerConfig,
        None,
        [
            f"images={tiny_field.undistorted_images}",
            f"output_dir={tmp_path / 'out'}",
            f"import_coco={tiny_field.boxes_undistorted}",
            "include_unseen=true",
        ],
    )
    out = run(cfg)
    ds = json.loads(out["coco"].read_text())
    want = {}
    ids = {im["id"]: im["file_name"] for im in truth["images"]}
    for a in truth["annotations"]:
        want.setdefault(Path(ids[a["image_id"]]).name, []).append(a["bbox"])
    got = {}
    ids = {im["id"]: im["file_name"] for im in ds["images"]}
    for a in ds["annotations"]:
        got.setdefault(ids[a["image_id"]], []).append(a["bbox"])
    assert set(got) == set(want)
    for name in want:
        g, w = np.array(got[name]), np.array(want[name])
        assert len(g) == len(w)
        nearest = np.abs(w[:, None, :] - g[None, :, :]).max(axis=2).min(axis=1)
        assert nearest.max() <= 0.011  # x, y and x2, y2 are kept to 0.01 px


# -- a real window -------------------------------------------------------------------------------------------


XVFB = textwrap.dedent("""
    import sys, json
    sys.path.insert(0, {tests!r})
    import matplotlib
    import matplotlib.pyplot as plt
    import gui_events as ge
    from matchplant.bbox_drawer.store import AnnotationStore
    from matchplant.bbox_drawer.gui import BboxDrawerGUI
    store = AnnotationStore({photos!r}, {out!r})
    g = BboxDrawerGUI(store, headless=False)
    def act():
        ge.drag(g.fig, g.ax, 20, 30, 60, 80)
        ge.key(g.fig, "n")
        ge.drag(g.fig, g.ax, 5, 5, 25, 45)
        g.fig.canvas.draw()
        g.fig.canvas.flush_events()
        ge.key(g.fig, "q")
    timer = g.fig.canvas.new_timer(interval=300)
    timer.single_shot = True
    timer.add_callback(act)
    timer.start()
    plt.show()
    print("BACKEND", matplotlib.get_backend())
    print("BOXES", json.dumps({{n: [b["xyxy"] for b in store.boxes(n)] for n in store.images}}))
""")


@pytest.mark.gui
def test_gui_in_a_real_window(photos, tmp_path):
    from conftest import run_in_xvfb, xvfb_available

    if not xvfb_available():
        pytest.skip("Xvfb is not installed")
    r = run_in_xvfb(XVFB.format(tests=str(TESTS), photos=str(photos), out=str(tmp_path / "out")), timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "backend tkagg" in r.stdout.lower()
    boxes = json.loads(r.stdout.split("BOXES", 1)[1])
    assert boxes == {"a.png": [[20, 30, 60, 80]], "b.png": [[5, 5, 25, 45]]}
    assert (tmp_path / "out" / "annotations.json").is_file()  # exported when the window closed


# -- real size ----------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.gui
def test_gui_on_a_20_megapixel_photo_with_3000_boxes(tmp_path):
    """A 5472 x 3648 photo with 3,000 boxes: the whole photo is shown from a reduced pyramid level and
    one box collection, a drag redraws only the dragged outline (no full redraw per mouse move), and
    every edit lands exactly. Timings are measured by bench/bench_bbox_drawer_gui.py."""
    import cv2
    import gui_events as ge
    from matplotlib.backend_bases import MouseEvent

    from matchplant.bbox_drawer.gui import BboxDrawerGUI
    from matchplant.bbox_drawer.store import ImportedBox

    W, H = 5472, 3648
    rng = np.random.default_rng(0)
    d = tmp_path / "photos"
    d.mkdir()
    small = rng.integers(0, 255, (H // 16, W // 16, 3), dtype=np.uint8)
    cv2.imwrite(str(d / "big.jpg"), cv2.resize(small, (W, H), interpolation=cv2.INTER_NEAREST))
    xy = np.stack([rng.uniform(0, W - 60, 4000), rng.uniform(0, H - 60, 4000)], 1).round()
    xy = xy[~((xy[:, 0] > 900) & (xy[:, 0] < 1600) & (xy[:, 1] > 900) & (xy[:, 1] < 1500))][:3000]  # free ground
    boxes = [[x, y, x + 30 + i % 30, y + 20 + i % 40] for i, (x, y) in enumerate(xy.tolist())]
    store = AnnotationStore(d, tmp_path / "out")
    assert store.import_boxes({"big.jpg": [ImportedBox(b, "plant") for b in boxes]}, "synthetic") == 3000
    g = BboxDrawerGUI(store, headless=True, dpi=100)
    fig, ax = g.fig, g.ax
    fig.canvas.draw()
    assert g.image_artist.shown_level >= 2  # the whole photo: never at full resolution
    assert len(ax.collections) == 1 and sum(len(p.vertices) for p in ax.collections[0].get_paths()) == 5 * 3000
    full_draws = []
    real_draw = fig.canvas.draw
    fig.canvas.draw = lambda *a, **k: (full_draws.append(1), real_draw(*a, **k))[1]
    # drag on empty ground: one full draw at the press, none while moving, one at the release
    free = (1000.0, 1000.0)
    ge.mouse(fig, ax, "button_press_event", *free)
    n_press = len(full_draws)
    for i in range(1, 11):  # motion events delivered without gui_events' redraw before each
        px, py = ax.transData.transform((free[0] + 40 * i, free[1] + 30 * i))
        fig.canvas.callbacks.process("motion_notify_event", MouseEvent("motion_notify_event", fig.canvas, px, py))
    assert len(full_draws) == n_press  # moves are blitted
    ge.mouse(fig, ax, "button_release_event", free[0] + 400, free[1] + 300)
    new = store.boxes("big.jpg")[-1]
    screen_px = 1 / g.px_per_unit()  # events come in whole screen pixels: ~5.7 photo pixels here
    assert np.allclose(new["xyxy"], [free[0], free[1], free[0] + 400, free[1] + 300], atol=screen_px + 0.5)
    assert g.selected == new["id"]
    # move the new box, zoom in to the photo's pixels, pan with the right button
    ge.drag(fig, ax, free[0] + 200, free[1] + 150, free[0] + 260, free[1] + 190, steps=2)
    moved = store.box("big.jpg", new["id"])["xyxy"]
    assert np.allclose(np.subtract(moved, new["xyxy"]), [60, 40, 60, 40], atol=2 * screen_px + 1)
    for _ in range(8):
        ge.mouse(fig, ax, "scroll_event", free[0] + 100, free[1] + 100, step=1)
    fig.canvas.draw()
    assert g.image_artist.shown_level == 0
    before = ax.get_xlim()
    ge.drag(fig, ax, free[0] + 100, free[1] + 100, free[0] + 80, free[1] + 100, steps=2, button=3)
    assert ax.get_xlim()[0] > before[0] + 5  # the photo follows the mouse (leftwards: the view moves right)
    assert len(store.boxes("big.jpg")) == 3001


def test_annotated_region_is_recorded_for_module_5(photos, tmp_path):
    owned = tmp_path / "owned.json"
    owned.write_text(json.dumps({"a.png": [[10, 10], [190, 10], [190, 140], [10, 140]]}))
    base = [f"images={photos}", "export_yolo=false", f"owned_areas={owned}"]
    for mode, expected in (("auto", [[10, 10], [190, 10], [190, 140], [10, 140]]), ("image", None)):
        cfg = load_config(
            BboxDrawerConfig,
            None,
            [*base, f"output_dir={tmp_path / mode}", f"annotated_region={mode}", "include_unseen=true"],
        )
        AnnotationStore(photos, tmp_path / mode).add("b.png", [5, 5, 40, 40])  # an export needs a box
        ds = json.loads(run(cfg)["coco"].read_text())
        regions = {im["file_name"]: im.get("annotated_region") for im in ds["images"]}
        assert regions == {"a.png": expected, "b.png": None}  # b.png has no owned area: annotated whole
    with pytest.raises(ConfigError, match="owned areas"):
        load_config(
            BboxDrawerConfig, None, [f"images={photos}", f"output_dir={tmp_path / 'x'}", "annotated_region=owned"]
        )


def test_the_folders_picture_of_the_window_shows_its_current_help():
    """``4_bbox_drawer/gui.png`` is drawn by docs/gui/folder_windows.py, which records the help it shows."""
    import hashlib

    from PIL import Image

    from matchplant.bbox_drawer.gui import HELP

    with Image.open(Path(__file__).resolve().parents[1] / "4_bbox_drawer" / "gui.png") as im:
        shown = im.text.get("help_sha1")
    assert shown == hashlib.sha1(HELP.encode()).hexdigest(), (
        "4_bbox_drawer/gui.png shows an older help panel: python docs/gui/folder_windows.py <demo output>"
    )
