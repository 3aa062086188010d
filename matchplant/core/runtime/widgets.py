"""The widgets of MatchPlant's windows: a text field that answers at once, a busy indicator, Tk's file
dialogs and the setup screens of modules 1, 3, 4, 5 (a "Browse" button per path, then Run).

Only the GUIs import this (through :mod:`matchplant.core.runtime.gui`): Matplotlib's widgets cost most of a
second at start-up, which a command run without a window never pays.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from matplotlib.backend_tools import Cursors
from matplotlib.figure import Figure
from matplotlib.widgets import Button, CheckButtons, TextBox

from matchplant.core.runtime.config import set_value, validate
from matchplant.core.runtime.errors import DependencyError, MatchPlantError
from matchplant.core.runtime.gui import figure, fit_to_axes

try:  # Tk's file dialogs come with Python (and Matplotlib's TkAgg backend); some Linux Pythons lack them
    import tkinter
    from tkinter import filedialog
except ImportError:  # pragma: no cover - depends on the Python build
    tkinter = filedialog = None


class QuietTextBox(TextBox):
    """A text field that answers at once in a large window.

    Matplotlib's TextBox redraws the whole figure on every keystroke (a photo with thousands of boxes, or a
    busy machine: typed text appeared a minute later) and on every click anywhere, once per box. This one
    redraws only its own axes (blitting) when it types, stops typing only when it was typing, and clips its
    text to the field: a path longer than the field shows its end (the file name), never runs over the
    Browse button or the window's edge."""

    def __init__(self, ax, label, initial="", **kwargs):
        super().__init__(ax, label, initial=initial, **kwargs)
        self._left_x = self.text_disp.get_position()[0]
        self._left_ha = self.text_disp.get_horizontalalignment()
        self.text_disp.set_clip_path(ax.patch)
        self.text_disp.set_clip_on(True)
        self.fit_text()  # a long initial path shows its end from the first draw, not only once typed into

    def stop_typing(self):
        """Stop typing only when the field was typing (Matplotlib redraws everything otherwise)."""
        if self.capturekeystrokes:
            super().stop_typing()

    def fit_text(self) -> bool:
        """Align the text as asked while it fits, else to the right so that its end shows; True when the
        alignment changed."""
        fig = self.ax.get_figure(root=True)
        # before the first draw the Agg canvases (Tk, Qt, macOS, headless) can still measure text
        renderer = fig._get_renderer() or getattr(fig.canvas, "get_renderer", lambda: None)()
        if renderer is None:
            return False
        before = self.text_disp.get_horizontalalignment()
        self.text_disp.set_horizontalalignment(self._left_ha)
        self.text_disp.set_x(self._left_x)
        if self.text_disp.get_window_extent(renderer).width > 0.92 * self.ax.bbox.width:
            self.text_disp.set_horizontalalignment("right")
            self.text_disp.set_x(0.98)
        return self.text_disp.get_horizontalalignment() != before

    def _click(self, event):
        # a click is placed in the text as it is shown: aligned first (a long path shows its end), so that the
        # cursor lands where the user clicked, never in the hidden part of the path
        self.fit_text()
        super()._click(event)

    def _rendercursor(self):
        fig = self.ax.get_figure(root=True)
        canvas = fig.canvas
        if fig._get_renderer() is None or not canvas.supports_blit:
            self.fit_text()
            super()._rendercursor()  # the first draw of a figure is a whole one anyway
            if self.fit_text():  # the first draw measured the text: place the cursor in the text as shown
                super()._rendercursor()
            return
        own = "draw" in vars(canvas)  # a headless GUI may have replaced draw on the instance
        draw = canvas.draw
        canvas.draw = lambda *args, **kwargs: None
        try:
            self.fit_text()
            super()._rendercursor()
        finally:
            if own:
                canvas.draw = draw
            else:
                del canvas.draw
        fig.draw_artist(self.ax)
        canvas.blit(self.ax.bbox)


