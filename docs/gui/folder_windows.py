"""The module windows as their folders show them (``1_gcp_finder/gui.png``, ``3_min_img_finder/gui.png``,
``4_bbox_drawer/gui.png``, ``5_img_splitter/gui.png``, ``9_spatial_stat_extractor/gui.png``), drawn headless from
the current code on a demo run's photos, boxes, plants and rasters:

    python docs/gui/folder_windows.py DEMO_OUT      (e.g. demo_output, after `make demo`)

Each shows a working state: module 1 half-way through marking (two GCPs done, a third just clicked), module 3
the selection it makes on opening, module 4 the demo's boxes, module 5 the tiling preview, module 9 the plants
coloured by a trait after Preview and Run + save, with the map's colour bar.

Each PNG records what it shows (modules 1 and 4: ``help_sha1``, their help line; modules 3, 5 and 9: ``widgets``,
the form's fields and choices): tests/test_gcp_finder.py, tests/test_min_img_finder.py, tests/test_bbox_drawer.py,
tests/test_img_splitter.py and tests/test_spatial_stat_extractor_gui.py fail when the window changed and the
picture was not drawn again (module 4's once showed a help panel two versions old, module 5's a text field for a
yes/no, module 9's a map without its colour bar and a form four fields short).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

from matchplant.bbox_drawer.gui import HELP, BboxDrawerGUI
from matchplant.bbox_drawer.store import AnnotationStore
from matchplant.core.formats.owned_areas import read_owned_areas
from matchplant.gcp_finder import gui as gcp_gui
from matchplant.gcp_finder.candidates import find_candidates
from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.marks import MarkStore
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.gui import ImgSplitterGUI
from matchplant.min_img_finder import gui as min_img_gui
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.spatial_stat_extractor import gui as stats_gui
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig

ROOT = Path(__file__).resolve().parents[2]


def help_sha1(text: str = HELP) -> str:
    """SHA-1 of a window's help text (module 4's by default), recorded in its picture so a test sees it change."""
    return hashlib.sha1(text.encode()).hexdigest()


def _click(fig, ax, x: float, y: float) -> None:
    """A left click at data coordinates (x, y) of ``ax``, delivered as a backend delivers it."""
    from matplotlib.backend_bases import MouseButton, MouseEvent

    fig.canvas.draw()
    px, py = ax.transData.transform((x, y))
    for kind in ("button_press_event", "button_release_event"):
        fig.canvas.callbacks.process(kind, MouseEvent(kind, fig.canvas, px, py, button=MouseButton.LEFT))


def gcp_finder(demo: Path, tmp: Path) -> Path:
    """The marking window half-way through: the first two GCPs marked in 3 images each (from the demo's
    gcp_list.txt), the third GCP's first image just clicked."""
    cfg = GcpFinderConfig(
        images=demo / "0_gps" / "images",
        survey=demo / "field" / "gcp" / "gcp_survey.csv",
        survey_crs="EPSG:32614",
        output_dir=tmp / "1",
    )
    finder = find_candidates(cfg)
    store = MarkStore(finder, tmp / "1" / "gcp_list.txt")
    done = MarkStore(finder, tmp / "1" / "demo_list.txt", autosave=False)
    done.load(demo / "1_gcp" / "gcp_list.txt")
    first, second, third = list(finder.gcps)[:3]
    for gid in (first, second):
        for c in finder.candidates[gid][:3]:
            if (gid, c.image) in done.marks:
                store.set(gid, c.image, *done.marks[(gid, c.image)], record=False)
    gui = gcp_gui.GcpFinderGUI(finder, store, zoom_px=cfg.zoom_px, headless=True)
    gui.select_gcp(list(finder.gcps).index(third))
    c = gui.candidate
    _click(gui.fig, gui.ax, *done.marks.get((third, c.image), (c.u, c.v)))
    path = ROOT / "1_gcp_finder" / "gui.png"
    gui.fig.savefig(path, dpi=80, metadata={"help_sha1": help_sha1(gcp_gui.HELP)})
    return path


def min_img_finder(demo: Path, tmp: Path) -> Path:
    """The coverage map with the selection the window makes when it opens on the demo's ODM project."""
    cfg = MinImgFinderConfig(project_dir=demo / "field", output_dir=tmp / "3")
    gui = min_img_gui.MinImgFinderGUI(cfg, headless=True)
    shown = {
        "fields": [gui.boxes[key].label.get_text().strip() for key, _ in min_img_gui.FIELDS],
        "methods": [t.get_text() for t in gui.method.labels],
    }
    path = ROOT / "3_min_img_finder" / "gui.png"
    gui.fig.savefig(path, dpi=80, metadata={"widgets": json.dumps(shown)})
    return path


