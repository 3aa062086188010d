"""Predictions to projected views: every detected box placed on the map, or listed with why it was not.

A "view" is one box of one photo (or tile) projected onto the map; a plant seen in a dozen photos has a
dozen views, merged later (:mod:`matchplant.plant_projection.merge`). Boxes on tiles are moved back to
their source photo first, and sides of a box cut by a photo or tile border are flagged, since a cut
edge is no plant edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from matchplant.core.coco import source_name
from matchplant.core.errors import InputError
from matchplant.core.log import get_logger
from matchplant.core.odm import ODMProject
from matchplant.core.progress import progress
from matchplant.core.reconstruction import Shot
from matchplant.core.surface import STATUS_TEXT
from matchplant.core.validate import did_you_mean, match_names
from matchplant.plant_projection.dsm import DsmSurfaces, ray_bounds
from matchplant.plant_projection.geometry import project_boxes

log = get_logger("projection")

# reasons a box is not projected (besides the ray statuses of matchplant.core.surface)
NOT_IN_RECONSTRUCTION = "image not in the reconstruction (ODM could not place it)"
BOX_OUTSIDE_IMAGE = "box lies outside the image (wrong image name or size?)"
EMPTY_BOX = "box has no area"
# sides of a view's map box not seen directly: behind the plant's top, behind another plant, or cut by a border
UNSEEN_COLUMNS = ("unseen_w", "unseen_s", "unseen_e", "unseen_n")
# sides beside a border cut: they bound only the part of the plant inside the photo (weaker evidence)
BESIDE_CUT_COLUMNS = ("beside_cut_w", "beside_cut_s", "beside_cut_e", "beside_cut_n")


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


def resolve_images(names, undistorted_ids: set[str], original_ids: set[str],
                   image_type: str = "auto") -> tuple[dict[str, tuple[str | None, bool]], dict[str, str]]:
    """:func:`resolve_image` for many names, then the loose match for the rest: a name that differs from a
    shot id only by case or extension (``IMG_1.tif`` or ``IMG_1.jpg.tif`` for shot ``IMG_1.JPG``) is that shot,
    said in the log. Returns ``({name: (shot id or None, undistorted?)}, {unmatched name: "did you mean" hint})``."""
    out = {name: resolve_image(name, undistorted_ids, original_ids, image_type) for name in names}
    loose, hints = [], {}
    for name, (sid, und) in out.items():
        if sid is not None:
            continue
        base = Path(str(name).replace("\\", "/")).name
        stripped = base[:-4] if base.lower().endswith(".tif") else None
        for candidate, ids, is_und in ((stripped or (base if image_type == "undistorted" else None),
                                        undistorted_ids, True),
                                       (base if image_type != "undistorted" else None, original_ids, False)):
            if candidate is None or (is_und and image_type == "original") or not ids:
                continue
            matched, _ = match_names([candidate], ids)
            if candidate in matched:
                out[name] = (matched[candidate], is_und)
                loose.append(f"{base} -> {matched[candidate]}")
                break
        else:
            hints[name] = did_you_mean(stripped or base, undistorted_ids | original_ids)
    if loose:
        log.warning("%d image name(s) differ from the reconstruction's shot ids only by case or extension and were "
                    "matched: %s", len(loose), "; ".join(loose[:5]) + (" ..." if len(loose) > 5 else ""))
    return out, hints


def _shot(project: ODMProject, shot_id: str, undistorted: bool, warned: set) -> Shot:
    if not undistorted:
        return project.nominal_shot(shot_id, undistorted=False)
    try:
        return project.shot(shot_id, undistorted=True)
    except InputError:
        # the undistorted image is not here (only its size was needed): use the camera's nominal size
        if "size" not in warned:
            warned.add("size")
            log.warning("undistorted images not found in %s; using the cameras' nominal image sizes",
                        project.path("undistorted_images"))
        return project.nominal_shot(shot_id, undistorted=True)


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
    und_ids, orig_ids = project.shot_ids(undistorted=True), project.shot_ids(undistorted=False)
    if image_type == "original" and not orig_ids:
        project.require("reconstruction")
    names = {Path(source_name(im).replace("\\", "/")).name for im in predictions["images"]}
    if not und_ids and (image_type == "undistorted" or (image_type == "auto" and orig_ids.isdisjoint(names) and
                                                        any(n.lower().endswith(".tif") for n in names))):
        project.require("undistorted_reconstruction")  # boxes on undistorted images: say what is missing

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
    resolved, hints = resolve_images(table["source_image"].unique(), und_ids, orig_ids, image_type)
    table["hint"] = [hints.get(name, "") for name in table["source_image"]]
    table["shot_id"] = table["source_image"].map({k: v[0] for k, v in resolved.items()})
    table["undistorted"] = table["source_image"].map({k: v[1] for k, v in resolved.items()}).astype(bool)
    reason[(reason == "") & table["shot_id"].isna().to_numpy()] = NOT_IN_RECONSTRUCTION
    if project.is_split:  # which submodel's frame placed each box (merge.align_submodels)
        owners = {sid: project.owner(sid).name for sid in table["shot_id"].dropna().unique()}
        table["submodel"] = table["shot_id"].map(owners).fillna("")
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
    frames = [project.frame_of(sid) for sid, _ in keys]  # a split project's submodels have a frame each
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
    surfaces = DsmSurfaces(dsm_path, frame.crs, ground_window)
    by_group = todo[np.argsort(group[todo], kind="stable")]
    keys_todo, starts = np.unique(group[by_group], return_index=True)
    groups = {int(k): idx for k, idx in zip(keys_todo, np.split(by_group, starts[1:]))}
    bounds = {k: ray_bounds(shots[k], frames[k], boxes[idx], surfaces.z_lo, surfaces.z_hi)
              for k, idx in groups.items()}
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
        r = project_boxes(shots[k], frames[k], surface, boxes[idx], edge_points=edge_points, map_box=map_box,
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
    views = table[done].drop(columns=["reason", "hint"]).reset_index(drop=True)
    rejected = table[~done][["pred_index", "image_id", "image", "source_image", "u1", "v1", "u2", "v2", "score",
                             "category", "reason", "hint"]].reset_index(drop=True)
    return ProjectedViews(views, outlines[done], frame.crs), rejected
