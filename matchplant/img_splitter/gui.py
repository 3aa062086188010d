"""Module 5's window: settings, a preview of one image's tile grid with kept and lost boxes, a summary,
and Run. A thin layer over :mod:`matchplant.img_splitter.run` (the preview uses the same plan as the run).

``--gui`` first opens a setup screen (:class:`ImgSplitterSetup`: the images, the annotations and the output
folder, with Tk's file pickers); **Preview** opens this window on them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.patches import Polygon, Rectangle
from matplotlib.widgets import Button

from matchplant.core.formats.images import display_rgb, read_image
from matchplant.core.runtime.config import parse_override, save_config, set_value, to_dict_value, validate
from matchplant.core.runtime.errors import InputError, MatchPlantError
from matchplant.core.runtime.gui import close, figure, fit_to_axes, require_display, reveal, show
from matchplant.core.runtime.widgets import QuietTextBox, SetupField, SetupScreen, setting_field
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.run import load_sources, plan_all, run

FIELDS = [
    "images",
    "annotations",
    "output_dir",
    "tile_size",
    "overlap",
    "min_visible",
    "min_box_side",
    "split",
    "seed",
    "split_mode",
    "negative_share",
    "yolo",
]
KEPT, LOST = "#39ff14", "#ff2a2a"
TILE_COLORS = ["white", "#ffd400", "#00e5ff", "#ff3df2"]  # neighbouring tiles in different colours


class ImgSplitterGUI:
    """The settings, the preview of one image and Run. ``headless=True`` (tests) draws on a figure of its
    own, outside pyplot."""

    def __init__(
        self,
        cfg: ImgSplitterConfig,
        config_path: Path | None = None,
        headless: bool | None = None,
        dpi: float | None = None,
    ):
        self.cfg = cfg
        self.config_path = config_path
        self.fig = figure(headless, figsize=(14, 8.5), dpi=dpi, title="5 Image splitter")
        self.fig.text(0.02, 0.965, "Tiling and split (module 5)", fontsize=13, weight="bold")
        self.boxes: dict[str, QuietTextBox] = {}
        for i, key in enumerate(FIELDS):
            ax = self.fig.add_axes([0.13, 0.90 - i * 0.05, 0.19, 0.036])
            value = getattr(cfg, key)
            # a yes/no setting is a check box (it was a text field holding "False")
            self.boxes[key] = setting_field(ax, key, value if isinstance(value, bool) else to_dict_value(value))
            if isinstance(self.boxes[key], QuietTextBox):
                self.boxes[key].label.set_fontsize(9)
        row = 0.90 - len(FIELDS) * 0.05
        self.buttons = {}
        for j, (label, action) in enumerate(
            [
                ("Preview", self.refresh),
                ("< image", lambda: self.step(-1)),
                ("image >", lambda: self.step(1)),
                ("Run", self.run),
                ("Save config", self.save),
            ]
        ):
            ax = self.fig.add_axes([0.02 + (j % 3) * 0.105, row - (j // 3) * 0.055, 0.095, 0.04])
            button = Button(ax, label)
            button.on_clicked(lambda _event, a=action: self._guarded(a))
            self.buttons[label] = button
        self.ax = self.fig.add_axes([0.36, 0.22, 0.62, 0.72])
        self.summary = self.fig.text(0.36, 0.03, "", fontsize=9, family="monospace", va="bottom")
        self.status = fit_to_axes(self.fig.text(0.02, 0.015, "", fontsize=9, color="black"))  # in the window
        self.sources = None
        self.index = 0
        self.result: dict | None = None
        self._guarded(self.refresh)

    # -- actions
    def _guarded(self, action) -> None:
        """Run a button's action; show a user error in the status line instead of raising."""
        try:
            action()
        except MatchPlantError as exc:
            self.say(str(exc).replace("\n", "   "), error=True)
        self.fig.canvas.draw_idle()

    def say(self, text: str, error: bool = False) -> None:
        """Show ``text`` in the status line, in red for an error."""
        self.status.set_text(text)
        self.status.set_color("#c00000" if error else "black")

    def apply_fields(self) -> None:
        """Copy the text boxes into the config (parsed like --set key=value) and check it."""
        for key, box in self.boxes.items():
            text = box.text.strip()
            _, value = parse_override(f"{key}={text}")
            if text in ("", "null", "None") and key in ("images", "annotations", "output_dir"):
                value = None
            if value is None:
                setattr(self.cfg, key, None)
            else:
                set_value(self.cfg, key, value, source="GUI", base=Path.cwd())
        validate(self.cfg, source="GUI")

    def refresh(self) -> None:
        """Re-plan every image's tiles with the settings in the fields and redraw (the Preview button)."""
        self.apply_fields()
        self.sources, _, self.missing = load_sources(self.cfg)
        plan_all(self.cfg, self.sources)
        self.index = min(self.index, len(self.sources) - 1)
        self.draw()
        self.say("preview updated; press Run to write the tiles")

    def step(self, delta: int) -> None:
        """Show the next (or, with a negative ``delta``, previous) image, wrapping round (the image buttons)."""
        if self.sources is None:
            self.refresh()
        self.index = (self.index + delta) % len(self.sources)
        self.draw()

    def run(self) -> None:
        """Write the tiles and splits with the settings in the fields (the Run button)."""
        self.apply_fields()
        self.say("running... (progress in the terminal)")
        self.fig.canvas.draw()
        self.fig.canvas.flush_events()
        self.result = run(self.cfg)
        self.refresh()
        self.say(f"done: {self.result['tiles']} tiles written to {self.cfg.output_dir}")

    def save(self) -> None:
        """Save the settings in the fields to the config file, or to output_dir (the Save config button)."""
        self.apply_fields()
        path = self.config_path or Path(self.cfg.output_dir) / "img_splitter.yaml"
        save_config(self.cfg, path)
        self.say(f"config saved to {path}")

    # -- drawing
    def draw(self) -> None:
        """Draw the current image with its tiles (written or dropped) and its boxes (kept or lost)."""
        s = self.sources[self.index]
        plan = s.plan
        ax = self.ax
        ax.clear()
        img = display_rgb(read_image(s.path))
        step = max(1, int(max(s.width, s.height) // 1500))  # a preview does not need every pixel
        ax.imshow(img[::step, ::step], extent=(0, s.width, s.height, 0), cmap="gray" if img.ndim == 2 else None)
        written = set(np.flatnonzero(plan.positive).tolist()) | set(s.negatives)
        for t, (x0, y0, x1, y1) in enumerate(plan.tiles):
            kept = t in written
            ax.add_patch(
                Rectangle(
                    (x0, y0),
                    x1 - x0,
                    y1 - y0,
                    fill=False,
                    lw=1.4 if kept else 0.8,
                    ec=TILE_COLORS[t % len(TILE_COLORS)] if kept else "0.55",
                    ls="-" if kept else ":",
                )
            )
        if s.region is not None:  # only this part was annotated: the rest of each tile is masked
            ax.add_patch(Polygon(s.region, closed=True, fill=False, lw=1.6, ls="--", ec="white"))
        anywhere = plan.kept_anywhere
        for (x1, y1, x2, y2), ok in zip(plan.boxes, anywhere):
            ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, lw=1.2, ec=KEPT if ok else LOST))
        ax.set_xlim(0, s.width)
        ax.set_ylim(s.height, 0)
        ax.set_title(
            f"{s.name}  ({self.index + 1}/{len(self.sources)}, {s.split})  -  coloured: tiles written, "
            f"dotted: empty tiles dropped, green: boxes kept, red: boxes lost",
            fontsize=9,
        )
        ax.set_xticks([])
        ax.set_yticks([])
        self.summary.set_text(self.summary_text())

    def summary_text(self) -> str:
        """Tile and box counts of the current image and of all images, for the summary under the preview."""
        s = self.sources[self.index]
        plan = s.plan
        n_pos = int(plan.positive.sum())
        lines = [
            f"this image: {len(plan.tiles)} tiles ({n_pos} with plants, {len(s.negatives)} negatives kept, "
            f"{len(plan.tiles) - n_pos - len(s.negatives)} empty dropped); {len(plan.boxes)} boxes, "
            f"{int((~plan.kept_anywhere).sum())} lost in every tile"
        ]
        per = {k: [x for x in self.sources if x.split == k] for k in ("train", "val", "test")}
        tiles = {k: sum(int(x.plan.positive.sum()) + len(x.negatives) for x in v) for k, v in per.items()}
        lines.append("all images: " + ", ".join(f"{k} {len(v)} images / {tiles[k]} tiles" for k, v in per.items()))
        lost = sum(int((~x.plan.kept_anywhere).sum()) for x in self.sources)
        total = sum(len(x.boxes) for x in self.sources)
        lines.append(
            f"boxes: {total - lost} of {total} kept in at least one tile; "
            f"{len(self.missing)} annotated image(s) missing on disk"
        )
        return "\n".join(lines)


