"""Shared pieces of the Matplotlib GUIs: one code path on every platform, thin over library functions.

GUIs are tested headless (Agg backend, events synthesised with :func:`tests.gui_events`) and in a real
window under Xvfb. Keep logic out of GUI classes: they call library functions and draw results.
"""

from __future__ import annotations

import os
import sys


def interactive_backend_available() -> bool:
    """True when a window can be opened (a display on Linux; always on macOS and Windows)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def pyplot(headless: bool | None = None):
    """Import pyplot with a backend that works here: Agg when headless (tests, servers)."""
    import matplotlib

    if headless is None:
        headless = not interactive_backend_available()
    if headless:
        matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def show(fig, headless: bool | None = None) -> None:
    """Show a figure window and block until it is closed (does nothing when headless)."""
    import matplotlib

    if headless or matplotlib.get_backend().lower() == "agg":
        return
    import matplotlib.pyplot as plt

    plt.show()


def status_text(ax, text: str = ""):
    """A one-line status area at the bottom of an axes: messages and errors for the user."""
    return ax.text(0.0, 0.0, text, transform=ax.transAxes, fontsize=9, va="bottom", ha="left",
                   family="monospace")
