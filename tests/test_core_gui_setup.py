"""The setup screens of modules 1, 3, 4, 5 and 9 (file pickers, then a full run), headless and in a real window.

Each test picks the files through the screen's "Browse" buttons (the Tk dialog replaced by a stand-in that
checks it was asked for the right kind, file or folder), presses the run button with synthesised events, and
checks the run's outputs against the synthetic field's truth. The Xvfb tests do the same in a TkAgg window.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import shapely
from conftest import run_in_xvfb, xvfb_available
from gui_events import click
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from matchplant.core.runtime.widgets import QuietTextBox

ROOT = Path(__file__).resolve().parents[1]


class Picker:
    """Stands in for Tk's dialog: answers ``(kind, path)`` pairs in order, checking the kind asked for."""

    def __init__(self, *answers: tuple[str, Path]):
        self.answers = list(answers)
        self.asked: list[str] = []

    def __call__(self, kind, title, initial=None):
        want_kind, path = self.answers.pop(0)
        assert kind == want_kind, (title, kind, want_kind)
        self.asked.append(title)
        return str(path)


def press(button) -> None:
    click(button.ax.figure, button.ax, 0.5, 0.5)


def browse(screen, key) -> None:
    """Press the Browse button of ``key`` (the screen's or the stats window's picker)."""
    press(screen.browse_buttons[key] if hasattr(screen, "browse_buttons") else screen.pickers[key])


def crs_of(field) -> str:
    return json.loads(field.field_json.read_text())["crs"]


def gcp_truth(field) -> dict:
    with open(field.gcp_pixels) as fh:
        return {(r["gcp_id"], r["image"]): (float(r["u"]), float(r["v"])) for r in csv.DictReader(fh)}


# -- module 1 ----------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.gui
def test_gcp_setup_screen_full_run(tiny_field, tmp_path):
    from matchplant.core.formats.gcp_list import read_gcp_list
    from matchplant.gcp_finder.config import GcpFinderConfig
    from matchplant.gcp_finder.gui import GcpFinderSetup

    cfg = GcpFinderConfig(auto=True, max_center_distance=1.0, edge_margin_px=0)
    picker = Picker(("folder", tiny_field.images), ("file", tiny_field.gcp_survey), ("folder", tmp_path / "gcp"))
    setup = GcpFinderSetup(cfg, headless=True, chooser=picker)
    screen = setup.screen
    press(screen.run_button)  # nothing chosen yet: a message, no run
    assert not screen.ran and "required" in screen.status.get_text()
    for key in ("images", "survey", "output_dir"):
        browse(screen, key)
    screen.boxes["survey_crs"].set_val(crs_of(tiny_field))
    assert screen.boxes["images"].text == str(tiny_field.images) and not picker.answers
    press(screen.run_button)
    assert screen.ran, screen.status.get_text()
    # the run's outputs: candidates, and auto-found targets within 2 px of the true centres
    assert (tmp_path / "gcp" / "candidates.csv").is_file()
    truth = gcp_truth(tiny_field)
    marks = {(m.gcp, m.image): (m.u, m.v) for m in read_gcp_list(tmp_path / "gcp" / "gcp_list.txt")[2]}
    common = [k for k in marks if k in truth]
    assert len(common) >= 0.7 * len(truth)
    assert all(math.dist(marks[k], truth[k]) < 2.0 for k in common)
    # the marking window opened on the candidates of the same run
    assert setup.marking is not None and setup.marking.finder is setup.finder


