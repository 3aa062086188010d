"""Benchmark of module 9's zonal statistics against rasterstats and exactextract.

20,000 plant boxes over an 8,000 x 8,000 float32 raster (a 80 m field at 1 cm), in one run:
``matchplant.spatial_stat_extractor.zonal.engine`` (pixel-centre rule) vs rasterstats, and (coverage-weighted) vs
exactextract.
Checks that the numbers agree, then prints the times and both ratios.

    python -m bench.bench_spatial_stat_extractor            # full size (a few minutes: rasterstats is slow)
    python -m bench.bench_spatial_stat_extractor --quick    # 2,000 x 2,000 raster, 1,250 boxes

The alternating, pinned comparison (docs/benchmarks.md's rows) is ``python -m bench --only zonal-coverage``
(and ``zonal-center``): see :func:`comparison`; ``--only zonal-coverage-process`` times the same work as whole
processes, module 9's command against a script calling exactextract (:func:`process_comparison`).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import exactextract
import geopandas as gpd
import numpy as np
import pandas as pd
import rasterio
import rasterstats
import shapely
import yaml
from affine import Affine

from bench.process import matchplant_command, run_process
from matchplant.core.formats.vectors import write_vector
from matchplant.spatial_stat_extractor.inputs import RasterFileSource
from matchplant.spatial_stat_extractor.zonal import zonal_stats

STATS = ["count", "min", "max", "mean", "median", "std", "sum"]
PERCENTILES = [95]


def make_field(folder: Path, size: int, n_plants: int, seed: int = 0):
    """A float32 GeoTIFF (tiled, with nodata holes) and a grid of jittered plant boxes over it."""
    rng = np.random.default_rng(seed)
    res = 0.01
    transform = Affine(res, 0, 500000.0, 0, -res, 4000000.0)
    path = folder / "raster.tif"
    profile = dict(
        driver="GTiff",
        width=size,
        height=size,
        count=1,
        dtype="float32",
        crs="EPSG:32615",
        transform=transform,
        nodata=-9999.0,
        tiled=True,
        blockxsize=512,
        blockysize=512,
    )
    with rasterio.open(path, "w", **profile) as dst:
        step = 1024
        for r in range(0, size, step):
            h = min(step, size - r)
            block = rng.gamma(2.0, 0.3, (h, size)).astype("float32")
            block[rng.random((h, size)) < 0.01] = -9999.0
            dst.write(block, 1, window=rasterio.windows.Window(0, r, size, h))
    k = int(np.ceil(np.sqrt(n_plants)))
    gx, gy = np.meshgrid(np.arange(k), np.arange(k))
    gx, gy = gx.ravel()[:n_plants], gy.ravel()[:n_plants]
    extent = size * res
    spacing = extent / k
    cx = 500000.0 + (gx + 0.5) * spacing + rng.normal(0, 0.05 * spacing, n_plants)
    cy = 4000000.0 - (gy + 0.5) * spacing - rng.normal(0, 0.05 * spacing, n_plants)
    half = rng.uniform(0.15, 0.35, n_plants) * spacing
    boxes = shapely.box(cx - half, cy - half, cx + half * rng.uniform(0.8, 1.2, n_plants), cy + half)
    return path, boxes


def timed(fn):
    """Call ``fn``; its result and the seconds it took."""
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def worst_difference(ours: dict, ref: dict) -> float:
    """Largest relative difference over every statistic (inf when they differ in which boxes have a value)."""
    worst = 0.0
    for key, a in ours.items():
        b = np.asarray(ref[key], dtype=float)
        both = np.isfinite(a) & np.isfinite(b)
        if not np.array_equal(np.isfinite(a), np.isfinite(b)):
            return float("inf")
        err = np.abs(a[both] - b[both]) / np.maximum(np.abs(b[both]), 1.0)
        worst = max(worst, float(err.max()) if err.size else 0.0)
    return worst


def compare(name: str, ours: dict, ref: dict, rtol: float) -> float:
    """The largest relative difference between two sets of statistics; stop with an error above ``rtol``."""
    worst = worst_difference(ours, ref)
    if worst > rtol:
        raise SystemExit(f"{name}: numbers differ (largest relative difference {worst:.2e})")
    return worst


EE_OPS = ["count", "min", "max", "mean", "median", "stdev", "sum", "quantile(q=0.95)"]
EE_MAP = {
    "count": "count",
    "min": "min",
    "max": "max",
    "mean": "mean",
    "median": "median",
    "std": "stdev",
    "sum": "sum",
    "p95": "quantile_95",
}
RS_STATS = "count min max mean median std sum percentile_95"
RS_MAP = {
    "count": "count",
    "min": "min",
    "max": "max",
    "mean": "mean",
    "median": "median",
    "std": "std",
    "sum": "sum",
    "p95": "percentile_95",
}


def run_ours(path: Path, boxes, mode: str) -> dict:
    """Our zonal statistics of the boxes on the raster, by column."""
    with rasterio.open(path) as ds:
        r = zonal_stats(boxes, RasterFileSource(ds), STATS, PERCENTILES, mode=mode)
    return {k: r.stats[k] for k in r.columns}


def run_exactextract(path: Path, gdf):
    """exactextract's statistics of the boxes on the raster, as a table."""
    return exactextract.exact_extract(str(path), gdf, EE_OPS, output="pandas", include_cols=["plant_id"])


