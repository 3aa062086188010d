"""Rays through a photo box's outline to the surface, and the plant's map box from where they land.

Everything here works on all the boxes of one image at once (arrays, no per-box loop). Relief decides
which surface a ray must meet: everything above the ground is displaced in the photo away from the
image's nadir point, so an edge facing that point is a leaf tip on the soil (its rays meet the ground
estimated from the DSM), while the other edges may be the image of the plant's top (their rays meet the
DSM and stop just above it, so a ray grazing the top stays on the plant). Camera and map conventions:
``docs/DESIGN.md`` §3.
"""

from __future__ import annotations

import numpy as np

from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.ground import rays_to_ground
from matchplant.core.geometry.raycast import LEVEL
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import HIT, NO_HIT, NODATA, NOT_DOWNWARD, OUTSIDE, Surface
from matchplant.plant_projection.dsm_noise import ground_noise
from matchplant.plant_projection.relief import Scene
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.silhouette import silhouette_boxes

RAY_PRIORITY = (NODATA, OUTSIDE, NOT_DOWNWARD, NO_HIT)  # which failed ray explains a box best
NADIR_DEPTH = 1000.0  # metres below the camera of the point whose image is the image's nadir point
STEEP = 0.1  # a far-edge ray whose height range would grow more than tenfold for the ground's slope: no top bound
TOP_MARGIN = 0.05  # metres: the DSM is searched this much above the tallest plant and below the ground hit
SETTLE = 2.0  # a ray stopped at the clearance settles onto a surface met within this many clearances further down


def box_outline(boxes: np.ndarray, edge_points: int) -> np.ndarray:
    """Points (M, P, 2) around boxes ``[x1, y1, x2, y2]`` (pixel edges, COCO), in camera pixel coordinates.

    COCO boxes are in edge coordinates (pixel ``i`` spans ``[i, i+1]``); the cameras put pixel centres at
    integers, hence the half-pixel shift. The outline runs corner to corner with ``edge_points`` points
    inside each edge, ``P = 4 (edge_points + 1)``.
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 4) - 0.5
    x1, y1, x2, y2 = (b[:, i : i + 1] for i in range(4))
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
    half = np.sqrt(a**2 + b**2)
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
        nadir = shot.project(frame.from_map((cam - [0.0, 0.0, NADIR_DEPTH])[None, :]))[0]
    out = np.zeros((len(boxes), 4), dtype=bool)
    if not np.isfinite(nadir).all():  # the camera does not look down
        return out
    b = np.asarray(boxes, dtype=float).reshape(-1, 4) - 0.5  # pixel edges -> camera pixels
    out[:, 0], out[:, 1] = nadir[1] < b[:, 1], nadir[0] > b[:, 2]
    out[:, 2], out[:, 3] = nadir[1] > b[:, 3], nadir[0] < b[:, 0]
    return out


def project_boxes(
    shot: Shot,
    frame: Frame,
    surface: Surface,
    boxes: np.ndarray,
    settings: ProjectionSettings,
    *,
    cut_edges: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Project pixel boxes ``[x1, y1, x2, y2]`` (M, 4) of one image onto the surface, all at once.

    Rays through each box outline (``settings.edge_points`` along each edge) meet the ground (estimated from the
    DSM, :meth:`Surface.ground` with ``settings.ground_window``) on the edges facing the image's nadir point, and
    the DSM, stopping ``settings.clearance`` metres above it (so a ray grazing a plant's top stays on the plant),
    on the others;
    :func:`silhouette_boxes` turns the hits into the plant's map box. ``cut_edges`` (M, 4: top, right,
    bottom, left) marks edges cut by the photo or tile border. Returns arrays over the M boxes: ``ok``
    (every ray needed hit the surface), ``status`` (the ray status explaining a failure,
    :data:`matchplant.core.geometry.surface.STATUS_TEXT`), ``outline`` (M, P, 3) map points, ``bounds`` (M, 4),
    ``centroid`` (M, 2, the box centre), ``z`` (mean height of the hits), ``area`` (m²), ``beside_cut`` (M, 4:
    map sides beside a border cut), ``unseen`` (M, 4:
    map sides west, south, east, north not seen directly: behind the plant's top or cut by a border),
    ``across`` (M, 4: map sides seen across the plant, :func:`silhouette_boxes`) and ``off_nadir`` (degrees
    between the plumb line and the ray to the centroid).
    """
    edge_points, clearance, ground_window = settings.edge_points, settings.clearance, settings.ground_window
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
        d_far = dirs[far]
        tan = np.hypot(d_far[:, 0], d_far[:, 1]) / np.maximum(-d_far[:, 2], LEVEL)
        rise = 1.0 - ground.max_slope * tan
        with np.errstate(invalid="ignore", divide="ignore"):
            top = np.where(
                rise > STEEP, gz + (surface.canopy_height(ground_window) + clearance) / rise + TOP_MARGIN, np.nan
            )
        # a ray stopped at the clearance that goes on to meet the surface within twice that height was an
        # exact hit (soil at a leaf tip, a plant's side) and settles there; one that would fall further grazed
        # a plant's top and stays
        # (the DSM's soil dips below the ground, lifted to the soil's level, down to the DSM's lowest envelope)
        bottom = gz - ground_noise(surface, ground_window).lift - TOP_MARGIN
        pts, st = rays_to_ground(
            shot, d_far, frame, surface, clearance=clearance, settle=SETTLE * clearance, heights=(top, bottom)
        )
        d_pts[far], d_status[far] = pts, st
    g_pts, d_pts = g_pts.reshape(m, p, 3), d_pts.reshape(m, p, 3)
    status = np.where(d_status != HIT, d_status, g_status).reshape(m, p)
    ok = (status == HIT).all(axis=1)
    reason = np.full(m, HIT, dtype=np.int8)
    for code in reversed(RAY_PRIORITY) if not ok.all() else ():  # the highest-priority failing status wins
        reason[(status == code).any(axis=1)] = code
    # the outline: DSM hits on the far edges, ground hits on the others (d_pts started as a copy of g_pts)
    cut = cut_edges if cut_edges is not None else np.zeros((m, 4), dtype=bool)
    scene = Scene.of(surface, cam, settings)
    sil = silhouette_boxes(g_pts, d_pts, near, ok, cut, scene, settings.map_box == "inscribed")
    return {
        "ok": ok,
        "status": reason,
        "outline": d_pts,
        "bounds": sil.bounds,
        "centroid": sil.centre,
        "z": sil.z,
        "area": sil.area,
        "off_nadir": sil.off_nadir,
        "unseen": sil.unseen,
        "beside_cut": sil.beside_cut,
        "across": sil.across,
    }