class BoolField:
    """A yes/no setting as a check box (never a text field holding ``False``), read like a text box: ``text``
    is ``"true"``/``"false"``, so that a form reads its fields one way; ``value`` is the bool."""

    def __init__(self, ax, label: str, initial: bool = False):
        self.ax = ax
        self.check = CheckButtons(ax, ["yes"], [bool(initial)])
        for t in self.check.labels:
            t.set_fontsize(9)
        # the setting's name left of the box, where a text field has its label
        self.label = ax.text(-0.02, 0.5, label, transform=ax.transAxes, ha="right", va="center", fontsize=9)
        ax.set_frame_on(False)

    @property
    def value(self) -> bool:
        """True when the box is ticked."""
        return bool(self.check.get_status()[0])

    @property
    def text(self) -> str:
        """``"true"`` or ``"false"``, as a text box would hold it."""
        return "true" if self.value else "false"

    def set_val(self, value) -> None:
        """Tick or untick the box from a text ("true", "1", "yes", "on" tick it)."""
        wanted = str(value).strip().lower() in ("true", "1", "yes", "on")
        if wanted != self.value:
            self.check.set_active(0)

    def on_changed(self, func: Callable[[bool], Any]) -> None:
        """Call ``func`` with the new value each time the box is clicked."""
        self.check.on_clicked(lambda _label: func(self.value))


def setting_field(ax, label: str, value: Any):
    """The widget of one setting in a form: a check box for a bool, a text field for anything else."""
    if isinstance(value, bool):
        return BoolField(ax, label, value)
    return QuietTextBox(ax, label + " ", initial="" if value is None else str(value), label_pad=0.02)


@contextmanager
def busy(fig: Figure, say: Callable[[str], None], text: str, area: Any = None) -> Iterator[None]:
    """Show ``text`` and a wait cursor at once, before a long action blocks the window's event loop (a plain
    draw_idle would only paint after the work), and restore the cursor after. ``area``: the axes holding the
    message, redrawn alone (the whole figure otherwise)."""
    say(text)
    canvas = fig.canvas
    if canvas.manager is not None:
        with suppress(Exception):  # a backend without cursors still shows the text
            canvas.set_cursor(Cursors.WAIT)
        if area is not None and canvas.supports_blit and fig._get_renderer() is not None:
            fig.draw_artist(area)
            canvas.blit(area.bbox)
        else:
            canvas.draw()
        canvas.flush_events()
    try:
        yield
    finally:
        if canvas.manager is not None:
            with suppress(Exception):
                canvas.set_cursor(Cursors.POINTER)


# -------------------------------------------------------------------------------------------------
# setup screens: the files a step needs, with Tk's file and folder dialogs


def ask_path(kind: str, title: str, initial: str | Path | None = None, parent: Any = None) -> str | None:
    """Tk's dialog for a ``file``, a ``folder`` or a ``save`` file name; None when cancelled."""
    if filedialog is None:
        raise DependencyError(
            "Tk's file dialogs are not available in this Python",
            fix="type the path in the box, or install Tk (e.g. apt install python3-tk)",
        )
    initial = Path(initial) if initial else None
    start = str(initial if initial is not None and initial.is_dir() else initial.parent) if initial else None
    own_root = None
    if parent is None:  # no Tk window of ours (another backend): a hidden root for the dialog
        own_root = tkinter.Tk()
        own_root.withdraw()
    try:
        if kind == "folder":
            chosen = filedialog.askdirectory(parent=parent or own_root, title=title, initialdir=start)
        elif kind == "save":
            chosen = filedialog.asksaveasfilename(parent=parent or own_root, title=title, initialdir=start)
        else:
            chosen = filedialog.askopenfilename(parent=parent or own_root, title=title, initialdir=start)
    finally:
        if own_root is not None:
            own_root.destroy()
    return str(chosen) if chosen else None


@dataclass
class SetupField:
    """One line of a setup screen: a config key, its label, and ``file``/``folder``/``save``/``text``."""

    key: str
    label: str
    kind: str = "file"


def _config_value(cfg: Any, key: str) -> Any:
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _as_text(value: Any) -> str:
    return "" if value is None else str(value)


