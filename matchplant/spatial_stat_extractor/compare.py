"""Comparison of two sets of plants (e.g. drawn by hand and predicted), as in the paper's Figure 10.

Plants are matched one to one by overlap: candidate pairs (polygons that intersect) are taken in order
of decreasing intersection over union (IoU), each plant at most once, down to ``min_iou``. Per trait:
the two-sample Kolmogorov-Smirnov test between the distributions of all plants of each set, and over
matched pairs Pearson's r and the absolute differences; the IoU of the matches is summarised too.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import shapely

from matchplant.core.geometry.boxes import greedy_matches
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path
from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.inputs import read_polygons
from matchplant.spatial_stat_extractor.zonal import extract_stats, write_csv

log = get_logger("spatial_stat_extractor")


def match_by_iou(geoms_a, geoms_b, min_iou: float = 0.3) -> pd.DataFrame:
    """One-to-one matches ``(index_a, index_b, iou)``, greedy by decreasing IoU (ties: lower indices)."""

    a, b = np.asarray(geoms_a, dtype=object), np.asarray(geoms_b, dtype=object)
    tree = shapely.STRtree(b)
    ia, ib = tree.query(a, predicate="intersects")
    inter = shapely.area(shapely.intersection(a[ia], b[ib]))
    union = shapely.area(a[ia]) + shapely.area(b[ib]) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    keep = iou >= max(min_iou, 1e-12)
    ia, ib, iou = ia[keep], ib[keep], iou[keep]
    kept = greedy_matches(ia, ib, np.lexsort((ib, ia, -iou)), len(a), len(b))
    return pd.DataFrame({"index_a": ia[kept], "index_b": ib[kept], "iou": iou[kept]}).astype(
        {"index_a": np.int64, "index_b": np.int64, "iou": float}
    )


def default_traits(columns: Sequence[str], trait_names: Sequence[str], dates: Sequence[str] = ()) -> list[str]:
    """chm_max (height), ndvi_mean and <band>_mean (with each date's suffix) that the table holds."""
    out = []
    for name in trait_names:
        prefix = f"{name}_{'max' if name == 'chm' else 'mean'}"
        out += [c for c in [prefix] + [f"{prefix}_{d}" for d in dates if d] if c in columns]
    return out


def compare_tables(
    table_a: pd.DataFrame,
    table_b: pd.DataFrame,
    matches: pd.DataFrame,
    traits: Sequence[str],
    label_a: str = "a",
    label_b: str = "b",
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-trait summary (KS, Pearson r, absolute differences) and the matched pairs table."""
    # scipy.stats on demand: ~1 s of imports that a run without compare.polygons never needs
    from scipy import stats as st

    ia, ib = matches["index_a"].to_numpy(), matches["index_b"].to_numpy()
    pairs = pd.DataFrame(
        {
            f"plant_id_{label_a}": table_a["plant_id"].to_numpy()[ia],
            f"plant_id_{label_b}": table_b["plant_id"].to_numpy()[ib],
            "iou": matches["iou"].to_numpy(),
        }
    )
    rows = []
    for t in traits:
        va, vb = table_a[t].to_numpy(float), table_b[t].to_numpy(float)
        pa, pb = va[ia], vb[ib]
        pairs[f"{t}_{label_a}"], pairs[f"{t}_{label_b}"] = pa, pb
        fa, fb = va[np.isfinite(va)], vb[np.isfinite(vb)]
        both = np.isfinite(pa) & np.isfinite(pb)
        row = {
            "trait": t,
            f"n_{label_a}": fa.size,
            f"n_{label_b}": fb.size,
            "n_matched": int(both.sum()),
            f"mean_{label_a}": fa.mean() if fa.size else np.nan,
            f"mean_{label_b}": fb.mean() if fb.size else np.nan,
        }
        if fa.size and fb.size:
            ks = st.ks_2samp(fa, fb)
            row.update(ks_statistic=float(ks.statistic), ks_pvalue=float(ks.pvalue))
        else:
            row.update(ks_statistic=np.nan, ks_pvalue=np.nan)
        d = np.abs(pa[both] - pb[both])
        if both.sum() >= 2 and np.ptp(pa[both]) > 0 and np.ptp(pb[both]) > 0:
            r = st.pearsonr(pa[both], pb[both])
            row.update(pearson_r=float(r.statistic), pearson_pvalue=float(r.pvalue))
        else:
            row.update(pearson_r=np.nan, pearson_pvalue=np.nan)
        row.update(
            mean_abs_diff=d.mean() if d.size else np.nan,
            median_abs_diff=np.median(d) if d.size else np.nan,
            max_abs_diff=d.max() if d.size else np.nan,
            mean_diff=float(np.mean(pb[both] - pa[both])) if d.size else np.nan,
        )
        rows.append(row)
    iou = matches["iou"].to_numpy()
    rows.append(
        {
            "trait": "iou",
            f"n_{label_a}": len(table_a),
            f"n_{label_b}": len(table_b),
            "n_matched": len(matches),
            "mean_iou": iou.mean() if iou.size else np.nan,
            "median_iou": np.median(iou) if iou.size else np.nan,
            f"unmatched_{label_a}": len(table_a) - len(matches),
            f"unmatched_{label_b}": len(table_b) - len(matches),
        }
    )
    return pd.DataFrame(rows), pairs


def comparison_figure(
    table_a,
    table_b,
    pairs: pd.DataFrame,
    summary: pd.DataFrame,
    traits: Sequence[str],
    path: Path,
    label_a: str = "a",
    label_b: str = "b",
) -> Path:
    """Distributions (histograms of both sets) and matched-pair scatter plots, one row per trait."""
    n = max(len(traits), 1)
    fig = figure(headless=True, figsize=(9, 3.2 * n), constrained_layout=True)
    axes = fig.subplots(n, 2, squeeze=False)
    for row, t in zip(axes, traits):
        va, vb = table_a[t].to_numpy(float), table_b[t].to_numpy(float)
        va, vb = va[np.isfinite(va)], vb[np.isfinite(vb)]
        both = np.concatenate([va, vb])
        s = summary.set_index("trait").loc[t]
        if both.size:
            lo, hi = both.min(), both.max()
            pad = 0.0 if hi - lo > 1e-6 * max(1.0, abs(hi)) else max(1e-3 * abs(hi), 1e-3)  # all equal
            bins = np.linspace(lo - pad, hi + pad, 31)
            row[0].hist(va, bins=bins, alpha=0.55, label=f"{label_a} (n={va.size})", color="tab:blue")
            row[0].hist(vb, bins=bins, alpha=0.55, label=f"{label_b} (n={vb.size})", color="tab:orange")
        row[0].locator_params(axis="x", nbins=6)
        row[0].set_xlabel(t)
        row[0].set_ylabel("plants")
        row[0].set_title(f"KS D = {s['ks_statistic']:.3f}, p = {s['ks_pvalue']:.3g}", fontsize=10)
        row[0].legend(fontsize=8)
        xa, xb = pairs[f"{t}_{label_a}"].to_numpy(float), pairs[f"{t}_{label_b}"].to_numpy(float)
        row[1].scatter(xa, xb, s=8, alpha=0.6)
        finite = np.concatenate([xa[np.isfinite(xa)], xb[np.isfinite(xb)]])
        if finite.size:
            lo, hi = finite.min(), finite.max()
            row[1].plot([lo, hi], [lo, hi], "k--", lw=1, label="1:1")
            row[1].legend(fontsize=8)
        row[1].set_xlabel(f"{t} ({label_a})")
        row[1].set_ylabel(f"{t} ({label_b})")
        row[1].set_title(
            f"r = {s['pearson_r']:.3f}, mean |diff| = {s['mean_abs_diff']:.3g}, n = {int(s['n_matched'])}", fontsize=10
        )
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return Path(path)


def run_comparison(cfg, polygons_a, table_a: pd.DataFrame, date_sets, out: Path) -> dict[str, Path]:
    """The ``compare`` part of module 9: statistics of the second set, matching, tables and figure."""

    c = cfg.compare
    polygons_b = read_polygons(c.polygons, c.id_column, c.layer, cfg.polygons_crs)
    if polygons_a.crs is not None and polygons_b.crs is not None and not polygons_b.crs.equals(polygons_a.crs):
        log.info("second plant set reprojected from %s to %s", polygons_b.crs.to_string(), polygons_a.crs.to_string())
        polygons_b = polygons_b.to_crs(polygons_a.crs)
    table_b, _ = extract_stats(
        polygons_b, date_sets, cfg.stats, cfg.percentiles, cfg.mode, nodata=cfg.nodata, layout="wide"
    )
    if cfg.layout == "long" and len(date_sets) > 1:  # compare on the wide form: one row per plant
        table_a, _ = extract_stats(
            polygons_a, date_sets, cfg.stats, cfg.percentiles, cfg.mode, nodata=cfg.nodata, layout="wide"
        )
    names = list(dict.fromkeys(layer.name for s in date_sets for layer in s.layers()))
    traits = list(c.traits) or default_traits(list(table_a.columns), names, [s.date for s in date_sets])
    missing = [t for t in traits if t not in table_a.columns]
    if missing:
        raise ConfigError(
            f"compare.traits {missing} are not columns of the statistics",
            fix=f"choose from {[x for x in table_a.columns if x not in ('plant_id', 'x', 'y')]}",
        )
    matches = match_by_iou(polygons_a.geometry.values, polygons_b.geometry.values, c.min_iou)
    summary, pairs = compare_tables(table_a, table_b, matches, traits, c.label_a, c.label_b)
    log.info(
        "comparison: %d of %d %s plants matched to %d %s plants (IoU >= %.2f)",
        len(matches),
        len(table_a),
        c.label_a,
        len(table_b),
        c.label_b,
        c.min_iou,
    )
    written = {
        "compare_summary": write_csv(summary, out / "compare_summary.csv"),
        "compare_matches": write_csv(pairs, out / "compare_matches.csv"),
        f"stats_{c.label_b}": write_csv(table_b, out / f"stats_{c.label_b}.csv"),
    }
    written["compare_figure"] = comparison_figure(
        table_a, table_b, pairs, summary, traits, out / "compare.png", c.label_a, c.label_b
    )
    return written