def exactextract_numbers(ee) -> dict:
    """exactextract's numbers in our columns (NaN where a box covers no valid pixel, as ours)."""
    empty = ee["count"].to_numpy() == 0
    ref = {}
    for k, col in EE_MAP.items():
        v = ee[col].to_numpy(float).copy()
        if k != "count":
            v[empty] = np.nan
        ref[k] = v
    return ref


def run_rasterstats(path: Path, boxes) -> dict:
    """rasterstats' statistics of the boxes on the raster, in our columns."""
    rs = rasterstats.zonal_stats(boxes, str(path), stats=RS_STATS)
    ref = {k: np.array([np.nan if r[c] is None else r[c] for r in rs], float) for k, c in RS_MAP.items()}
    ref["count"] = np.nan_to_num(ref["count"])
    return ref


PEER_SCRIPT = """import sys

import geopandas as gpd
from exactextract import exact_extract

raster, plants, out = sys.argv[1:]
ops = {ops!r}
exact_extract(raster, gpd.read_file(plants), ops, include_cols=["plant_id"], output="pandas").to_csv(out, index=False)
"""


def process_comparison(work: Path, quick: bool):
    """``zonal-coverage-process``: module 9's command (box statistics only, coverage-weighted, the statistics
    table written) against a user's script calling exactextract's Python ``exact_extract`` with the GeoTIFF's
    path (read through rasterio where GDAL's own Python bindings are not installed, as here) and the plants
    read by geopandas (exactextract opens a vector path only through osgeo or fiona), writing the same table as
    CSV; whole processes, imports included."""
    from bench.harness import Comparison

    size, n = (2000, 1250) if quick else (8000, 20000)
    path, boxes = make_field(work, size, n)
    plants = work / "plants.gpkg"
    write_vector(gpd.GeoDataFrame({"plant_id": np.arange(n)}, geometry=boxes, crs="EPSG:32615"), plants)
    ours_out, peer_out = work / "ours", work / "exactextract.csv"
    cfg = work / "module9.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "polygons": str(plants),
                "rasters": {"chm": str(path)},
                "mode": "coverage",
                "stats": STATS,
                "percentiles": PERCENTILES,
                "canopy": {"enabled": False},
                "vector_formats": [],
                "workers": 1,
                "output_dir": str(ours_out),
            }
        )
    )
    script = work / "exactextract_stats.py"
    script.write_text(PEER_SCRIPT.format(ops=EE_OPS))

    def check() -> dict:
        ours = pd.read_csv(ours_out / "stats.csv").sort_values("plant_id")
        ee = pd.read_csv(peer_out).sort_values("plant_id")
        ref = exactextract_numbers(ee)
        worst = worst_difference({k: ours[f"chm_{k}"].to_numpy(float) for k in ref}, ref)
        return {"largest_relative_difference": worst, "equal_within_1e-6": worst <= 1e-6}

    return Comparison(
        "zonal-coverage-process",
        f"{n} boxes (GeoPackage) over a {size} x {size} float32 GeoTIFF; "
        f"{', '.join(STATS)}, p95 to CSV, whole processes",
        "matchplant spatial_stat_extractor (coverage)",
        "python + exactextract.exact_extract",
        lambda: run_process(matchplant_command("spatial_stat_extractor", cfg)),
        lambda: run_process([sys.executable, str(script), str(path), str(plants), str(peer_out)]),
        check=check,
        items=n,
        unit="boxes",
        notes={"peer_input": "raster path (rasterio), plants by geopandas.read_file"},
    )


