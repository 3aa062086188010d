"""Truth for traits and plots: each plant's vigour (leaf NDVI) and canopy, the plot layout with its missing
plants, and a later date with grown plants.

* Vigour (``vigour: true``): every plant's leaves get their own NDVI (drawn from a stream of their own, so
  every other output of the field stays as it was); ``truth/traits.csv`` lists it with the plant's true
  canopy (pixels of ``truth/plant_ids.tif``, its area) for every field.
* Plots (always): the sowing plan cut into plots of ``ROWS_PER_PLOT`` rows x ``SLOTS_PER_PLOT`` seed
  positions; ``truth/plots.json`` (the grid: corners, columns, ranges, plot size, spacings),
  ``truth/plots.csv`` (plot id, WKT outline, expected plants, stand count, gaps), ``truth/gaps.csv``
  (every empty seed position) and ``truth/field_book.csv`` (plot id, genotype, rep).
* A later date (``second_date: true``): the plants grown (taller, longer leaves: neighbours may touch) and
  the whole map shifted as two orthomosaics of different flights are (a few centimetres, smoothly
  varying); rasters and truth under ``date2/`` in the same layout.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import shapely

from matchplant.simfield.config import Settings
from matchplant.simfield.scene import PLANT_SPACING, ROW_SPACING, Plants, Terrain, row_layout, row_shift

ROWS_PER_PLOT = 2
SLOTS_PER_PLOT = 10
GENOTYPES = 12


def vigour(n: int, rng: np.random.Generator) -> np.ndarray:
    """Leaf NDVI of ``n`` plants, independent of their size (0.45..0.9)."""
    return np.clip(rng.normal(0.70, 0.08, n), 0.45, 0.90)


def grow(plants: Plants, terrain: Terrain, rng: np.random.Generator) -> Plants:
    """The same plants a week later, seen on a map that is shifted by a few centimetres (misregistration
    between flights: a constant shift plus a smooth wave)."""
    n = len(plants)
    g = rng.uniform(1.25, 1.45, n)
    leaf = rng.uniform(1.15, 1.30, n)[:, None]
    ang = rng.uniform(0, 2 * np.pi)
    kx, ky, ph = rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.5), rng.uniform(0, 2 * np.pi, 2)
    dx = 0.04 * np.cos(ang) + 0.015 * np.sin(kx * plants.y + ph[0])
    dy = 0.04 * np.sin(ang) + 0.015 * np.sin(ky * plants.x + ph[1])
    x, y = plants.x + dx, plants.y + dy
    return replace(
        plants,
        x=x,
        y=y,
        z=terrain.height(x, y),
        height=plants.height * g,
        leaf_len=plants.leaf_len * leaf,
        core=plants.core * g,
    )


def traits_rows(plants: Plants, label: np.ndarray, res: float, offset: np.ndarray) -> list[list]:
    """Rows of ``truth/traits.csv``: id, x, y, height, ndvi, canopy_pixels, canopy_area_m2."""
    count = np.bincount(np.clip(label.ravel(), 0, None), minlength=len(plants) + 1)[1 : len(plants) + 1]
    ndvi = plants.ndvi if plants.ndvi is not None else np.full(len(plants), 0.8)
    return [
        [int(i), f"{x + offset[0]:.4f}", f"{y + offset[1]:.4f}", f"{h:.4f}", f"{v:.4f}", int(c), f"{c * res * res:.6f}"]
        for i, x, y, h, v, c in zip(plants.ids, plants.x, plants.y, plants.height, ndvi, count)
    ]


def plot_truth(s: Settings, plants: Plants, offset: np.ndarray, crs: str) -> dict:
    """The plot layout and its truth (see the module doc); returns the files' contents.

    With ``plot_skew_deg`` the grid is a parallelogram: each row's seeds start ``row_shift`` further north,
    the ranges' edges run along ``across = (width, width tan(skew))`` and every plot is the parallelogram
    of its cell, as module 9's ``plot_grid`` builds it from the corners."""
    row_x, slots = row_layout(s)
    shift = row_shift(s, row_x)
    tan = np.tan(np.radians(s.plot_skew_deg))
    cols, ranges = len(row_x) // ROWS_PER_PLOT, len(slots) // SLOTS_PER_PLOT
    width, length = ROWS_PER_PLOT * ROW_SPACING, SLOTS_PER_PLOT * PLANT_SPACING
    x0 = row_x[0] - ROW_SPACING / 2
    y0 = slots[0] - PLANT_SPACING / 2 - (row_x[0] - x0) * tan  # the first range's edge at x0
    occupied = np.zeros((len(row_x), len(slots)), bool)
    slot = np.round((plants.y - shift[plants.row - 1] - slots[0]) / PLANT_SPACING).astype(int)
    ok = (slot >= 0) & (slot < len(slots))
    occupied[plants.row[ok] - 1, slot[ok]] = True
    across, along = np.array([width, width * tan]), np.array([0.0, length])  # one plot's sides
    origin = np.array([x0, y0]) + offset[:2]
    plots, gaps, book = [], [], []
    for j in range(ranges):
        for i in range(cols):
            pid = j * cols + i + 1
            rs = slice(i * ROWS_PER_PLOT, (i + 1) * ROWS_PER_PLOT)
            ss = slice(j * SLOTS_PER_PLOT, (j + 1) * SLOTS_PER_PLOT)
            occ = occupied[rs, ss]
            a = origin + i * across + j * along
            outline = shapely.Polygon([a, a + across, a + across + along, a + along])
            plots.append([pid, j + 1, i + 1, occ.size, int(occ.sum()), int((~occ).sum()), outline.wkt])
            for r, k in zip(*np.nonzero(~occ)):
                rr = i * ROWS_PER_PLOT + r
                gaps.append(
                    [
                        pid,
                        rr + 1,
                        f"{row_x[rr] + offset[0]:.4f}",
                        f"{slots[j * SLOTS_PER_PLOT + k] + shift[rr] + offset[1]:.4f}",
                    ]
                )
            book.append([pid, f"G{(pid - 1) % GENOTYPES + 1:02d}", (pid - 1) // GENOTYPES + 1])
    c0 = origin
    corners = [c0, c0 + cols * across, c0 + cols * across + ranges * along, c0 + ranges * along]
    grid = {
        "crs": crs,
        "corners": [[float(c[0]), float(c[1])] for c in corners],
        "corners_meaning": "first plot's outer corner, then along the first range across the rows, "
        "then the far corners: plot 1 is at corner 1, plots numbered across then along",
        "columns": cols,
        "ranges": ranges,
        "plot_width": width,
        "plot_length": length,
        "rows_per_plot": ROWS_PER_PLOT,
        "row_spacing": ROW_SPACING,
        "plant_spacing": PLANT_SPACING,
        "skew_deg": float(s.plot_skew_deg),
        "row_direction": [0.0, 1.0],
        "row_direction_meaning": "unit vector along the crop rows (north); with a skew the ranges' edges "
        "are not perpendicular to it",
    }
    return {"grid": grid, "plots": plots, "gaps": gaps, "field_book": book}
