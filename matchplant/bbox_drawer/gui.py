"""Module 4's window: draw and correct plant boxes. A thin layer over
:class:`~matchplant.bbox_drawer.store.AnnotationStore`, so that every edit is tested without a window
and saved the moment it is made.

Mouse: drag on empty image to draw a box; click a box to select it; drag a selected box to move it,
drag its edge or corner to resize it; right or middle drag pans; the wheel zooms around the cursor.
Every edit is saved at once by the store; the help panel (key ``h``) lists the keys.

Category keys ``1``-``5`` choose the category of the NEXT box drawn. They relabel a box only when the
user picked it (clicked it, or pressed it to drag it); the box just drawn keeps its handles for a quick
resize but is not picked, so switching category right after drawing never relabels it.

``--gui`` first opens a setup screen (:class:`BboxDrawerSetup`: images, output folder, optional owned areas
and boxes to correct, with Tk's file pickers); **Open images** opens this window on them.

Fast on 20 MP photos with thousands of boxes (``bench/bench_bbox_drawer_gui.py``): the photo is shown
from a display pyramid, cropped to the view (:mod:`matchplant.bbox_drawer.view`); all boxes are one
collection; while a box is drawn, moved or resized only the dragged outline is redrawn over a saved
background (blitting), and the whole axes is drawn once at the press and once at the release.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.patches import Polygon, Rectangle

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.run import annotated_regions, open_session
from matchplant.bbox_drawer.store import AnnotationStore
from matchplant.bbox_drawer.view import BoxLayer, PanelImage, PyramidImage
from matchplant.core.formats.images import display_rgb, match_name, read_image
from matchplant.core.formats.owned_areas import read_owned_areas
from matchplant.core.runtime.config import validate
from matchplant.core.runtime.guard import check_outputs
from matchplant.core.runtime.gui import close, figure, fit_to_axes, require_display, reveal, show
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.widgets import SetupField, SetupScreen

log = get_logger("bbox_drawer")

COLORS = ["#ffd400", "#00e5ff", "#ff3df2", "#7cff4d", "#ff8c1a"]  # category 1..5, visible on green and soil
HANDLE_PX = 8  # how near (screen pixels) an edge must be to grab it
CLICK_PX = 3  # a press and release closer than this (screen pixels) is a click, not a drag
ZOOM_STEP = 1.25

HELP = """MOUSE
 drag on image    draw a box
 click box        select it
 drag selected    move it
 drag its edge    resize it
 right/middle drag
                  pan
 wheel            zoom

KEYS
 1-5        category of the next
            box; relabels a box
            you clicked
 delete, d  delete selected box
 z / ctrl+z undo
 y / ctrl+y redo
 n, pgdown  next image
 p, pgup    previous image
 arrows     pan
 + / -      zoom in / out
 0, home    whole image
 escape     deselect
 e          export COCO/YOLO now
 h          hide/show this help
 q          export and close