class SetupScreen:
    """A window to pick a step's files and folders (a "Browse" button per path: Tk's dialogs), then Run.

    ``on_run(cfg)`` does the work with the validated config and returns a message for the status line; it
    may raise a :class:`MatchPlantError`, shown in red. ``chooser(kind, title, initial)`` replaces Tk's
    dialog (tests). The window stays open after a run, so the user can change a file and run again.
    """

    def __init__(
        self,
        title: str,
        cfg: Any,
        fields: list[SetupField],
        on_run: Callable[[Any], str],
        headless: bool | None = None,
        chooser: Callable[..., str | None] | None = None,
        run_label: str = "Run",
        prefill: Callable[[dict[str, str]], dict[str, str]] | None = None,
    ):
        self.cfg, self.fields, self.on_run = cfg, fields, on_run
        self.chooser = chooser
        # prefill(texts of every box) -> {key: path}: what the previous module wrote where its README says,
        # put into the boxes that are still empty
        self.prefill = prefill
        self.fig = figure(headless, title=title, toolbar=False, figsize=(10, 1.6 + 0.55 * len(fields)))
        n = len(fields)
        row = 1.0 / (n + 3)
        self.fig.text(0.02, 1 - 0.6 * row, title, fontsize=13, weight="bold", va="center")
        self.boxes: dict[str, TextBox] = {}
        self.browse_buttons: dict[str, Button] = {}
        for i, f in enumerate(fields):
            y = 1 - (i + 1.6) * row
            box = QuietTextBox(
                self.fig.add_axes((0.22, y, 0.62, 0.7 * row)),
                f.label + " ",
                initial=_as_text(_config_value(cfg, f.key)),
            )
            self.boxes[f.key] = box
            if f.kind != "text":
                button = Button(self.fig.add_axes((0.86, y, 0.12, 0.7 * row)), "Browse...")
                button.on_clicked(lambda _e, key=f.key: self.browse(key))
                self.browse_buttons[f.key] = button
        self.run_button = Button(self.fig.add_axes((0.86, 0.5 * row, 0.12, 0.8 * row)), run_label)
        self.run_button.on_clicked(lambda _e: self.run())
        # the status line in an axes of its own, so that "working ..." is drawn alone and at once
        self.status_area = self.fig.add_axes((0.0, 0.0, 0.85, 1.8 * row))
        self.status_area.set_axis_off()
        self.status = fit_to_axes(  # kept left of the Run button and inside the window, however long
            self.status_area.text(
                0.02 / 0.85,
                0.5,
                f"Choose the files (Browse... or type a path), then {run_label}.",
                fontsize=9,
                family="monospace",
                va="center",
            )
        )
        self.ran = False
        self.fill_in()

    def fill_in(self) -> list[str]:
        """Fill the empty boxes the ``prefill`` hook knows a value for; the keys filled."""
        if self.prefill is None:
            return []
        texts = {key: box.text.strip() for key, box in self.boxes.items()}
        filled = [key for key, value in self.prefill(texts).items() if key in self.boxes and not texts[key] and value]
        for key in filled:
            self.boxes[key].set_val(self.prefill(texts)[key])
        return filled

    def say(self, text: str, error: bool = False) -> None:
        """Show a status line under the form (red for an error)."""
        self.status.set_text(text)
        self.status.set_color("#c62828" if error else "black")
        self.fig.canvas.draw_idle()

    def _tk_parent(self):
        widget = getattr(self.fig.canvas, "get_tk_widget", None)
        return widget() if widget is not None else None

    def browse(self, key: str) -> str | None:
        """Open the dialog for ``key`` and put the chosen path in its box."""
        f = next(f for f in self.fields if f.key == key)
        current = self.boxes[key].text.strip() or None
        try:
            if self.chooser is not None:
                chosen = self.chooser(f.kind, f"Choose the {f.label.lower()}", current)
            else:
                chosen = ask_path(f.kind, f"Choose the {f.label.lower()}", current, parent=self._tk_parent())
        except MatchPlantError as exc:
            self.say(f"error: {exc}".replace("\n", " | "), error=True)
            return None
        if chosen:
            self.boxes[key].set_val(chosen)
            filled = self.fill_in()
            labels = [g.label for g in self.fields if g.key in filled]
            self.say(f"{f.label}: {chosen}" + (f" (filled in: {', '.join(labels)})" if labels else ""))
        return chosen

    def apply(self) -> bool:
        """Copy every box into the config and validate it; errors go to the status line."""
        self.fill_in()
        try:
            for f in self.fields:
                text = self.boxes[f.key].text.strip()
                set_value(self.cfg, f.key, text or None, source="window", base=Path.cwd())
            validate(self.cfg, source="window")
        except MatchPlantError as exc:
            self.say(f"error: {exc}".replace("\n", " | "), error=True)
            return False
        return True

    def run(self) -> bool:
        """Apply the boxes and run the step; True when it finished."""
        if not self.apply():
            return False
        try:
            with busy(self.fig, self.say, "working ... (the window answers again when this is done)", self.status_area):
                message = self.on_run(self.cfg)
        except MatchPlantError as exc:
            self.say(f"error: {exc}".replace("\n", " | "), error=True)
            return False
        self.ran = True
        self.say(message)
        return True
