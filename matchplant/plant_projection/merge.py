"""Views of one plant joined into one record: the photos overlap, so a plant is seen a dozen times.

Views are compared in map space, where relief has already been accounted for; the view closest to nadir
(least relief displacement) anchors its plant, and the spread of the views' centroids is kept as an
uncertainty measure.
"""

from __future__ import annotations

import numba
import numpy as np
import pandas as pd

from matchplant.core.geometry.boxes import overlapping_pairs
from matchplant.plant_projection.submodels import align_submodels
from matchplant.plant_projection.views import ACROSS_COLUMNS, BESIDE_CUT_COLUMNS, UNSEEN_COLUMNS, ProjectedViews

MERGE_CONTAINED = 0.75  # a view lying this much inside another (intersection / smaller area) may join it
MERGE_CUT_INSIDE = 0.25  # the same for a view cut by the photo or tile border
MERGE_GAP = 0.05  # metres: a plant seen only in border-cut slivers this close to a plant seen whole is that plant
FUSE_QUANTILE = 0.25  # merge "fuse": each side of the box from this quantile of the views' inner bounds
MERGE_TOLERANCE = 0.01  # metres: how far a seen side of a partly guessed view may stick out of the plant it joins
# (poses, DSM and the alignment of a split project's submodels disagree by millimetres to a centimetre)
# on a noisy DSM (dsm_noise.soil_level) seen sides move with the soil they land on: the tolerance is at least its
# spread (ProjectedViews.soil_spread; on the realistic small field 1 spread: 1,297 records for 1,292 plants, 1,303
# with the 1 cm alone)
TOLERANCE_SPREADS = 1.0
TILE_REPEAT = 0.7  # a cut box lying this much inside a box of another tile of its photo repeats that box
SLIVER_SHARE = 0.5  # a plant seen only in slivers joins a whole one at most 1 / SLIVER_SHARE times its size
MOST_OF_PLANT = 0.5  # a view cut beside a side shows most of its plant with this share of its representative's area
ROW_DECIMALS = 1  # plants are numbered north to south in rows of 10 ** -ROW_DECIMALS metres, then west to east


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
        keep = (tile[i] != tile[j]) & (cut[i] | cut[j]) & (inside >= TILE_REPEAT)
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
    (:data:`MERGE_CUT_INSIDE`) since its cut edge is no plant edge. Near-nadir views are the most accurate,
    so they anchor the plants.
    A view with a side it did not see (behind the plant's top or a neighbour: a guess, which may overshoot)
    joins a view it lies mostly inside, within :data:`MERGE_TOLERANCE` (or the DSM's soil noise,
    :data:`TOLERANCE_SPREADS` times ``views.soil_spread``, when larger), or whose corner it saw
    (:func:`_seen_sides_match`); views this close count as overlapping, so a thin visible sliver
    of a hidden plant beside its plant's box is no second plant.

    Views from the submodels of a split-merge project are first brought into one frame
    (:func:`~matchplant.plant_projection.submodels.align_submodels`).

    ``merge="fuse"`` replaces each plant's box by the robust intersection of its whole views (the
    :data:`FUSE_QUANTILE` of each side): every view's box contains the plant's footprint, and views from
    different sides overshoot on different sides.
    """
    align_submodels(views)  # a split-merge project: its submodels' views into one frame first
    tol = max(MERGE_TOLERANCE, TOLERANCE_SPREADS * views.soil_spread)
    t = views.table
    n = len(t)
    rep, iou_to_rep = np.arange(n), np.ones(n)
    if merge != "none" and n:
        rep, iou_to_rep = _representatives(t, merge_iou, tol)
    # number plants in map order (north to south, then west to east) so ids are stable and readable
    reps = np.unique(rep)
    ry = t["cy"].to_numpy()[reps]
    rx = t["cx"].to_numpy()[reps]
    ranked = reps[np.lexsort((rx, -np.round(ry, ROW_DECIMALS)))]
    pid_of_rep = np.empty(n, dtype=np.int64)
    pid_of_rep[ranked] = np.arange(1, len(ranked) + 1)
    t["plant_id"] = pid_of_rep[rep]
    t["representative"] = rep == np.arange(n)
    t["iou_to_representative"] = iou_to_rep
    return _plant_table(t, ranked, merge)


def _representatives(t: pd.DataFrame, merge_iou: float, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """``(each view's representative, its IoU with it)``: the claims of :func:`merge_views`' rules, then boxes cut
    by a tile border that repeat a neighbouring tile's box, then slivers."""
    n = len(t)
    box = t[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
    order = np.lexsort((t["off_nadir_deg"].to_numpy(), t["cut"].to_numpy()))
    # pairs of views that overlap, or come within the tolerance (a sliver beside its plant's box)
    i, j, _ = overlapping_pairs(box + [-tol, -tol, tol, tol], ordered=False)  # their order does not matter here
    cat = t["category_id"].to_numpy()
    cut = t["cut"].to_numpy()
    partial = [c for c in UNSEEN_COLUMNS + BESIDE_CUT_COLUMNS if c in t]
    guessed = t[partial].to_numpy().any(axis=1) if partial else np.zeros(n, dtype=bool)
    unseen = (
        t[list(UNSEEN_COLUMNS)].to_numpy(bool) if all(c in t for c in UNSEEN_COLUMNS) else np.zeros((n, 4), dtype=bool)
    )
    # boxes of one detector image (photo or tile) went through its non-maximum suppression together
    image = pd.factorize(t["image_id"])[0] if "image_id" in t else np.arange(n)
    iou, strong = _pair_rules(
        np.ascontiguousarray(box),
        i,
        j,
        np.ascontiguousarray(cat, dtype=np.int64),
        np.ascontiguousarray(image, dtype=np.int64),
        cut.astype(np.bool_),
        guessed.astype(np.bool_),
        np.ascontiguousarray(unseen),
        float(merge_iou),
        MERGE_CONTAINED,
        MERGE_CUT_INSIDE,
        tol,
    )
    seed, rep, iou_to_rep = _claims(order, i, j, iou, strong, n)
    # a box cut by its tile border that repeats a box of a neighbouring tile follows that box's plant
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    ti, tj = _tile_duplicates(t)
    for a, b in zip(np.r_[ti, tj], np.r_[tj, ti]):
        if cut[a] and rank[b] < rank[a] and rep[a] != rep[b]:
            members = (rep == rep[a]) if seed[a] else (np.arange(n) == a)
            rep[members] = rep[b]
    _join_slivers(rep, box, cut, cat)
    return rep, iou_to_rep


def _plant_table(t: pd.DataFrame, ranked: np.ndarray, merge: str) -> pd.DataFrame:
    """One row per plant, in plant id order (``ranked``: the positions of the plants' representative views): its
    box (the representative's, or fused from its whole views), views, spread and the representative's values."""
    reps_pos = ranked  # position of each plant's representative view, in plant id order
    reps_t = t.iloc[reps_pos]
    groups = _Groups(t["plant_id"].to_numpy(), len(reps_pos))
    cx, cy = t["cx"].to_numpy(), t["cy"].to_numpy()
    mean_x, mean_y = groups.mean(cx), groups.mean(cy)
    pid = t["plant_id"].to_numpy() - 1
    plants = pd.DataFrame({"plant_id": np.arange(1, len(reps_pos) + 1)})
    plants["views"] = groups.size
    plants["spread_m"] = np.sqrt(groups.mean((cx - mean_x[pid]) ** 2 + (cy - mean_y[pid]) ** 2))
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
            _observed_sides(plants, t, reps_t, groups)
    for c in ("z", "area_m2", "source_image", "score", "category_id", "category", "off_nadir_deg", "cut"):
        plants[c] = reps_t[c].to_numpy()
    plants["score_max"] = groups.max(t["score"].to_numpy(float))
    if "truth_plant_id" in reps_t:
        plants["truth_plant_id"] = reps_t["truth_plant_id"].to_numpy()
    plants["view_index"] = reps_pos
    return plants


@numba.njit(cache=True, nogil=True)
def _claims(order, i, j, iou, strong, n):
    """Representatives and who joins whom, from the pairs of views (``i``, ``j``, their ``iou``) that overlap
    enough (``strong``). Views visited in ``order`` that no earlier representative claimed become
    representatives and claim their partners; every claimed view then joins the representative it overlaps
    most (ties: the lowest index). A loop over views, compiled: only representatives do any work in the first pass.
    Returns ``(representative?, representative of each view, IoU with it)``."""
    start = np.zeros(n + 1, dtype=np.int64)  # each view's partners, both directions (a counting sort)
    for k in range(len(i)):
        if strong[k]:
            start[i[k] + 1] += 1
            start[j[k] + 1] += 1
    start = np.cumsum(start)
    fill = start[:-1].copy()
    partner = np.empty(start[-1], dtype=np.int64)
    pair = np.empty(start[-1], dtype=np.int64)
    for k in range(len(i)):
        if not strong[k]:
            continue
        a, b = i[k], j[k]
        partner[fill[a]], pair[fill[a]] = b, k
        fill[a] += 1
        partner[fill[b]], pair[fill[b]] = a, k
        fill[b] += 1
    seed = np.zeros(n, dtype=np.bool_)
    claimed = np.zeros(n, dtype=np.bool_)
    for v in order:
        if claimed[v]:
            continue
        seed[v] = True
        for q in range(start[v], start[v + 1]):
            claimed[partner[q]] = True
    rep = np.arange(n)
    to_rep = np.ones(n)
    for v in range(n):
        if seed[v]:
            continue
        best, best_iou = -1, -1.0
        for q in range(start[v], start[v + 1]):
            w = partner[q]
            if seed[w] and (iou[pair[q]] > best_iou or (iou[pair[q]] == best_iou and w < best)):
                best, best_iou = w, iou[pair[q]]
        if best >= 0:
            rep[v], to_rep[v] = best, best_iou
    return seed, rep, to_rep


@numba.njit(cache=True, nogil=True)
def _pair_rules(box, i, j, cat, image, cut, guessed, unseen, merge_iou, contained, cut_inside, tol):
    """The IoU of each pair of views ``(i[k], j[k])`` and whether they are one plant (see :func:`merge_views`), in
    one pass. Two boxes of one detector ``image`` are one plant only when their IoU reaches ``merge_iou``: the
    detector's non-maximum suppression left at most one box per plant there, so a box lying inside another box
    of its own image is a second plant (a guessed side can make a view swallow its neighbour's).
    Two views of one category are when their IoU reaches ``merge_iou``; or one lies ``contained``
    inside the other with half that IoU; or one is cut by a border and ``cut_inside`` inside the other; or the
    smaller has a side it did not see (a guess) and lies ``contained`` inside the other grown by ``tol`` (a thin
    view of a plant mostly hidden by its neighbour is pushed out of its own plant by the millimetres poses and
    DSM disagree); or one with a guessed side saw a corner of the other: an east or west and a north or south side
    within ``tol`` of the other's same sides, which it saw too (seen sides are the plant's edges, and a corner
    pins the plant; a guessed side can overshoot by decimetres)."""
    m = i.size
    iou = np.zeros(m)
    strong = np.zeros(m, dtype=np.bool_)
    for k in range(m):
        a, b = i[k], j[k]
        iw = max(min(box[a, 2], box[b, 2]) - max(box[a, 0], box[b, 0]), 0.0)
        ih = max(min(box[a, 3], box[b, 3]) - max(box[a, 1], box[b, 1]), 0.0)
        inter = iw * ih
        area_a = (box[a, 2] - box[a, 0]) * (box[a, 3] - box[a, 1])
        area_b = (box[b, 2] - box[b, 0]) * (box[b, 3] - box[b, 1])
        union = area_a + area_b - inter
        v = inter / union if union > 0 else 0.0
        iou[k] = v
        if cat[a] != cat[b]:
            continue
        if image[a] == image[b]:
            strong[k] = v >= merge_iou
            continue
        small, big = (a, b) if area_a <= area_b else (b, a)
        least = min(area_a, area_b)
        inside = inter / least if least > 0 else 0.0
        if (
            v >= merge_iou
            or (inside >= contained and v >= merge_iou / 2)
            or ((cut[a] or cut[b]) and inside >= cut_inside)
        ):
            strong[k] = True
        elif guessed[small] and least > 0:
            w = min(box[small, 2], box[big, 2] + tol) - max(box[small, 0], box[big, 0] - tol)
            h = min(box[small, 3], box[big, 3] + tol) - max(box[small, 1], box[big, 1] - tol)
            strong[k] = w > 0 and h > 0 and w * h / least >= contained
        if not strong[k]:
            strong[k] = (guessed[a] and _seen_sides_match(box, unseen, a, b, tol)) or (
                guessed[b] and _seen_sides_match(box, unseen, b, a, tol)
            )
    return iou, strong


@numba.njit(cache=True, nogil=True)
def _seen_sides_match(box, unseen, a, b, tol):
    """View ``a`` saw an east or west side and a north or south side that lie within ``tol`` of view ``b``'s same
    sides, which ``b`` saw too: a corner of the plant (its other seen sides may be off, in a steep view)."""
    x = y = False
    for q in range(4):
        if not unseen[a, q] and not unseen[b, q] and abs(box[a, q] - box[b, q]) <= tol:
            if q % 2 == 0:
                x = True
            else:
                y = True
    return x and y


def _join_slivers(rep: np.ndarray, box: np.ndarray, cut: np.ndarray, cat: np.ndarray) -> None:
    """A plant seen only in views cut by a photo border (slivers at the images' edges) whose box comes within
    :data:`MERGE_GAP` of a plant seen whole, and is at most half its size, joins that plant (in place on
    ``rep``). Poses of different submodels of a split-merge project disagree by a few centimetres, so a
    sliver from one submodel can miss the plant its whole views from another submodel place."""
    reps, inverse = np.unique(rep, return_inverse=True)
    only_cut = np.ones(len(reps), dtype=bool)
    np.logical_and.at(only_cut, inverse, cut)
    if not only_cut.any() or only_cut.all():
        return
    b = box[reps].copy()
    b[only_cut] += [-MERGE_GAP, -MERGE_GAP, MERGE_GAP, MERGE_GAP]
    i, j, _ = overlapping_pairs(b)
    keep = (only_cut[i] != only_cut[j]) & (cat[reps[i]] == cat[reps[j]])
    sliver, whole = np.where(only_cut[i[keep]], i[keep], j[keep]), np.where(only_cut[i[keep]], j[keep], i[keep])
    area = (box[reps, 2] - box[reps, 0]) * (box[reps, 3] - box[reps, 1])
    small = area[sliver] <= SLIVER_SHARE * area[whole]
    sliver, whole = sliver[small], whole[small]
    if not sliver.size:
        return
    c_s = (box[reps[sliver], :2] + box[reps[sliver], 2:]) / 2  # the nearest whole plant wins
    c_w = (box[reps[whole], :2] + box[reps[whole], 2:]) / 2
    order = np.lexsort((np.hypot(*(c_s - c_w).T), sliver))
    first = np.r_[True, sliver[order][1:] != sliver[order][:-1]]
    target = dict(zip(reps[sliver[order][first]], reps[whole[order][first]]))
    for a, b_ in target.items():
        rep[rep == a] = b_


class _Groups:
    """The views of each plant (ids 1 .. ``n``, every plant with a view): sums, means, maxima and medians per
    plant over the views sorted once by plant, where pandas would factorize the ids again for each."""

    def __init__(self, plant_id: np.ndarray, n: int):
        self.order = np.argsort(plant_id, kind="stable")
        self.starts = np.searchsorted(plant_id[self.order], np.arange(1, n + 2))
        self.size = np.diff(self.starts)

    def mean(self, values: np.ndarray) -> np.ndarray:
        return np.add.reduceat(values[self.order], self.starts[:-1]) / self.size

    def max(self, values: np.ndarray) -> np.ndarray:
        return np.maximum.reduceat(values[self.order], self.starts[:-1])

    def median(self, values: np.ndarray) -> np.ndarray:
        """Median of each plant's values that are not NaN (NaN where there are none)."""
        return _group_median(np.ascontiguousarray(values[self.order], dtype=np.float64), self.starts)


@numba.njit(cache=True, nogil=True)
def _group_median(values, starts):
    out = np.full(starts.shape[0] - 1, np.nan)
    buf = np.empty(max(np.max(starts[1:] - starts[:-1]), 1))
    for g in range(out.shape[0]):
        k = 0
        for q in range(starts[g], starts[g + 1]):  # the values that are not NaN, kept sorted (a few dozen)
            v = values[q]
            if v == v:
                p = k
                while p > 0 and buf[p - 1] > v:
                    buf[p] = buf[p - 1]
                    p -= 1
                buf[p] = v
                k += 1
        if k:
            out[g] = buf[k // 2] if k % 2 else 0.5 * (buf[k // 2 - 1] + buf[k // 2])
    return out


def _observed_sides(plants: pd.DataFrame, t: pd.DataFrame, reps_t: pd.DataFrame, groups: _Groups) -> None:
    """A side of the representative view that was not seen directly (behind the plant's top or another
    plant, cut by a border, or beside a cut) is replaced by the median of that side in the plant's other
    views that saw it; failing those, in its views cut beside that side that show at least half the
    representative's area; failing those, by the median of the whole views' guesses of it.

    A side seen across the plant (``across_*``: the photo edge facing away from the nadir point) can only
    overshoot: a ray that passed over the plant's top unnoticed (a thin plant, a DSM that rounds its top) lands
    on the soil beyond it, taken for the plant's edge. So when every view that saw the side saw it across the
    plant, and they place it beyond every whole view's guess of it (each mirrored about the plant's top from
    its own direction) by more than :data:`MERGE_TOLERANCE`, the representative's guess is kept. A side that
    some view saw from its own side (a leaf tip on the soil, facing the nadir point) is taken as seen."""

    def area(df: pd.DataFrame) -> pd.Series:
        return (df["xmax"] - df["xmin"]) * (df["ymax"] - df["ymin"])

    rep_area = t["plant_id"].map(pd.Series(area(reps_t).to_numpy(), index=reps_t["plant_id"].to_numpy()))
    beside_cols = BESIDE_CUT_COLUMNS if all(c in t for c in BESIDE_CUT_COLUMNS) else (None,) * 4
    across_cols = ACROSS_COLUMNS if all(c in t for c in ACROSS_COLUMNS) else (None,) * 4
    changed = np.zeros(len(plants), dtype=bool)
    whole = ~t["cut"].to_numpy()
    for side, h, bc, ac in zip(("xmin", "ymin", "xmax", "ymax"), UNSEEN_COLUMNS, beside_cols, across_cols):
        beside = t[bc] if bc else pd.Series(False, index=t.index)
        tiers = [
            t[side].where(~t[h] & ~beside),  # seen whole
            t[side].where(~t[h] & beside & (area(t) >= MOST_OF_PLANT * rep_area)),  # most of the plant in view
            t[side].where(~t["cut"]),
        ]  # the whole views' guesses
        med = np.full(len(plants), np.nan)
        for values in tiers:
            med = np.where(np.isfinite(med), med, groups.median(values.to_numpy(float)))
        unseen_rep = reps_t[h].to_numpy() | (reps_t[bc].to_numpy() if bc else False)
        # the outermost guess of the side among the whole views (-inf: none guessed it, nothing to compare)
        outward = -1.0 if side in ("xmin", "ymin") else 1.0  # larger = further out
        widest = groups.max(np.where(t[h].to_numpy() & whole, outward * t[side].to_numpy(), -np.inf))
        # ... and whether some view saw the side from its own side (nothing then overshoots)
        seen_near = (~t[h] & ~beside & ~t[ac]).to_numpy() if ac else np.ones(len(t), dtype=bool)
        trusted = groups.max(seen_near.astype(np.int8)) > 0
        with np.errstate(invalid="ignore"):  # NaN: no value for this side
            overshoot = (
                reps_t[h].to_numpy() & ~trusted & np.isfinite(widest) & (outward * med > widest + MERGE_TOLERANCE)
            )
        med = np.where(overshoot, reps_t[side].to_numpy(), med)
        use = unseen_rep & np.isfinite(med)
        plants.loc[use, side] = med[use]
        changed |= use
    ok = changed & (plants["xmax"] > plants["xmin"]) & (plants["ymax"] > plants["ymin"])
    bad = changed & ~ok
    for c in ("xmin", "ymin", "xmax", "ymax"):  # sides that cross: keep the representative's box
        plants.loc[bad, c] = reps_t[c].to_numpy()[bad]
    plants.loc[ok, "cx"] = (plants["xmin"] + plants["xmax"])[ok] / 2
    plants.loc[ok, "cy"] = (plants["ymin"] + plants["ymax"])[ok] / 2
