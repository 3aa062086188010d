"""Module 9 at survey scale (issue 30): a 30,000 x 30,000 float32 CHM (tiled, deflate, 0.3 cm pixels: about
one hectare) and 100,000 plant boxes, made with plain numpy and rasterio (no simfield), through module 9's
command as a user runs it: box statistics, outlines, canopy statistics and plots.

    python bench/bench_spatial_stat_extractor_survey.py --scale 0.1       # 3000², 1000 plants: seconds
    python bench/bench_spatial_stat_extractor_survey.py --scale 0.3       # 9000², 9000 plants: minutes
    python bench/bench_spatial_stat_extractor_survey.py  # the full survey (an hour and more, ~4 GB disk)
    taskset -c 1 python bench/bench_spatial_stat_extractor_survey.py --workers 1 --max-memory 3GB
    # 60,000 x 30,000 px: 2 ha
    python bench/bench_spatial_stat_extractor_survey.py --length 2 --max-memory 4GB --no-crop

Each run is a whole process (``python -m matchplant.cli spatial_stat_extractor``): its wall time, CPU time and
peak memory (``os.wait4``: the process and its worker processes) and, from its ``stats_report.json``, the
wall, CPU and peak memory after each stage. Runs: box statistics only (``canopy.enabled: false``), then the
whole module (canopy + plots). Then the crop check: module 9 on a crop of the raster with the plants inside
it gives the same numbers plant by plant as the whole field (``--no-crop`` skips it). ``--python`` and
``--pythonpath`` run another checkout (the code before issue 30) on the same field.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import rasterio
import yaml
from affine import Affine
from rasterio.windows import Window

RES = 0.003  # m per pixel
ORIGIN = (500000.0, 4500000.0)
CRS = "EPSG:32615"
FULL_SIDE, FULL_PLANTS = 30000, 100000
STRIP = 512


def make_field(root: Path, scale: float, seed: int = 0, length: float = 1.0) -> dict:
    """The CHM (written strip by strip, never whole in memory) and the plant boxes; cached in ``root``. The
    field is ``scale`` x 30,000 px wide and ``length`` times as long (rows of the raster), plants alike."""
    side = max(256, round(FULL_SIDE * scale))
    rows = max(256, round(side * length))
    per_row = max(2, round(np.sqrt(FULL_PLANTS) * side / FULL_SIDE))
    per_col = max(2, round(per_row * rows / side))
    meta_path = root / "field.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if meta["side"] == side and meta.get("rows", side) == rows and meta["seed"] == seed:
            return meta
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    spacing = side / per_row
    gy, gx = np.mgrid[0:per_col, 0:per_row]
    # plants in crop rows (y) with some jitter; domes whose radius follows their height
    cx = (gx.ravel() + 0.5) * spacing + rng.normal(0, 0.06 * spacing, gx.size)
    cy = (gy.ravel() + 0.5) * spacing + rng.normal(0, 0.06 * spacing, gx.size)
    h = rng.uniform(0.15, 0.9, gx.size)
    r = spacing * (0.28 + 0.14 * h)  # a few neighbours touch
    order = np.argsort(cy)
    cx, cy, h, r = cx[order], cy[order], h[order], r[order]
    t = Affine(RES, 0, ORIGIN[0], 0, -RES, ORIGIN[1])
    path = root / "chm.tif"
    profile = {
        "driver": "GTiff",
        "width": side,
        "height": rows,
        "count": 1,
        "dtype": "float32",
        "crs": CRS,
        "transform": t,
        "tiled": True,
        "blockxsize": 512,
        "blockysize": 512,
        "compress": "deflate",
        "nodata": -9999.0,
        "BIGTIFF": "IF_SAFER",
    }
    tmp = path.with_suffix(".partial.tif")
    with rasterio.open(tmp, "w", **profile) as ds:
        for r0 in range(0, rows, STRIP):
            r1 = min(rows, r0 + STRIP)
            a = rng.normal(0.0, 0.004, (r1 - r0, side)).astype(np.float32)  # soil noise
            sel = np.flatnonzero((cy + r > r0) & (cy - r < r1))
            for k in sel:
                y0, y1 = int(max(r0, np.floor(cy[k] - r[k]))), int(min(r1, np.ceil(cy[k] + r[k])))
                x0, x1 = int(max(0, np.floor(cx[k] - r[k]))), int(min(side, np.ceil(cx[k] + r[k])))
                yy, xx = np.mgrid[y0:y1, x0:x1]
                d2 = ((xx + 0.5 - cx[k]) ** 2 + (yy + 0.5 - cy[k]) ** 2) / r[k] ** 2
                dome = (h[k] * (1 - d2)).astype(np.float32)
                win = a[y0 - r0 : y1 - r0, x0:x1]
                np.maximum(win, dome, out=win)
            ds.write(a, 1, window=Window(0, r0, side, r1 - r0))
    os.replace(tmp, path)
    # boxes as a detector gives them: the canopy's extent with a few percent of error on each side
    half = r[:, None] * (1 + rng.normal(0, 0.04, (len(r), 4)))
    xmin, xmax = cx - half[:, 0], cx + half[:, 1]
    ymin, ymax = cy - half[:, 2], cy + half[:, 3]  # rows
    boxes = pd.DataFrame(
        {
            "plant_id": np.arange(1, len(cx) + 1),
            "xmin": ORIGIN[0] + xmin * RES,
            "xmax": ORIGIN[0] + xmax * RES,
            "ymin": ORIGIN[1] - ymax * RES,
            "ymax": ORIGIN[1] - ymin * RES,
            "crs": CRS,
        }
    )
    # 1% second boxes of one plant (a detector's duplicates), some across strip edges
    dup = rng.choice(len(cx), max(1, len(cx) // 100), replace=False)
    extra = boxes.iloc[dup].copy()
    extra[["ymin", "ymax"]] += rng.normal(0, 0.2, (len(dup), 1)) * (r[dup, None] * RES)
    extra["plant_id"] = np.arange(len(cx) + 1, len(cx) + 1 + len(dup))
    boxes = pd.concat([boxes, extra], ignore_index=True)
    boxes.to_csv(root / "plants.csv", index=False)
    meta = {
        "side": side,
        "rows": rows,
        "seed": seed,
        "plants": len(boxes),
        "spacing_px": spacing,
        "per_row": per_row,
        "chm": str(path),
        "plants_csv": str(root / "plants.csv"),
        "chm_mb": round(path.stat().st_size / 1e6, 1),
    }
    meta_path.write_text(json.dumps(meta, indent=1))
    return meta


def config(meta: dict, out: Path, chm: str, plants: str, canopy: bool, plots: bool, args) -> Path:
    """Write module 9's YAML config for one survey run (CHM, plants, canopy, plots); its path."""
    side, rows, per_row = meta["side"], meta.get("rows", meta["side"]), meta["per_row"]
    cfg = {
        "polygons": plants,
        "rasters": {"chm": chm},
        "output_dir": str(out),
        "canopy": {"enabled": canopy},
        "vector_formats": ["gpkg"],
    }
    if not args.before:
        cfg.update(max_memory=args.max_memory, workers=args.workers)
    if plots:
        x0, y0 = ORIGIN[0], ORIGIN[1] - rows * RES
        x1, y1 = ORIGIN[0] + side * RES, ORIGIN[1]
        columns = max(1, round(50 * side / FULL_SIDE))
        ranges = max(1, round(197 * rows / FULL_SIDE))
        cfg["plots"] = {
            "corners": [[x0, y0], [x0, y1], [x1, y1], [x1, y0]],
            "columns": columns,
            "ranges": ranges,
            "rows_per_plot": max(1, per_row // columns),
            "plant_spacing": meta["spacing_px"] * RES,
        }
    path = out.parent / f"{out.name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def run_module(cfg_path: Path, args) -> dict:
    """Module 9's command as a whole process: wall, CPU and peak memory (the process and its workers)."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", MPLBACKEND="Agg")
    if args.pythonpath:
        env["PYTHONPATH"] = args.pythonpath
    cmd = [args.python, "-m", "matchplant.cli", "spatial_stat_extractor", "--config", str(cfg_path)]
    t0 = time.perf_counter()
    # cwd: the run's own folder, so that -m finds matchplant on PYTHONPATH, not in the current folder
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=cfg_path.parent)
    out = proc.stdout.read()
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.decode()[-3000:]}")
    report = json.loads((Path(yaml.safe_load(cfg_path.read_text())["output_dir"]) / "stats_report.json").read_text())
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
        "peak_mb": round(ru.ru_maxrss / (1024**2 if sys.platform == "darwin" else 1024), 1),
        "stages": report.get("memory", {}).get("stages", {}),
    }


def crop_check(meta: dict, work: Path, full_out: Path, args) -> dict:
    """Module 9 on a crop of the field (a quarter of each side, in the middle) with the plants well inside it:
    the same statistics, plant by plant, as in the whole field's run."""
    side = meta["side"]
    c0, r0 = side * 3 // 8, meta.get("rows", side) * 3 // 8
    size = max(256, side // 4)
    crop = work / "crop_chm.tif"
    with rasterio.open(meta["chm"]) as src:
        win = Window(c0, r0, size, size)
        profile = src.profile | {"width": size, "height": size, "transform": src.window_transform(win)}
        with rasterio.open(crop, "w", **profile) as dst:
            dst.write(src.read(1, window=win), 1)
    plants = pd.read_csv(meta["plants_csv"])
    m = 1.5 * meta["spacing_px"] * RES  # a plant's neighbours all inside the crop too
    x0, y1 = ORIGIN[0] + c0 * RES, ORIGIN[1] - r0 * RES
    x1, y0 = x0 + size * RES, y1 - size * RES
    inside = plants[(plants.xmin > x0 + m) & (plants.xmax < x1 - m) & (plants.ymin > y0 + m) & (plants.ymax < y1 - m)]
    if len(inside) == 0:
        return {"plants": 0, "skipped": "no plant well inside the crop (raise --scale)"}
    inside.to_csv(work / "crop_plants.csv", index=False)
    out = work / "crop_out"
    cfg_path = config(meta, out, str(crop), str(work / "crop_plants.csv"), True, False, args)
    # the whole field's canopy thresholds: the crop holds canopies of plants cut by its edge and left out of its
    # list, which the automatic ground-noise sample takes for bare ground (SD 0.3 m: every plant 'low'); this
    # check is about windows and strips, not about the noise estimate
    chosen = json.loads((full_out / "stats_report.json").read_text())["canopy"]["dates"][0]
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg["canopy"].update(min_height=chosen["min_height"], min_top=chosen["min_top"])
    cfg_path.write_text(yaml.safe_dump(cfg))
    run_module(cfg_path, args)
    a = pd.read_csv(full_out / "stats.csv").set_index("plant_id").loc[inside.plant_id]
    b = pd.read_csv(out / "stats.csv").set_index("plant_id").loc[inside.plant_id]
    num = [c for c in b.columns if c in a.columns and pd.api.types.is_numeric_dtype(b[c])]
    diff = (a[num].astype(float) - b[num].astype(float)).abs()
    tol = 1e-6 * (1 + a[num].astype(float).abs())
    bad = ~((diff <= tol) | (a[num].isna() & b[num].isna()))
    flags_same = float(
        (a["outline_flag"].astype(object).fillna("") == b["outline_flag"].astype(object).fillna("")).mean()
    )
    return {
        "plants": len(inside),
        "columns": len(num),
        "plants_differing": int(bad.any(axis=1).sum()),
        "max_abs_diff": float(np.nanmax(diff.to_numpy(dtype=float, na_value=np.nan), initial=0.0)),
        "flags_same": flags_same,
        "differing_columns": sorted(c for c in num if bad[c].any()),
    }


def main(argv=None) -> int:
    """Parse the options, build the survey-scale CHM and boxes, run module 9 on them and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=float, default=1.0, help="side as a share of 30,000 px (plants: its square)")
    ap.add_argument(
        "--length",
        type=float,
        default=1.0,
        help="the field's rows as a multiple of its width (2: the 60,000 x 30,000 px, 2 ha field)",
    )
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "matchplant_bench_survey")
    ap.add_argument("--max-memory", default="3GB")
    ap.add_argument("--workers", type=int, default=1, help="module 9's workers (1: one core; 0: one per core)")
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--pythonpath", default=os.environ.get("PYTHONPATH", ""))
    ap.add_argument("--before", action="store_true", help="a checkout without max_memory and workers (before issue 30)")
    ap.add_argument("--no-crop", action="store_true")
    ap.add_argument("--only-full", action="store_true", help="skip the box-statistics-only run")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args(argv)
    field_dir = args.work / (f"scale_{args.scale:g}" + (f"_x{args.length:g}" if args.length != 1 else ""))
    work = field_dir / ("before" if args.before else "after")
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    meta = make_field(field_dir, args.scale, length=args.length)
    print(
        f"field: {meta.get('rows', meta['side'])} x {meta['side']} px float32 CHM ({meta['chm_mb']} MB tiled "
        f"deflate), {meta['plants']} plants "
        f"(made in {time.perf_counter() - t0:.0f} s or cached) in {work}",
        flush=True,
    )
    res = {"field": meta, "max_memory": args.max_memory, "workers": args.workers}
    if not args.only_full:
        res["box_only"] = run_module(
            config(meta, work / "box_out", meta["chm"], meta["plants_csv"], False, False, args), args
        )
        print("box statistics only:", json.dumps(res["box_only"]), flush=True)
    res["full"] = run_module(config(meta, work / "full_out", meta["chm"], meta["plants_csv"], True, True, args), args)
    print("box + outlines + canopy + plots:", json.dumps(res["full"]), flush=True)
    st = res["full"]["stages"]
    if "box statistics" in st and "outlines and canopy statistics" in st:
        res["outlines_over_box"] = round(
            st["outlines and canopy statistics"]["wall_s"] / st["box statistics"]["wall_s"], 2
        )
        print(f"outlines + canopy statistics / box statistics (wall): {res['outlines_over_box']}x", flush=True)
    if not args.no_crop:
        res["crop"] = crop_check(meta, work, work / "full_out", args)
        print("crop check:", json.dumps(res["crop"]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
