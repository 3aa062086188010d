"""Predictions to projected views: every detected box placed on the map, or listed with why it was not.

A "view" is one box of one photo (or tile) projected onto the map; a plant seen in a dozen photos has a
dozen views, merged later (:mod:`matchplant.plant_projection.merge`). Boxes on tiles are moved back to
their source photo first, and sides of a box cut by a photo or tile border are flagged, since a cut
edge is no plant edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path

import numpy as np
import pandas as pd

from matchplant.core.formats.coco import source_name
from matchplant.core.formats.odm import OUTPUTS, ODMProject
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import NODATA, OUTSIDE, STATUS_TEXT
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.core.runtime.validate import did_you_mean, match_names
from matchplant.plant_projection.dsm import DsmSurfaces, ray_bounds
from matchplant.plant_projection.dsm_noise import Holes
from matchplant.plant_projection.geometry import project_boxes
from matchplant.plant_projection.settings import ProjectionSettings

log = get_logger("plant_projection")

# reasons a box is not projected (besides the ray statuses of matchplant.core.geometry.surface)
NOT_IN_RECONSTRUCTION = "image not in the reconstruction (ODM could not place it)"
BOX_OUTSIDE_IMAGE = "box lies outside the image (wrong image name or size?)"
EMPTY_BOX = "box has no area"
# sides of a view's map box not seen directly: behind the plant's top, behind another plant, or cut by a border
UNSEEN_COLUMNS = ("unseen_w", "unseen_s", "unseen_e", "unseen_n")
# sides beside a border cut: they bound only the part of the plant inside the photo (weaker evidence)
BESIDE_CUT_COLUMNS = ("beside_cut_w", "beside_cut_s", "beside_cut_e", "beside_cut_n")
# sides seen across the plant (the photo edge facing away from the nadir point): a ray that passed over the
# plant's top unnoticed lands on the soil beyond it, so such a side can overshoot (merge._observed_sides)
ACROSS_COLUMNS = ("across_w", "across_s", "across_e", "across_n")
OUTSIDE_SLACK = 1.0  # pixels a box may reach past its image's border (rounding of the detector's boxes)
BAND_ROWS = 64  # pixel rows per band of the projection order (neighbouring boxes share DSM cells in the cache)


@dataclass
class ProjectedViews:
    """Every projected box ("view"): a table plus the outline points in the map CRS (:meth:`outlines`)."""

    table: pd.DataFrame
    # the outline points, rows in the order the boxes were projected (image by image): float32 offsets (R, P, 3)
    # from an origin per row (R, 3; the view's centre) hold them to a micrometre in half the memory
    points: np.ndarray
    origins: np.ndarray
    rows: np.ndarray  # view i's row in points and origins
    crs: object
    soil_spread: float = 0.0  # metres: the DSM's noise on bare soil (dsm_noise.soil_level), 0 on an exact DSM
    dsm_holes: dict = field(default_factory=dict)  # DSM path -> its holes left unfilled (dsm_noise.Holes)

    def outlines(self, views: np.ndarray | None = None) -> np.ndarray:
        """Outline points (N, P, 3) of the views ``views`` (indices into the table; None: all)."""
        rows = self.rows if views is None else self.rows[np.asarray(views)]
        return self.points[rows].astype(np.float64) + self.origins[rows][:, None, :]


def resolve_image(
    name: str, undistorted_ids: set[str], original_ids: set[str], image_type: str = "auto"
) -> tuple[str | None, bool]:
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


def resolve_images(
    names, undistorted_ids: set[str], original_ids: set[str], image_type: str = "auto"
) -> tuple[dict[str, tuple[str | None, bool]], dict[str, str]]:
    """:func:`resolve_image` for many names, then the loose match for the rest: a name that differs from a
    shot id only by case or extension (``IMG_1.tif`` or ``IMG_1.jpg.tif`` for shot ``IMG_1.JPG``) is that shot,
    said in the log. Returns ``({name: (shot id or None, undistorted?)}, {unmatched name: "did you mean" hint})``."""
    out = {name: resolve_image(name, undistorted_ids, original_ids, image_type) for name in names}
    loose, hints = [], {}
    for name, (sid, _und) in out.items():
        if sid is not None:
            continue
        base = Path(str(name).replace("\\", "/")).name
        stripped = base[:-4] if base.lower().endswith(".tif") else None
        for candidate, ids, is_und in (
            (stripped or (base if image_type == "undistorted" else None), undistorted_ids, True),
            (base if image_type != "undistorted" else None, original_ids, False),
        ):
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
        log.warning(
            "%d image name(s) differ from the reconstruction's shot ids only by case or extension and were matched: %s",
            len(loose),
            "; ".join(loose[:5]) + (" ..." if len(loose) > 5 else ""),
        )
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
            log.warning(
                "undistorted images not found in %s; using the cameras' nominal image sizes",
                project.path("undistorted_images"),
            )
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


def _per_image(images: list[dict]) -> tuple[list, dict[str, np.ndarray]]:
    """The image ids (the last entry of a repeated id wins, as a dict would keep it) and, per image, its file
    name, source photo name, tile offset and size (NaN where the image is not a tile)."""
    by_id = {im["id"]: im for im in images}
    ims = list(by_id.values())
    x0 = np.array([float(im.get("x0", 0) or 0) for im in ims]).reshape(-1)
    y0 = np.array([float(im.get("y0", 0) or 0) for im in ims]).reshape(-1)
    tiled = np.array([im.get("x0") is not None or im.get("y0") is not None for im in ims], dtype=bool)
    tile = np.column_stack(
        [x0, y0, [float(im.get("width") or np.nan) for im in ims], [float(im.get("height") or np.nan) for im in ims]]
    ).reshape(-1, 4)
    tile[~tiled] = np.nan
    return list(by_id), {
        "image": np.array([im.get("file_name", "") for im in ims], dtype=object),
        "source_image": np.array([Path(source_name(im).replace("\\", "/")).name for im in ims], dtype=object),
        "offset": np.column_stack([x0, y0]).reshape(-1, 2),
        "tile": tile,
    }


def _dsm_paths(project: ODMProject, keys: list[tuple[str, bool]], dsm: Path | None) -> list[Path]:
    """The DSM each (shot, undistorted) group's rays meet: ``dsm`` when given; in a split-merge project the
    shot's own submodel's DSM, which agrees with its poses (the merged one mixes submodels near the seams),
    or the merged DSM for a submodel without one (said once); else the project's DSM."""
    if dsm is not None:
        return [Path(dsm)] * len(keys)
    if not project.is_split:
        project.require("dsm")
        return [project.path("dsm")] * len(keys)
    own = {sid: project.own_raster(sid, "dsm") for sid in dict.fromkeys(sid for sid, _ in keys)}
    without = sorted({project.owner(sid).name for sid, p in own.items() if p is None})
    merged = None
    if without:
        project.require("dsm")
        merged = project.path("dsm")
        log.info(
            "submodel(s) %s have no DSM of their own (odm_dem/dsm.tif); their shots' boxes meet the merged DSM %s",
            ", ".join(without),
            merged,
        )
    return [own[sid] or merged for sid, _ in keys]


