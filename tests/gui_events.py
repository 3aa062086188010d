"""Synthesised Matplotlib events for headless GUI tests (Agg): press, drag, release, keys, scroll.

Coordinates are data coordinates of ``ax``; events go through the canvas's callback registry exactly as
a real backend delivers them.
"""

from __future__ import annotations

from matplotlib.backend_bases import KeyEvent, MouseButton, MouseEvent


def _xy(ax, x, y):
    return ax.transData.transform((x, y))


def mouse(
    fig, ax, kind: str, x: float, y: float, button=MouseButton.LEFT, key=None, step: float = 0, dblclick: bool = False
) -> None:
    """``kind`` is button_press_event, button_release_event, motion_notify_event or scroll_event."""
    fig.canvas.draw_idle()
    px, py = _xy(ax, x, y)
    if kind == "scroll_event":
        ev = MouseEvent(kind, fig.canvas, px, py, button="up" if step > 0 else "down", key=key, step=step)
    else:
        ev = MouseEvent(
            kind,
            fig.canvas,
            px,
            py,
            button=button if kind != "motion_notify_event" else None,
            key=key,
            dblclick=dblclick,
        )
    fig.canvas.callbacks.process(kind, ev)


def drag(fig, ax, x0, y0, x1, y1, steps: int = 4, button=MouseButton.LEFT, key=None) -> None:
    mouse(fig, ax, "button_press_event", x0, y0, button=button, key=key)
    for i in range(1, steps + 1):
        t = i / steps
        mouse(fig, ax, "motion_notify_event", x0 + (x1 - x0) * t, y0 + (y1 - y0) * t, key=key)
    mouse(fig, ax, "button_release_event", x1, y1, button=button, key=key)


def click(fig, ax, x, y, button=MouseButton.LEFT, key=None) -> None:
    mouse(fig, ax, "button_press_event", x, y, button=button, key=key)
    mouse(fig, ax, "button_release_event", x, y, button=button, key=key)


def key(fig, name: str, x: float = 0, y: float = 0) -> None:
    for kind in ("key_press_event", "key_release_event"):
        ev = KeyEvent(kind, fig.canvas, name, x, y)
        fig.canvas.callbacks.process(kind, ev)