# -- module 3 ----------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.gui
def test_min_images_setup_screen_full_run_and_legend(tiny_field, tmp_path, monkeypatch):
    from matchplant.min_img_finder.config import MinImgFinderConfig
    from matchplant.min_img_finder.gui import MinImgFinderGUI, MinImgFinderSetup

    # the map is drawn before the outputs are written (they take seconds: the map once stayed blank meanwhile)
    save, drawn_before_saving = MinImgFinderGUI.save, []

    def checked_save(self):
        drawn_before_saving.append(not self.fig.stale and bool(self.ax.collections or self.ax.patches))
        return save(self)

    monkeypatch.setattr(MinImgFinderGUI, "save", checked_save)
    # as in a window, an idle draw waits for the event loop (which a long action blocks): Agg's draws at once
    monkeypatch.setattr(FigureCanvasAgg, "draw_idle", lambda self, *args, **kwargs: None)
    out = tmp_path / "sel"
    setup = MinImgFinderSetup(
        MinImgFinderConfig(), headless=True, chooser=Picker(("folder", tiny_field.root), ("folder", out))
    )
    browse(setup.screen, "project_dir")
    browse(setup.screen, "output_dir")
    press(setup.screen.run_button)
    assert setup.screen.ran, setup.screen.status.get_text()
    assert drawn_before_saving == [True]
    summary = json.loads((out / "selection.json").read_text())
    rows = list(csv.DictReader(open(out / "selected_images.csv")))
    assert summary["images_selected"] == len(rows) == len(setup.editor.result.selection.indices) > 0
    # as much as asked, or as much as all the images together cover
    finder = setup.editor.finder
    reachable = 100 * shapely.union_all([f.polygon for f in finder.footprints]).intersection(finder.aoi).area
    reachable /= finder.aoi.area
    assert summary["coverage_pct"] >= min(summary["requested_coverage_pct"], reachable) - 0.5
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(r["file"] for r in rows)
    # the coverage map explains its marks
    legend = setup.editor.ax.get_legend()
    labels = [t.get_text() for t in legend.get_texts()]
    assert len(labels) == 5 and any("not covered" in t for t in labels) and any("owns" in t for t in labels)


@pytest.mark.slow
@pytest.mark.gui
def test_min_images_setup_screen_reports_a_wrong_folder(tmp_path):
    from matchplant.min_img_finder.config import MinImgFinderConfig
    from matchplant.min_img_finder.gui import MinImgFinderSetup

    setup = MinImgFinderSetup(
        MinImgFinderConfig(), headless=True, chooser=Picker(("folder", tmp_path), ("folder", tmp_path / "o"))
    )
    browse(setup.screen, "project_dir")
    browse(setup.screen, "output_dir")
    press(setup.screen.run_button)
    assert not setup.screen.ran and setup.screen.status.get_color() == "#c62828"
    assert not (tmp_path / "o" / "selection.json").exists()


# -- module 9 ----------------------------------------------------------------------------------------


@pytest.mark.gui
def test_stats_window_pickers_full_run(tiny_field, tmp_path):
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
    from matchplant.spatial_stat_extractor.gui import SpatialStatExtractorGUI

    picker = Picker(
        ("file", tiny_field.map_boxes),
        ("file", tiny_field.dsm),
        ("file", tiny_field.dtm),
        ("folder", tmp_path / "stats"),
    )
    gui = SpatialStatExtractorGUI(SpatialStatExtractorConfig(), headless=True, chooser=picker)
    for key in ("polygons", "rasters.dsm", "rasters.dtm", "output_dir"):
        browse(gui, key)
    gui.boxes["polygons_crs"].set_val(crs_of(tiny_field))
    press(gui.btn_run)
    gui.wait(120)
    assert gui.status.get_text().startswith("done"), gui.status.get_text()
    table = pd.read_csv(tmp_path / "stats" / "stats.csv")
    truth = pd.read_csv(tiny_field.plants_csv).set_index("id")
    res = json.loads(tiny_field.field_json.read_text())["raster_res"]
    err = np.abs(table["chm_max"].to_numpy() - truth.loc[table["plant_id"], "height"].to_numpy())
    assert len(table) == len(truth) and err.max() < res


# -- module 4 ----------------------------------------------------------------------------------------


def free_spots(boxes, width, height, n=2, side=12, margin=12):
    """``n`` squares of ``side`` px on free ground (``margin`` px from every box and from the edges)."""
    b = np.asarray(boxes, float).reshape(-1, 4)
    spots = []
    for y in range(margin, height - side - margin, 4):
        for x in range(margin, width - side - margin, 4):
            if not (
                (b[:, 0] - margin < x + side)
                & (x < b[:, 2] + margin)
                & (b[:, 1] - margin < y + side)
                & (y < b[:, 3] + margin)
            ).any():
                spots.append((x, y))
                b = np.vstack([b, [x, y, x + side, y + side]])
                if len(spots) == n:
                    return spots
    raise AssertionError("no free ground in the image")


