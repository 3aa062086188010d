"""Module 1's GUI: step through each GCP's candidate images and click the target's centre.

One Matplotlib window on every OS, thin over :mod:`matchplant.gcp_finder`: the image opens zoomed around
the predicted position (cyan cross); a click marks the GCP (red circle), dragging the mark moves it;
every change is saved to ``gcp_list.txt`` at once (:class:`~matchplant.gcp_finder.marks.MarkStore`). The list
on the right shows each GCP's marked/candidate images; ODM wants at least 3 per GCP.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from PIL import Image

from matchplant.core.runtime.gui import close as close_figure
from matchplant.core.runtime.gui import figure, is_headless, require_display, reveal, show, status_text
from matchplant.core.runtime.widgets import SetupField, SetupScreen
from matchplant.gcp_finder.candidates import Finder
from matchplant.gcp_finder.config import MIN_IMAGES_PER_GCP, GcpFinderConfig
from matchplant.gcp_finder.marks import MarkStore, store_for
from matchplant.gcp_finder.run import run
from matchplant.gcp_finder.target import load_gray, locate_target

HELP = "click: mark | drag: move | right-drag: pan | scroll: zoom | n/p: image | ]/[: GCP | h: all keys | q: quit"
KEYS = (
    "cyan +: predicted position, red o: your mark (saved at once)   click: mark   drag the mark: move it\n"
    "right-drag: pan   scroll or +/-: zoom   f: whole image   c: back to the prediction   a: find the target\n"
    "n/p or right/left: next/previous image   ]/[ or down/up: next/previous GCP   d: delete   u: undo   "
    "q: quit"
)
PICK_PX = 12  # a press this close (screen pixels) to the mark drags it
CLICK_PX = 5  # a press-release that moves less than this is a click


class GcpFinderGUI:
    """The marking window: one GCP's candidate images, the user's marks on them and the list of GCPs."""

    def __init__(
        self,
        finder: Finder,
        store: MarkStore,
        zoom_px: int = 150,
        target_size_m: float = 0.5,
        target_pattern: str = "checker",
        headless: bool | None = None,
    ):
        self.finder, self.store, self.zoom_px = finder, store, zoom_px
        self.target_size_m, self.target_pattern = target_size_m, target_pattern
        self.gcp_ids = list(finder.gcps)
        self.gi = next((i for i, g in enumerate(self.gcp_ids) if finder.candidates[g]), 0)
        self.ci = 0
        self._image_cache: tuple[str, np.ndarray] | None = None
        self._press = None  # (kind, display xy, data xy, limits)
        # tests: a coarser canvas draws faster
        offscreen = is_headless(headless) or matplotlib.get_backend().lower() == "agg"
        self.fig = figure(headless, figsize=(13, 8), dpi=50 if offscreen else None, title="1 GCP finder (marking)")
        manager = self.fig.canvas.manager
        if manager is not None and getattr(manager, "key_press_handler_id", None) is not None:
            self.fig.canvas.mpl_disconnect(manager.key_press_handler_id)  # our keys, not Matplotlib's
        self.ax = self.fig.add_axes((0.03, 0.12, 0.68, 0.82))
        self.side = self.fig.add_axes((0.73, 0.12, 0.26, 0.82))
        self.side.set_axis_off()
        self.help = self.fig.text(0.01, 0.003, HELP, fontsize=8, family="monospace", va="bottom")
        self.status = status_text(self.fig.add_axes((0.03, 0.065, 0.9, 0.03), frameon=False), "")
        self.status.axes.set_axis_off()
        self.mark_artist = None
        self.pred_artist = None
        for name, handler in (
            ("button_press_event", self.on_press),
            ("button_release_event", self.on_release),
            ("motion_notify_event", self.on_motion),
            ("scroll_event", self.on_scroll),
            ("key_press_event", self.on_key),
            ("pick_event", self.on_pick),
        ):
            self.fig.canvas.mpl_connect(name, handler)
        self.open()

    # -- state -------------------------------------------------------------------------------------
    @property
    def gcp(self) -> str:
        """Id of the GCP being marked."""
        return self.gcp_ids[self.gi]

    @property
    def candidates(self):
        """Candidate images of the current GCP, best first."""
        return self.finder.candidates[self.gcp]

    @property
    def candidate(self):
        """The candidate image on screen, or None when the GCP lies in no image."""
        c = self.candidates
        return c[self.ci] if c else None

    def _image(self, name: str) -> np.ndarray:
        if self._image_cache is None or self._image_cache[0] != name:
            with Image.open(self.finder.images[name].path) as im:
                arr = np.asarray(im.convert("RGB") if im.mode not in ("RGB", "L") else im)
            self._image_cache = (name, arr)
        return self._image_cache[1]

    # -- drawing -----------------------------------------------------------------------------------
    def open(self, keep_view: bool = False) -> None:
        """Show the current GCP's current candidate image, zoomed on the mark or the prediction."""
        ax = self.ax
        lims = (ax.get_xlim(), ax.get_ylim())
        ax.cla()
        c = self.candidate
        if c is None:
            ax.text(0.5, 0.5, f"GCP {self.gcp} lies in no image", ha="center", transform=ax.transAxes)
            self.mark_artist = self.pred_artist = None
        else:
            img = self._image(c.image)
            ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest")
            (self.pred_artist,) = ax.plot([c.u], [c.v], "+", color="cyan", ms=22, mew=1.2, label="predicted")
            (self.mark_artist,) = ax.plot([], [], "o", mfc="none", mec="red", ms=16, mew=2, label="mark")
            (self.centre_artist,) = ax.plot([], [], "+", color="red", ms=8, mew=1)
            mark = self.store.marks.get((self.gcp, c.image))
            if keep_view:
                ax.set_xlim(*lims[0])
                ax.set_ylim(*lims[1])
            else:
                u, v = mark if mark else (c.u, c.v)
                self.zoom_to(u, v, self.zoom_px)
            ax.set_title(
                f"{self.gcp}: image {self.ci + 1} of {len(self.candidates)}  {c.image}  "
                f"(rank {c.rank}, {c.center_distance:.2f} from centre)",
                fontsize=10,
            )
            ax.tick_params(labelsize=7, length=2)
            ax.locator_params(nbins=4)
        self.draw_mark()
        self.draw_side()
        self.fig.canvas.draw_idle()

    def zoom_to(self, u: float, v: float, half: float) -> None:
        """Show the square of half-side ``half`` pixels around image point (u, v)."""
        self.ax.set_xlim(u - half, u + half)
        self.ax.set_ylim(v + half, v - half)  # image rows grow downwards

    def fit(self) -> None:
        """Show the whole image (keys f and 0)."""
        info = self.finder.images[self.candidate.image] if self.candidate else None
        if info:
            self.ax.set_xlim(-0.5, info.width - 0.5)
            self.ax.set_ylim(info.height - 0.5, -0.5)
            self.fig.canvas.draw_idle()

    def draw_mark(self) -> None:
        """Draw the user's mark on the image on screen, or no mark when it has none."""
        c = self.candidate
        if c is None or self.mark_artist is None:
            return
        mark = self.store.marks.get((self.gcp, c.image))
        data = ([mark[0]], [mark[1]]) if mark else ([], [])
        self.mark_artist.set_data(*data)
        self.centre_artist.set_data(*data)

    def draw_side(self) -> None:
        """Redraw the side list: each GCP's marked and candidate image counts, coloured by whether it has enough."""
        s = self.side
        s.cla()
        s.set_axis_off()
        s.set_xlim(0, 1)
        s.set_ylim(0, 1)
        s.text(0, 1, "GCP    marked / images", family="monospace", fontsize=9, weight="bold", va="top")
        step = min(0.05, 0.9 / max(1, len(self.gcp_ids)))
        for i, gid in enumerate(self.gcp_ids):
            n, m = self.store.count(gid), len(self.finder.candidates[gid])
            ok = n >= MIN_IMAGES_PER_GCP
            state = "ok" if ok else "need 3" if m else "not seen"
            text = f"{'>' if i == self.gi else ' '} {gid:<8} {n:>2} / {m:<3} {state}"
            s.text(
                0,
                0.95 - i * step,
                text,
                family="monospace",
                fontsize=9,
                va="top",
                picker=True,
                color="tab:green" if ok else "tab:red" if n else "black",
                weight="bold" if i == self.gi else "normal",
            ).gcp_index = i
        s.text(0, 0.02, f"saved to {Path(self.store.path).name} after every change", fontsize=8, color="0.4")

    def message(self, text: str) -> None:
        """Show ``text`` in the status line."""
        self.status.set_text(text)
        self.fig.canvas.draw_idle()

    # -- actions -----------------------------------------------------------------------------------
    def mark(self, u: float, v: float) -> None:
        """Mark the current GCP at pixel (u, v) of the image on screen; the store saves it."""
        c = self.candidate
        if c is None:
            return
        self.store.set(self.gcp, c.image, u, v)
        self.draw_mark()
        self.draw_side()
        self.message(
            f"marked {self.gcp} in {c.image} at ({u:.1f}, {v:.1f}); {self.store.count(self.gcp)} image(s) for this GCP"
        )

    def next_image(self, step: int = 1) -> None:
        """Open the GCP's next (or, with a negative step, previous) candidate image, wrapping round (keys n/p)."""
        if self.candidates:
            self.ci = (self.ci + step) % len(self.candidates)
            self.open()

    def next_gcp(self, step: int = 1) -> None:
        """Go to the next (or, with a negative step, previous) GCP, wrapping round (keys ]/[)."""
        self.select_gcp((self.gi + step) % len(self.gcp_ids))

    def select_gcp(self, index: int) -> None:
        """Open the first candidate image of GCP number ``index``."""
        self.gi, self.ci = index, 0
        self.open()
        if not self.candidates:
            self.message(f"GCP {self.gcp} lies in no image: check its coordinates")

    def undo(self) -> None:
        """Undo the last mark change and show the image it was in (keys u and ctrl+z)."""
        key = self.store.undo()
        if key is None:
            self.message("nothing to undo")
            return
        gid, image = key
        if gid != self.gcp or (self.candidate and image != self.candidate.image):
            self.gi = self.gcp_ids.index(gid)
            self.ci = next((i for i, c in enumerate(self.candidates) if c.image == image), 0)
            self.open()
        else:
            self.draw_mark()
            self.draw_side()
        self.message(f"undone: {gid} in {image}")

    def delete(self) -> None:
        """Delete the current GCP's mark in the image on screen (key d)."""
        c = self.candidate
        if c is not None and self.store.delete(self.gcp, c.image):
            self.draw_mark()
            self.draw_side()
            self.message(f"deleted the mark of {self.gcp} in {c.image}")

    def auto_find(self) -> None:
        """Look for the target around the mark or the prediction and mark its centre if found (key a)."""
        c = self.candidate
        if c is None:
            return
        centre = self.store.marks.get((self.gcp, c.image), (c.u, c.v))
        gray = load_gray(self.finder.images[c.image].path)
        uv = locate_target(
            gray,
            centre[0],
            centre[1],
            self.target_size_m / self.finder.gsd(self.gcp, c.image),
            pattern=self.target_pattern,
        )
        if uv is None:
            self.message("no target found here; click its centre")
            return
        self.mark(*uv)

    def zoom(self, factor: float, x: float | None = None, y: float | None = None) -> None:
        """Zoom in by ``factor`` (out when below 1) about (x, y), the view's centre by default."""
        (x0, x1), (y0, y1) = self.ax.get_xlim(), self.ax.get_ylim()
        x = (x0 + x1) / 2 if x is None else x
        y = (y0 + y1) / 2 if y is None else y
        self.ax.set_xlim(x + (x0 - x) / factor, x + (x1 - x) / factor)
        self.ax.set_ylim(y + (y0 - y) / factor, y + (y1 - y) / factor)
        self.fig.canvas.draw_idle()

    # -- events ------------------------------------------------------------------------------------
    def _toolbar_busy(self) -> bool:
        tb = getattr(self.fig.canvas, "toolbar", None)
        return getattr(getattr(tb, "mode", None), "name", "NONE") != "NONE"

    def on_press(self, ev) -> None:
        """Answer a mouse press on the image: start a drag of the mark, a click, or a pan (right or middle button)."""
        if ev.inaxes is not self.ax or self._toolbar_busy() or self.candidate is None:
            return
        lims = (self.ax.get_xlim(), self.ax.get_ylim())
        if ev.button == 1:
            mark = self.store.marks.get((self.gcp, self.candidate.image))
            if mark is not None:
                mx, my = self.ax.transData.transform(mark)
                if np.hypot(mx - ev.x, my - ev.y) <= PICK_PX:
                    self._press = ("drag", (ev.x, ev.y), (ev.xdata, ev.ydata), lims)
                    return
            self._press = ("click", (ev.x, ev.y), (ev.xdata, ev.ydata), lims)
        elif ev.button in (2, 3):
            self._press = ("pan", (ev.x, ev.y), (ev.xdata, ev.ydata), lims)

    def on_motion(self, ev) -> None:
        """Answer a mouse move: follow the cursor with the dragged mark, or pan the image."""
        if self._press is None:
            return
        kind, (px, py), _, ((x0, x1), (y0, y1)) = self._press
        if kind == "drag" and ev.inaxes is self.ax:
            self.mark_artist.set_data([ev.xdata], [ev.ydata])
            self.centre_artist.set_data([ev.xdata], [ev.ydata])
            self.fig.canvas.draw_idle()
        elif kind == "pan":
            inv = self.ax.transData.inverted()
            # the limits at the press, so the image follows the cursor exactly
            a = inv.transform((px, py))
            b = inv.transform((ev.x, ev.y))
            dx, dy = a[0] - b[0], a[1] - b[1]
            self.ax.set_xlim(x0 + dx, x1 + dx)
            self.ax.set_ylim(y0 + dy, y1 + dy)
            self.fig.canvas.draw_idle()

    def on_release(self, ev) -> None:
        """Answer a mouse release: place the dragged mark, or mark the GCP where the user clicked."""
        press, self._press = self._press, None
        if press is None:
            return
        kind, (px, py), _, _ = press
        moved = np.hypot(ev.x - px, ev.y - py)
        inside = ev.inaxes is self.ax and ev.xdata is not None
        if kind == "drag":
            if inside and moved > 0:
                self.mark(ev.xdata, ev.ydata)
            else:
                self.draw_mark()
        elif kind == "click" and inside and moved < CLICK_PX:
            self.mark(ev.xdata, ev.ydata)

    def on_scroll(self, ev) -> None:
        """Answer the scroll wheel: zoom about the cursor."""
        if ev.inaxes is self.ax:
            self.zoom(1.25 if ev.button == "up" else 1 / 1.25, ev.xdata, ev.ydata)

    def on_pick(self, ev) -> None:
        """Answer a click on a GCP in the side list: open that GCP."""
        index = getattr(ev.artist, "gcp_index", None)
        if index is not None:
            self.select_gcp(index)

    def on_key(self, ev) -> None:
        """Answer a key press with its action (the keys listed by h)."""
        k = ev.key
        actions = {
            "right": self.next_image,
            "n": self.next_image,
            " ": self.next_image,
            "left": lambda: self.next_image(-1),
            "p": lambda: self.next_image(-1),
            "down": self.next_gcp,
            "]": self.next_gcp,
            "up": lambda: self.next_gcp(-1),
            "[": lambda: self.next_gcp(-1),
            "u": self.undo,
            "ctrl+z": self.undo,
            "d": self.delete,
            "delete": self.delete,
            "backspace": self.delete,
            "a": self.auto_find,
            "f": self.fit,
            "0": self.fit,
            "+": lambda: self.zoom(1.5),
            "=": lambda: self.zoom(1.5),
            "-": lambda: self.zoom(1 / 1.5),
            "c": self.open,
            "s": self.save,
            "h": self.toggle_help,
            "q": self.close,
            "escape": self.close,
        }
        if k in actions:
            actions[k]()

    def toggle_help(self) -> None:
        """Switch the help line between the short and the full list of keys (key h)."""
        self.help.set_text(KEYS if self.help.get_text() == HELP else HELP)
        self.fig.canvas.draw_idle()

    def save(self) -> None:
        """Write gcp_list.txt now (key s)."""
        path = self.store.save()
        self.message(f"saved {path}")

    def close(self) -> None:
        """Save gcp_list.txt and close the window (keys q and escape)."""
        self.store.save()
        close_figure(self.fig)

    def show(self) -> None:
        """Open the window and wait until the user closes it (nothing when headless)."""
        show(self.fig)


