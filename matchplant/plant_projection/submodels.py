"""Views from the submodels of a split-merge project, brought into agreement before they are merged.

ODM aligns the submodels of a split run to each other, but a few centimetres remain between them, and a
plant in the split overlap is seen from shots of two submodels: its views from one lie a few centimetres
from its views from the other, enough to split a narrow plant into two. The plants both submodels see
measure that offset (the median shift between their matching whole views); each submodel's views are
then moved by its share of it, so that the submodels meet in their average frame (docs/DESIGN.md §6).
"""

from __future__ import annotations

import numpy as np

from matchplant.core.geometry.boxes import overlapping_pairs
from matchplant.core.runtime.log import get_logger
from matchplant.plant_projection.views import UNSEEN_COLUMNS, ProjectedViews

log = get_logger("plant_projection")

MATCH_IOU = 0.3  # whole views of two submodels overlapping this much are taken as one plant
MIN_PAIRS = 5  # plants two submodels must share before their offset is trusted


def align_submodels(views: ProjectedViews) -> dict[str, tuple[float, float]]:
    """Move each submodel's views (table and outlines, in place) by the shift that brings the submodels into
    their average frame; returns the shift applied per submodel (metres, east and north)."""
    t = views.table
    if "submodel" not in t or t["submodel"].nunique() < 2:
        return {}
    names = sorted(t["submodel"].unique())
    sub = t["submodel"].map({n: k for k, n in enumerate(names)}).to_numpy()
    whole = ~t["cut"].to_numpy()
    for c in UNSEEN_COLUMNS:
        if c in t:
            whole &= ~t[c].to_numpy()
    idx = np.flatnonzero(whole)
    box = t[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)[idx]
    i, j, iou = overlapping_pairs(box)
    a, b = idx[i], idx[j]
    keep = (iou >= MATCH_IOU) & (sub[a] != sub[b]) & (t["category_id"].to_numpy()[a] == t["category_id"].to_numpy()[b])
    a, b = a[keep], b[keep]
    centre = np.column_stack([(t["xmin"] + t["xmax"]).to_numpy(), (t["ymin"] + t["ymax"]).to_numpy()]) / 2
    rows, offsets, weights = [], [], []
    for p in range(len(names)):
        for q in range(p + 1, len(names)):
            sel = ((sub[a] == p) & (sub[b] == q)) | ((sub[a] == q) & (sub[b] == p))
            if sel.sum() < MIN_PAIRS:
                continue
            lo, hi = np.where(sub[a[sel]] == p, a[sel], b[sel]), np.where(sub[a[sel]] == p, b[sel], a[sel])
            d = np.median(centre[hi] - centre[lo], axis=0)  # where q places the plants, relative to p
            row = np.zeros(len(names))
            row[p], row[q] = -1.0, 1.0
            rows.append(row)
            offsets.append(d)
            weights.append(np.sqrt(sel.sum()))
            log.info(
                "submodels %s and %s place the %d view pairs of plants both see %.1f cm apart (east %.1f, north %.1f)",
                names[p],
                names[q],
                int(sel.sum()),
                100 * np.hypot(*d),
                100 * d[0],
                100 * d[1],
            )
    if not rows:
        return {}
    # least squares: position_q - position_p = offset_pq, positions summing to zero (the average frame)
    A = np.vstack([np.array(rows) * np.array(weights)[:, None], np.ones((1, len(names)))])
    rhs = np.vstack([np.array(offsets) * np.array(weights)[:, None], np.zeros((1, 2))])
    pos = np.linalg.lstsq(A, rhs, rcond=None)[0]
    shift = -pos[sub]  # (N, 2): each view back into the average frame
    for k, c in enumerate(("xmin", "ymin", "xmax", "ymax")):
        t[c] = t[c].to_numpy() + shift[:, k % 2]
    t["cx"] = t["cx"].to_numpy() + shift[:, 0]
    t["cy"] = t["cy"].to_numpy() + shift[:, 1]
    views.origins[views.rows, :2] += shift  # the outlines move with their origin
    return {n: (float(-pos[k, 0]), float(-pos[k, 1])) for k, n in enumerate(names)}
