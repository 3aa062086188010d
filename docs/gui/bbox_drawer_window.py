"""Module 4's window as its folder shows it (``4_bbox_drawer/gui.png``), drawn from the current code on a demo
run's photos and boxes:  python docs/gui/bbox_drawer_window.py DEMO_OUT  (e.g. runs/demo, after `make demo`).

The PNG records which help text it shows (``help_sha1``): tests/test_bbox_drawer.py fails when the window's help
changes and the picture was not drawn again (the folder once showed a help panel two versions old).
"""

from __future__ import annotations

import hashlib
import sys
import tempfile
from pathlib import Path

from matchplant.bbox_drawer.gui import HELP, BboxDrawerGUI
from matchplant.bbox_drawer.store import AnnotationStore
from matchplant.core.formats.owned_areas import read_owned_areas

ROOT = Path(__file__).resolve().parents[2]


def help_sha1() -> str:
    return hashlib.sha1(HELP.encode()).hexdigest()


def main(demo: Path) -> Path:
    with tempfile.TemporaryDirectory() as tmp:
        store = AnnotationStore(
            demo / "3_select" / "images",
            Path(tmp) / "out",
            ["plant", "weed"],
            resume_from=demo / "4_annotate" / "session.json",
        )
        owned = read_owned_areas(demo / "3_select" / "owned_areas.json")
        gui = BboxDrawerGUI(store, owned_areas=owned, headless=True)
        path = ROOT / "4_bbox_drawer" / "gui.png"
        gui.fig.savefig(path, dpi=80, metadata={"help_sha1": help_sha1()})  # about the size of the other pictures
    return path


if __name__ == "__main__":
    print(main(Path(sys.argv[1])))