def truth_boxes(field) -> dict:
    """Image name -> the true (undistorted) boxes ``[x1, y1, x2, y2]`` of the synthetic field."""
    truth = json.loads(field.boxes_undistorted.read_text())
    names = {im["id"]: Path(im["file_name"]).name for im in truth["images"]}
    out = {}
    for a in truth["annotations"]:
        x, y, w, h = a["bbox"]
        out.setdefault(names[a["image_id"]], []).append([x, y, x + w, y + h])
    return out


def check_annotations(out: Path, truth: dict, drawn: dict) -> None:
    """annotations.json holds every true box (imported) plus the ``drawn`` boxes with their categories."""
    ds = json.loads((out / "annotations.json").read_text())
    names = {im["id"]: im["file_name"] for im in ds["images"]}
    cats = {c["id"]: c["name"] for c in ds["categories"]}
    got = {}
    for a in ds["annotations"]:
        x, y, w, h = a["bbox"]
        got.setdefault(names[a["image_id"]], []).append(([x, y, x + w, y + h], cats[a["category_id"]]))
    assert set(got) == set(truth)
    for name, boxes in truth.items():
        # imported boxes to the 0.01 px COCO keeps; drawn ones to 1 px (events come in whole screen pixels)
        want = [(b, "plant", 0.011) for b in boxes] + [(b, c, 1.0) for b, c in drawn.get(name, [])]
        assert len(got[name]) == len(want), name
        for box, cat, tol in want:  # each wanted box found, with its category
            assert any(c == cat and np.abs(np.subtract(g, box)).max() <= tol for g, c in got[name]), (name, box, cat)


@pytest.mark.slow
@pytest.mark.gui
def test_bbox_setup_screen_full_run(tiny_field, tmp_path):
    import gui_events as ge

    from matchplant.bbox_drawer.config import BboxDrawerConfig
    from matchplant.bbox_drawer.gui import BboxDrawerSetup

    out = tmp_path / "labels"
    picker = Picker(("folder", tiny_field.undistorted_images), ("folder", out), ("file", tiny_field.boxes_undistorted))
    setup = BboxDrawerSetup(BboxDrawerConfig(categories=["plant", "weed"]), headless=True, chooser=picker, dpi=50)
    screen = setup.screen
    press(screen.run_button)  # nothing chosen yet: a message, no window
    assert not screen.ran and "required" in screen.status.get_text() and setup.window is None
    for key in ("images", "output_dir", "import_coco"):
        browse(screen, key)
    assert not picker.answers
    press(screen.run_button)
    assert screen.ran, screen.status.get_text()
    g = setup.window
    truth = truth_boxes(tiny_field)
    assert g.store.count() == sum(map(len, truth.values()))  # the chosen import, every box
    # draw a plant, press 2 (the next box is a weed: the plant stays a plant), draw a weed, quit
    (x0, y0), (x1, y1) = free_spots(truth[g.name], *g.store.size(g.name))
    ge.drag(g.fig, g.ax, x0, y0, x0 + 12, y0 + 12, steps=1)
    ge.key(g.fig, "2")
    ge.drag(g.fig, g.ax, x1, y1, x1 + 12, y1 + 12, steps=1)
    ge.key(g.fig, "q")
    check_annotations(
        out, truth, {g.name: [([x0, y0, x0 + 12, y0 + 12], "plant"), ([x1, y1, x1 + 12, y1 + 12], "weed")]}
    )
    assert (out / "yolo" / "classes.txt").read_text().split() == ["plant", "weed"]


@pytest.mark.slow
@pytest.mark.gui
def test_bbox_setup_screen_reports_a_bad_import(tiny_field, tmp_path):
    from matchplant.bbox_drawer.config import BboxDrawerConfig
    from matchplant.bbox_drawer.gui import BboxDrawerSetup

    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    setup = BboxDrawerSetup(
        BboxDrawerConfig(),
        headless=True,
        dpi=50,
        chooser=Picker(("folder", tiny_field.undistorted_images), ("folder", tmp_path / "o"), ("file", bad)),
    )
    for key in ("images", "output_dir", "import_coco"):
        browse(setup.screen, key)
    press(setup.screen.run_button)
    assert not setup.screen.ran and setup.window is None and setup.screen.status.get_color() == "#c62828"
    assert "bad.json" in setup.screen.status.get_text()