Every edit is saved at once;
reopen to resume."""


class BboxDrawerGUI:
    """The annotation window over ``store``. ``headless=True`` (tests) draws on a figure of its own, outside pyplot."""

    def __init__(
        self,
        store: AnnotationStore,
        owned_areas: dict[str, np.ndarray] | None = None,
        headless: bool | None = None,
        export_yolo: bool = True,
        include_unseen: bool = False,
        dpi: float | None = None,
        regions: dict[str, np.ndarray] | None = None,
    ):
        self.store = store
        # owned-area polygons keyed by this folder's image names (module 3 may name the shot, not the .tif)
        self.owned = {match_name(k, store.files): v for k, v in (owned_areas or {}).items()}
        self.export_options = {"yolo": export_yolo, "include_unseen": include_unseen, "regions": regions}
        self.fig = figure(headless, figsize=(13, 8), dpi=dpi, title="4 Bounding-box drawer")
        self._quiet_default_keys()
        self.ax = self.fig.add_axes([0.01, 0.05, 0.74, 0.90])
        self.help_ax = self.fig.add_axes([0.76, 0.05, 0.23, 0.90])
        self.help_ax.axis("off")
        # in the window, one line under the photo
        self.status = fit_to_axes(self.fig.text(0.01, 0.012, "", fontsize=9, family="monospace"), rows=1)
        self.category = 1
        self.selected: int | None = None
        self.picked = False  # the selected box was clicked by the user (category keys relabel it)
        self.closed = False
        self.drag: dict | None = None
        self.layer: BoxLayer | None = None
        self.sel_rect = self.sel_dots = None
        self.preview = None
        self.background = None  # the axes without the dragged box, saved at the press (blitting)
        self.image_artist = None
        self.message = ""
        self._draw_help()
        for event, handler in (
            ("button_press_event", self.on_press),
            ("motion_notify_event", self.on_motion),
            ("button_release_event", self.on_release),
            ("key_press_event", self.on_key),
            ("scroll_event", self.on_scroll),
            ("close_event", self.on_close),
        ):
            self.fig.canvas.mpl_connect(event, handler)
        self.show_image(store.current)

    # -- setup and drawing
    def _quiet_default_keys(self) -> None:
        """Matplotlib's own keys (s = save, l = log scale, ...) would clash with ours."""
        handler = getattr(self.fig.canvas.manager, "key_press_handler_id", None) if self.fig.canvas.manager else None
        if handler is not None:
            self.fig.canvas.mpl_disconnect(handler)

    def _draw_help(self) -> None:
        """The help panel, rendered once as a picture: redrawing ~40 lines of text on every mouse move
        would make the window sluggish."""
        pos = self.help_ax.get_position()
        w, h = self.fig.get_size_inches()
        panel = figure(True, figsize=(pos.width * w, pos.height * h), dpi=self.fig.dpi, facecolor="white")
        cats = "\n".join(f"     {i + 1}  {name}" for i, name in enumerate(self.store.categories))
        text = panel.text(
            0.02,
            0.99,
            "CATEGORIES\n" + cats + "\n\n" + HELP,
            va="top",
            ha="left",
            family="monospace",
            fontsize=8.5,
            linespacing=1.25,
        )
        panel.canvas.draw()
        # colour swatches in front of the category lines (line height from the rendered text)
        box = text.get_window_extent()
        line = box.height / (text.get_text().count("\n") + 1) / (pos.height * h * self.fig.dpi)
        for i in range(len(self.store.categories)):
            panel.patches.append(
                Rectangle(
                    (0.03, 0.99 - line * (i + 1.95)),
                    0.06,
                    line * 0.7,
                    transform=panel.transFigure,
                    figure=panel,
                    color=COLORS[i],
                )
            )
        panel.canvas.draw()
        self.help_ax.clear()
        self.help_ax.axis("off")
        self.help_ax.add_image(PanelImage(self.help_ax, np.array(panel.canvas.buffer_rgba())))

    @property
    def name(self) -> str:
        """Name of the photo on screen."""
        return self.store.current

    def show_image(self, name: str) -> None:
        """Open photo ``name`` with its boxes and owned area, the whole photo in view and nothing selected."""
        self.store.set_current(name)
        self.message = ""  # "box added" and the like were about the previous image
        self.selected = None
        self.picked = False
        self.drag = None
        img = display_rgb(read_image(self.store.files[name]))
        self.ax.clear()
        self.image_artist = None  # the previous photo's pyramid is freed before the next one is built
        # data coordinates on pixel edges: x = 0 is the left edge of the first pixel (COCO)
        self.image_artist = PyramidImage(self.ax, img)
        del img
        self.ax.add_image(self.image_artist)
        self.ax.set_aspect("equal")  # square pixels, as imshow would set
        poly = self.owned.get(name)
        if poly is not None:
            self.ax.add_patch(Polygon(poly, closed=True, fill=False, ls="--", lw=1.5, ec="white"))
        self.ax.set_xticks([])
        self.ax.set_yticks([])
        self.layer = BoxLayer(self.ax, COLORS)
        self.sel_rect = Rectangle((0, 0), 0, 0, fill=False, lw=2.6, visible=False, zorder=4)
        self.ax.add_patch(self.sel_rect)
        (self.sel_dots,) = self.ax.plot([], [], "s", ms=6, mfc="white", visible=False, zorder=5)
        self.preview = Rectangle(
            (0, 0), 0, 0, fill=False, ec="white", lw=1.2, ls=":", animated=True, visible=False, zorder=6
        )
        self.ax.add_patch(self.preview)
        self.background = None
        self.reset_view()
        self.redraw()

    def reset_view(self) -> None:
        """Show the whole photo (keys 0 and home)."""
        w, h = self.store.size(self.name)
        self.ax.set_xlim(0, w)
        self.ax.set_ylim(h, 0)

    def redraw(self, hidden: int | None = None, draw: bool = True) -> None:
        """Update the box collection, the selection and the status; ``hidden`` leaves a box out (it is
        being dragged). ``draw=False`` leaves the drawing to the caller."""
        boxes = self.store.boxes(self.name)
        self.layer.set_boxes(boxes, hidden)
        sel = next((b for b in boxes if b["id"] == self.selected), None) if self.selected != hidden else None
        self.sel_rect.set_visible(sel is not None)
        self.sel_dots.set_visible(sel is not None)
        if sel is not None:
            x1, y1, x2, y2 = sel["xyxy"]
            color = COLORS[sel["category_id"] - 1]
            self.sel_rect.set_bounds(x1, y1, x2 - x1, y2 - y1)
            self.sel_rect.set_edgecolor(color)
            self.sel_rect.set_linestyle("--" if "score" in sel else "-")
            self.sel_dots.set_data([x1, x2, x2, x1], [y1, y1, y2, y2])
            self.sel_dots.set_markeredgecolor(color)
        self.ax.set_title(self.name, fontsize=10)
        i = self.store.images.index(self.name) + 1
        cat = self.store.categories[self.category - 1]
        picked = (
            f"   selected: {self.store.categories[sel['category_id'] - 1]} (keys relabel it)"
            if sel is not None and self.picked
            else ""
        )
        self.status.set_text(
            f"image {i}/{len(self.store.images)}   boxes {len(boxes)}   next box: "
            f"{self.category}={cat}{picked}   {self.message}"
        )
        if draw:
            self.fig.canvas.draw_idle()

    # -- geometry helpers
    def data_xy(self, event, snap: bool = False) -> tuple[float, float]:
        """Image coordinates of an event, also when the mouse has left the axes (a box dragged past the
        edge). ``snap`` rounds to whole pixel edges: boxes drawn by hand are in whole pixels."""
        x, y = self.ax.transData.inverted().transform((event.x, event.y))
        return (float(round(x)), float(round(y))) if snap else (float(x), float(y))

    def px_per_unit(self) -> float:
        """Screen pixels per photo pixel at the current zoom."""
        x0, x1 = self.ax.get_xlim()
        return self.ax.bbox.width / abs(x1 - x0)

    def hit(self, x: float, y: float) -> tuple[int | None, str]:
        """The box under (x, y) and which part: edges like 'lt' or 'r' for resizing, 'in' for moving."""
        tol = HANDLE_PX / self.px_per_unit()
        boxes = self.store.boxes(self.name)
        if not boxes:
            return None, ""
        xyxy = np.array([b["xyxy"] for b in boxes], float)
        near = np.flatnonzero(
            (xyxy[:, 0] - tol <= x) & (x <= xyxy[:, 2] + tol) & (xyxy[:, 1] - tol <= y) & (y <= xyxy[:, 3] + tol)
        )  # vectorised pre-filter
        order = sorted(
            (boxes[i] for i in near),
            key=lambda b: (b["id"] != self.selected, (b["xyxy"][2] - b["xyxy"][0]) * (b["xyxy"][3] - b["xyxy"][1])),
        )
        for b in order:
            x1, y1, x2, y2 = b["xyxy"]
            if not (x1 - tol <= x <= x2 + tol and y1 - tol <= y <= y2 + tol):
                continue
            if b["id"] == self.selected:
                edges = ("l" if abs(x - x1) <= tol else "r" if abs(x - x2) <= tol else "") + (
                    "t" if abs(y - y1) <= tol else "b" if abs(y - y2) <= tol else ""
                )
                if edges:
                    return b["id"], edges
            if x1 <= x <= x2 and y1 <= y <= y2:
                return b["id"], "in"
        return None, ""

    # -- mouse
    def on_press(self, event) -> None:
        """Answer a mouse press: start drawing a box, moving or resizing the box under the cursor, or panning."""
        if event.inaxes is not self.ax:
            return
        x, y = self.data_xy(event)
        start = self.data_xy(event, snap=True)
        if event.button in (2, 3):
            self.drag = {
                "mode": "pan",
                "px": (event.x, event.y),
                "xlim": self.ax.get_xlim(),
                "ylim": self.ax.get_ylim(),
            }
            return
        if event.button != 1:
            return
        box_id, part = self.hit(x, y)
        if box_id is None:
            self.selected = None
            self.picked = False
            self.drag = {"mode": "draw", "start": start, "px": (event.x, event.y)}
        else:
            # pressing another box picks it; dragging the box just drawn (to fix it) does not
            self.picked = self.picked or box_id != self.selected
            self.selected = box_id
            self.drag = {
                "mode": "resize" if part != "in" else "move",
                "edges": part,
                "start": start,
                "px": (event.x, event.y),
                "box": self.store.box(self.name, box_id),
            }
        self._start_blit(box_id)

    def _start_blit(self, dragged: int | None) -> None:
        """Draw everything but the dragged box once and keep that picture: each mouse move then
        pastes it back and draws the dragged outline alone."""
        self.redraw(hidden=dragged, draw=False)
        self.fig.canvas.draw()
        self.background = self.fig.canvas.copy_from_bbox(self.ax.bbox)
        if dragged is not None:  # a pressed box stays visible until the mouse moves
            x1, y1, x2, y2 = self.drag["box"]["xyxy"]
            self._blit_preview(x1, y1, x2, y2)

    def _blit_preview(self, x1: float, y1: float, x2: float, y2: float) -> None:
        canvas = self.fig.canvas
        if self.background is not None:
            canvas.restore_region(self.background)
        self.preview.set_bounds(min(x1, x2), min(y1, y2), abs(x2 - x1), abs(y2 - y1))
        self.preview.set_visible(True)
        self.ax.draw_artist(self.preview)
        canvas.blit(self.ax.bbox)

    @staticmethod
    def _dragged_box(d: dict, x: float, y: float) -> list[float]:
        x0, y0 = d["start"]
        if d["mode"] == "draw":
            return [x0, y0, x, y]
        x1, y1, x2, y2 = d["box"]["xyxy"]
        dx, dy = x - x0, y - y0
        if d["mode"] == "move":
            return [x1 + dx, y1 + dy, x2 + dx, y2 + dy]
        e = d["edges"]
        return [
            x1 + dx if "l" in e else x1,
            y1 + dy if "t" in e else y1,
            x2 + dx if "r" in e else x2,
            y2 + dy if "b" in e else y2,
        ]

    @staticmethod
    def _is_click(d: dict, event) -> bool:
        px0, py0 = d["px"]
        return abs(event.x - px0) < CLICK_PX and abs(event.y - py0) < CLICK_PX

    def on_motion(self, event) -> None:
        """Answer a mouse move: pan, or preview the box being drawn, moved or resized."""
        if not self.drag:
            return
        if self.drag["mode"] == "pan":
            inv = self.ax.transData.inverted()
            (ax0, ay0), (ax1, ay1) = inv.transform([self.drag["px"], (event.x, event.y)])
            xl, yl = self.drag["xlim"], self.drag["ylim"]
            self.ax.set_xlim(xl[0] - (ax1 - ax0), xl[1] - (ax1 - ax0))
            self.ax.set_ylim(yl[0] - (ay1 - ay0), yl[1] - (ay1 - ay0))
            self.fig.canvas.draw_idle()
            return
        if self._is_click(self.drag, event):
            return
        self._blit_preview(*self._dragged_box(self.drag, *self.data_xy(event, snap=True)))

    def on_release(self, event) -> None:
        """Answer a mouse release: add, move or resize the box in the store, or select the box clicked."""
        d, self.drag = self.drag, None
        self.preview.set_visible(False)
        self.background = None
        if not d or d["mode"] == "pan":
            return
        click = self._is_click(d, event)
        box = self._dragged_box(d, *self.data_xy(event, snap=True))
        if click:
            self.picked = d["mode"] != "draw"  # a click on a box picks it
            self.message = "" if d["mode"] == "draw" else "selected"
        elif d["mode"] == "draw":
            new = self.store.add(self.name, box, self.category)
            self.selected, self.picked = new, False  # handles to fix it; category keys leave it alone
            self.message = "box added" if new is not None else "too small: no box"
        elif d["mode"] == "move":
            x1, y1 = d["box"]["xyxy"][:2]
            self.store.move(self.name, d["box"]["id"], box[0] - x1, box[1] - y1)
            self.message = "box moved"
        else:
            self.store.resize(self.name, d["box"]["id"], box)
            self.message = "box resized"
        self.redraw()

    def on_scroll(self, event) -> None:
        """Answer the scroll wheel: zoom about the cursor."""
        if event.inaxes is not self.ax:
            return
        self.zoom(ZOOM_STEP ** (event.step if event.step else (1 if event.button == "up" else -1)), self.data_xy(event))

    def zoom(self, factor: float, center: tuple[float, float] | None = None) -> None:
        """Zoom in by ``factor`` (out when below 1) about ``center``, the view's centre by default."""
        (x0, x1), (y0, y1) = self.ax.get_xlim(), self.ax.get_ylim()
        cx, cy = center if center else ((x0 + x1) / 2, (y0 + y1) / 2)
        self.ax.set_xlim(cx + (x0 - cx) / factor, cx + (x1 - cx) / factor)
        self.ax.set_ylim(cy + (y0 - cy) / factor, cy + (y1 - cy) / factor)
        self.fig.canvas.draw_idle()

    def pan(self, fx: float, fy: float) -> None:
        """Move the view by fractions ``fx``, ``fy`` of its width and height (arrow keys)."""
        (x0, x1), (y0, y1) = self.ax.get_xlim(), self.ax.get_ylim()
        dx, dy = fx * (x1 - x0), fy * (y0 - y1)  # y axis is inverted (image rows grow downwards)
        self.ax.set_xlim(x0 + dx, x1 + dx)
        self.ax.set_ylim(y0 + dy, y1 + dy)
        self.fig.canvas.draw_idle()

    # -- keys
    def on_key(self, event) -> None:
        """Answer a key press: category, delete, undo, redo, next or previous photo, pan, zoom, help, export, quit."""
        k = (event.key or "").lower()
        if k in {str(i) for i in range(1, len(self.store.categories) + 1)}:
            self.category = int(k)
            if self.selected is not None and self.picked:
                self.store.set_category(self.name, self.selected, self.category)
                self.message = "category changed"
            else:
                self.message = f"next box: {self.store.categories[self.category - 1]}"
        elif k in ("delete", "backspace", "d") and self.selected is not None:
            self.store.delete(self.name, self.selected)
            self.selected, self.picked = None, False
            self.message = "box deleted"
        elif k in ("z", "ctrl+z", "cmd+z"):
            self._history(self.store.undo(), "undone", "nothing to undo")
            return
        elif k in ("y", "ctrl+y", "cmd+y", "ctrl+shift+z"):
            self._history(self.store.redo(), "redone", "nothing to redo")
            return
        elif k in ("n", "pagedown", " "):
            self.export()
            self.show_image(self.store.images[(self.store.images.index(self.name) + 1) % len(self.store.images)])
            return
        elif k in ("p", "pageup"):
            self.export()
            self.show_image(self.store.images[self.store.images.index(self.name) - 1])
            return
        elif k in ("left", "right", "up", "down"):
            self.pan(*{"left": (-0.2, 0), "right": (0.2, 0), "up": (0, -0.2), "down": (0, 0.2)}[k])
            return
        elif k in ("+", "="):
            self.zoom(ZOOM_STEP)
            return
        elif k == "-":
            self.zoom(1 / ZOOM_STEP)
            return
        elif k in ("0", "home"):
            self.reset_view()
        elif k == "escape":
            self.selected, self.picked = None, False
        elif k in ("h", "f1", "?"):
            self.help_ax.set_visible(not self.help_ax.get_visible())
        elif k in ("e", "ctrl+s"):
            paths = self.export()
            self.message = f"exported {paths['coco'].name}" + (" + YOLO" if "yolo" in paths else "")
        elif k == "q":
            self.finish()
            return
        else:
            return
        self.redraw()

    def _history(self, image: str | None, done: str, nothing: str) -> None:
        self.message = done if image else nothing
        if image and image != self.name:
            self.show_image(image)  # show the edit that was undone
            self.message = done
        self.selected, self.picked = None, False
        self.redraw()

    # -- saving
    def export(self) -> dict:
        """Write the session's boxes as COCO annotations.json (and what else the config asks for); the paths written."""
        return self.store.export(coco=True, **self.export_options)

    def on_close(self, event=None) -> None:
        """Answer the window closing: export the annotations, once."""
        if self.closed:
            return
        self.closed = True
        paths = self.export()
        log.info("annotations exported to %s", paths["coco"])

    def finish(self) -> None:
        """Export and close (a headless figure has no window to close: exported here)."""
        self.on_close()
        close(self.fig)


