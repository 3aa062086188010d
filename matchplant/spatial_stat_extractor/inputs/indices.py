"""Vegetation indices as band formulas: the RGB indices of an ordinary drone's orthophoto (ExG, ExGR,
VARI, GLI, NGRDI) and any index a user writes, e.g. ``(b5 - b3) / (b5 + b3)`` or, with band_order,
``(nir - red) / (nir + red)``.

A formula is parsed once (Python syntax, checked node by node: numbers, band names, ``+ - * / **`` and
parentheses only: nothing is ever ``eval``-ed) and evaluated window by window on float64 arrays; a
division by zero gives NaN, which the statistics mask. In RGB formulas ``R, G, B`` are the bands and
``r, g, b`` the chromatic coordinates ``R / (R + G + B)`` …; in other formulas ``b1``, ``b2`` … are the
raster's bands (and the names band_order gives them). An orthophoto's alpha band (ODM's is band 4)
masks the pixels where it is 0.

Which band is which (band_order, band descriptions, colour labels where they mean something) is
:mod:`~matchplant.spatial_stat_extractor.inputs.bands`.
"""

from __future__ import annotations

import ast

import numpy as np

from matchplant.core.runtime.errors import ConfigError

RGB_INDICES = {
    "exg": "2 * g - r - b",
    "exgr": "(2 * g - r - b) - (1.4 * r - g)",
    "vari": "(G - R) / (G + R - B)",
    "gli": "(2 * G - R - B) / (2 * G + R + B)",
    "ngrdi": "(G - R) / (G + R)",
}
_OPS = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.divide, ast.Pow: np.power}


def parse_formula(text: str, names: set[str], key: str) -> ast.Expression:
    """The checked syntax tree of ``text``; a ConfigError naming ``key`` when it is not a band formula."""
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        raise ConfigError(
            f"{key}: '{text}' is not a formula ({exc.msg})", fix="write it like (b2 - b1) / (b2 + b1)"
        ) from exc
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id not in names:
            raise ConfigError(
                f"{key}: '{node.id}' in '{text}' is not a band name", fix=f"use {', '.join(sorted(names))}"
            )
        if isinstance(node, ast.Constant) and not isinstance(node.value, (int, float)):
            raise ConfigError(f"{key}: only numbers may appear as constants in '{text}'", fix="remove the text")
        if not isinstance(
            node, (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Name, ast.Constant, ast.Load, ast.USub, ast.UAdd, *_OPS)
        ):
            raise ConfigError(
                f"{key}: '{text}' uses {type(node).__name__}; only + - * / ** and parentheses are allowed",
                fix="write the index with arithmetic on the bands",
            )
    return tree


def evaluate(tree: ast.Expression, values: dict[str, np.ndarray]) -> np.ndarray:
    """The formula on arrays; non-finite results (division by zero) become NaN."""

    def ev(node):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Name):
            return values[node.id]
        if isinstance(node, ast.UnaryOp):
            v = ev(node.operand)
            return -v if isinstance(node.op, ast.USub) else v
        return _OPS[type(node.op)](ev(node.left), ev(node.right))

    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = np.asarray(ev(tree), dtype=float)
    return np.where(np.isfinite(out), out, np.nan)


def needed_names(tree: ast.Expression) -> set[str]:
    """The names (bands) a formula uses."""
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}


class FormulaSource:
    """A formula over bands, read window by window. ``bands``: name -> a band source (``read`` gives float
    with NaN holes); ``chromatic``: also offer r, g, b from R, G, B; ``alpha``: a band source whose 0
    masks the pixel."""

    def __init__(self, tree: ast.Expression, bands: dict, chromatic: bool = False, alpha=None):
        self.tree, self.bands, self.chromatic, self.alpha = tree, bands, chromatic, alpha
        first = next(iter(bands.values()))
        self.transform, self.crs, self.width, self.height = first.transform, first.crs, first.width, first.height
        self.used = needed_names(tree)

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """The formula's values over a window (rows ``row0:row1``, cols ``col0:col1``)."""
        wanted = set(self.used)
        if self.chromatic and wanted & {"r", "g", "b"}:
            wanted |= {"R", "G", "B"}
        values = {k: self.bands[k].read(row0, row1, col0, col1) for k in wanted if k in self.bands}
        if self.chromatic and self.used & {"r", "g", "b"}:
            with np.errstate(invalid="ignore", divide="ignore"):
                total = values["R"] + values["G"] + values["B"]
                for c in "RGB":
                    values[c.lower()] = np.where(total > 0, values[c] / total, np.nan)
        out = evaluate(self.tree, values)
        out = np.broadcast_to(out, (row1 - row0, col1 - col0)).astype(float)
        if self.alpha is not None:
            out = np.where(self.alpha.read(row0, row1, col0, col1) > 0, out, np.nan)
        return out
