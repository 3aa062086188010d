"""Module 9's trait outputs scored against the synthetic field's truth (demo, benchmarks, tests).

Reads only files: the truth written by the generator (``truth/traits.csv``, ``plant_ids.tif``,
``plots.csv``, ``gaps.csv``, ``date2/``) and module 9's outputs (a plant table with ``x, y`` and
``top_x, top_y``, the outline polygons, the plot table and gaps).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import rasterio
from rasterio.features import rasterize
from scipy.spatial import cKDTree

from matchplant.simfield.layout import FieldPaths

# the statistic each true trait is scored with, over the box and over the canopy, and its name: the scores,
# the demo's figure and its report line all take them from here, so they describe the same statistic
TRAIT_STATS = {
    "height": ("chm_max", "chm_canopy_max", "CHM max"),
    "ndvi": ("ndvi_mean", "ndvi_canopy_mean", "NDVI mean"),
}


def pearson(a, b) -> float:
    """Pearson correlation over the finite pairs; NaN with fewer than 3 pairs or a constant side."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return float("nan")
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def match_to_truth(xy: np.ndarray, truth_xy: np.ndarray, max_dist: float = 0.1) -> np.ndarray:
    """Index of the true plant nearest to each position (within ``max_dist`` m, one-to-one, nearest
    first), -1 where none."""
    d, j = cKDTree(truth_xy).query(xy, distance_upper_bound=max_dist)
    out = np.full(len(xy), -1)
    taken = set()
    for i in np.argsort(d):
        if np.isfinite(d[i]) and j[i] not in taken:
            out[i] = j[i]
            taken.add(j[i])
    return out


def positions(table: pd.DataFrame, top: tuple[str, str] = ("top_x", "top_y")) -> np.ndarray:
    """(n, 2) each plant's position: its top where module 9 found one, else its polygon's centre."""
    xy = table[["x", "y"]].to_numpy(float).copy()
    if all(c in table.columns for c in top):
        t = table[list(top)].to_numpy(float)
        ok = np.isfinite(t).all(axis=1)
        xy[ok] = t[ok]
    return xy


def trait_scores(
    table: pd.DataFrame,
    field: FieldPaths,
    height_col: str = TRAIT_STATS["height"][1],
    ndvi_col: str = TRAIT_STATS["ndvi"][1],
    box_ndvi_col: str = TRAIT_STATS["ndvi"][0],
) -> dict:
    """Height and NDVI of the plants found against each matched plant's truth."""
    truth = pd.read_csv(field.traits_csv)
    m = match_to_truth(positions(table), truth[["x", "y"]].to_numpy(float))
    ok = m >= 0
    t = truth.iloc[m[ok]]
    box_height = TRAIT_STATS["height"][0]
    out = {
        "plants": int(len(table)),
        "matched": int(ok.sum()),
        "true_plants": int(len(truth)),
        "height_r": pearson(t["height"], table.loc[ok, height_col]),
        "height_box_r": pearson(t["height"], table.loc[ok, box_height]) if box_height in table else float("nan"),
        "height_mae_m": float(np.nanmean(np.abs(table.loc[ok, height_col].to_numpy() - t["height"].to_numpy()))),
    }
    if ndvi_col in table.columns:
        out["ndvi_r"] = pearson(t["ndvi"], table.loc[ok, ndvi_col])
        out["ndvi_mae"] = float(np.nanmean(np.abs(table.loc[ok, ndvi_col].to_numpy() - t["ndvi"].to_numpy())))
    if box_ndvi_col in table.columns:
        out["ndvi_box_r"] = pearson(t["ndvi"], table.loc[ok, box_ndvi_col])
    return out


def outline_ious(geoms, table: pd.DataFrame, field: FieldPaths) -> np.ndarray:
    """IoU of each plant's outline (polygons on the truth raster's grid) with its matched true canopy
    (its pixels in ``truth/plant_ids.tif``); NaN for plants without a match."""
    truth = pd.read_csv(field.traits_csv)
    m = match_to_truth(positions(table), truth[["x", "y"]].to_numpy(float))
    with rasterio.open(field.plant_ids) as ds:
        true_lab = ds.read(1)
        pred = rasterize(
            ((g, k + 1) for k, g in enumerate(geoms) if g is not None and not g.is_empty),
            out_shape=ds.shape,
            transform=ds.transform,
            fill=0,
            dtype="int32",
        )
    n = len(table)
    pred_count = np.bincount(pred.ravel(), minlength=n + 1)[1:]
    true_id = np.where(m >= 0, truth["id"].to_numpy()[np.maximum(m, 0)], -10)
    true_count = np.bincount(np.clip(true_lab.ravel(), 0, None))
    both = (pred > 0) & (true_lab > 0)
    p, t = pred[both] - 1, true_lab[both]
    inter = np.bincount(p[t == true_id[p]], minlength=n).astype(float)
    tc = np.where(m >= 0, true_count[np.clip(true_id, 0, len(true_count) - 1)], 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = inter / (pred_count + tc - inter)
    return np.where(m >= 0, iou, np.nan)


def plot_scores(plots: pd.DataFrame, gaps: pd.DataFrame, field: FieldPaths, spacing: float = 0.2) -> dict:
    """Stand counts and gaps per plot against the truth (plots matched by id)."""
    tp = pd.read_csv(field.plots_csv)
    tg = pd.read_csv(field.gaps_csv)
    j = tp.merge(plots, on="plot_id", suffixes=("_true", ""))
    exact = float(np.mean(j["stand_count"] == j["stand_count_true"])) if len(j) else float("nan")
    found = false = 0
    if len(tg) and len(gaps):
        d, _ = cKDTree(gaps[["x", "y"]].to_numpy(float)).query(tg[["x", "y"]].to_numpy(float))
        found = int((d < spacing / 2).sum())
        d2, _ = cKDTree(tg[["x", "y"]].to_numpy(float)).query(gaps[["x", "y"]].to_numpy(float))
        false = int((d2 >= spacing / 2).sum())
    return {
        "plots": int(len(j)),
        "stand_count_exact_share": exact,
        "true_gaps": int(len(tg)),
        "gaps_reported": int(len(gaps)),
        "gaps_found_share": found / len(tg) if len(tg) else float("nan"),
        "false_gap_share": false / len(gaps) if len(gaps) else 0.0,
    }


def growth_scores(table: pd.DataFrame, field: FieldPaths, later_top: tuple[str, str]) -> dict:
    """Centre error on the later date: the reused box centres (``x, y``) and the re-centred tops
    (columns ``later_top``) against the plants' true positions on that date."""
    truth1 = pd.read_csv(field.plants_csv)
    truth2 = pd.read_csv(field.later.plants_csv).set_index("id")
    m = match_to_truth(positions(table), truth1[["x", "y"]].to_numpy(float))
    ok = m >= 0
    true2 = truth2.loc[truth1["id"].to_numpy()[m[ok]], ["x", "y"]].to_numpy(float)
    reused = np.hypot(*(table.loc[ok, ["x", "y"]].to_numpy(float) - true2).T)
    moved = np.hypot(*(table.loc[ok, list(later_top)].to_numpy(float) - true2).T)
    return {
        "plants": int(ok.sum()),
        "reused_box_centre_error_median_m": float(np.nanmedian(reused)),
        "recentred_error_median_m": float(np.nanmedian(moved)),
    }