def comparison(name: str, work: Path, quick: bool, device: str):
    """For ``python -m bench``: ``zonal-center`` (vs rasterstats) or ``zonal-coverage`` (vs exactextract)
    on 20,000 boxes over an 8000 x 8000 raster (quick: 1,250 over 2000 x 2000)."""
    from bench.harness import Comparison

    if name == "zonal-coverage-process":
        return process_comparison(work, quick)
    size, n = (2000, 1250) if quick else (8000, 20000)
    path, boxes = make_field(work, size, n)
    gdf = gpd.GeoDataFrame({"plant_id": np.arange(n)}, geometry=boxes, crs="EPSG:32615")
    last: dict[str, dict] = {}

    def keep(key: str, fn: Callable[[], dict]) -> Callable[[], None]:
        return lambda: last.__setitem__(key, fn())

    mode = "center" if name == "zonal-center" else "coverage"
    if mode == "center":
        peer, label = keep("peer", lambda: run_rasterstats(path, boxes)), "rasterstats"
    else:
        peer, label = keep("peer", lambda: exactextract_numbers(run_exactextract(path, gdf))), "exactextract"

    def check() -> dict:
        worst = worst_difference(last["ours"], last["peer"])
        return {"largest_relative_difference": worst, "equal_within_1e-6": worst <= 1e-6}

    return Comparison(
        name,
        f"{n} boxes over a {size} x {size} float32 GeoTIFF; {', '.join(STATS)}, p95",
        f"matchplant ({mode})",
        label,
        keep("ours", lambda: run_ours(path, boxes, mode)),
        peer,
        check=check,
        items=n,
        unit="boxes",
    )


def main(argv=None) -> int:
    """Parse the options, time our zonal statistics against rasterstats and exactextract, check they agree, print."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small run (2,000 px raster, 1,250 boxes)")
    ap.add_argument("--size", type=int, help="raster side in pixels (default 8000, quick 2000)")
    ap.add_argument("--plants", type=int, help="number of boxes (default 20000, quick 1250)")
    ap.add_argument("--skip-rasterstats", action="store_true", help="leave out the slow rasterstats run")
    args = ap.parse_args(argv)
    size = args.size or (2000 if args.quick else 8000)
    n = args.plants or (1250 if args.quick else 20000)
    os.environ.setdefault("MATCHPLANT_QUIET", "1")

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"making a {size} x {size} raster and {n} boxes ...", flush=True)
        path, boxes = make_field(tmp, size, n)
        gdf = gpd.GeoDataFrame({"plant_id": np.arange(n)}, geometry=boxes, crs="EPSG:32615")
        px = np.median(gdf.area.to_numpy()) / 0.01**2
        print(f"median box: {px:.0f} pixels", flush=True)

        def ours(mode):
            with rasterio.open(path) as ds:
                src = RasterFileSource(ds)
                r = zonal_stats(boxes, src, STATS, PERCENTILES, mode=mode)
            return {k: r.stats[k] for k in r.columns}

        rows = []
        ours_c, t_oc = timed(lambda: ours("center"))
        print(f"matchplant (pixel centre):   {t_oc:8.2f} s", flush=True)
        ours_w, t_ow = timed(lambda: ours("coverage"))
        print(f"matchplant (coverage):       {t_ow:8.2f} s", flush=True)

        ee, t_ee = timed(lambda: run_exactextract(path, gdf))
        print(f"exactextract (coverage):     {t_ee:8.2f} s", flush=True)
        err_ee = compare("exactextract", ours_w, exactextract_numbers(ee), 1e-4)
        print(f"  same numbers as exactextract (largest relative difference {err_ee:.1e})")
        rows.append(("exactextract", t_ee, t_ow))

        if not args.skip_rasterstats:
            rs_stats = "count min max mean median std sum percentile_95"
            rs, t_rs = timed(lambda: rasterstats.zonal_stats(boxes, str(path), stats=rs_stats))
            print(f"rasterstats (pixel centre):  {t_rs:8.2f} s", flush=True)
            rs_map = {
                "count": "count",
                "min": "min",
                "max": "max",
                "mean": "mean",
                "median": "median",
                "std": "std",
                "sum": "sum",
                "p95": "percentile_95",
            }
            ref = {k: np.array([np.nan if r[c] is None else r[c] for r in rs], float) for k, c in rs_map.items()}
            ref["count"] = np.nan_to_num(ref["count"])
            err_rs = compare("rasterstats", ours_c, ref, 1e-4)
            print(f"  same numbers as rasterstats (largest relative difference {err_rs:.1e})")
            rows.append(("rasterstats", t_rs, t_oc))

        print(f"\n{n} boxes over a {size} x {size} raster; statistics: {', '.join(STATS)}, p95")
        for name, t_ref, t_ours in rows:
            print(f"  vs {name:<13} {t_ref:8.2f} s / {t_ours:6.2f} s = {t_ref / t_ours:6.1f}x faster")
    return 0


if __name__ == "__main__":
    sys.exit(main())