# -- module 5 ----------------------------------------------------------------------------------------

TILING = dict(tile_size=256, overlap=40, negative_share=1.0, workers=1, min_box_side=0.0, min_visible=0.0)


def check_tiles(out: Path, field) -> None:
    """Every true box kept, and every tile of every photo's grid written (negative_share=1), split 3 ways."""
    truth = json.loads(field.boxes_undistorted.read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert summary["boxes"] == len(truth["annotations"]) and summary["boxes_kept"] == summary["boxes"]
    tiles = [(k, im) for k in ("train", "val", "test") for im in json.loads((out / f"{k}.json").read_text())["images"]]

    def per_axis(length: int) -> int:  # a 256 px tile every 216 px, the last one flush with the edge
        return 1 + math.ceil(max(length - 256, 0) / (256 - 40))

    grid = sum(per_axis(im["width"]) * per_axis(im["height"]) for im in truth["images"])
    assert len(tiles) == grid and all((out / k / "images" / im["file_name"]).is_file() for k, im in tiles)
    assert {k for k, _ in tiles} == {"train", "val", "test"}


@pytest.mark.slow
@pytest.mark.gui
def test_tiling_setup_screen_full_run(tiny_field, tmp_path):
    from matchplant.img_splitter.config import ImgSplitterConfig
    from matchplant.img_splitter.gui import ImgSplitterSetup

    out = tmp_path / "tiles"
    picker = Picker(("folder", tiny_field.undistorted_images), ("file", tiny_field.boxes_undistorted), ("folder", out))
    setup = ImgSplitterSetup(ImgSplitterConfig(**TILING), headless=True, chooser=picker, dpi=40)
    press(setup.screen.run_button)  # nothing chosen yet
    assert not setup.screen.ran and "required" in setup.screen.status.get_text() and setup.preview is None
    for key in ("images", "annotations", "output_dir"):
        browse(setup.screen, key)
    press(setup.screen.run_button)
    assert setup.screen.ran, setup.screen.status.get_text()
    preview = setup.preview
    assert preview.boxes["images"].text == str(tiny_field.undistorted_images)  # the chosen paths, in its boxes
    assert len(preview.sources) == 9 and "boxes: 339 of 339 kept" in preview.summary.get_text()
    assert not out.exists()  # a preview writes nothing
    press(preview.buttons["Run"])
    assert preview.status.get_text().startswith("done"), preview.status.get_text()
    check_tiles(out, tiny_field)


@pytest.mark.slow
@pytest.mark.gui
def test_tiling_setup_screen_reports_bad_annotations(tiny_field, tmp_path):
    from matchplant.img_splitter.config import ImgSplitterConfig
    from matchplant.img_splitter.gui import ImgSplitterSetup

    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    setup = ImgSplitterSetup(
        ImgSplitterConfig(**TILING),
        headless=True,
        dpi=40,
        chooser=Picker(("folder", tiny_field.undistorted_images), ("file", bad), ("folder", tmp_path / "o")),
    )
    for key in ("images", "annotations", "output_dir"):
        browse(setup.screen, key)
    press(setup.screen.run_button)
    assert not setup.screen.ran and setup.preview is None and setup.screen.status.get_color() == "#c62828"
    assert "bad.json" in setup.screen.status.get_text() and not (tmp_path / "o").exists()


# -- no display ------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "folder,script",
    [
        ("1_gcp_finder", "gcp_finder.py"),
        ("3_min_img_finder", "min_img_finder.py"),
        ("4_bbox_drawer", "bbox_drawer.py"),
        ("5_img_splitter", "img_splitter.py"),
        ("9_spatial_stat_extractor", "spatial_stat_extractor.py"),
    ],
)
def test_gui_without_display_is_a_clear_error(folder, script):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = subprocess.run(
        [sys.executable, str(ROOT / folder / script), "--gui"], capture_output=True, text=True, timeout=120, env=env
    )
    assert r.returncode == 2, r.stderr
    assert "needs a window" in r.stderr and "without --gui" in r.stderr and "Traceback" not in r.stderr


# -- real windows ------------------------------------------------------------------------------------