def dsm_files(project: ODMProject, dsm: Path | None) -> list[Path]:
    """The DSM files :func:`_dsm_paths` will give the shots (checked before a run): ``dsm`` when set; in a
    split-merge project each submodel's own DSM, and the merged one only when a submodel has none; else the
    project's."""
    if dsm is not None:
        return [Path(dsm)]
    if not project.is_split:
        project.require("dsm")
        return [project.path("dsm")]
    own = [sub.root / OUTPUTS["dsm"].relpath for sub in project.submodels]
    have = [p for p in own if p.is_file()]
    if len(have) < len(own):
        project.require("dsm")
        have.append(project.path("dsm"))
    return have


def project_predictions(
    project: ODMProject, predictions: dict, settings: ProjectionSettings | None = None
) -> tuple[ProjectedViews, pd.DataFrame]:
    """Project every prediction box; returns the projected views and the boxes that were not projected.

    ``predictions`` is :func:`matchplant.core.formats.predictions.read_predictions`'s dict, checked there (tile
    boxes are moved back to their source image with the tile's ``x0``, ``y0``); ``settings`` None: the config's
    defaults. The rejected table has one row per box with its reason. In a split-merge project each shot's boxes
    meet its own submodel's DSM (docs/DESIGN.md §6) unless ``settings.dsm`` is given. The bookkeeping is done per
    image (names, shots, frames) and per box only in numpy.
    """
    settings = settings if settings is not None else ProjectionSettings.from_config()
    boxes = _box_table(predictions)
    log.info("%d detections on %d images", len(boxes.xyxy), boxes.images)
    frame = project.frame()
    ids = _shot_ids(project, predictions["images"], settings.image_type)
    shot_of, und_of = _resolve_sources(project, boxes, ids, settings.image_type)
    reason = _reasons_before_rays(boxes, shot_of, settings.min_score)
    shots = _ShotGroups(project, boxes, shot_of, und_of)
    reason[(reason == "") & _outside(boxes.xyxy, shots.size)] = BOX_OUTSIDE_IMAGE
    run = _Projection(shots, boxes, frame.crs, settings, reason)
    dsm_of = run.on_own_dsms(project)
    run.retry_on_merged_dsm(project, dsm_of)
    return run.assemble(boxes.cols)


