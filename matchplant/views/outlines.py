"""Each plant's shape in three dimensions, as its outline appears from any camera.

A plant polygon on the map is flat; the plant is not. Seen from the side of a photo its top leans outwards by
``height * tan(off-nadir)``, which is as large as the plant itself at the edge of a low flight. So each polygon
is draped over the DSM once and kept as a stack of flat rings: the polygon's own outline at the DSM's height
along it, then the outline of the part of the polygon above each of a few heights between its lowest and highest
DSM value (like contour lines). Each level ring stands as a prism down to the level below it (the part of the
plant above a height is solid down to the next height), and a photo sees the union of those prisms, projected:
the silhouette of the draped surface, to within the spacing of the levels.

The DSM is read by tiles of plants, so memory follows the tile, not the field.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import shapely

from matchplant.core.geometry.surface import Surface

TILE = 20.0  # metres: plants are draped a tile of the DSM at a time
SUBPIXEL = 4  # bits of sub-cell precision when a polygon is drawn into the DSM grid


@dataclass
class Outlines:
    """Every plant's rings: ``points[ring_start[r]:ring_start[r + 1]]`` is ring ``r`` (map x, y, z), standing down
    to ``floor[r]`` (its prism's bottom; the outline's ring has its own heights there); plant ``p`` owns rings
    ``plant_ring[p]:plant_ring[p + 1]``; ``centre`` is its polygon's centroid on the ground."""

    points: np.ndarray  # (M, 3) map coordinates
    floor: np.ndarray  # (M,) the height of each point's prism bottom
    ring_start: np.ndarray  # (R + 1,)
    plant_ring: np.ndarray  # (P + 1,)
    centre: np.ndarray  # (P, 3)

    def __len__(self) -> int:
        return len(self.centre)

    def point_range(self, p: int) -> tuple[int, int]:
        """The first and one-past-last point of plant ``p``."""
        return int(self.ring_start[self.plant_ring[p]]), int(self.ring_start[self.plant_ring[p + 1]])

    def ring_cuts(self, p: int) -> np.ndarray:
        """Where plant ``p``'s rings start within its points, the first left out (for ``np.split``)."""
        return self.ring_start[self.plant_ring[p] + 1 : self.plant_ring[p + 1]] - self.point_range(p)[0]

    def plant_points(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points of plants ``idx`` concatenated, each followed by its prism's bottom point (2 per point, in
        pairs), and where each plant's run of pairs starts (len(idx) + 1)."""
        starts = self.ring_start[self.plant_ring[idx]]
        ends = self.ring_start[self.plant_ring[idx + 1]]
        counts = ends - starts
        offsets = np.concatenate([[0], np.cumsum(counts)])
        take = np.repeat(starts - offsets[:-1], counts) + np.arange(offsets[-1])
        top = self.points[take]
        bottom = np.column_stack([top[:, :2], self.floor[take]])
        return np.stack([top, bottom], axis=1).reshape(-1, 3), offsets


def drape(polygons, dsm_path, levels: int) -> Outlines:
    """The rings of every polygon (shapely geometries in the DSM's CRS), in order.

    A polygon over DSM holes keeps its outline at the median height of its valid cells (or, with none, of the
    tile): it can be cut, though its lean is unknown."""
    geoms = np.asarray(polygons, dtype=object)
    cx, cy = shapely.get_x(shapely.centroid(geoms)), shapely.get_y(shapely.centroid(geoms))
    tiles = np.floor(cx / TILE) * 1e6 + np.floor(cy / TILE)
    rings: list[list[np.ndarray]] = [[] for _ in geoms]  # (n, 4): x, y, z, floor
    ground = np.zeros(len(geoms))
    for tile in np.unique(tiles):
        members = np.flatnonzero(tiles == tile)
        bounds = shapely.total_bounds(geoms[members])
        pad = 0.05 * TILE
        surface = Surface.open(dsm_path, bounds=(bounds[0] - pad, bounds[1] - pad, bounds[2] + pad, bounds[3] + pad))
        for p in members:
            rings[p], ground[p] = _plant_rings(geoms[p], surface, levels)
    sizes = [len(r) for plant in rings for r in plant]
    points = np.concatenate([r for plant in rings for r in plant]) if sizes else np.zeros((0, 4))
    ring_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    plant_ring = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    return Outlines(points[:, :3], points[:, 3], ring_start, plant_ring, np.column_stack([cx, cy, ground]))


