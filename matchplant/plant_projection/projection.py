"""Module 8: put detected plants on the map through the camera poses and the DSM (MatchPlant's key idea).

Plants are detected on the (undistorted) photos; each box is then projected onto the map:

1. rays through the box outline (its corners and points along its edges) leave the camera
   (:meth:`Shot.ray_directions`, exact for perspective, brown and fisheye cameras) and are intersected
   with the real surface (:func:`matchplant.core.ground.rays_to_ground`) - not a flat plane at the lowest
   height, which is what the published code did: edges facing the image's nadir point (leaf tips on the
   soil) meet the ground estimated from the DSM, the others the DSM itself (they may show the plant's top);
2. the hits form the plant's polygon in the project's CRS; its centroid and an axis-aligned box follow;
3. a plant seen in several photos (85 % overlap: dozens of views) or in two tiles becomes one record:
   views are merged in map space, the view closest to nadir is kept (or the views are fused), and the
   number of views and the spread of their centroids are kept as an uncertainty measure.

Boxes that cannot be projected (image not in the reconstruction, box outside the image, rays that fall
into a DSM hole or leave the DSM) are listed with the reason in ``unprojected_boxes.csv``, never dropped
silently. ``mode: evaluate`` compares projected plants with boxes drawn on the orthophoto.

Library use::

    views, rejected = project_predictions(ODMProject("field"), read_predictions("predictions.json"))
    plants = merge_views(views)
    metrics = evaluate_boxes(reference_bounds, plant_bounds)
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
from pyproj import CRS

from matchplant.core.coco import read_predictions, source_name
from matchplant.core.config import param, section
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.frames import Frame
from matchplant.core.ground import rays_to_ground
from matchplant.core.io import atomic_open, atomic_path, write_json
from matchplant.core.log import get_logger
from matchplant.core.odm import ODMProject
from matchplant.core.progress import progress
from matchplant.core.reconstruction import Shot
from matchplant.core.surface import HIT, NO_HIT, NODATA, NOT_DOWNWARD, OUTSIDE, STATUS_TEXT, Surface

log = get_logger("projection")

# reasons a box is not projected (besides the ray statuses of matchplant.core.surface)
NOT_IN_RECONSTRUCTION = "image not in the reconstruction (ODM could not place it)"
BOX_OUTSIDE_IMAGE = "box lies outside the image (wrong image name or size?)"
EMPTY_BOX = "box has no area"
RAY_PRIORITY = (NODATA, OUTSIDE, NOT_DOWNWARD, NO_HIT)  # which failed ray explains a box best
MAX_SURFACE_CELLS = 40_000_000  # above this the DSM is read per image instead of once
APEX_REACH = 0.25  # how far past a hidden side (share of the box) the plant's top is looked for
SKIM = 0.1  # metres: a ray that passed this close over a plant before landing on the soil missed the plant's top
MERGE_CONTAINED = 0.75  # a view lying this much inside another (intersection / smaller area) may join it
MERGE_CUT_INSIDE = 0.25  # the same for a view cut by the photo or tile border
# sides of a view's map box not seen directly: behind the plant's top, behind another plant, or cut by a border
UNSEEN_COLUMNS = ("unseen_w", "unseen_s", "unseen_e", "unseen_n")
# sides beside a border cut: they bound only the part of the plant inside the photo (weaker evidence)
BESIDE_CUT_COLUMNS = ("beside_cut_w", "beside_cut_s", "beside_cut_e", "beside_cut_n")
FUSE_QUANTILE = 0.25  # merge "fuse": each side of the box from this quantile of the views' inner bounds


# --------------------------------------------------------------------------------------------------
# configuration


@dataclass
class EvaluateConfig:
    """Evaluation against boxes drawn on the orthophoto (mode: evaluate or both)."""

    reference: Path | None = param(None, "reference plant boxes: COCO JSON over the orthophoto, a vector file "
                                         "(GeoPackage, shapefile, GeoJSON) or a CSV with xmin,ymin,xmax,ymax "
                                         "in the map CRS", path="file")
    plants: Path | None = param(None, "projected plants to evaluate (GeoPackage, shapefile or CSV); "
                                      "null: plants.gpkg in output_dir", path="file")
    orthophoto: Path | None = param(None, "orthophoto for COCO references and the figure; null: the ODM "
                                          "project's odm_orthophoto.tif", path="file")
    iou_threshold: float = param(0.5, "a reference box counts as well projected above this IoU (paper: 0.5)",
                                 min=0.0, max=1.0)
    figure_pixels: int = param(1600, "longest side of the orthophoto in the figure, pixels", min=200, max=10000)


@dataclass
class ProjectionConfig:
    """Project detected plant boxes from the photos onto the map through the camera poses and the DSM."""

    mode: Literal["project", "evaluate", "both"] = param(
        "project", "project: boxes to map plants; evaluate: compare plants with reference boxes; both: one then the other",
        choices=("project", "evaluate", "both"))
    project: Path | None = param(None, "ODM project folder (holds opensfm/, odm_dem/, odm_orthophoto/)", path="dir")
    predictions: Path | None = param(None, "detections: module 7's predictions JSON, or a COCO results list "
                                           "(then also set images_from)", path="file")
    images_from: Path | None = param(None, "COCO dataset giving the image entries of a plain results list", path="file")
    image_type: Literal["auto", "undistorted", "original"] = param(
        "auto", "which photos the boxes are on: undistorted (<name>.tif, ODM's undistorted images), original "
                "(the raw photos, brown/fisheye camera) or auto (from the file names)",
        choices=("auto", "undistorted", "original"))
    dsm: Path | None = param(None, "surface to intersect the rays with; null: the project's odm_dem/dsm.tif",
                             path="file")
    min_score: float = param(0.5, "ignore detections scoring below this (they are counted in the summary)",
                             min=0.0, max=1.0)
    edge_points: int = param(4, "rays along each box edge besides the corners (more follow the relief better)",
                             min=0, max=50)
    silhouette_clearance: float = param(
        0.02, "metres: a ray stops when it comes this close above the DSM. The far edge of a photo box is the image "
              "of the plant's top (relief); its ray only grazes the top and would land on the soil behind the plant, "
              "making the map box too long. A few cm keeps it on the plant; too much stops rays over leaves "
              "(0 = plain intersection)", min=0.0, max=1.0)
    hidden_height: float = param(
        0.05, "metres: a box side whose grazing hit stands this much above the ground lay behind the plant's top (or "
              "behind another plant); it is taken from views that saw that side, else mirrored about the plant's top",
        min=0.0)
    ground_window: float = param(
        1.5, "metres: the ground under the plants is estimated from the DSM by removing every bump narrower than "
             "this; set it above the widest plant (or row, once the canopy closes)", min=0.05)
    map_box: Literal["inscribed", "outline"] = param(
        "inscribed", "the plant's map box: inscribed = box of the ellipse inscribed in the projected outline "
                     "(right for roundish plants whatever the flight direction); outline = box around the outline",
        choices=("inscribed", "outline"))
    merge: Literal["nadir", "fuse", "none"] = param(
        "nadir", "one plant in several views: nadir = keep the view closest to nadir; fuse = robust "
                 "intersection of the views' boxes (trims relief displacement of tall plants); none = keep every "
                 "view as its own record", choices=("nadir", "fuse", "none"))
    merge_iou: float = param(0.25, "views whose map boxes overlap this much (IoU) are the same plant (half of it when one box lies "
                            "inside the other)",
                             min=0.01, max=0.99)
    border_pixels: float = param(2.0, "a box this close to the image (or tile) border is cut; a whole view is "
                                      "preferred to a cut one", min=0.0)
    geometry: Literal["outline", "box"] = param(
        "outline", "the plants' geometry: the projected outline (follows the relief) or the axis-aligned box",
        choices=("outline", "box"))
    layer: str = param("plants", "layer name in the GeoPackage")
    write_shapefile: bool = param(False, "also write plants.shp (for older GIS tools)")
    write_views: bool = param(True, "also write views.csv: every projected box with the plant it was merged into")
    output_dir: Path = param(Path("projection_out"), "folder for the outputs and the run log", path="out")
    evaluate: EvaluateConfig = section(EvaluateConfig)

    def check(self) -> None:
        if self.mode in ("project", "both"):
            for key in ("project", "predictions"):
                if getattr(self, key) is None:
                    raise ConfigError(f"config key '{key}' is required for mode '{self.mode}'",
                                      fix=f"set '{key}: ...' in the config or pass --set {key}=PATH")
        if self.mode in ("evaluate", "both") and self.evaluate.reference is None:
            raise ConfigError(f"config key 'evaluate.reference' is required for mode '{self.mode}'",
                              fix="set it to the boxes drawn on the orthophoto (COCO JSON, vector file or CSV)")
        if self.mode == "evaluate" and self.evaluate.plants is None and not (self.output_dir / "plants.gpkg").is_file():
            raise ConfigError("mode 'evaluate' needs projected plants: set 'evaluate.plants', or run mode "
                              "'project' first", path=self.output_dir / "plants.gpkg",
                              fix="set evaluate.plants to the plants.gpkg written by the projection")


# --------------------------------------------------------------------------------------------------
# geometry of one image's boxes (vectorised)


def box_outline(boxes: np.ndarray, edge_points: int) -> np.ndarray:
    """Points (M, P, 2) around boxes ``[x1, y1, x2, y2]`` (pixel edges, COCO), in camera pixel coordinates.

    COCO boxes are in edge coordinates (pixel ``i`` spans ``[i, i+1]``); the cameras put pixel centres at
    integers, hence the half-pixel shift. The outline runs corner to corner with ``edge_points`` points
    inside each edge, ``P = 4 (edge_points + 1)``.
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 4) - 0.5
    x1, y1, x2, y2 = (b[:, i:i + 1] for i in range(4))
    t = np.arange(edge_points + 1) / (edge_points + 1)
    one = np.ones_like(t)
    xs = np.concatenate([x1 + (x2 - x1) * t, x2 * one, x2 + (x1 - x2) * t, x1 * one], axis=1)
    ys = np.concatenate([y1 * one, y1 + (y2 - y1) * t, y2 * one, y2 + (y1 - y2) * t], axis=1)
    return np.stack([xs, ys], axis=-1)