XVFB = """
import sys
import matplotlib.pyplot as plt
sys.path.insert(0, {tests!r})
from gui_events import click
{build}
assert plt.get_backend().lower().startswith("tk"), plt.get_backend()
fig = screen.fig
widget = fig.canvas.get_tk_widget()
def pick(button, path):
    # press a Browse button: Tk's real dialog opens; the "user" chooses ``path`` in it a moment later
    widget.after(400, lambda: widget.tk.eval("set ::tk::Priv(selectFilePath) {{%s}}" % path))
    click(fig, button.ax, 0.5, 0.5)
def go():
    for key, path in {answers!r}:
        pick(buttons[key], path)
    {actions}
    print("RAN", {ran})
    plt.close("all")
t = fig.canvas.new_timer(interval=300)
t.single_shot = True
t.add_callback(go)
t.start()
killer = fig.canvas.new_timer(interval=120000)
killer.add_callback(lambda: plt.close("all"))
killer.start()
plt.show()
"""


def _xvfb(answers, build, actions, ran):
    code = XVFB.format(
        tests=str(Path(__file__).parent),
        answers=[(k, str(p)) for k, p in answers],
        build=build,
        actions=actions,
        ran=ran,
    )
    r = run_in_xvfb(textwrap.dedent(code), timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    assert "RAN True" in r.stdout, r.stdout + r.stderr[-3000:]


@pytest.mark.gui
@pytest.mark.skipif(not xvfb_available(), reason="Xvfb not installed")
def test_setup_screens_in_real_windows(tiny_field, tmp_path):
    """Each screen in a TkAgg window on a virtual display, its files chosen in Tk's real dialogs."""
    run = "click(fig, screen.run_button.ax, 0.5, 0.5)"
    _xvfb(
        [("images", tiny_field.images), ("survey", tiny_field.gcp_survey), ("output_dir", tmp_path / "gcp")],
        "from matchplant.gcp_finder.config import GcpFinderConfig\n"
        "from matchplant.gcp_finder.gui import GcpFinderSetup\n"
        f"setup = GcpFinderSetup(GcpFinderConfig(survey_crs={crs_of(tiny_field)!r}, auto=True))\n"
        "screen = setup.screen\nbuttons = screen.browse_buttons",
        run,
        "screen.ran and setup.marking is not None",
    )
    assert (tmp_path / "gcp" / "gcp_list.txt").is_file()
    _xvfb(
        [("project_dir", tiny_field.root), ("output_dir", tmp_path / "sel")],
        "from matchplant.min_img_finder.config import MinImgFinderConfig\n"
        "from matchplant.min_img_finder.gui import MinImgFinderSetup\n"
        "setup = MinImgFinderSetup(MinImgFinderConfig())\n"
        "screen = setup.screen\nbuttons = screen.browse_buttons",
        run,
        "screen.ran and setup.editor.ax.get_legend() is not None",
    )
    assert (tmp_path / "sel" / "coverage.png").is_file()
    _xvfb(
        [
            ("polygons", tiny_field.map_boxes),
            ("rasters.dsm", tiny_field.dsm),
            ("rasters.dtm", tiny_field.dtm),
            ("output_dir", tmp_path / "stats"),
        ],
        "from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig\n"
        "from matchplant.spatial_stat_extractor.gui import SpatialStatExtractorGUI\n"
        "screen = SpatialStatExtractorGUI(SpatialStatExtractorConfig())\nbuttons = screen.pickers\n"
        f"screen.boxes['polygons_crs'].set_val({crs_of(tiny_field)!r})",
        "click(fig, screen.btn_run.ax, 0.5, 0.5); screen.wait(120)",
        "screen.status.get_text().startswith('done')",
    )
    assert len(pd.read_csv(tmp_path / "stats" / "stats.csv")) == len(pd.read_csv(tiny_field.plants_csv))


@pytest.mark.gui
@pytest.mark.skipif(not xvfb_available(), reason="Xvfb not installed")
def test_setup_screens_4_and_5_in_real_windows(tiny_field, tmp_path):
    """Modules 4 and 5: files chosen in Tk's real dialogs, the next window shown (not left hidden), a full run."""
    truth = truth_boxes(tiny_field)
    first = sorted(truth)[0]
    (x0, y0), (x1, y1) = free_spots(truth[first], 400, 300)
    draw = "drag(g.fig, g.ax, {0}, {1}, {0} + 12, {1} + 12, steps=1)"
    _xvfb(
        [
            ("images", tiny_field.undistorted_images),
            ("output_dir", tmp_path / "labels"),
            ("import_coco", tiny_field.boxes_undistorted),
        ],
        "from gui_events import drag, key as type_key\n"  # the template's loop has its own 'key'
        "from matchplant.bbox_drawer.run import BboxDrawerConfig\n"
        "from matchplant.bbox_drawer.gui import BboxDrawerSetup\n"
        "setup = BboxDrawerSetup(BboxDrawerConfig(categories=['plant', 'weed']))\n"
        "screen = setup.screen\nbuttons = screen.browse_buttons",
        "click(fig, screen.run_button.ax, 0.5, 0.5); g = setup.window; "
        "shown = g.fig.canvas.manager.window.state() == 'normal'; "
        f"{draw.format(x0, y0)}; type_key(g.fig, '2'); {draw.format(x1, y1)}; type_key(g.fig, 'q')",
        f"screen.ran and shown and g.name == {first!r}",
    )
    check_annotations(
        tmp_path / "labels",
        truth,
        {first: [([x0, y0, x0 + 12, y0 + 12], "plant"), ([x1, y1, x1 + 12, y1 + 12], "weed")]},
    )
    _xvfb(
        [
            ("images", tiny_field.undistorted_images),
            ("annotations", tiny_field.boxes_undistorted),
            ("output_dir", tmp_path / "tiles"),
        ],
        "from matchplant.img_splitter.run import ImgSplitterConfig\n"
        "from matchplant.img_splitter.gui import ImgSplitterSetup\n"
        f"setup = ImgSplitterSetup(ImgSplitterConfig(**{TILING!r}))\n"
        "screen = setup.screen\nbuttons = screen.browse_buttons",
        "click(fig, screen.run_button.ax, 0.5, 0.5); p = setup.preview; "
        "shown = p.fig.canvas.manager.window.state() == 'normal'; "
        "click(p.fig, p.buttons['Run'].ax, 0.5, 0.5)",
        "screen.ran and shown and p.result is not None",
    )
    check_tiles(tmp_path / "tiles", tiny_field)


@pytest.mark.gui
def test_bbox_setup_screen_prefills_module_3s_owned_areas(tmp_path):
    """Module 3 writes owned_areas.json beside the images/ folder it fills: choosing that folder in module 4
    fills in the owned-areas box; a box the user filled is left alone."""
    from matchplant.bbox_drawer.config import BboxDrawerConfig
    from matchplant.bbox_drawer.gui import BboxDrawerSetup

    sel = tmp_path / "min_images"
    (sel / "images").mkdir(parents=True)
    (sel / "owned_areas.json").write_text("{}")
    setup = BboxDrawerSetup(BboxDrawerConfig(), headless=True, chooser=Picker(("folder", sel / "images")), dpi=50)
    browse(setup.screen, "images")
    assert setup.screen.boxes["owned_areas"].text == str(sel / "owned_areas.json")
    assert "filled in: Owned areas" in setup.screen.status.get_text()
    mine = tmp_path / "mine.json"
    cfg = BboxDrawerConfig(owned_areas=mine)
    setup = BboxDrawerSetup(cfg, headless=True, chooser=Picker(("folder", sel / "images")), dpi=50)
    browse(setup.screen, "images")
    assert setup.screen.boxes["owned_areas"].text == str(mine)


def test_a_long_path_given_at_start_shows_its_end_inside_its_field():
    """Issue 29: a long path filled in from the config (not typed) shows its file name from the first draw and
    stays inside its field; a short one stays left-aligned."""
    fig = Figure(figsize=(8, 3))
    FigureCanvasAgg(fig)
    long = "/home/breeder/field_trials/2026/sorghum_north/flight_07/odm_project/odm_dem/dsm_final.tif"
    boxes = {
        text: QuietTextBox(fig.add_axes((0.3, y, 0.4, 0.2)), "DSM ", initial=text)
        for text, y in ((long, 0.6), ("dsm.tif", 0.2))
    }
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ext = {text: box.text_disp.get_window_extent(renderer) for text, box in boxes.items()}
    field = {text: box.ax.bbox for text, box in boxes.items()}
    assert field[long].x0 > ext[long].x0 and ext[long].x1 <= field[long].x1 + 1  # its end inside, its start cut
    assert boxes[long].text_disp.get_clip_on()
    assert field["dsm.tif"].x0 <= ext["dsm.tif"].x0 and ext["dsm.tif"].x1 < field["dsm.tif"].x1


# -- status lines stay in their box -------------------------------------------------------------------


@pytest.mark.gui
def test_a_long_status_stays_left_of_the_run_button_and_inside_the_window(tmp_path):
    """A long message (an error naming a deep path, or what a module saved after `q`) wraps inside the status
    area: it neither runs over the Run button nor out of the window; the whole message is still the text."""
    from dataclasses import dataclass

    from matchplant.core.runtime.config import param
    from matchplant.core.runtime.widgets import SetupField, SetupScreen

    @dataclass
    class Cfg:
        path: str = param("", "a path")

    screen = SetupScreen("4 Test step", Cfg(), [SetupField("path", "A file")], lambda cfg: "done", headless=True)
    deep = "/home/breeder/field_trials/2026/sorghum_north/flight_07/" + "odm_project_" * 12 + "annotations.json"
    message = f"4 boxes saved to {deep}; the window can be closed, or choose other files and run again. " * 3
    screen.say(message, error=True)
    fig = screen.fig
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    text_box, run_box = screen.status.get_window_extent(renderer), screen.run_button.ax.bbox
    assert screen.status.get_text() == message
    assert text_box.x1 <= run_box.x0 and text_box.x0 >= 0 and text_box.y0 >= 0, (text_box, run_box)
    assert text_box.y1 <= screen.status_area.bbox.y1 + 1
    assert "\u2026" in screen.status._get_wrapped_text()  # cut, and said to be cut


@pytest.mark.gui
def test_a_window_status_line_of_a_figure_stays_in_the_window():
    from matchplant.core.runtime.gui import figure, fit_to_axes, status_text

    fig = figure(headless=True, figsize=(6, 4))
    on_axes = status_text(fig.add_axes((0.05, 0.0, 0.5, 0.05), frameon=False), "")
    on_fig = fit_to_axes(fig.text(0.02, 0.01, "", fontsize=9))
    long = "a message " + "/very/long/path" * 30
    on_axes.set_text(long)
    on_fig.set_text(long)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    assert on_axes.get_window_extent(r).x1 <= on_axes.axes.bbox.x1
    assert 0 <= on_fig.get_window_extent(r).x0 and on_fig.get_window_extent(r).x1 <= fig.bbox.x1
    assert on_fig._get_wrapped_text().count("\n") <= 1  # at most two lines at the bottom of the window


@pytest.mark.gui
@pytest.mark.parametrize("blit", [True, False])
def test_a_click_into_a_long_path_puts_the_cursor_where_clicked(monkeypatch, blit):
    """A path longer than its field shows its end; a click lands on the character under the mouse, and typed
    text goes there (not into the hidden middle of the path), whether the canvas blits or redraws whole."""
    from gui_events import key

    from matchplant.core.runtime.gui import figure

    fig = figure(headless=True, figsize=(10, 2))
    monkeypatch.setattr(type(fig.canvas), "supports_blit", blit)
    ax = fig.add_axes((0.2, 0.4, 0.6, 0.3))
    long = "/home/breeder/field_trials/2026/sorghum_north/flight_07/" + "odm_project_/" * 12 + "dsm_final.tif"
    box = QuietTextBox(ax, "DSM ", initial=long)
    fig.canvas.draw()
    char = ax.bbox.width / 60  # generous: a character is narrower than this at any of the fonts used
    for frac in (0.95, 0.7, 0.4):
        x = ax.bbox.x0 + frac * ax.bbox.width
        click(fig, ax, *ax.transData.inverted().transform((x, ax.bbox.y0 + ax.bbox.height / 2)))
        cursor_x = box.cursor.get_segments()[0][0][0]
        assert abs(cursor_x - x) < char, (frac, cursor_x, x)
    index = box.cursor_index
    key(fig, "X")
    assert box.text == long[:index] + "X" + long[index:]
    cursor_x = box.cursor.get_segments()[0][0][0]
    assert ax.bbox.x0 < cursor_x < ax.bbox.x1  # the typed character is in the part of the path shown