@dataclass
class _Boxes:
    """The predictions as one flat table of boxes in source-image pixels: its columns so far, and what ties each
    box to its image and source photo."""

    cols: dict[str, np.ndarray]
    xyxy: np.ndarray  # (n, 4) x1, y1, x2, y2 in source-image pixels
    tile: np.ndarray  # (n, 4) the box's tile in its photo: x0, y0, width, height (NaN: the whole photo)
    src: np.ndarray  # (n,) each box's source photo, a code into sources
    sources: np.ndarray  # the source photos' names
    images: int  # how many images (photos or tiles) the predictions list


def _box_table(predictions: dict) -> _Boxes:
    """One pass per field over the prediction dicts, the rest per image (its code in the image ids) and per
    source photo."""
    image_keys, per_image = _per_image(predictions["images"])
    cats = {c["id"]: c.get("name", str(c["id"])) for c in predictions.get("categories", [])}
    preds = predictions["predictions"]
    n = len(preds)
    image_ids = [p["image_id"] for p in preds]
    score = np.fromiter([p.get("score", 1.0) for p in preds], dtype=float, count=n)
    category_id = np.fromiter([int(p.get("category_id", 1)) for p in preds], dtype=np.int64, count=n)
    code = pd.Index(image_keys).get_indexer(pd.Index(image_ids)) if n else np.zeros(0, dtype=np.int64)
    b = np.fromiter(chain.from_iterable(p["bbox"] for p in preds), dtype=float, count=4 * n).reshape(-1, 4)
    off = per_image["offset"][code]
    xyxy = np.column_stack([b[:, :2] + off, b[:, :2] + off + b[:, 2:]])
    src_of_image, sources = pd.factorize(per_image["source_image"])
    cat_codes, cat_values = pd.factorize(category_id)
    cols = {
        "pred_index": np.arange(n),
        "image_id": pd.Series(image_ids).to_numpy(),
        "score": score,
        "category_id": category_id,
        "image": per_image["image"][code],
        "source_image": per_image["source_image"][code],
        "category": np.array([cats.get(c, str(c)) for c in cat_values], dtype=object)[cat_codes],
        "u1": xyxy[:, 0],
        "v1": xyxy[:, 1],
        "u2": xyxy[:, 2],
        "v2": xyxy[:, 3],
    }
    if any("plant_id" in p for p in preds):  # ground-truth ids travel through (synthetic field, tests)
        ids = [p.get("plant_id", -1) for p in preds]
        as_array = np.array(ids)  # integer ids (the usual case) make an integer array at once
        cols["truth_plant_id"] = as_array if as_array.dtype.kind in "iu" else pd.Series(ids).to_numpy()
    return _Boxes(cols, xyxy, per_image["tile"][code], src_of_image[code], sources, len(image_keys))


