"""Shared pieces of the Matplotlib GUIs and figures: one code path on every platform, no global state.

No function here changes Matplotlib's global state (the backend, rcParams, pyplot's figure list):
- :func:`figure` with ``headless=True`` makes a figure with an Agg canvas of its own, outside pyplot,
  for files (training curves, coverage maps) and for tests that drive a GUI with synthesised events;
- with ``headless=False`` it asks pyplot for a window figure, on the backend Matplotlib chose for this
  process (``MPLBACKEND``, else its own choice: a window where a display exists, Agg elsewhere).

GUIs are tested headless (events synthesised by ``tests/gui_events.py``) and in a real window under
Xvfb. Keep logic out of GUI classes: they call library functions and draw results.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from matchplant.core.runtime.config import set_value, validate
from matchplant.core.runtime.errors import DependencyError, MatchPlantError

try:  # Tk's file dialogs come with Python (and Matplotlib's TkAgg backend); some Linux Pythons lack them
    import tkinter
    from tkinter import filedialog
except ImportError:  # pragma: no cover - depends on the Python build
    tkinter = filedialog = None

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Matplotlib is imported on first use, not with this module: every command imports this module (for
# require_display) and pyplot alone costs ~2 s of CPU at start-up, which a headless run never needs.


def _pyplot():
    import matplotlib.pyplot as plt  # on demand (see above)

    return plt


def _widgets():
    from matplotlib import widgets  # on demand (see above)

    return widgets


def _quiet_text_box() -> type:
    class QuietTextBox(_widgets().TextBox):
        """Matplotlib's TextBox redraws the whole figure on every click anywhere, once per box (a dozen full
        redraws per click in a settings panel); only a box that was being typed in needs to stop typing."""

        def stop_typing(self):
            if self.capturekeystrokes:
                super().stop_typing()

    QuietTextBox.__module__ = __name__
    return QuietTextBox


def __getattr__(name: str):
    # QuietTextBox subclasses a Matplotlib widget: made (once) when a GUI first asks for it
    if name == "QuietTextBox":
        cls = globals()["QuietTextBox"] = _quiet_text_box()
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def interactive_backend_available() -> bool:
    """True when a window can be opened (a display on Linux; always on macOS and Windows)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def gui_unavailable_reason() -> str | None:
    """None when a window can be opened here, else why not (no display, or no interactive backend)."""
    if not interactive_backend_available():
        return "there is no display here (DISPLAY and WAYLAND_DISPLAY are not set)"
    backend = _pyplot().get_backend().lower()
    if backend in ("agg", "pdf", "ps", "svg", "cairo", "pgf", "template") or backend.startswith("module://"):
        return f"Matplotlib's backend is '{backend}', which cannot open a window (MPLBACKEND={os.environ.get('MPLBACKEND', '')!r})"
    return None


def require_display(command: str) -> None:
    """Raise a :class:`DependencyError` (exit code 2) when no window can be opened."""
    reason = gui_unavailable_reason()
    if reason is not None:
        raise DependencyError(f"the GUI needs a window, and {reason}",
                              fix=f"run the step without the GUI: '{command}' without --gui does the same work "
                                  "headless from the config and --set values; or use a desktop, 'ssh -X', or "
                                  "'xvfb-run' for a virtual display")


def is_headless(headless: bool | None) -> bool:
    """``headless`` as asked, or, when None, whether this process cannot show a window."""
    if headless is not None:
        return headless
    return not interactive_backend_available() or _pyplot().get_backend().lower() == "agg"


def figure(headless: bool | None = None, **kwargs) -> Figure:
    """A new figure (``kwargs`` as for :class:`matplotlib.figure.Figure`: figsize, dpi, ...)."""
    if is_headless(headless):
        # on demand (see above)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(**kwargs)
        FigureCanvasAgg(fig)
        return fig
    return _pyplot().figure(**kwargs)


def show(fig: Figure) -> None:
    """Show a window figure and block until it is closed (does nothing for a headless figure)."""
    if fig.canvas.manager is None:  # a headless figure: nothing to show
        return
    _pyplot().show(block=True)


def reveal(fig: Figure) -> None:
    """Show a window figure made while another window's event loop runs (a setup screen's button): pyplot
    keeps such a window hidden until its manager is shown. Nothing for a headless figure."""
    if fig.canvas.manager is not None:
        fig.canvas.manager.show()


def close(fig: Figure) -> None:
    """Release a figure (a window figure is also removed from pyplot's list)."""
    if fig.canvas.manager is not None:
        _pyplot().close(fig)


def status_text(ax, text: str = ""):
    """A one-line status area at the bottom of an axes: messages and errors for the user."""
    return ax.text(0.0, 0.0, text, transform=ax.transAxes, fontsize=9, va="bottom", ha="left",
                   family="monospace")


# -------------------------------------------------------------------------------------------------
# setup screens: the files a step needs, with Tk's file and folder dialogs


def ask_path(kind: str, title: str, initial: str | Path | None = None, parent: Any = None) -> str | None:
    """Tk's dialog for a ``file``, a ``folder`` or a ``save`` file name; None when cancelled."""
    if filedialog is None:
        raise DependencyError("Tk's file dialogs are not available in this Python",
                              fix="type the path in the box, or install Tk (e.g. apt install python3-tk)")
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

    def __init__(self, title: str, cfg: Any, fields: list[SetupField], on_run: Callable[[Any], str],
                 headless: bool | None = None, chooser: Callable[..., str | None] | None = None,
                 run_label: str = "Run"):
        self.cfg, self.fields, self.on_run = cfg, fields, on_run
        self.chooser = chooser
        self.fig = figure(headless, figsize=(10, 1.6 + 0.55 * len(fields)))
        if self.fig.canvas.manager is not None:
            self.fig.canvas.manager.set_window_title(f"MatchPlant - {title}")
        n = len(fields)
        row = 1.0 / (n + 3)
        self.fig.text(0.02, 1 - 0.6 * row, title, fontsize=13, weight="bold", va="center")
        widgets = _widgets()
        self.boxes: dict[str, widgets.TextBox] = {}
        self.browse_buttons: dict[str, widgets.Button] = {}
        for i, f in enumerate(fields):
            y = 1 - (i + 1.6) * row
            box = widgets.TextBox(self.fig.add_axes((0.22, y, 0.62, 0.7 * row)), f.label + " ",
                                  initial=_as_text(_config_value(cfg, f.key)))
            self.boxes[f.key] = box
            if f.kind != "text":
                button = widgets.Button(self.fig.add_axes((0.86, y, 0.12, 0.7 * row)), "Browse...")
                button.on_clicked(lambda _e, key=f.key: self.browse(key))
                self.browse_buttons[f.key] = button
        self.run_button = widgets.Button(self.fig.add_axes((0.86, 0.5 * row, 0.12, 0.8 * row)), run_label)
        self.run_button.on_clicked(lambda _e: self.run())
        self.status = self.fig.text(0.02, 0.9 * row, "Choose the files (Browse... or type a path), then "
                                    f"{run_label}.", fontsize=9, family="monospace", va="center")
        self.ran = False

    def say(self, text: str, error: bool = False) -> None:
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
            self.say(f"{f.label}: {chosen}")
        return chosen

    def apply(self) -> bool:
        """Copy every box into the config and validate it; errors go to the status line."""
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
        self.say("running ...")
        try:
            message = self.on_run(self.cfg)
        except MatchPlantError as exc:
            self.say(f"error: {exc}".replace("\n", " | "), error=True)
            return False
        self.ran = True
        self.say(message)
        return True