def _plant_rings(geom, surface: Surface, levels: int) -> tuple[list[np.ndarray], float]:
    """One polygon's rings (outline on the DSM, then the flat level rings) and its ground height."""
    t = surface.transform
    cell = abs(t.a)
    parts = [p for p in shapely.get_parts(geom) if not p.is_empty]
    # simplified to half a cell (the DSM knows no finer), sampled at least every few centimetres (the relief under it)
    outlines = [
        np.asarray(shapely.segmentize(shapely.simplify(p.exterior, cell / 2), max(4 * cell, 0.03)).coords)[:-1, :2]
        for p in parts
    ]
    xy = np.concatenate(outlines)
    z_edge = surface.sample(xy[:, 0], xy[:, 1])
    # the cells inside the polygon: drawn into the DSM grid (cell centres at integers)
    col, row = _to_cells(t, xy[:, 0], xy[:, 1])
    c0, r0 = int(np.floor(col.min())) - 1, int(np.floor(row.min())) - 1
    c1, r1 = int(np.ceil(col.max())) + 2, int(np.ceil(row.max())) + 2
    h, w = surface.data.shape
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, w), min(r1, h)
    inside = np.zeros((max(r1 - r0, 1), max(c1 - c0, 1)), np.uint8)
    scale = float(1 << SUBPIXEL)
    for ring in outlines:
        cc, rr = _to_cells(t, ring[:, 0], ring[:, 1])
        pts = np.round(np.column_stack([cc - 0.5 - c0, rr - 0.5 - r0]) * scale).astype(np.int32)
        cv2.fillPoly(inside, [pts], 1, shift=SUBPIXEL)
    z = surface.data[r0:r1, c0:c1]
    valid = (inside > 0) & np.isfinite(z) if z.size else np.zeros_like(inside, bool)
    heights = z[valid] if z.size else np.zeros(0)
    ok = np.isfinite(z_edge)
    fallback = np.nanmedian(heights) if heights.size else np.nanmedian(surface.data)
    z_edge = np.where(ok, z_edge, fallback)
    out, start = [], 0
    for ring in outlines:
        edge = z_edge[start : start + len(ring)]
        out.append(np.column_stack([ring, edge, edge]))
        start += len(ring)
    base = float(np.percentile(z_edge, 10))  # the ground: neighbours may overhang parts of the outline
    if heights.size == 0:
        return out, base
    low, top = float(np.min(z_edge)), float(heights.max())
    steps = np.linspace(low, top, levels + 2)
    for below, level in zip(steps[:-2], steps[1:-1]):
        above = (valid & (z >= level)).astype(np.uint8)
        contours, _ = cv2.findContours(above, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        for c in contours:
            cr = cv2.approxPolyDP(c, 0.5, True)[:, 0, :].astype(float)  # within half a cell
            mx, my = _to_map(t, cr[:, 0] + c0 + 0.5, cr[:, 1] + r0 + 0.5)
            out.append(np.column_stack([mx, my, np.full(len(cr), level), np.full(len(cr), below)]))
    peak = np.unravel_index(np.argmax(np.where(valid, z, -np.inf)), z.shape)
    px, py = _to_map(t, peak[1] + c0 + 0.5, peak[0] + r0 + 0.5)
    out.append(np.array([[px, py, top, steps[-2]]]))
    return out, base


def _to_cells(t, x, y):
    """Map coordinates to (column, row) cell coordinates of a north-up grid (cell edges at integers)."""
    return (np.asarray(x) - t.c) / t.a, (np.asarray(y) - t.f) / t.e


def _to_map(t, col, row):
    """(column, row) cell coordinates of a north-up grid to map coordinates."""
    return t.c + np.asarray(col) * t.a, t.f + np.asarray(row) * t.e