def _shot_ids(project: ODMProject, images: list[dict], image_type: str) -> tuple[set[str], set[str]]:
    """The reconstruction's undistorted and original shot ids; a reconstruction the boxes need and the project
    lacks is said at once."""
    und_ids, orig_ids = project.shot_ids(undistorted=True), project.shot_ids(undistorted=False)
    if image_type == "original" and not orig_ids:
        project.require("reconstruction")
    names = {Path(source_name(im).replace("\\", "/")).name for im in images}
    if not und_ids and (
        image_type == "undistorted"
        or (image_type == "auto" and orig_ids.isdisjoint(names) and any(n.lower().endswith(".tif") for n in names))
    ):
        project.require("undistorted_reconstruction")  # boxes on undistorted images: say what is missing
    return und_ids, orig_ids


def _resolve_sources(
    project: ODMProject, boxes: _Boxes, ids: tuple[set[str], set[str]], image_type: str
) -> tuple[np.ndarray, np.ndarray]:
    """Each source photo's shot id (None: not in the reconstruction) and whether the boxes are on its undistorted
    image; adds the boxes' ``hint``, ``shot_id``, ``undistorted`` (and ``submodel``) columns."""
    src, sources = boxes.src, boxes.sources
    seen = pd.unique(src)  # source photos in order of their first box
    resolved, hints = resolve_images(sources[seen], *ids, image_type)
    shot_of = np.array([resolved.get(s, (None, False))[0] for s in sources], dtype=object)
    und_of = np.array([bool(resolved.get(s, (None, True))[1]) for s in sources], dtype=bool)
    boxes.cols["hint"] = np.array([hints.get(s, "") for s in sources], dtype=object)[src]
    boxes.cols["shot_id"] = shot_of[src]
    boxes.cols["undistorted"] = und_of[src]
    if project.is_split:  # which submodel's frame placed each box (merge.align_submodels)
        boxes.cols["submodel"] = np.array(
            [project.owner(s).name if s is not None else "" for s in shot_of], dtype=object
        )[src]
    return shot_of, und_of


def _reasons_before_rays(boxes: _Boxes, shot_of: np.ndarray, min_score: float) -> np.ndarray:
    """Why each box is not projected, as far as known before any ray is cast ("": not known to fail)."""
    xyxy = boxes.xyxy
    reason = np.full(len(xyxy), "", dtype=object)
    reason[boxes.cols["score"] < min_score] = "score below min_score"
    reason[(reason == "") & ~pd.notna(shot_of[boxes.src])] = NOT_IN_RECONSTRUCTION
    reason[(reason == "") & ~((xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1]))] = EMPTY_BOX
    return reason