def polygon_moments(xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """Area, centroid and variances of polygons (M, P, 2) (shoelace sums; orientation does not matter).

    Coordinates are taken relative to each polygon's mean vertex, so UTM-sized numbers lose no precision.
    Returns ``area, cx, cy, var_x, var_y`` (variances of a uniform density over the polygon).
    """
    mean = xy.mean(axis=1, keepdims=True)
    p = xy - mean
    x, y = p[..., 0], p[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    a2 = cross.sum(axis=1)  # twice the signed area
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = ((x + xn) * cross).sum(axis=1) / (3.0 * a2)
        cy = ((y + yn) * cross).sum(axis=1) / (3.0 * a2)
        ixx = ((x * x + x * xn + xn * xn) * cross).sum(axis=1) / (6.0 * a2)
        iyy = ((y * y + y * yn + yn * yn) * cross).sum(axis=1) / (6.0 * a2)
    return np.abs(a2) / 2.0, cx + mean[:, 0, 0], cy + mean[:, 0, 1], ixx - cx * cx, iyy - cy * cy


def outline_boxes(xy: np.ndarray, how: str = "inscribed") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis-aligned boxes (M, 4) ``[xmin, ymin, xmax, ymax]``, centroids (M, 2) and areas of outlines (M, P, 2)
    that start at a box corner and pass the other corners at P/4, P/2 and 3P/4 (:func:`box_outline`).

    ``inscribed``: the box of the ellipse inscribed in the parallelogram of the four corners. When the photo's
    axes follow the map axes this is the outline's own box; when the flight runs at an angle, the outline's
    box would be up to 41 % too wide for a round plant, and this box is the round plant's box.
    """
    area, cx, cy, _, _ = polygon_moments(xy)
    env = np.concatenate([xy.min(axis=1), xy.max(axis=1)], axis=1)
    good = np.isfinite(cx) & np.isfinite(cy) & (area > 0)
    centroid = np.where(good[:, None], np.stack([cx, cy], axis=1), (env[:, :2] + env[:, 2:]) / 2)
    if how == "outline":
        return env, centroid, area
    q = xy.shape[1] // 4
    c0, c1, c2, c3 = (xy[:, k * q] for k in range(4))
    centre = (c0 + c1 + c2 + c3) / 4
    a = (c1 - c0 + c2 - c3) / 4  # half-axis along the photo's x
    b = (c3 - c0 + c2 - c1) / 4  # half-axis along the photo's y
    half = np.sqrt(a ** 2 + b ** 2)
    return np.concatenate([centre - half, centre + half], axis=1), centroid, area


def _edge_indices(edge_points: int) -> list[np.ndarray]:
    """Outline indices of the top, right, bottom and left edge (corners included) of :func:`box_outline`."""
    q = edge_points + 1
    return [(np.arange(q + 1) + k * q) % (4 * q) for k in range(4)]


def near_edges(shot: Shot, frame: Frame, boxes: np.ndarray) -> np.ndarray:
    """Which edges (top, right, bottom, left) of photo boxes (M, 4) face the image's nadir point (M, 4).

    Relief displaces everything above the ground away from the nadir point. On an edge facing it the
    plant's outermost point is therefore a leaf tip on the soil, whatever stands in front of the plant;
    on the other edges it may be the plant's displaced top.
    """
    cam = frame.to_map(shot.center[None, :])[0]
    with np.errstate(invalid="ignore"):
        nadir = shot.project(frame.from_map((cam - [0.0, 0.0, 1000.0])[None, :]))[0]
    out = np.zeros((len(boxes), 4), dtype=bool)
    if not np.isfinite(nadir).all():  # the camera does not look down
        return out
    b = np.asarray(boxes, dtype=float).reshape(-1, 4) - 0.5  # pixel edges -> camera pixels
    out[:, 0], out[:, 1] = nadir[1] < b[:, 1], nadir[0] > b[:, 2]
    out[:, 2], out[:, 3] = nadir[1] > b[:, 3], nadir[0] < b[:, 0]
    return out


def _skimmed(hits: np.ndarray, cam: np.ndarray, surface: Surface, ground: Surface, hidden_height: float,
             skim: float, canopy: float, samples: int = 16) -> np.ndarray:
    """Rays (camera to ``hits`` on the soil) that passed less than ``skim`` above a plant (the DSM standing
    ``hidden_height`` above the ground) on their way down: they went over the plant's top without a ray
    grazing it, so where they landed is not the plant's edge."""
    if len(hits) == 0:
        return np.zeros(0, dtype=bool)
    d = hits - cam
    d /= -d[:, 2:3]  # per metre of descent
    u = (np.arange(1, samples + 1) / samples) * (canopy + skim)  # heights above the hit
    p = hits[:, None, :] - u[None, :, None] * d[:, None, :]
    top = surface.sample(p[..., 0], p[..., 1])
    plant = top - ground.sample(p[..., 0], p[..., 1]) > hidden_height
    return (plant & (p[..., 2] - top < skim)).any(axis=1)


def silhouette_boxes(edges: list[np.ndarray], corners: np.ndarray, near: np.ndarray, ground: Surface,
                     surface: Surface | None = None, *, hidden_height: float = 0.05, apex_grid: int = 9,
                     how: str = "inscribed", cam: np.ndarray | None = None, skim: float = 0.1,
                     canopy: float = 0.0) -> dict[str, np.ndarray]:
    """Map boxes (M, 4) of plants from the hits of the rays along their photo box's edges.

    ``edges``: the hits (M, Q, 3) of the top, right, bottom and left edge (:func:`box_outline` order);
    ``corners`` (M, 4, 2): the box corners on the ground, which set the frame of the projected box (axes
    along the photo's x and y, so any flight heading works); ``near`` (M, 4): edges facing the image's
    nadir point (:func:`near_edges`), whose rays met the ground (a leaf tip on the soil, even behind a
    neighbour). The other edges' rays met the DSM and stopped just above it: such an edge may be the
    image of the plant's *top* displaced outwards by relief, and only its ray grazing the top (stopped on
    it by the intersection's clearance) marks where the plant is. So each side is the *innermost* hit of
    its edge. A side whose innermost hit stands more than ``hidden_height`` above the ground lay behind
    the plant's top (or behind another plant): it is mirrored from the opposite side about the plant's
    top (the highest DSM point inside the box), assuming a roughly symmetric plant.

    ``how``: ``inscribed`` = box of the ellipse inscribed in the resulting parallelogram (a round plant's
    box whatever the flight heading), ``outline`` = box of the parallelogram. Returns ``bounds``,
    ``centre`` (M, 2), ``area`` (of the parallelogram), ``hidden`` (M, 4: photo edges) and ``faces``
    (M, 4, 4): which map sides (west, south, east, north) each photo edge bears on.
    """
    c0, c1, c2, c3 = (corners[:, k] for k in range(4))
    centre = (c0 + c1 + c2 + c3) / 4
    a = (c1 - c0 + c2 - c3) / 4  # half-axis along the photo's x
    b = (c3 - c0 + c2 - c1) / 4  # half-axis along the photo's y
    det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    det = np.where(np.abs(det) > 1e-18, det, np.nan)
    m = len(corners)
    inner = np.empty((m, 4))
    hidden = np.zeros((m, 4), dtype=bool)
    rows = np.arange(m)
    for k, e in enumerate(edges):  # top, right, bottom, left: the innermost coordinate of each edge
        d = e[..., :2] - centre[:, None]
        if k % 2:  # right, left: -1 left .. 1 right
            c = (d[..., 0] * b[:, None, 1] - d[..., 1] * b[:, None, 0]) / det[:, None]
        else:  # top, bottom: -1 top .. 1 bottom
            c = (a[:, None, 0] * d[..., 1] - a[:, None, 1] * d[..., 0]) / det[:, None]
        arg = c.argmin(axis=1) if k in (1, 2) else c.argmax(axis=1)
        inner[:, k] = c[rows, arg]
        hit = e[rows, arg]
        far = ~near[:, k]
        if far.any():
            hidden[far, k] = hit[far, 2] - ground.sample(hit[far, 0], hit[far, 1]) > hidden_height
            if cam is not None and surface is not None:
                on_soil = np.flatnonzero(far & ~hidden[:, k])
                hidden[on_soil, k] = _skimmed(hit[on_soil], cam, surface, ground, hidden_height, skim, canopy)
    t, r, bo, le = (inner[:, k].copy() for k in range(4))
    # an inverted box (a side mirrored past the other, or rays crossing) falls back to the corners' box
    sel = np.flatnonzero(hidden.any(axis=1) & (r > le) & (bo > t))
    if surface is not None and sel.size:
        # the plant's top: the highest DSM point in the box, which reaches past a hidden side (the clearance
        # stops a grazing ray a little before its tangent point, short of the top)
        g = (np.arange(apex_grid) + 0.5) / apex_grid
        hs = hidden[sel].astype(float) * APEX_REACH
        a0, a1 = le[sel] - (r - le)[sel] * hs[:, 3], r[sel] + (r - le)[sel] * hs[:, 1]
        b0, b1 = t[sel] - (bo - t)[sel] * hs[:, 0], bo[sel] + (bo - t)[sel] * hs[:, 2]
        ga = a0[:, None, None] + (a1 - a0)[:, None, None] * g[None, None, :]
        gb = b0[:, None, None] + (b1 - b0)[:, None, None] * g[None, :, None]
        ga, gb = np.broadcast_arrays(ga, gb)
        gx = centre[sel, 0, None, None] + ga * a[sel, 0, None, None] + gb * b[sel, 0, None, None]
        gy = centre[sel, 1, None, None] + ga * a[sel, 1, None, None] + gb * b[sel, 1, None, None]
        h = surface.sample(gx, gy).reshape(len(sel), -1)
        h = np.where(np.isfinite(h), h, -np.inf)
        top_i = h.argmax(axis=1)
        aa, ab = ga.reshape(len(sel), -1)[np.arange(len(sel)), top_i], gb.reshape(len(sel), -1)[np.arange(len(sel)), top_i]
        hs = hidden[sel]
        t2, r2, bo2, le2 = t[sel].copy(), r[sel].copy(), bo[sel].copy(), le[sel].copy()
        t2[hs[:, 0]] = np.minimum(t[sel], 2 * ab - bo[sel])[hs[:, 0]]
        bo2[hs[:, 2]] = np.maximum(bo[sel], 2 * ab - t[sel])[hs[:, 2]]
        r2[hs[:, 1]] = np.maximum(r[sel], 2 * aa - le[sel])[hs[:, 1]]
        le2[hs[:, 3]] = np.minimum(le[sel], 2 * aa - r[sel])[hs[:, 3]]
        t[sel], r[sel], bo[sel], le[sel] = t2, r2, bo2, le2
    good = (r > le) & (bo > t) & np.isfinite(det)
    t, bo = np.where(good, t, -1.0), np.where(good, bo, 1.0)
    le, r = np.where(good, le, -1.0), np.where(good, r, 1.0)
    mid = centre + ((le + r) / 2)[:, None] * a + ((t + bo) / 2)[:, None] * b
    ha = a * ((r - le) / 2)[:, None]
    hb = b * ((bo - t) / 2)[:, None]
    half = np.sqrt(ha ** 2 + hb ** 2) if how == "inscribed" else np.abs(ha) + np.abs(hb)
    area = np.abs(det) * (r - le) * (bo - t)
    # the map sides (west, south, east, north) a photo edge bears on: those its outward normal faces
    normals = np.stack([-b, a, b, -a], axis=1)  # top, right, bottom, left
    normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-300)
    faces = np.stack([-normals[..., 0], -normals[..., 1], normals[..., 0], normals[..., 1]], axis=2) > 0.3
    return {"bounds": np.concatenate([mid - half, mid + half], axis=1), "centre": mid, "area": area,
            "hidden": hidden, "faces": faces}


def project_boxes(shot: Shot, frame: Frame, surface: Surface, boxes: np.ndarray, *, edge_points: int = 4,
                  map_box: str = "inscribed", clearance: float = 0.02, hidden_height: float = 0.05,
                  ground_window: float = 1.5, cut_edges: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Project pixel boxes ``[x1, y1, x2, y2]`` (M, 4) of one image onto the surface, all at once.

    Rays through each box outline meet the ground (estimated from the DSM, :meth:`Surface.ground` with
    ``ground_window``) on the edges facing the image's nadir point, and the DSM, stopping ``clearance``
    metres above it (so a ray grazing a plant's top stays on the plant), on the others;
    :func:`silhouette_boxes` turns the hits into the plant's map box. ``cut_edges`` (M, 4: top, right,
    bottom, left) marks edges cut by the photo or tile border. Returns arrays over the M boxes: ``ok``
    (every ray needed hit the surface), ``status`` (the ray status explaining a failure,
    :data:`matchplant.core.surface.STATUS_TEXT`), ``outline`` (M, P, 3) map points, ``bounds`` (M, 4),
    ``centroid`` (M, 2, the box centre), ``z`` (mean height of the hits), ``area`` (m²), ``beside_cut`` (M, 4:
    map sides beside a border cut), ``unseen`` (M, 4:
    map sides west, south, east, north not seen directly: behind the plant's top or cut by a border)
    and ``off_nadir`` (degrees between the plumb line and the ray to the centroid).
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    uv = box_outline(boxes, edge_points)
    m, p = uv.shape[:2]
    cam = frame.to_map(shot.center[None, :])[0]
    dirs = shot.ray_directions(uv.reshape(-1, 2))
    near = near_edges(shot, frame, boxes)
    edges = _edge_indices(edge_points)
    on_far = np.zeros((m, p), dtype=bool)  # outline points of edges that may show the plant's top
    for k, e in enumerate(edges):
        on_far[:, e] |= ~near[:, k, None]
    ground = surface.ground(ground_window)
    g_pts, g_status = rays_to_ground(shot, dirs, frame, ground)
    d_pts, d_status = g_pts.copy(), g_status.copy()
    far = np.flatnonzero(on_far.ravel())
    if far.size:
        # the DSM is met between the ground hit and the tallest plant above it (the ground rising at most
        # max_slope per metre towards the camera)
        gz = np.where(g_status[far] == HIT, g_pts[far, 2], np.nan)
        tan = np.hypot(dirs[far, 0], dirs[far, 1]) / np.maximum(-dirs[far, 2], 1e-12)
        rise = 1.0 - ground.max_slope * tan
        with np.errstate(invalid="ignore", divide="ignore"):
            top = np.where(rise > 0.1, gz + (surface.canopy_height(ground_window) + clearance) / rise + 0.05, np.nan)
        pts, st = rays_to_ground(shot, dirs[far], frame, surface, clearance=clearance, heights=(top, gz - 0.05))
        if clearance > 0:
            # a ray stopped at the clearance that goes on to meet the surface within twice that height was an
            # exact hit (soil at a leaf tip, a plant's side); one that would fall further grazed a plant's top
            hit = st == HIT
            pts[hit] = surface.drop(pts[hit], pts[hit] - cam, 2 * clearance)  # along the ray, in map space
        d_pts[far], d_status[far] = pts, st
    g_pts, d_pts = g_pts.reshape(m, p, 3), d_pts.reshape(m, p, 3)
    status = np.where(d_status != HIT, d_status, g_status).reshape(m, p)
    ok = (status == HIT).all(axis=1)
    reason = np.full(m, HIT, dtype=np.int8)
    for code in reversed(RAY_PRIORITY):  # the highest-priority failing status wins
        reason[(status == code).any(axis=1)] = code
    out = {"ok": ok, "status": reason, "outline": np.where(on_far[..., None], d_pts, g_pts),
           "bounds": np.full((m, 4), np.nan), "centroid": np.full((m, 2), np.nan),
           "z": np.full(m, np.nan), "area": np.full(m, np.nan), "off_nadir": np.full(m, np.nan),
           "unseen": np.zeros((m, 4), dtype=bool), "beside_cut": np.zeros((m, 4), dtype=bool)}
    if ok.any():
        nr = near[ok]
        edge_hits = [np.where(nr[:, k, None, None], g_pts[ok][:, e], d_pts[ok][:, e]) for k, e in enumerate(edges)]
        corners = g_pts[ok][:, [e[0] for e in edges], :2]
        sb = silhouette_boxes(edge_hits, corners, nr, ground, surface, hidden_height=hidden_height, how=map_box,
                              cam=cam, skim=SKIM, canopy=surface.canopy_height(ground_window))
        centroid = sb["centre"]
        z = out["outline"][ok][..., 2].mean(axis=1)
        d = np.column_stack([centroid - cam[:2], z - cam[2]])
        off = np.degrees(np.arccos(np.clip(-d[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0)))
        cut = cut_edges[ok] if cut_edges is not None else np.zeros_like(sb["hidden"])
        unseen_edges = sb["hidden"] | cut
        # a box cut by a border bounds only the plant's part inside the photo: the edges beside the cut
        # are the plant's only if its outermost point there lies inside the photo
        beside = (np.roll(cut, 1, axis=1) | np.roll(cut, -1, axis=1)) & ~unseen_edges
        out["beside_cut"][ok] = (sb["faces"] & beside[:, :, None]).any(axis=1)
        out["bounds"][ok], out["centroid"][ok], out["area"][ok] = sb["bounds"], centroid, sb["area"]
        out["z"][ok], out["off_nadir"][ok] = z, off
        out["unseen"][ok] = (sb["faces"] & unseen_edges[:, :, None]).any(axis=1)
    return out


# --------------------------------------------------------------------------------------------------
# predictions -> projected views


@dataclass
class ProjectedViews:
    """Every projected box ("view"): a table plus the outline points (N, P, 3) in the map CRS."""

    table: pd.DataFrame
    outlines: np.ndarray
    crs: object


def resolve_image(name: str, undistorted_ids: set[str], original_ids: set[str],
                  image_type: str = "auto") -> tuple[str | None, bool]:
    """The shot id and whether it is the undistorted image, for an image file name (or path).

    ODM names undistorted images ``<original name>.tif``; ``auto`` decides from the name.
    """
    base = Path(str(name).replace("\\", "/")).name
    stripped = base[:-4] if base.lower().endswith(".tif") else None
    if image_type in ("auto", "undistorted"):
        if stripped is not None and stripped in undistorted_ids:
            return stripped, True
        if image_type == "undistorted" and base in undistorted_ids:
            return base, True
    if image_type in ("auto", "original") and base in original_ids:
        return base, False
    return None, image_type != "original"


def _reconstruction_ids(project: ODMProject, undistorted: bool) -> set[str]:
    name = "undistorted_reconstruction" if undistorted else "reconstruction"
    return set(project.reconstruction(undistorted=undistorted).shots) if project.has(name) else set()


def _shot(project: ODMProject, shot_id: str, undistorted: bool, warned: set) -> Shot:
    if not undistorted:
        return project.reconstruction(undistorted=False).shot(shot_id)
    try:
        return project.shot(shot_id, undistorted=True)
    except InputError:
        # the undistorted image is not here (only its size was needed): use the camera's nominal size
        if "size" not in warned:
            warned.add("size")
            log.warning("undistorted images not found in %s; using the cameras' nominal image sizes",
                        project.path("undistorted_images"))
        return project.reconstruction(undistorted=True).shot(shot_id)


def _cut(boxes: np.ndarray, size: np.ndarray, tile: np.ndarray, border: float) -> np.ndarray:
    """Edges (N, 4: top, right, bottom, left) of boxes (N, 4) on their photo's border (``size`` (N, 2))
    or on an inner border of their tile (``tile`` (N, 4): x0, y0, width, height; NaN when the box was
    found on the whole photo)."""
    x1, y1, x2, y2 = boxes.T
    W, H = size.T
    tx0, ty0, tw, th = tile.T
    with np.errstate(invalid="ignore"):
        top = (y1 <= border) | ((y1 - ty0 <= border) & (ty0 > border))
        right = (W - x2 <= border) | ((tx0 + tw - x2 <= border) & (W - tx0 - tw > border))
        bottom = (H - y2 <= border) | ((ty0 + th - y2 <= border) & (H - ty0 - th > border))
        left = (x1 <= border) | ((x1 - tx0 <= border) & (tx0 > border))
    return np.stack([top, right, bottom, left], axis=1)


def _approx_heights(path: Path) -> tuple[float, float]:
    """DSM height range from a decimated read (for the window of the rays), with a margin."""
    import rasterio

    with rasterio.open(path) as src:
        f = max(1, int(max(src.width, src.height) // 512))
        arr = src.read(1, out_shape=(max(1, src.height // f), max(1, src.width // f)), masked=True)
    data = arr.astype(float).filled(np.nan)
    data[data <= -9999] = np.nan
    if not np.isfinite(data).any():
        raise InputError("the DSM holds no valid heights", path=path, fix="check the DSM (re-run ODM with --dsm)")
    lo, hi = float(np.nanmin(data)), float(np.nanmax(data))
    pad = 1.0 + 0.2 * (hi - lo)
    return lo - pad, hi + pad


def _ray_bounds(shot: Shot, frame: Frame, boxes: np.ndarray, z_lo: float, z_hi: float) -> np.ndarray | None:
    """Map bounds where the boxes' corner rays cross the heights z_lo and z_hi (None if a ray looks up)."""
    uv = box_outline(boxes, 0).reshape(-1, 2)
    d = shot.ray_directions(uv)
    c = shot.center
    c_map = frame.to_map(c[None, :])[0]
    far = frame.to_map(c[None, :] + 100.0 * d)
    dm = (far - c_map) / 100.0
    if (dm[:, 2] > -1e-6).any():
        return None
    pts = [c_map[:2] + ((z - c_map[2]) / dm[:, 2])[:, None] * dm[:, :2] for z in (z_lo, z_hi)]
    pts = np.concatenate(pts)
    return np.concatenate([pts.min(axis=0), pts.max(axis=0)])


class _Surfaces:
    """The DSM read once over every image's rays when that fits in memory, else per image."""

    def __init__(self, path: Path, crs, ground_window: float):
        import rasterio

        self.path, self.crs, self.ground_window = path, crs, ground_window
        self._whole: Surface | None = None
        with rasterio.open(path) as src:
            small = src.width * src.height <= MAX_SURFACE_CELLS
        if small:  # the whole DSM fits: read it once, its heights bound the rays
            self._whole = Surface.open(path)
            pad = 1.0 + 0.2 * (self._whole.zmax - self._whole.zmin)
            self.z_lo, self.z_hi = self._whole.zmin - pad, self._whole.zmax + pad
        else:
            self.z_lo, self.z_hi = _approx_heights(path)

    def prepare(self, all_bounds: list[np.ndarray | None]) -> None:
        import rasterio

        with rasterio.open(self.path) as src:
            res = min(abs(src.transform.a), abs(src.transform.e))
            dsm_crs = src.crs
        if dsm_crs is not None and self.crs is not None and not CRS.from_user_input(dsm_crs).equals(self.crs):
            raise InputError(f"the DSM is in {dsm_crs} but the reconstruction in {self.crs.name}", path=self.path,
                             fix="use the DSM of this ODM project (or reproject it to the project's CRS)")
        if self._whole is not None:
            return
        if any(b is None for b in all_bounds):
            self._whole = Surface.open(self.path)
            return
        b = np.array(all_bounds)
        union = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
        cells = (union[2] - union[0]) * (union[3] - union[1]) / res ** 2
        if cells <= MAX_SURFACE_CELLS:
            self._whole = self._open(union, res)

    def _open(self, bounds, res) -> Surface:
        pad = 4 * res + self.ground_window  # the ground estimate needs terrain around the rays
        return Surface.open(self.path, bounds=(bounds[0] - pad, bounds[1] - pad, bounds[2] + pad, bounds[3] + pad))

    def get(self, bounds: np.ndarray) -> Surface:
        if self._whole is not None:
            return self._whole
        import rasterio
        with rasterio.open(self.path) as src:
            res = min(abs(src.transform.a), abs(src.transform.e))
        return self._open(bounds, res)


def project_predictions(project: ODMProject, predictions: dict, *, image_type: str = "auto",
                        dsm: Path | None = None, min_score: float = 0.0, edge_points: int = 4,
                        map_box: str = "inscribed", border_pixels: float = 2.0,
                        clearance: float = 0.02, hidden_height: float = 0.05,
                        ground_window: float = 1.5) -> tuple[ProjectedViews, pd.DataFrame]:
    """Project every prediction box; returns the projected views and the boxes that were not projected.

    ``predictions`` is :func:`matchplant.core.coco.read_predictions`'s dict (tile boxes are moved back to their
    source image with the tile's ``x0``, ``y0``). The rejected table has one row per box with its reason.
    """
    images = {im["id"]: im for im in predictions["images"]}
    cats = {c["id"]: c.get("name", str(c["id"])) for c in predictions.get("categories", [])}
    preds = predictions["predictions"]
    n = len(preds)
    log.info("%d detections on %d images", n, len(images))
    frame = project.frame()
    und_ids, orig_ids = _reconstruction_ids(project, True), _reconstruction_ids(project, False)
    if image_type == "original" and not orig_ids:
        project.require("reconstruction")
    if image_type == "undistorted" and not und_ids:
        project.require("undistorted_reconstruction")

    # one flat table of boxes in source-image pixels
    table = pd.DataFrame({"pred_index": np.arange(n), "image_id": [p["image_id"] for p in preds],
                          "score": [float(p.get("score", 1.0)) for p in preds],
                          "category_id": [int(p.get("category_id", 1)) for p in preds]})
    ims = pd.DataFrame({"image_id": list(images),
                        "image": [im.get("file_name", "") for im in images.values()],
                        "source_image": [Path(source_name(im).replace("\\", "/")).name for im in images.values()],
                        "x0": [float(im.get("x0", 0) or 0) for im in images.values()],
                        "y0": [float(im.get("y0", 0) or 0) for im in images.values()],
                        "tiled": [im.get("x0") is not None or im.get("y0") is not None for im in images.values()],
                        "tile_w": [float(im.get("width") or np.nan) for im in images.values()],
                        "tile_h": [float(im.get("height") or np.nan) for im in images.values()]})
    per = ims.set_index("image_id").loc[table["image_id"]].reset_index(drop=True)
    b = np.array([p["bbox"] for p in preds], dtype=float).reshape(-1, 4)
    off = per[["x0", "y0"]].to_numpy(float)
    boxes = np.column_stack([b[:, :2] + off, b[:, :2] + off + b[:, 2:]])
    table["image"], table["source_image"] = per["image"].to_numpy(), per["source_image"].to_numpy()
    table["category"] = [cats.get(c, str(c)) for c in table["category_id"]]
    table[["u1", "v1", "u2", "v2"]] = boxes
    if any("plant_id" in p for p in preds):  # ground-truth ids travel through (synthetic field, tests)
        table["truth_plant_id"] = [p.get("plant_id", -1) for p in preds]

    reason = np.full(n, "", dtype=object)
    reason[table["score"].to_numpy() < min_score] = "score below min_score"
    resolved = {name: resolve_image(name, und_ids, orig_ids, image_type) for name in table["source_image"].unique()}
    table["shot_id"] = table["source_image"].map({k: v[0] for k, v in resolved.items()})
    table["undistorted"] = table["source_image"].map({k: v[1] for k, v in resolved.items()}).astype(bool)
    reason[(reason == "") & table["shot_id"].isna().to_numpy()] = NOT_IN_RECONSTRUCTION
    reason[(reason == "") & ~((boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1]))] = EMPTY_BOX

    # one group per (shot, undistorted?): its camera, its boxes
    known = table["shot_id"].notna().to_numpy()
    group = np.full(n, -1)
    shot_codes, shot_ids = pd.factorize(table.loc[known, "shot_id"])
    codes, pairs = pd.factorize(2 * shot_codes + table.loc[known, "undistorted"].to_numpy(int))
    group[known] = codes
    keys = [(shot_ids[p // 2], bool(p % 2)) for p in pairs]
    warned: set = set()
    shots = [_shot(project, sid, bool(und), warned) for sid, und in keys]
    size = np.full((n, 2), np.nan)
    if keys:
        wh = np.array([[s.camera.width, s.camera.height] for s in shots], dtype=float)
        size[known] = wh[codes]
    with np.errstate(invalid="ignore"):
        outside = (boxes[:, 0] < -1) | (boxes[:, 1] < -1) | (boxes[:, 2] > size[:, 0] + 1) | (boxes[:, 3] > size[:, 1] + 1)
    reason[(reason == "") & outside] = BOX_OUTSIDE_IMAGE
    todo = np.flatnonzero(reason == "")

    dsm_path = Path(dsm) if dsm is not None else project.path("dsm")
    if dsm is None:
        project.require("dsm")
    surfaces = _Surfaces(dsm_path, frame.crs, ground_window)
    by_group = todo[np.argsort(group[todo], kind="stable")]
    keys_todo, starts = np.unique(group[by_group], return_index=True)
    groups = {int(k): idx for k, idx in zip(keys_todo, np.split(by_group, starts[1:]))}
    bounds = {k: _ray_bounds(shots[k], frame, boxes[idx], surfaces.z_lo, surfaces.z_hi) for k, idx in groups.items()}
    surfaces.prepare(list(bounds.values()))

    P = 4 * (edge_points + 1)
    outlines = np.full((n, P, 3), np.nan)
    res_cols = {c: np.full(n, np.nan) for c in ("xmin", "ymin", "xmax", "ymax", "cx", "cy", "z", "area_m2",
                                                  "off_nadir_deg")}
    unseen = np.zeros((n, 4), dtype=bool)
    beside_cut = np.zeros((n, 4), dtype=bool)
    tiles = np.where(per[["tiled"]].to_numpy(), per[["x0", "y0", "tile_w", "tile_h"]].to_numpy(), np.nan)
    cut_edges = _cut(boxes, size, tiles, border_pixels)
    for k in progress(list(groups), desc="projecting", unit="image"):
        idx = groups[k]
        surface = surfaces.get(bounds[k])
        r = project_boxes(shots[k], frame, surface, boxes[idx], edge_points=edge_points, map_box=map_box,
                          clearance=clearance, hidden_height=hidden_height, ground_window=ground_window,
                          cut_edges=cut_edges[idx])
        good = idx[r["ok"]]
        bad = idx[~r["ok"]]
        reason[bad] = [STATUS_TEXT[int(s)] for s in r["status"][~r["ok"]]]
        outlines[good] = r["outline"][r["ok"]]
        for j, c in enumerate(("xmin", "ymin", "xmax", "ymax")):
            res_cols[c][good] = r["bounds"][r["ok"], j]
        res_cols["cx"][good], res_cols["cy"][good] = r["centroid"][r["ok"]].T
        res_cols["z"][good], res_cols["area_m2"][good] = r["z"][r["ok"]], r["area"][r["ok"]]
        res_cols["off_nadir_deg"][good] = r["off_nadir"][r["ok"]]
        unseen[good], beside_cut[good] = r["unseen"][r["ok"]], r["beside_cut"][r["ok"]]
    for c, v in res_cols.items():
        table[c] = v
    for j, c in enumerate(UNSEEN_COLUMNS):
        table[c] = unseen[:, j]
    for j, c in enumerate(BESIDE_CUT_COLUMNS):
        table[c] = beside_cut[:, j]
    table["reason"] = reason

    done = reason == ""
    table["cut"] = cut_edges.any(axis=1)
    views = table[done].drop(columns=["reason"]).reset_index(drop=True)
    rejected = table[~done][["pred_index", "image_id", "image", "source_image", "u1", "v1", "u2", "v2", "score",
                             "category", "reason"]].reset_index(drop=True)
    return ProjectedViews(views, outlines[done], frame.crs), rejected


# --------------------------------------------------------------------------------------------------
# merging views into plants


def iou_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of box pairs ``a[i]``, ``b[i]`` (each (N, 4), ``[xmin, ymin, xmax, ymax]``)."""
    iw = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0, None)
    ih = np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0, None)
    inter = iw * ih
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    union = area(a) + area(b) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def overlapping_pairs(a: np.ndarray, b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs of overlapping boxes and their IoU (within one set when ``b`` is None, i < j)."""
    import shapely

    same = b is None
    b = a if same else b
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # one bulk R-tree query of the envelopes (which are the boxes: no geometric predicate needed)
    gb = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    i, j = shapely.STRtree(gb).query(gb if same else shapely.box(a[:, 0], a[:, 1], a[:, 2], a[:, 3]))
    if same:
        keep = i < j
        i, j = i[keep], j[keep]
    iou = iou_pairs(a[i], b[j])
    keep = iou > 0
    return i[keep], j[keep], iou[keep]


def _tile_duplicates(t: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of boxes of one photo found on two overlapping tiles: a box cut by its tile border that lies
    mostly inside a box of another tile, compared in pixels (where relief plays no part). Returns the
    index pairs."""
    if "image_id" not in t or "shot_id" not in t:
        return np.zeros(0, int), np.zeros(0, int)
    out_i, out_j = [], []
    for _, idx in t.groupby(["shot_id", "undistorted"]).indices.items():
        if len(idx) < 2 or t["image_id"].iloc[idx].nunique() < 2:
            continue
        px = t[["u1", "v1", "u2", "v2"]].to_numpy(float)[idx]
        i, j, iou = overlapping_pairs(px)
        area = (px[:, 2] - px[:, 0]) * (px[:, 3] - px[:, 1])
        inside = iou * (area[i] + area[j]) / (1.0 + iou) / np.minimum(area[i], area[j])
        tile = t["image_id"].to_numpy()[idx]
        cut = t["cut"].to_numpy()[idx]
        keep = (tile[i] != tile[j]) & (cut[i] | cut[j]) & (inside >= 0.7)
        out_i.append(idx[i[keep]])
        out_j.append(idx[j[keep]])
    if not out_i:
        return np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(out_i), np.concatenate(out_j)


def merge_views(views: ProjectedViews, *, merge: str = "nadir", merge_iou: float = 0.25) -> pd.DataFrame:
    """One row per plant from the projected views; adds ``plant_id`` and ``representative`` to views.table.

    Views are visited best first (whole before cut by a border, then closest to nadir). The first view of
    a plant becomes its representative and claims the views that overlap it (non-maximum suppression in
    map space); each claimed view then joins the representative it overlaps most. Two views of one category
    overlap enough when their IoU reaches ``merge_iou``, or when one lies mostly inside the other
    (:data:`MERGE_CONTAINED`) with at least half that IoU: a tall plant seen obliquely projects too far on
    its far side (relief displacement), so its oblique views contain its near-nadir view rather than
    match it; a view cut by the photo or tile border needs only a modest overlap
    (:data:`MERGE_CUT_INSIDE`) since its cut edge is no plant edge. Near-nadir views are the most accurate, so they anchor the plants.

    ``merge="fuse"`` replaces each plant's box by the robust intersection of its whole views (the
    :data:`FUSE_QUANTILE` of each side): every view's box contains the plant's footprint, and views from
    different sides overshoot on different sides.
    """
    t = views.table
    n = len(t)
    box = t[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
    rep = np.arange(n)
    iou_to_rep = np.ones(n)
    if merge != "none" and n:
        import scipy.sparse as sp

        order = np.lexsort((t["off_nadir_deg"].to_numpy(), t["cut"].to_numpy()))
        i, j, iou = overlapping_pairs(box)
        area = (box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])
        inter = iou * (area[i] + area[j]) / (1.0 + iou)
        inside = inter / np.minimum(area[i], area[j])
        cat = t["category_id"].to_numpy()
        cut = t["cut"].to_numpy()
        # a view cut by a border is partial, and its cut edge is no plant edge (with relief, the ray at the
        # border passes over the plant): a modest overlap is enough, and the best overlap wins below
        # a view with a side it did not see (its box partly guessed) that lies inside another is that plant
        partial = [c for c in UNSEEN_COLUMNS + BESIDE_CUT_COLUMNS if c in t]
        guessed = t[partial].to_numpy().any(axis=1) if partial else np.zeros(n, dtype=bool)
        smaller = np.where(area[i] <= area[j], i, j)
        strong = (cat[i] == cat[j]) & ((iou >= merge_iou) | ((inside >= MERGE_CONTAINED) & (iou >= merge_iou / 2))
                                       | ((inside >= MERGE_CONTAINED) & guessed[smaller])
                                       | ((cut[i] | cut[j]) & (inside >= MERGE_CUT_INSIDE)))
        adj = sp.coo_matrix((iou[strong], (i[strong], j[strong])), shape=(n, n)).tocsr()
        adj = (adj + adj.T).tocsr()
        seed = np.zeros(n, dtype=bool)
        claimed = np.zeros(n, dtype=bool)
        indptr, indices = adj.indptr, adj.indices
        for k in order:  # a loop over views, but only representatives do any work
            if claimed[k]:
                continue
            seed[k] = True
            claimed[indices[indptr[k]:indptr[k + 1]]] = True
        # every claimed view joins the representative it overlaps most
        coo = adj.tocoo()
        m = seed[coo.col] & ~seed[coo.row]
        r, c, v = coo.row[m], coo.col[m], coo.data[m]
        best = np.lexsort((-v, r))
        first = np.r_[True, r[best][1:] != r[best][:-1]] if best.size else np.zeros(0, bool)
        rep[r[best][first]] = c[best][first]
        iou_to_rep[r[best][first]] = v[best][first]
        # a box cut by its tile border that repeats a box of a neighbouring tile follows that box's plant
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        ti, tj = _tile_duplicates(t)
        for a, b in zip(np.r_[ti, tj], np.r_[tj, ti]):
            if cut[a] and rank[b] < rank[a] and rep[a] != rep[b]:
                members = (rep == rep[a]) if seed[a] else (np.arange(n) == a)
                rep[members] = rep[b]
    # number plants in map order (north to south, then west to east) so ids are stable and readable
    reps = np.unique(rep)
    ry = t["cy"].to_numpy()[reps]
    rx = t["cx"].to_numpy()[reps]
    ranked = reps[np.lexsort((rx, -np.round(ry, 1)))]
    pid_of_rep = np.empty(n, dtype=np.int64)
    pid_of_rep[ranked] = np.arange(1, len(ranked) + 1)
    t["plant_id"] = pid_of_rep[rep]
    t["representative"] = rep == np.arange(n)
    t["iou_to_representative"] = iou_to_rep

    reps_pos = ranked  # position of each plant's representative view, in plant id order
    reps_t = t.iloc[reps_pos]
    g = t.groupby("plant_id", sort=True)
    mean_c = g[["cx", "cy"]].transform("mean")
    d2 = (t["cx"] - mean_c["cx"]) ** 2 + (t["cy"] - mean_c["cy"]) ** 2
    plants = pd.DataFrame({"plant_id": np.arange(1, len(reps_pos) + 1)})
    plants["views"] = g.size().to_numpy()
    plants["spread_m"] = np.sqrt(d2.groupby(t["plant_id"]).mean()).to_numpy()
    if merge == "fuse":
        only_cut = t.groupby("plant_id")["cut"].transform("min").astype(bool)
        whole = t[~t["cut"] | only_cut]  # cut views are partial: use them only when there is nothing else
        gw = whole.groupby("plant_id", sort=True)
        lo = gw[["xmin", "ymin"]].quantile(1 - FUSE_QUANTILE).to_numpy()
        hi = gw[["xmax", "ymax"]].quantile(FUSE_QUANTILE).to_numpy()
        med = gw[["xmin", "ymin", "xmax", "ymax"]].median().to_numpy()
        fused = np.where((hi > lo).all(axis=1)[:, None], np.hstack([lo, hi]), med)
        for k, c in enumerate(("xmin", "ymin", "xmax", "ymax")):
            plants[c] = fused[:, k]
        plants["cx"] = (plants["xmin"] + plants["xmax"]) / 2
        plants["cy"] = (plants["ymin"] + plants["ymax"]) / 2
    else:
        for c in ("xmin", "ymin", "xmax", "ymax", "cx", "cy"):
            plants[c] = reps_t[c].to_numpy()
        if merge == "nadir" and all(c in t for c in UNSEEN_COLUMNS):
            _observed_sides(plants, t, reps_t)
    for c in ("z", "area_m2", "source_image", "score", "category_id", "category", "off_nadir_deg", "cut"):
        plants[c] = reps_t[c].to_numpy()
    plants["score_max"] = g["score"].max().to_numpy()
    if "truth_plant_id" in reps_t:
        plants["truth_plant_id"] = reps_t["truth_plant_id"].to_numpy()
    plants["view_index"] = reps_pos
    return plants


def _observed_sides(plants: pd.DataFrame, t: pd.DataFrame, reps_t: pd.DataFrame) -> None:
    """A side of the representative view that was not seen directly (behind the plant's top or another
    plant, cut by a border, or beside a cut) is replaced by the median of that side in the plant's other
    views that saw it; failing those, in its views cut beside that side that show at least half the
    representative's area; failing those, by the median of the whole views' guesses of it."""
    def area(df: pd.DataFrame) -> pd.Series:
        return (df["xmax"] - df["xmin"]) * (df["ymax"] - df["ymin"])

    rep_area = t["plant_id"].map(pd.Series(area(reps_t).to_numpy(), index=reps_t["plant_id"].to_numpy()))
    beside_cols = BESIDE_CUT_COLUMNS if all(c in t for c in BESIDE_CUT_COLUMNS) else (None,) * 4
    changed = np.zeros(len(plants), dtype=bool)
    for side, h, bc in zip(("xmin", "ymin", "xmax", "ymax"), UNSEEN_COLUMNS, beside_cols):
        beside = t[bc] if bc else pd.Series(False, index=t.index)
        tiers = [t[side].where(~t[h] & ~beside),  # seen whole
                 t[side].where(~t[h] & beside & (area(t) >= 0.5 * rep_area)),  # most of the plant in view
                 t[side].where(~t["cut"])]  # the whole views' guesses
        med = np.full(len(plants), np.nan)
        for values in tiers:
            m = values.groupby(t["plant_id"]).median().reindex(plants["plant_id"]).to_numpy()
            med = np.where(np.isfinite(med), med, m)
        unseen_rep = reps_t[h].to_numpy() | (reps_t[bc].to_numpy() if bc else False)
        use = unseen_rep & np.isfinite(med)
        plants.loc[use, side] = med[use]
        changed |= use
    ok = changed & (plants["xmax"] > plants["xmin"]) & (plants["ymax"] > plants["ymin"])
    bad = changed & ~ok
    for c in ("xmin", "ymin", "xmax", "ymax"):  # sides that cross: keep the representative's box
        plants.loc[bad, c] = reps_t[c].to_numpy()[bad]
    plants.loc[ok, "cx"] = (plants["xmin"] + plants["xmax"])[ok] / 2
    plants.loc[ok, "cy"] = (plants["ymin"] + plants["ymax"])[ok] / 2


# --------------------------------------------------------------------------------------------------
# writing


def plant_geometries(plants: pd.DataFrame, views: ProjectedViews, geometry: str = "outline"):
    """Shapely polygons of the plants: the representative view's projected outline, or the box."""
    import shapely

    boxes = shapely.box(plants["xmin"], plants["ymin"], plants["xmax"], plants["ymax"])
    if geometry == "box" or len(plants) == 0:
        return boxes
    rings = views.outlines[plants["view_index"].to_numpy()]
    polys = shapely.polygons(rings)  # 3D: the heights where the rays met the surface
    polys = shapely.make_valid(polys)
    polys = shapely.intersection(polys, boxes)  # the outline overshoots the sides hidden behind the plant
    # a self-crossing outline (rays hitting a steep plant edge) falls back to the box
    bad = ~shapely.is_valid(polys) | (shapely.get_type_id(polys) != 3)
    return np.where(bad, boxes, polys)


def write_plants(plants: pd.DataFrame, views: ProjectedViews, out_dir: Path, *, layer: str = "plants",
                 geometry: str = "outline", shapefile: bool = False) -> dict[str, Path]:
    import geopandas as gpd

    out_dir = Path(out_dir)
    cols = [c for c in plants.columns if c != "view_index"]
    gdf = gpd.GeoDataFrame(plants[cols].copy(), geometry=plant_geometries(plants, views, geometry), crs=views.crs)
    written = {}
    with atomic_path(out_dir / "plants.gpkg") as tmp:
        gdf.to_file(tmp, layer=layer, driver="GPKG")
    written["gpkg"] = out_dir / "plants.gpkg"
    with atomic_open(out_dir / "plants.csv") as fh:
        plants[cols].to_csv(fh, index=False, float_format="%.4f")
    written["csv"] = out_dir / "plants.csv"
    if shapefile:
        written["shp"] = _write_shapefile(gdf, out_dir / "plants.shp")
    return written


SHAPEFILE_NAMES = {"source_image": "src_image", "off_nadir_deg": "off_nadir", "category_id": "cat_id",
                   "score_max": "score_max", "truth_plant_id": "truth_id"}


def _write_shapefile(gdf, path: Path) -> Path:
    """A shapefile is several files: write them in a temporary folder, then move each into place."""
    tmp = Path(tempfile.mkdtemp(prefix=".plants_shp_", dir=path.parent))
    try:
        g = gdf.rename(columns=SHAPEFILE_NAMES)
        g["cut"] = g["cut"].astype(int)
        g.to_file(tmp / path.name, driver="ESRI Shapefile")
        for f in tmp.iterdir():
            os.replace(f, path.parent / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_table(df: pd.DataFrame, path: Path) -> Path:
    with atomic_open(path) as fh:
        df.to_csv(fh, index=False, float_format="%.4f")
    return Path(path)


def run_projection(cfg: ProjectionConfig) -> dict:
    out = Path(cfg.output_dir)
    project = ODMProject(cfg.project)
    preds = read_predictions(cfg.predictions, cfg.images_from)
    views, rejected = project_predictions(project, preds, image_type=cfg.image_type, dsm=cfg.dsm,
                                          min_score=cfg.min_score, edge_points=cfg.edge_points,
                                          map_box=cfg.map_box, border_pixels=cfg.border_pixels,
                                          clearance=cfg.silhouette_clearance, hidden_height=cfg.hidden_height,
                                          ground_window=cfg.ground_window)
    plants = merge_views(views, merge=cfg.merge, merge_iou=cfg.merge_iou)
    geometry = "box" if cfg.merge == "fuse" else cfg.geometry  # fused boxes have no single outline
    written = write_plants(plants, views, out, layer=cfg.layer, geometry=geometry, shapefile=cfg.write_shapefile)
    low = rejected["reason"] == "score below min_score"
    failed = rejected[~low]
    written["unprojected"] = write_table(failed, out / "unprojected_boxes.csv")
    if cfg.write_views:
        written["views"] = write_table(views.table, out / "views.csv")
    summary = {
        "detections": int(len(preds["predictions"])),
        "below_min_score": int(low.sum()),
        "projected_boxes": int(len(views.table)),
        "not_projected": int(len(failed)),
        "not_projected_by_reason": {str(k): int(v) for k, v in failed["reason"].value_counts().items()},
        "plants": int(len(plants)),
        "views_per_plant_median": float(plants["views"].median()) if len(plants) else 0.0,
        "spread_m_median": float(plants["spread_m"].median()) if len(plants) else 0.0,
        "crs": views.crs.to_string() if views.crs is not None else None,
        "outputs": {k: str(v) for k, v in written.items()},
    }
    write_json(out / "projection_summary.json", summary)
    log.info("%d of %d detections projected -> %d plants (median %.0f views each)", summary["projected_boxes"],
             summary["detections"], summary["plants"], summary["views_per_plant_median"])
    if len(failed):
        reasons = "; ".join(f"{v} x {k}" for k, v in summary["not_projected_by_reason"].items())
        log.warning("%d boxes could not be projected (%s); see %s", len(failed), reasons, written["unprojected"])
    if low.any():
        log.info("%d detections scored below min_score=%.2f and were left out", int(low.sum()), cfg.min_score)
    log.info("plants: %s and %s", written["gpkg"], written["csv"])
    return summary


# --------------------------------------------------------------------------------------------------
# evaluation against boxes drawn on the orthophoto


def read_boxes(path: Path, *, orthophoto: Path | None = None, crs=None) -> np.ndarray:
    """Map boxes (N, 4) from a COCO JSON over the orthophoto, a vector file or a CSV (xmin,ymin,xmax,ymax)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return _coco_map_boxes(path, orthophoto)
    if suffix in (".csv", ".txt"):
        df = pd.read_csv(path)
        need = ["xmin", "ymin", "xmax", "ymax"]
        missing = [c for c in need if c not in df.columns]
        if missing:
            raise InputError(f"the CSV lacks the column(s) {', '.join(missing)}", path=path,
                             fix="give a CSV with a header xmin,ymin,xmax,ymax in the map CRS")
        return df[need].to_numpy(float)
    import geopandas as gpd

    try:
        gdf = gpd.read_file(path)
    except Exception as exc:  # noqa: BLE001 - GDAL's many formats; say which file failed
        raise InputError(f"cannot read the vector file: {exc}", path=path,
                         fix="give a GeoPackage, shapefile or GeoJSON (or a CSV / COCO JSON)") from exc
    if crs is not None and gdf.crs is not None and not gdf.crs.equals(crs):
        gdf = gdf.to_crs(crs)
    return np.asarray(gdf.geometry.bounds[["minx", "miny", "maxx", "maxy"]], dtype=float).reshape(-1, 4)


def _coco_map_boxes(path: Path, orthophoto: Path | None) -> np.ndarray:
    import rasterio

    from matchplant.core.coco import read_dataset, to_source_pixels

    if orthophoto is None or not Path(orthophoto).is_file():
        raise InputError("boxes drawn on the orthophoto need the orthophoto to be placed on the map", path=path,
                         fix="set evaluate.orthophoto (or project) so odm_orthophoto.tif can be found")
    ds = read_dataset(path, validate=False)
    images = {im["id"]: im for im in ds["images"]}
    with rasterio.open(orthophoto) as src:
        t = src.transform
    names = {Path(source_name(im)).name for im in images.values()}
    if names - {Path(orthophoto).name}:
        log.warning("reference boxes are on %s; placing them on %s", ", ".join(sorted(names)), Path(orthophoto).name)
    boxes = []
    for a in ds["annotations"]:
        x, y, w, h = to_source_pixels(a["bbox"], images[a["image_id"]])
        xs, ys = t @ (np.array([x, x + w]), np.array([y, y + h]))
        boxes.append([min(xs), min(ys), max(xs), max(ys)])
    return np.array(boxes, dtype=float).reshape(-1, 4)


def match_boxes(reference: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching, highest IoU first: for each reference box its predicted index (-1) and IoU."""
    i, j, iou = overlapping_pairs(reference, predicted)
    order = np.argsort(-iou, kind="stable")
    ref_match = np.full(len(reference), -1, dtype=np.int64)
    ref_iou = np.zeros(len(reference))
    used = np.zeros(len(predicted), dtype=bool)
    for k in order:
        a, b = i[k], j[k]
        if ref_match[a] < 0 and not used[b]:
            ref_match[a], ref_iou[a], used[b] = b, iou[k], True
    return ref_match, ref_iou


def evaluate_boxes(reference: np.ndarray, predicted: np.ndarray, iou_threshold: float = 0.5) -> dict:
    """The paper's two numbers and more: share of reference boxes matched (any overlap), the IoU
    distribution of the matches, and the share with IoU above the threshold."""
    match, iou = match_boxes(reference, predicted)
    matched = match >= 0
    n_ref, n_pred = len(reference), len(predicted)
    m_iou = iou[matched]
    q = (lambda p: float(np.quantile(m_iou, p)) if m_iou.size else 0.0)
    return {
        "reference_boxes": int(n_ref),
        "projected_boxes": int(n_pred),
        "matched": int(matched.sum()),
        "share_matched": float(matched.mean()) if n_ref else 0.0,
        f"share_iou_above_{iou_threshold:g}": float((iou > iou_threshold).mean()) if n_ref else 0.0,
        f"share_of_matched_iou_above_{iou_threshold:g}": float((m_iou > iou_threshold).mean()) if m_iou.size else 0.0,
        "iou_mean": float(m_iou.mean()) if m_iou.size else 0.0,
        "iou_median": q(0.5),
        "iou_p10": q(0.1),
        "iou_p90": q(0.9),
        "unmatched_projected": int(n_pred - matched.sum()),
        "iou_threshold": iou_threshold,
        "_match": match,
        "_iou": iou,
    }


def read_plants_boxes(path: Path) -> tuple[np.ndarray, object]:
    """Boxes and CRS of projected plants (our GeoPackage/shapefile/CSV)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return read_boxes(path), None
    import geopandas as gpd

    gdf = gpd.read_file(path)
    if {"xmin", "ymin", "xmax", "ymax"} <= set(gdf.columns):
        return gdf[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float), gdf.crs
    return np.asarray(gdf.geometry.bounds, dtype=float).reshape(-1, 4), gdf.crs


def evaluation_figure(path: Path, reference: np.ndarray, predicted: np.ndarray, metrics: dict,
                      orthophoto: Path | None = None, max_pixels: int = 1600) -> Path:
    """Both box sets over the orthophoto (read at reduced resolution) and the IoU histogram."""
    from matplotlib.collections import PolyCollection

    from matchplant.core.gui import pyplot

    plt = pyplot(headless=True)
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(14, 7), gridspec_kw={"width_ratios": [2.2, 1]})
    if orthophoto is not None and Path(orthophoto).is_file():
        _draw_orthophoto(ax, orthophoto, max_pixels)

    def rects(b):
        return np.stack([b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1)

    match, iou = metrics["_match"], metrics["_iou"]
    thr = metrics["iou_threshold"]
    good = iou > thr
    ax.add_collection(PolyCollection(rects(reference[good]), facecolors="none", edgecolors="yellow", linewidths=0.8,
                                     label=f"reference, IoU > {thr:g}"))
    ax.add_collection(PolyCollection(rects(reference[~good]), facecolors="none", edgecolors="red", linewidths=1.2,
                                     label=f"reference, IoU <= {thr:g} or unmatched"))
    ax.add_collection(PolyCollection(rects(predicted), facecolors="none", edgecolors="cyan", linewidths=0.6,
                                     linestyles="--", label="projected"))
    allb = np.concatenate([reference, predicted]) if len(predicted) else reference
    if len(allb):
        pad = 0.02 * max(allb[:, 2].max() - allb[:, 0].min(), allb[:, 3].max() - allb[:, 1].min())
        ax.set_xlim(allb[:, 0].min() - pad, allb[:, 2].max() + pad)
        ax.set_ylim(allb[:, 1].min() - pad, allb[:, 3].max() + pad)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("projected plants (cyan) and reference boxes")
    ax.ticklabel_format(useOffset=False, style="plain")
    matched_iou = iou[match >= 0]
    axh.hist(matched_iou, bins=np.linspace(0, 1, 21), color="tab:green", edgecolor="black")
    axh.axvline(thr, color="red", linestyle="--")
    axh.set_xlabel("IoU of matched boxes")
    axh.set_ylabel("reference boxes")
    axh.set_title(f"{metrics['share_matched']:.1%} matched, "
                  f"{metrics[f'share_iou_above_{thr:g}']:.1%} with IoU > {thr:g}\nmedian IoU {metrics['iou_median']:.3f}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)
    return Path(path)


def _draw_orthophoto(ax, path: Path, max_pixels: int) -> None:
    import rasterio

    with rasterio.open(path) as src:
        f = max(1.0, max(src.width, src.height) / max_pixels)
        shape = (max(1, int(src.height / f)), max(1, int(src.width / f)))
        bands = min(src.count, 4)
        arr = src.read(list(range(1, bands + 1)), out_shape=(bands,) + shape)
        b = src.bounds
    img = np.moveaxis(arr, 0, -1)
    if img.dtype != np.uint8:
        hi = np.nanpercentile(img[..., :3], 99) or 1.0
        img = np.clip(img / hi * 255, 0, 255).astype(np.uint8)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    ax.imshow(img, extent=(b.left, b.right, b.bottom, b.top), origin="upper", interpolation="nearest")


def run_evaluation(cfg: ProjectionConfig) -> dict:
    e = cfg.evaluate
    out = Path(cfg.output_dir)
    plants_path = e.plants or out / "plants.gpkg"
    ortho = e.orthophoto
    if ortho is None and cfg.project is not None:
        p = ODMProject(cfg.project)
        ortho = p.path("orthophoto") if p.has("orthophoto") else None
    predicted, crs = read_plants_boxes(plants_path)
    reference = read_boxes(e.reference, orthophoto=ortho, crs=crs)
    metrics = evaluate_boxes(reference, predicted, e.iou_threshold)
    match, iou = metrics.pop("_match"), metrics.pop("_iou")
    write_table(pd.DataFrame({"reference_index": np.arange(len(reference)), "xmin": reference[:, 0],
                              "ymin": reference[:, 1], "xmax": reference[:, 2], "ymax": reference[:, 3],
                              "plant_index": match, "iou": iou}), out / "evaluation_matches.csv")
    metrics.update(reference=str(e.reference), plants=str(plants_path))
    write_json(out / "evaluation.json", metrics)
    fig = evaluation_figure(out / "evaluation.png", reference, predicted, dict(metrics, _match=match, _iou=iou),
                            ortho, e.figure_pixels)
    thr = e.iou_threshold
    log.info("%d reference boxes: %.1f%% matched, %.1f%% with IoU > %g, median IoU %.3f; figure %s",
             metrics["reference_boxes"], 100 * metrics["share_matched"],
             100 * metrics[f"share_iou_above_{thr:g}"], thr, metrics["iou_median"], fig)
    return metrics


def run(cfg: ProjectionConfig) -> dict:
    result = {}
    if cfg.mode in ("project", "both"):
        result["projection"] = run_projection(cfg)
    if cfg.mode in ("evaluate", "both"):
        result["evaluation"] = run_evaluation(cfg)
    return result
