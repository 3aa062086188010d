"""Module 3's GUI: the coverage map over the orthophoto, the selection's parameters, click to toggle images, Save.

Thin over :class:`~matchplant.min_img_finder.run.MinImageFinder`: the window only edits the config, calls
``select`` / ``evaluate`` / :func:`~matchplant.min_img_finder.output.save_selection` and draws with
:func:`~matchplant.min_img_finder.output.draw_coverage`, so what it saves is what the CLI would write.

* Left: the map - every footprint in grey, the selected ones numbered with the area each owns, uncovered
  parts of the field in red.
* Right: the parameters (uncovered threshold, max overlap, overlap penalty, method), **Select** to run the
  selection, **Save** to write every output (and the config beside them), and a status line.
* Click a footprint on the map to add or remove that image (the smallest footprint under the pointer that
  is not selected is added; a click inside a selected image's owned area removes it).
"""

from __future__ import annotations

from pathlib import Path

import shapely
from matplotlib.widgets import Button, RadioButtons, TextBox

from matchplant.core.runtime.config import save_config, validate
from matchplant.core.runtime.errors import InputError, MatchPlantError
from matchplant.core.runtime.gui import close, figure, require_display, reveal, show, status_text
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.widgets import SetupField, SetupScreen
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.output import draw_coverage, save_selection
from matchplant.min_img_finder.run import MinImageFinder, Result

log = get_logger("min_img_finder.gui")

FIELDS = [
    ("uncovered_threshold", "uncovered %"),
    ("max_overlap", "max overlap %"),
    ("overlap_penalty", "overlap penalty"),
]


def selection_words(sel, reachable: float, asked_pct: float) -> str:
    """The status line after a selection: what was chosen, and why the coverage asked for was not reached
    (every image together covers less) or needed more overlap than the cap."""
    words = f"{sel.method}: {len(sel.indices)} images in {sel.seconds:.2f} s"
    short = 100 * reachable < asked_pct - 1e-6
    if short:
        words += f" - all images together cover only {100 * reachable:.1f}% (asked {asked_pct:g}%)"
    if sel.relaxed:
        words += " - overlap cap relaxed to reach " + ("that" if short else "the coverage")
    return words


class MinImgFinderGUI:
    """The selection window: coverage map, parameter boxes, Select and Save buttons and a status line."""

    def __init__(self, cfg: MinImgFinderConfig, config_path: Path | None = None, headless: bool | None = None):
        self.cfg = cfg
        self.config_path = config_path
        self.fig = figure(headless, figsize=(13, 8), title="3 Minimum image finder")
        self.ax = self.fig.add_axes([0.09, 0.08, 0.58, 0.86])
        panel = self.fig.add_axes([0.70, 0.08, 0.28, 0.86])
        panel.axis("off")
        panel.text(0.0, 1.0, "Minimum image finder", fontsize=14, weight="bold", va="top")
        panel.text(0.0, 0.955, "click a footprint to add / remove it", fontsize=9, va="top", color="0.3")
        self.boxes = {}
        for k, (key, label) in enumerate(FIELDS):
            bax = self.fig.add_axes([0.83, 0.82 - 0.06 * k, 0.14, 0.045])
            self.boxes[key] = TextBox(bax, label + " ", initial=f"{getattr(cfg, key):g}")
        rax = self.fig.add_axes([0.83, 0.56, 0.14, 0.09])
        self.method = RadioButtons(rax, ("greedy", "milp"), active=0 if cfg.method == "greedy" else 1)
        self.fig.text(0.71, 0.60, "method", fontsize=10)
        self.select_btn = Button(self.fig.add_axes([0.72, 0.45, 0.12, 0.06]), "Select")
        self.save_btn = Button(self.fig.add_axes([0.85, 0.45, 0.12, 0.06]), "Save")
        self.select_btn.on_clicked(lambda _e: self.run_selection())
        self.save_btn.on_clicked(lambda _e: self.save())
        self.info = panel.text(0.0, 0.36, "", fontsize=9, va="top", family="monospace")
        self.status = status_text(self.fig.add_axes([0.05, 0.0, 0.9, 0.04], frame_on=False), "")
        self.status.axes.axis("off")
        self.fig.canvas.mpl_connect("button_press_event", self.on_click)
        self.finder: MinImageFinder | None = None
        self.result: Result | None = None
        self.saved: dict | None = None
        self.load()

    # -- actions ---------------------------------------------------------------------------------
    def say(self, text: str, error: bool = False) -> None:
        """Show ``text`` in the status line, in red for an error."""
        self.status.set_text(text)
        self.status.set_color("red" if error else "black")
        self.fig.canvas.draw_idle()

    def read_params(self) -> bool:
        """Copy the parameter boxes into the config and check it; False (and the error shown) when a value is wrong."""
        try:
            for key, box in self.boxes.items():
                setattr(self.cfg, key, float(box.text))
            self.cfg.method = self.method.value_selected
            validate(self.cfg, check_paths=False)
            return True
        except (ValueError, MatchPlantError) as exc:
            self.say(f"invalid parameter: {exc}".splitlines()[0], error=True)
            return False

    def load(self) -> None:
        """Load the ODM project of the config and run a first selection; a load error goes to the status line."""
        if self.cfg.project_dir is None:
            self.say("set project_dir in the config (or --set project_dir=...) and reopen", error=True)
            return
        try:
            self.finder = MinImageFinder(self.cfg)
        except MatchPlantError as exc:
            self.say(str(exc).replace("\n", " | "), error=True)
            return
        self.run_selection()

    def run_selection(self) -> None:
        """Select images with the parameters in the boxes and show the result (the Select button)."""
        if self.finder is None or not self.read_params():
            return
        try:
            sel = self.finder.select()
        except MatchPlantError as exc:
            self.say(str(exc).replace("\n", " | "), error=True)
            return
        self.show_result(self.finder.evaluate(sel))
        self.say(selection_words(sel, self.finder.reachable, 100 - self.finder.cfg.uncovered_threshold))

    def toggle(self, index: int) -> None:
        """Add or remove one image and re-evaluate (coverage, owned areas)."""
        chosen = list(self.result.selection.indices) if self.result else []
        chosen.remove(index) if index in chosen else chosen.append(index)
        self.show_result(self.finder.evaluate(self.finder.with_indices(chosen)))
        name = self.finder.footprints[index].name
        self.say(f"{'added' if index in chosen else 'removed'} {name}")

    def on_click(self, event) -> None:
        """Answer a click on the map: add or remove the image under the pointer (not while zooming or panning)."""
        if event.inaxes is not self.ax or self.finder is None or event.xdata is None:
            return
        if getattr(self.fig.canvas, "toolbar", None) is not None and getattr(self.fig.canvas.toolbar, "mode", ""):
            return  # zoom/pan in progress
        index = self.image_at(event.xdata, event.ydata)
        if index is not None:
            self.toggle(index)

    def image_at(self, x: float, y: float) -> int | None:
        """Index of the image a click at ground point (x, y) toggles, or None when no footprint is there."""
        p = shapely.Point(x, y)
        if self.result is not None:  # inside a selected image's owned area: that image
            for i in self.result.selection.indices:
                if self.result.owned[self.finder.footprints[i].name].contains(p):
                    return i
        chosen = set(self.result.selection.indices) if self.result else set()
        hits = [
            (f.polygon.area, i)
            for i, f in enumerate(self.finder.footprints)
            if i not in chosen and f.polygon.contains(p)
        ]
        return min(hits)[1] if hits else None

    def show_result(self, result: Result) -> None:
        """Draw an evaluated selection on the map and its figures in the info box."""
        self.result = result
        draw_coverage(self.ax, self.finder, result)
        s = result.selection
        self.info.set_text(
            f"images       {len(s.indices)} of {len(self.finder.footprints)}\n"
            f"coverage     {100 * result.exact_coverage:.1f} %\n"
            f"asked        {100 * s.target:.1f} %\n"
            f"uncovered    {result.uncovered.area:.2f} m2\n"
            f"area         {self.finder.aoi.area:.1f} m2\n"
            f"method       {s.method}"
        )
        self.fig.canvas.draw_idle()

    def save(self) -> dict | None:
        """Write the shown selection's outputs and the config beside them (the Save button); the paths, or None."""
        if self.result is None:
            self.say("nothing to save yet", error=True)
            return None
        try:
            paths = save_selection(self.finder, self.result)
            out = Path(self.cfg.output_dir)
            save_config(self.cfg, out / "min_img_finder_config.yaml")
        except (MatchPlantError, OSError) as exc:
            self.say(f"save failed: {exc}".replace("\n", " | "), error=True)
            return None
        self.saved = paths
        self.say(f"saved {len(self.result.selection.indices)} images, CSV, figure and GeoPackage to {out}")
        return paths