class _ShotGroups:
    """One group per (shot, undistorted?): its camera and frame, groups numbered in order of their first box;
    ``group`` (each box's, -1: no shot) and ``size`` (each box's image width and height, NaN: no shot)."""

    def __init__(self, project: ODMProject, boxes: _Boxes, shot_of: np.ndarray, und_of: np.ndarray):
        n, src = len(boxes.xyxy), boxes.src
        known = pd.notna(shot_of[src])
        shot_code, shot_names = pd.factorize(shot_of)  # two names can be one shot (IMG_1.tif, img_1.tif)
        pair_codes = 2 * shot_code[src] + und_of[src]
        self.group = np.full(n, -1)
        self.group[known], pairs = pd.factorize(pair_codes[known])
        self.keys = [(shot_names[p // 2], bool(p % 2)) for p in pairs]
        warned: set = set()
        self.shots = [_shot(project, sid, bool(und), warned) for sid, und in self.keys]
        self.frames = [project.frame_of(sid) for sid, _ in self.keys]  # a split project's submodels: a frame each
        self.size = np.full((n, 2), np.nan)
        if self.keys:
            wh = np.array([[s.camera.width, s.camera.height] for s in self.shots], dtype=float)
            self.size[known] = wh[self.group[known]]


def _outside(xyxy: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Boxes reaching more than :data:`OUTSIDE_SLACK` pixels past their image's border."""
    with np.errstate(invalid="ignore"):
        return (
            (xyxy[:, 0] < -OUTSIDE_SLACK)
            | (xyxy[:, 1] < -OUTSIDE_SLACK)
            | (xyxy[:, 2] > size[:, 0] + OUTSIDE_SLACK)
            | (xyxy[:, 3] > size[:, 1] + OUTSIDE_SLACK)
        )


def _by_position(xyxy: np.ndarray, group: np.ndarray, todo: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The boxes ``todo`` in projection order, and by group ({group: box indices}): by group, within a group by
    position (bands of :data:`BAND_ROWS` pixel rows, then columns): neighbouring boxes read neighbouring DSM
    cells, which stay in the CPU's cache (detections come in score order)."""
    by_group = todo[np.lexsort((xyxy[todo, 0], np.floor(xyxy[todo, 1] / BAND_ROWS), group[todo]))]
    keys_todo, starts = np.unique(group[by_group], return_index=True)
    return by_group, {int(k): idx for k, idx in zip(keys_todo, np.split(by_group, starts[1:]))}


class _Projection:
    """The boxes left after the checks, projected group by group onto the DSMs; their results in ``res`` and
    the reasons of those that fail in ``reason``."""

    def __init__(self, shots: _ShotGroups, boxes: _Boxes, crs, settings: ProjectionSettings, reason: np.ndarray):
        self.shots, self.xyxy, self.crs, self.settings, self.reason = shots, boxes.xyxy, crs, settings, reason
        order, self.groups = _by_position(boxes.xyxy, shots.group, np.flatnonzero(reason == ""))
        self.cut_edges = _cut(boxes.xyxy, shots.size, boxes.tile, settings.border_pixels)
        self.res = _Results(len(boxes.xyxy), settings.edge_points, order)
        self.soil_spread = 0.0  # metres: the largest spread of the bare soil measured on the DSMs (dsm_noise)
        self.dsm_holes: dict[Path, Holes] = {}

    def on_own_dsms(self, project: ODMProject) -> list[Path]:
        """Every group onto its DSM, one DSM at a time (a split project: one per submodel, read by window);
        returns each group's DSM."""
        dsm_of = _dsm_paths(project, [self.shots.keys[k] for k in self.groups], self.settings.dsm)
        dsms = list(dict.fromkeys(dsm_of))
        for path in dsms:
            mine = {k: self.groups[k] for k, p in zip(self.groups, dsm_of) if p == path}
            self._project(path, mine, "projecting" if len(dsms) == 1 else f"projecting ({path.parent.parent.name})")
        return dsm_of

    def retry_on_merged_dsm(self, project: ODMProject, dsm_of: list[Path]) -> None:
        """ODM crops each submodel's DSM inside its own reconstruction: rays of its edge images that left it, or
        met a hole in it, are tried again on the merged DSM, which covers the whole field."""
        merged = project.root / OUTPUTS["dsm"].relpath
        if not (project.is_split and self.settings.dsm is None and merged.is_file()):
            return
        lost = {STATUS_TEXT[OUTSIDE], STATUS_TEXT[NODATA]}
        retry = {
            k: self.groups[k][np.isin(self.reason[self.groups[k]], list(lost))]
            for k, p in zip(self.groups, dsm_of)
            if p != merged
        }
        retry = {k: idx for k, idx in retry.items() if idx.size}
        if retry:
            count = sum(idx.size for idx in retry.values())
            log.info("%d box(es) whose rays left their own submodel's DSM: projected on the merged DSM", count)
            for idx in retry.values():
                self.reason[idx] = ""
            self._project(merged, retry, "projecting (merged DSM)")

    def _project(self, path: Path, groups: dict[int, np.ndarray], desc: str) -> None:
        """The boxes ``groups`` ({group: box indices}) onto the DSM at ``path`` (read by window,
        :class:`DsmSurfaces`)."""
        shots, frames = self.shots.shots, self.shots.frames
        surfaces = DsmSurfaces(path, self.crs, self.settings.ground_window, self.settings.fill_holes)
        bounds = {
            k: ray_bounds(shots[k], frames[k], self.xyxy[idx], surfaces.z_lo, surfaces.z_hi)
            for k, idx in groups.items()
        }
        surfaces.check_below(np.array([frames[k].to_map(shots[k].center[None, :])[0, 2] for k in groups]))
        surfaces.prepare(list(bounds.values()))
        for k in progress(list(groups), desc=desc, unit="image"):
            idx = groups[k]
            r = project_boxes(
                shots[k],
                frames[k],
                surfaces.get(bounds[k]),
                self.xyxy[idx],
                self.settings,
                cut_edges=self.cut_edges[idx],
            )
            self.res.store(idx, r, self.reason)
        self.soil_spread = max(self.soil_spread, surfaces.report())
        self.dsm_holes[path] = surfaces.holes()

    def assemble(self, cols: dict[str, np.ndarray]) -> tuple[ProjectedViews, pd.DataFrame]:
        """The projected views and the rejected boxes, from the box table's columns and the results."""
        cols = dict(cols, **self.res.columns(), reason=self.reason, cut=self.cut_edges.any(axis=1))
        done = self.reason == ""
        table = pd.DataFrame(cols)
        rejected = table.loc[~done, list(REJECTED_COLUMNS)].reset_index(drop=True)
        views = (table if done.all() else table[done]).drop(columns=["reason", "hint"]).reset_index(drop=True)
        res = self.res
        return (
            ProjectedViews(views, res.points, res.origins, res.row[done], self.crs, self.soil_spread, self.dsm_holes),
            rejected,
        )


REJECTED_COLUMNS = (
    "pred_index",
    "image_id",
    "image",
    "source_image",
    "u1",
    "v1",
    "u2",
    "v2",
    "score",
    "category",
    "reason",
    "hint",
)
RESULT_COLUMNS = ("xmin", "ymin", "xmax", "ymax", "cx", "cy", "z", "area_m2", "off_nadir_deg")


class _Results:
    """project_boxes' results gathered per box: outlines, map bounds, centroid, height, area, sides unseen."""

    def __init__(self, n: int, edge_points: int, order: np.ndarray):
        # outlines (a field's are a hundred MB and more) are kept in projection ``order``, written in sequence
        # image by image, as float32 offsets: fresh memory costs more to touch than to write (page faults)
        self.points = np.empty((len(order), 4 * (edge_points + 1), 3), dtype=np.float32)
        self.origins = np.empty((len(order), 3))
        self.row = np.full(n, -1, dtype=np.int64)
        self.row[order] = np.arange(len(order))
        self.values = {c: np.full(n, np.nan) for c in RESULT_COLUMNS}
        self.sides = {c: np.zeros(n, dtype=bool) for c in UNSEEN_COLUMNS + BESIDE_CUT_COLUMNS + ACROSS_COLUMNS}

    def store(self, idx: np.ndarray, r: dict, reason: np.ndarray) -> None:
        ok = r["ok"]
        if ok.all():  # the usual case: no copies of the selection
            ok = slice(None)
        good = idx[ok]
        if not isinstance(ok, slice):
            reason[idx[~ok]] = [STATUS_TEXT[int(s)] for s in r["status"][~ok]]
        rows = self.row[idx]
        origin = np.column_stack([r["centroid"], r["z"]])
        self.origins[rows] = origin
        self.points[rows] = r["outline"] - origin[:, None, :]  # stored as float32 offsets (ProjectedViews)
        v = self.values
        for k, c in enumerate(("xmin", "ymin", "xmax", "ymax")):
            v[c][good] = r["bounds"][ok, k]
        v["cx"][good], v["cy"][good] = r["centroid"][ok, 0], r["centroid"][ok, 1]
        v["z"][good], v["area_m2"][good], v["off_nadir_deg"][good] = r["z"][ok], r["area"][ok], r["off_nadir"][ok]
        for key, names in (("unseen", UNSEEN_COLUMNS), ("beside_cut", BESIDE_CUT_COLUMNS), ("across", ACROSS_COLUMNS)):
            for k, c in enumerate(names):
                self.sides[c][good] = r[key][ok, k]

    def columns(self) -> dict[str, np.ndarray]:
        return {**self.values, **self.sides}
