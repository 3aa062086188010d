"""The synthetic field's plants rebuilt from its seed: their exact outlines on the map and in any photo.

The generator (``matchplant.simfield.generate``) draws the terrain, the GCPs and the plants from the first three
streams of its seed, in that order; this rebuilds them the same way (a test of the crops checks against the
generator's own geometry, never against the DSM the crops read).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import shapely

from matchplant.simfield.config import SimFieldConfig, resolve
from matchplant.simfield.scene import Terrain, make_gcps, make_plants
from matchplant.simfield.truth import RING


def field_plants(preset: str, seed: int, **overrides):
    """``(plants, terrain)`` of the field ``generate_field(preset, seed, **overrides)`` wrote (local frame)."""
    s = resolve(SimFieldConfig(preset=preset, seed=seed, **overrides))
    streams = np.random.SeedSequence(seed).spawn(6)
    rng_terrain, rng_gcp, rng_plants = (np.random.default_rng(x) for x in streams[:3])
    terrain = Terrain.random(s, rng_terrain)
    gcps = make_gcps(s, terrain, rng_gcp)
    return make_plants(s, terrain, rng_plants, gcps), terrain


def map_outlines(plants, terrain, offset) -> list:
    """Each plant's true outline on the map (its outermost canopy ring, leaf tips included), map CRS."""
    pts = plants.surface_points(np.arange(len(plants)), terrain)
    outer = pts.reshape(len(plants), -1, RING, 3)[:, -1, :, :2] + np.asarray(offset)[:2]
    return [shapely.make_valid(shapely.Polygon(ring)) for ring in outer]


def true_plants(paths, preset: str = "tiny", seed: int = 0):
    """The field's plants as a GeoDataFrame in its CRS: ``plant_id``, the traits of ``truth/traits.csv``
    (height, ndvi, canopy_area_m2) and each plant's true outline."""
    import geopandas as gpd
    import pandas as pd

    meta = json.loads(paths.field_json.read_text())
    plants, terrain = field_plants(preset, seed)
    traits = pd.read_csv(paths.traits_csv)
    return gpd.GeoDataFrame(
        {"plant_id": plants.ids, **{c: traits[c] for c in ("height", "ndvi", "canopy_area_m2")}},
        geometry=map_outlines(plants, terrain, meta["offset"]),
        crs=meta["crs"],
    )


def photo_points(plants, terrain, p: int, shot) -> np.ndarray:
    """Plant ``p``'s canopy surface points in ``shot``'s pixels (centres at integers), ring by ring (n, RING, 2);
    shot in the field's local frame."""
    pts = plants.surface_points(np.array([p]), terrain)[0]
    return shot.project(pts).reshape(-1, RING, 2)


def photo_mask(plants, terrain, p: int, shot, window: tuple[int, int, int, int], scale: int = 8) -> np.ndarray:
    """Plant ``p``'s true silhouette in ``shot`` with nothing in front of it, on the pixels of ``window`` (x0, y0,
    width, height) refined ``scale`` times: its canopy surface, a mesh of triangles between consecutive rings,
    each projected and filled (a projected ring folds over itself in an oblique view; a triangle stays one)."""
    uv = photo_points(plants, terrain, p, shot)
    a, b = uv[:-1], uv[1:]  # ring k and ring k + 1, point for point
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    tris = np.concatenate([np.stack([a, a1, b1], axis=2), np.stack([a, b1, b], axis=2)]).reshape(-1, 3, 2)
    return fill(tris, window, scale)


def fill(polygons, window: tuple[int, int, int, int], scale: int = 8) -> np.ndarray:
    """Polygons (each (k, 2), photo pixels) filled one by one (their union) on ``window``'s refined grid: a
    sample is in when its centre is."""
    x0, y0, w, h = window
    mask = np.zeros((h * scale, w * scale), np.uint8)
    for poly in polygons:
        pts = np.round(((np.asarray(poly) - [x0, y0] + 0.5) * scale - 0.5) * 256).astype(np.int32)
        cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=8)
    return mask.astype(bool)


def crop_ious(index, plants, terrain, shots) -> np.ndarray:
    """For each crop of ``index`` (crops' index.csv): the IoU of its ``outline_px`` and the plant's true
    silhouette in its photo, on the crop's pixels refined 8 times; asserts the plant lies inside the crop."""
    ious = []
    for r in index.itertuples():
        window = (r.x0, r.y0, r.width, r.height)
        p = int(r.plant_id) - 1
        true = photo_mask(plants, terrain, p, shots[r.photo], window)
        mine = fill([np.asarray(shapely.from_wkt(r.outline_px).exterior.coords) + [r.x0, r.y0]], window)
        ious.append((true & mine).sum() / (true | mine).sum())
        # the plant lies inside the crop, but for what lies outside the photo (a view judged whole from the
        # draped DSM may have a true leaf tip a pixel past the edge: test_every_whole_view_is_cut_and_no_other)
        cam = shots[r.photo].camera
        uv = photo_points(plants, terrain, p, shots[r.photo]).reshape(-1, 2)
        uv = np.clip(uv, -0.5, [cam.width - 0.5, cam.height - 0.5]) - [r.x0, r.y0]
        assert uv.min() >= -0.5 and (uv.max(axis=0) <= [r.width - 0.5, r.height - 0.5]).all(), r
    return np.array(ious)
