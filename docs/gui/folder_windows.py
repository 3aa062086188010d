"""The module windows as their folders show them (``4_bbox_drawer/gui.png``, ``5_img_splitter/gui.png``), drawn
from the current code on a demo run's photos and boxes:

    python docs/gui/folder_windows.py DEMO_OUT      (e.g. demo_output, after `make demo`)

Each PNG records what it shows (module 4: ``help_sha1``, its help text; module 5: ``widgets``, each setting's
widget): tests/test_bbox_drawer.py and tests/test_img_splitter.py fail when the window changed and the picture
was not drawn again (module 4's once showed a help panel two versions old, module 5's a text field for a yes/no).
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

from matchplant.bbox_drawer.gui import HELP, BboxDrawerGUI
from matchplant.bbox_drawer.store import AnnotationStore
from matchplant.core.formats.owned_areas import read_owned_areas
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.gui import ImgSplitterGUI

ROOT = Path(__file__).resolve().parents[2]


def help_sha1() -> str:
    return hashlib.sha1(HELP.encode()).hexdigest()


def bbox_drawer(demo: Path, tmp: Path) -> Path:
    store = AnnotationStore(
        demo / "3_select" / "images", tmp / "4", ["plant", "weed"], resume_from=demo / "4_annotate" / "session.json"
    )
    gui = BboxDrawerGUI(store, owned_areas=read_owned_areas(demo / "3_select" / "owned_areas.json"), headless=True)
    path = ROOT / "4_bbox_drawer" / "gui.png"
    gui.fig.savefig(path, dpi=80, metadata={"help_sha1": help_sha1()})  # about the size of the other pictures
    return path


def img_splitter(demo: Path, tmp: Path) -> Path:
    cfg = ImgSplitterConfig(
        images=demo / "3_select" / "images",
        annotations=demo / "4_annotate" / "annotations.json",
        output_dir=tmp / "5",
        tile_size=256,
        overlap=40,
    )
    gui = ImgSplitterGUI(cfg, headless=True, dpi=80)
    widgets = {key: type(w).__name__ for key, w in gui.boxes.items()}
    path = ROOT / "5_img_splitter" / "gui.png"
    gui.fig.savefig(path, metadata={"widgets": json.dumps(widgets)})
    return path


def main(demo: Path) -> list[Path]:
    with tempfile.TemporaryDirectory() as tmp:
        return [bbox_drawer(demo, Path(tmp)), img_splitter(demo, Path(tmp))]


if __name__ == "__main__":
    print(*main(Path(sys.argv[1])), sep="\n")