def open_window(cfg: BboxDrawerConfig, headless: bool | None = None, dpi: float | None = None) -> BboxDrawerGUI:
    """The drawing window for a config: the session opened or resumed, the imports applied."""
    validate(cfg, source="GUI")
    check_outputs(cfg, source="GUI")
    store = open_session(cfg)
    return BboxDrawerGUI(
        store,
        read_owned_areas(cfg.owned_areas),
        headless=headless,
        dpi=dpi,
        export_yolo=cfg.export_yolo,
        include_unseen=cfg.include_unseen,
        regions=annotated_regions(cfg, store),
    )


SETUP_FIELDS = [
    SetupField("images", "Images folder", "folder"),
    SetupField("output_dir", "Output folder", "folder"),
    SetupField("owned_areas", "Owned areas (optional)", "file"),
    SetupField("import_coco", "Boxes to fix (COCO, opt.)", "file"),
    SetupField("import_predictions", "Predictions (module 7, opt.)", "file"),
]


def owned_areas_beside(texts: dict[str, str]) -> dict[str, str]:
    """Module 3 writes ``owned_areas.json`` beside the ``images/`` folder it fills: offer it for those images."""
    images = texts.get("images")
    candidate = Path(images).parent / "owned_areas.json" if images else None
    return {"owned_areas": str(candidate)} if candidate is not None and candidate.is_file() else {}


