"""Owned areas: every covered point of the field is given to exactly one selected image.

So that each plant is labelled once (step 4 shows the annotator only the image's own part), the covered
area is partitioned: first by nearest footprint centre (a Voronoi partition, which keeps each image's part
near its centre, where it is least distorted), then what the nearest image does not see goes to the
selected image that sees most of it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box


def owned_areas(aoi, polygons: Sequence[Polygon], min_area: float = 1e-6) -> list[Polygon | MultiPolygon]:
    """Split the covered AOI among the selected footprints: each point goes to exactly one image.

    First every image gets the part of its footprint nearer its own centre than any other selected centre
    (a Voronoi partition); what is left (seen, but not by the nearest image) goes piece by piece to the
    image that sees most of the piece.
    """
    if not polygons:
        return []
    fps = [shapely.make_valid(p.intersection(aoi)) for p in polygons]
    centres = shapely.MultiPoint([p.centroid for p in polygons])
    owned = [shapely.Polygon() for _ in polygons]
    if len(polygons) == 1:
        owned = [fps[0]]
    else:
        extent = box(*shapely.union_all([aoi, *polygons]).bounds).buffer(1.0)
        cells = shapely.voronoi_polygons(centres, extend_to=extent)
        by_site = {}
        for cell in cells.geoms:
            for j, p in enumerate(polygons):
                if j not in by_site and cell.contains(p.centroid):
                    by_site[j] = cell
                    break
        for j, fp in enumerate(fps):
            if j in by_site:
                owned[j] = fp.intersection(by_site[j])
    covered = shapely.union_all(fps)
    left = covered.difference(shapely.union_all(owned))
    pieces = [g for g in getattr(left, "geoms", [left]) if g.area > min_area]
    guard = 0
    while pieces and guard < 10_000:
        guard += 1
        piece = pieces.pop()
        shares = [fp.intersection(piece).area for fp in fps]
        j = int(np.argmax(shares))
        if shares[j] <= min_area:
            continue
        part = fps[j].intersection(piece)
        owned[j] = owned[j].union(part)
        rest = piece.difference(part)
        pieces += [g for g in getattr(rest, "geoms", [rest]) if g.area > min_area]
    return [polygonal(o) for o in owned]


def polygonal(geom):
    """Only the areas of a geometry: overlays can leave zero-area lines or points in a collection."""
    geom = shapely.make_valid(geom)
    parts = [g for g in shapely.get_parts(geom) if isinstance(g, (Polygon, MultiPolygon)) and g.area > 0]
    if not parts:
        return Polygon()
    return parts[0] if len(parts) == 1 else shapely.union_all(parts)


def largest_polygon(geom) -> Polygon:
    """The largest piece of an area (owned_areas.json holds one outline per image)."""
    if isinstance(geom, Polygon):
        return geom
    parts = [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]
    return max(parts, key=lambda g: g.area) if parts else Polygon()
