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

import matplotlib.pyplot as plt
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def interactive_backend_available() -> bool:
    """True when a window can be opened (a display on Linux; always on macOS and Windows)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def is_headless(headless: bool | None) -> bool:
    """``headless`` as asked, or, when None, whether this process cannot show a window."""
    if headless is not None:
        return headless
    return not interactive_backend_available() or plt.get_backend().lower() == "agg"


def figure(headless: bool | None = None, **kwargs) -> Figure:
    """A new figure (``kwargs`` as for :class:`matplotlib.figure.Figure`: figsize, dpi, ...)."""
    if is_headless(headless):
        fig = Figure(**kwargs)
        FigureCanvasAgg(fig)
        return fig
    return plt.figure(**kwargs)


def show(fig: Figure) -> None:
    """Show a window figure and block until it is closed (does nothing for a headless figure)."""
    if fig.canvas.manager is None:  # a headless figure: nothing to show
        return
    plt.show(block=True)


def close(fig: Figure) -> None:
    """Release a figure (a window figure is also removed from pyplot's list)."""
    if fig.canvas.manager is not None:
        plt.close(fig)


def status_text(ax, text: str = ""):
    """A one-line status area at the bottom of an axes: messages and errors for the user."""
    return ax.text(0.0, 0.0, text, transform=ax.transAxes, fontsize=9, va="bottom", ha="left",
                   family="monospace")