SETUP_FIELDS = [
    SetupField("project_dir", "ODM project folder", "folder"),
    SetupField("aoi_file", "Area to cover (optional)", "file"),
    SetupField("output_dir", "Output folder", "folder"),
]


class MinImgFinderSetup:
    """Module 3's setup screen: the ODM project, the area to cover and the output folder with file pickers;
    **Select images** runs the selection, writes every output and opens the map to edit the choice."""

    def __init__(
        self, cfg: MinImgFinderConfig, config_path: Path | None = None, headless: bool | None = None, chooser=None
    ):
        self.config_path, self.headless = config_path, headless
        self.editor: MinImgFinderGUI | None = None
        self.screen = SetupScreen(
            "Minimum image finder: choose the ODM project",
            cfg,
            SETUP_FIELDS,
            self._run,
            headless=headless,
            chooser=chooser,
            run_label="Select images",
        )

    def _run(self, cfg: MinImgFinderConfig) -> str:
        if self.editor is not None:
            close(self.editor.fig)
        self.editor = MinImgFinderGUI(cfg, self.config_path, headless=self.headless)
        reveal(self.editor.fig)
        if self.editor.result is None:  # the finder could not load the project: its message
            raise InputError(self.editor.status.get_text(), path=cfg.project_dir)
        # the map drawn now, before the outputs are written: writing them takes seconds (the images, the figure,
        # the GeoPackage), and a window's first draw waits for its event loop, so the map stayed blank meanwhile
        self.editor.say("the selection is on the map; saving the images, the figure and the GeoPackage ...")
        self.editor.fig.canvas.draw()
        self.editor.fig.canvas.flush_events()
        if self.editor.save() is None:
            raise InputError(self.editor.status.get_text(), path=cfg.output_dir)
        return (
            f"{len(self.editor.result.selection.indices)} images selected and saved to {cfg.output_dir}; "
            "click footprints on the map to change the choice, then Save"
        )


def launch(cfg: MinImgFinderConfig, config_path: Path | None = None, chooser=None) -> MinImgFinderSetup:
    """The setup screen, then the coverage map; blocks until the windows are closed."""
    require_display("python 3_min_img_finder/min_img_finder.py --set project_dir=FOLDER")
    setup = MinImgFinderSetup(cfg, config_path, chooser=chooser)
    show(setup.screen.fig)
    return setup
