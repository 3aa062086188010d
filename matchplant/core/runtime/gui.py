"""Shared pieces of the Matplotlib GUIs and figures: one code path on every platform, no global state.

No function here changes Matplotlib's global state (the backend, rcParams, pyplot's figure list):
- :func:`figure` with ``headless=True`` makes a figure with an Agg canvas of its own, outside pyplot,
  for files (training curves, coverage maps) and for tests that drive a GUI with synthesised events;
- with ``headless=False`` it asks pyplot for a window figure, on the backend Matplotlib chose for this
  process (``MPLBACKEND``, else its own choice: a window where a display exists, Agg elsewhere).

GUIs are tested headless (events synthesised by ``tests/gui_events.py``) and in a real window under
Xvfb. Keep logic out of GUI classes: they call library functions and draw results. The widgets (text fields,
setup screens, file dialogs) are in :mod:`matchplant.core.runtime.widgets`, which only the GUIs import.
"""

from __future__ import annotations

import os
import sys
import textwrap
from typing import TYPE_CHECKING

from matchplant.core.runtime.errors import DependencyError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Matplotlib is imported on first use, not with this module: every command imports this module (for
# require_display) and pyplot alone costs ~2 s of CPU at start-up, which a headless run never needs.


def _pyplot():
    import matplotlib.pyplot as plt  # on demand (see above)

    return plt


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
        setting = os.environ.get("MPLBACKEND", "")
        return f"Matplotlib's backend is '{backend}', which cannot open a window (MPLBACKEND={setting!r})"
    return None


def require_display(command: str) -> None:
    """Raise a :class:`DependencyError` (exit code 2) when no window can be opened."""
    reason = gui_unavailable_reason()
    if reason is not None:
        raise DependencyError(
            f"the GUI needs a window, and {reason}",
            fix=f"run the step without the GUI: '{command}' without --gui does the same work "
            "headless from the config and --set values; or use a desktop, 'ssh -X', or "
            "'xvfb-run' for a virtual display",
        )


def is_headless(headless: bool | None) -> bool:
    """``headless`` as asked, or, when None, whether this process cannot show a window."""
    if headless is not None:
        return headless
    return not interactive_backend_available() or _pyplot().get_backend().lower() == "agg"


def figure(headless: bool | None = None, title: str | None = None, toolbar: bool = True, **kwargs) -> Figure:
    """A new figure (``kwargs`` as for :class:`matplotlib.figure.Figure`: figsize, dpi, ...); a window is
    titled "MatchPlant - <title>" (the step), not pyplot's "Figure 2". ``toolbar=False``: a window of
    forms, without Matplotlib's pan/zoom toolbar (which would sit under the fields and buttons)."""
    if is_headless(headless):
        # on demand (see above)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(**kwargs)
        FigureCanvasAgg(fig)
        return fig
    plt = _pyplot()
    with plt.rc_context({} if toolbar else {"toolbar": "None"}):
        fig = plt.figure(**kwargs)
    if title and fig.canvas.manager is not None:
        fig.canvas.manager.set_window_title(f"MatchPlant - {title}")
    return fig


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
    """A status area at the bottom of an axes: messages and errors for the user, kept inside the axes."""
    return fit_to_axes(
        ax.text(0.0, 0.0, text, transform=ax.transAxes, fontsize=9, va="bottom", ha="left", family="monospace")
    )


def fit_to_axes(text, rows: int | None = None):
    """Keep a status text inside its axes, however long the message and whatever the window's size: wrapped at
    the axes' right edge (a long path is broken too), as many lines as the axes holds, the last cut with an
    ellipsis, and clipped there. ``get_text()`` still gives the whole message (the console logs it whole).
    A figure's text (no axes) is kept inside the window, in at most ``rows`` lines (default: 2).

    (Matplotlib's own ``wrap=True`` wraps at the figure's edge, over the buttons beside the status line, and
    never breaks a path: its wrapping step is replaced on this one artist.)"""
    text.set_wrap(True)
    text.set_clip_on(True)
    box = text.axes.bbox if text.axes is not None else text.get_figure(root=True).bbox
    text.set_clip_box(box)
    text._get_wrapped_text = lambda: _fitted(text, box, rows if rows or text.axes is not None else 2)
    return text


def _fitted(text, box, max_rows: int | None) -> str:
    message = text.get_text()
    if text._renderer is None or not message:
        return message
    x0 = text.get_transform().transform(text.get_position())[0]
    width = box.x1 - max(x0, box.x0) - 2
    char = max(text._get_rendered_text_width("M" * 10) / 10, 1.0)  # monospace: every character; else the widest
    # a line's height, on the safe side: the font's own line height ("normal" spacing in newer Matplotlib) is
    # about 1.6 times its size in points for DejaVu Sans Mono; a numeric spacing multiplies about 1.3
    spacing = getattr(text, "_linespacing", None)
    spacing = 1.3 * spacing if isinstance(spacing, (int, float)) else 1.6
    line = text.get_fontsize() * text.get_figure(root=True).dpi / 72 * spacing
    cols, rows = max(int(width / char), 4), max(int(box.height / line), 1)
    rows = min(rows, max_rows) if max_rows else rows
    lines = [
        piece
        for paragraph in message.split("\n")
        for piece in (textwrap.wrap(paragraph, cols, break_long_words=True, break_on_hyphens=False) or [""])
    ]
    if len(lines) > rows:
        lines = lines[:rows]
        lines[-1] = lines[-1][: cols - 1] + "\u2026"
    return "\n".join(lines)