class BboxDrawerSetup:
    """Module 4's setup screen: the images, the output folder and, optionally, module 3's owned areas and
    boxes to correct, with file pickers; **Open images** opens the drawing window on them (again: the
    previous window is exported and closed first)."""

    def __init__(self, cfg: BboxDrawerConfig, headless: bool | None = None, chooser=None, dpi: float | None = None):
        self.headless, self.dpi = headless, dpi
        self.window: BboxDrawerGUI | None = None
        self.screen = SetupScreen(
            "Box drawer: choose the images to annotate",
            cfg,
            SETUP_FIELDS,
            self._run,
            headless=headless,
            chooser=chooser,
            run_label="Open images",
            prefill=owned_areas_beside,
        )

    def _run(self, cfg: BboxDrawerConfig) -> str:
        if self.window is not None:
            self.window.finish()
        self.window = open_window(cfg, self.headless, self.dpi)
        reveal(self.window.fig)
        store = self.window.store
        return (
            f"{len(store.images)} images, {store.count()} boxes; drawing window open; every edit is saved "
            f"to {store.path}"
        )


def launch(cfg: BboxDrawerConfig, config_path=None, chooser=None) -> BboxDrawerSetup:
    """The setup screen, then the drawing window; blocks until the windows are closed."""
    require_display("python 4_bbox_drawer/bbox_drawer.py --set images=FOLDER --set output_dir=FOLDER")
    setup = BboxDrawerSetup(cfg, chooser=chooser)
    show(setup.screen.fig)
    if setup.window is not None:
        setup.window.on_close()  # exported when its window closed; once more is a no-op
    return setup
