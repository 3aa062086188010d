"""Checks of a drawn Matplotlib figure that a reader would otherwise catch only by looking at the PNG.

``outside_figure(fig)``: every text drawn (titles, axis labels, tick labels, colour-bar labels, legends) lies
inside the figure, so that nothing is clipped when the figure is saved; ``colour_names(text)``: the colour words
of a caption, to compare with the colours the artists are drawn with.
"""

from __future__ import annotations

import re

import matplotlib.colors as mcolors


def _drawn_texts(fig):
    """The texts the last draw put on the page (tick labels outside the view are not drawn)."""
    out = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            for tick in axis._update_ticks():  # the ticks inside the view: the ones drawn
                out += [t for t in (tick.label1, tick.label2) if t.get_visible()]
            out.append(axis.label)
            out.append(axis.offsetText)
        out += [ax.title, ax._left_title, ax._right_title]
        out += list(ax.texts)
        legend = ax.get_legend()
        if legend is not None:
            out += list(legend.get_texts())
    out += list(fig.texts)
    if getattr(fig, "_suptitle", None) is not None:
        out.append(fig._suptitle)
    return [t for t in out if t.get_visible() and t.get_text().strip()]


def outside_figure(fig, tolerance_px: float = 1.0) -> list[str]:
    """The drawn texts that run out of the figure (clipped on saving), each with how far; [] when all fit."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    w, h = fig.bbox.width, fig.bbox.height
    bad = []
    for t in _drawn_texts(fig):
        bb = t.get_window_extent(renderer)
        over = max(-bb.x0, -bb.y0, bb.x1 - w, bb.y1 - h)
        if over > tolerance_px:
            bad.append(f"{t.get_text()!r} runs {over:.0f} px out of the figure")
    return bad


def colour_names(text: str) -> set[str]:
    """The colour names (Matplotlib's CSS4 names) a caption mentions."""
    return {w for w in re.findall(r"[a-z]+", text.lower()) if w in mcolors.CSS4_COLORS}


def same_colour(a, b) -> bool:
    return mcolors.to_rgb(a) == mcolors.to_rgb(b)