SETUP_FIELDS = [
    SetupField("images", "Images folder", "folder"),
    SetupField("survey", "GCP survey (id,x,y,z)", "file"),
    SetupField("survey_crs", "Survey CRS", "text"),
    SetupField("output_dir", "Output folder", "folder"),
]


class GcpFinderSetup:
    """Module 1's setup screen (the paper's Fig. 2a): images, survey and output folder with file pickers;
    **Find GCPs** writes the candidates (and, with ``auto``, gcp_list.txt) and opens the marking window."""

    def __init__(self, cfg: GcpFinderConfig, headless: bool | None = None, chooser=None):
        self.headless = headless
        self.finder: Finder | None = None
        self.store: MarkStore | None = None
        self.marking: GcpFinderGUI | None = None
        self.screen = SetupScreen(
            "GCP finder: choose the images and the GCP survey",
            cfg,
            SETUP_FIELDS,
            self._run,
            headless=headless,
            chooser=chooser,
            run_label="Find GCPs",
        )

    def _run(self, cfg: GcpFinderConfig) -> str:
        self.finder = run(cfg)
        self.store = store_for(cfg, self.finder, autosave=True)
        if self.marking is not None:
            close_figure(self.marking.fig)
        self.marking = GcpFinderGUI(
            self.finder,
            self.store,
            zoom_px=cfg.zoom_px,
            target_size_m=cfg.target_size_m,
            target_pattern=cfg.target_pattern,
            headless=self.headless,
        )
        reveal(self.marking.fig)
        seen = sum(1 for c in self.finder.candidates.values() if c)
        return (
            f"{seen} of {len(self.finder.gcps)} GCPs seen; candidates in {Path(cfg.output_dir) / 'candidates.csv'}"
            f"; marks go to {Path(self.store.path).name} (marking window open)"
        )


def launch(cfg: GcpFinderConfig, config_path: Path | None = None, chooser=None) -> GcpFinderSetup:
    """The setup screen, then the marking window; blocks until the windows are closed."""
    require_display("python 1_gcp_finder/gcp_finder.py --config FILE --set auto=true")
    setup = GcpFinderSetup(cfg, chooser=chooser)
    show(setup.screen.fig)
    if setup.store is not None:
        setup.store.save()
        setup.store.warn_few()
    return setup