@contextlib.contextmanager
def in_demo_output(demo: Path, tmp: Path, *inputs: str):
    """Work in ``tmp``, where ``demo_output`` holds links to the demo's ``inputs`` folders (and the outputs, in
    real folders beside them): a form shows the paths a user of ``make demo`` types, not a temporary folder's."""
    (tmp / "demo_output").mkdir(exist_ok=True)
    for name in inputs:
        link = tmp / "demo_output" / name
        if not link.exists():
            link.symlink_to(demo.resolve() / name, target_is_directory=True)
    here = Path.cwd()
    os.chdir(tmp)
    try:
        yield
    finally:
        os.chdir(here)


def spatial_stat_extractor(demo: Path, tmp: Path) -> Path:
    """The window after Preview and Run + save on the demo's plants and rasters: the plants coloured by a
    trait, with the colour bar beside the map (the status line names the output folder in full)."""
    with in_demo_output(demo, tmp, "8_plants", "field"):
        gui = stats_gui.SpatialStatExtractorGUI(SpatialStatExtractorConfig(), headless=True)
        for key, value in (
            ("polygons", "demo_output/8_plants/plants.gpkg"),
            ("rasters.dsm", "demo_output/field/odm_dem/dsm.tif"),
            ("rasters.dtm", "demo_output/field/odm_dem/dtm.tif"),
            ("rasters.multispectral", "demo_output/field/multispectral/multispectral.tif"),
            ("output_dir", "demo_output/9_stats"),
        ):
            gui.boxes[key].set_val(value)
        if not gui.preview():
            raise SystemExit(gui.status.get_text())
        gui.run()
        gui.wait(600)
    if gui.colorbar is None:
        raise SystemExit(f"module 9's run showed no result: {gui.status.get_text()}")
    shown = {
        "fields": [[key, gui.boxes[key].label.get_text().strip()] for key, _ in stats_gui.TEXT_FIELDS],
        "pickers": sorted(gui.pickers),
        "stats": [t.get_text() for t in gui.stat_checks.labels],
        "modes": [t.get_text() for t in gui.mode_radio.labels],
        "colour_bar": gui.colorbar.ax.get_ylabel(),
    }
    path = ROOT / "9_spatial_stat_extractor" / "gui.png"
    gui.fig.savefig(path, dpi=80, metadata={"widgets": json.dumps(shown)})
    return path


def bbox_drawer(demo: Path, tmp: Path) -> Path:
    """Draw module 4's window on the demo's selected photos and boxes; the PNG's path."""
    store = AnnotationStore(
        demo / "3_select" / "images", tmp / "4", ["plant", "weed"], resume_from=demo / "4_annotate" / "session.json"
    )
    gui = BboxDrawerGUI(store, owned_areas=read_owned_areas(demo / "3_select" / "owned_areas.json"), headless=True)
    path = ROOT / "4_bbox_drawer" / "gui.png"
    gui.fig.savefig(path, dpi=80, metadata={"help_sha1": help_sha1()})  # about the size of the other pictures
    return path


def img_splitter(demo: Path, tmp: Path) -> Path:
    """Draw module 5's window with its tiling preview of the demo's photos; the PNG's path."""
    cfg = ImgSplitterConfig(
        images=Path("demo_output/3_select/images"),
        annotations=Path("demo_output/4_annotate/annotations.json"),
        output_dir=Path("demo_output/5_tiles"),
        tile_size=256,
        overlap=40,
    )
    with in_demo_output(demo, tmp, "3_select", "4_annotate"):
        gui = ImgSplitterGUI(cfg, headless=True, dpi=80)
    widgets = {key: type(w).__name__ for key, w in gui.boxes.items()}
    path = ROOT / "5_img_splitter" / "gui.png"
    gui.fig.savefig(path, metadata={"widgets": json.dumps(widgets)})
    return path


def main(demo: Path) -> list[Path]:
    """Draw every module window from the demo run in ``demo``; the PNGs' paths."""
    with tempfile.TemporaryDirectory(prefix="matchplant-") as tmp:
        tmp = Path(tmp)
        return [
            gcp_finder(demo, tmp),
            min_img_finder(demo, tmp),
            bbox_drawer(demo, tmp),
            img_splitter(demo, tmp),
            spatial_stat_extractor(demo, tmp),
        ]


if __name__ == "__main__":
    print(*main(Path(sys.argv[1])), sep="\n")