SETUP_FIELDS = [
    SetupField("images", "Images folder", "folder"),
    SetupField("annotations", "Annotations (COCO JSON)", "file"),
    SetupField("output_dir", "Output folder", "folder"),
]


class ImgSplitterSetup:
    """Module 5's setup screen: the annotated images, their boxes (module 4's annotations.json; a YOLO
    labels folder can be typed) and the output folder, with file pickers; **Preview** opens the tiling
    window (settings, preview, Run) on them."""

    def __init__(
        self,
        cfg: ImgSplitterConfig,
        config_path: Path | None = None,
        headless: bool | None = None,
        chooser=None,
        dpi: float | None = None,
    ):
        self.config_path, self.headless, self.dpi = config_path, headless, dpi
        self.preview: ImgSplitterGUI | None = None
        self.screen = SetupScreen(
            "Image splitter: choose the annotated images",
            cfg,
            SETUP_FIELDS,
            self._run,
            headless=headless,
            chooser=chooser,
            run_label="Preview",
        )

    def _run(self, cfg: ImgSplitterConfig) -> str:
        if self.preview is not None:
            close(self.preview.fig)
        self.preview = ImgSplitterGUI(cfg, self.config_path, headless=self.headless, dpi=self.dpi)
        if self.preview.sources is None:  # the preview could not read the images or boxes: its message
            message = self.preview.status.get_text()
            close(self.preview.fig)
            self.preview = None
            raise InputError(message, path=cfg.annotations)
        reveal(self.preview.fig)  # made inside this window's event loop: pyplot keeps it hidden until shown
        return (
            f"{len(self.preview.sources)} annotated images; preview window open: check the tiles, then press Run there"
        )


def launch(cfg: ImgSplitterConfig, config_path: Path | None = None, chooser=None) -> ImgSplitterSetup:
    """The setup screen, then the preview window; blocks until the windows are closed."""
    require_display(
        "python 5_img_splitter/img_splitter.py --set images=FOLDER --set annotations=FILE --set output_dir=FOLDER"
    )
    setup = ImgSplitterSetup(cfg, config_path, chooser=chooser)
    show(setup.screen.fig)
    return setup
