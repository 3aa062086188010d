"""Benchmark of module 9's traits (issue 19): outlines, canopy statistics, growth and plots against the truth,
and the speed of canopy statistics against box statistics.

    python bench/bench_spatial_stat_extractor_traits.py  # the small field (vigour, second date), generated once
    python bench/bench_spatial_stat_extractor_traits.py --quick        # the tiny field
    # an existing field generated with vigour and second_date
    python bench/bench_spatial_stat_extractor_traits.py --field DIR
    # + 20,000 plants on an 8000 x 8000 raster (--quick: 2000², 1250)
    python bench/bench_spatial_stat_extractor_traits.py --speed

The plants are the field's true image boxes projected by module 8 (as bench_plant_projection.py does), so
the numbers measure module 9 on realistic boxes, not the detector. Prints the acceptance figures of
issue 19: canopy NDVI r (and the box mean's), height r, outline IoU median, stand count exact share,
gaps found / false, growth centre errors, and the speed ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import geopandas as gpd  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import rasterio  # noqa: E402
import shapely  # noqa: E402
from affine import Affine  # noqa: E402
from rasterio.windows import Window  # noqa: E402

from matchplant.core.formats.coco import read_dataset  # noqa: E402
from matchplant.core.formats.odm import ODMProject  # noqa: E402
from matchplant.core.formats.vectors import write_vector  # noqa: E402
from matchplant.core.runtime.config import load_config  # noqa: E402
from matchplant.plant_projection.merge import merge_views  # noqa: E402
from matchplant.plant_projection.views import project_predictions  # noqa: E402
from matchplant.simfield.layout import FieldPaths  # noqa: E402
from matchplant.simfield.scoring import growth_scores, outline_ious, plot_scores, trait_scores  # noqa: E402
from matchplant.spatial_stat_extractor.canopy import (  # noqa: E402
    SegmentSettings,
    canopy_stats,  # noqa: E402
    segment,
)
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig  # noqa: E402
from matchplant.spatial_stat_extractor.inputs import RasterFileSource  # noqa: E402
from matchplant.spatial_stat_extractor.run import extract_and_write  # noqa: E402
from matchplant.spatial_stat_extractor.zonal import zonal_stats  # noqa: E402


def field(preset: str, given: str | None) -> FieldPaths:
    """The given field, else the preset's field with vigour and a second date (generated once in the temp folder)."""
    if given:
        return FieldPaths(Path(given))
    root = Path(tempfile.gettempdir()) / "matchplant_bench_fields" / f"{preset}_traits_seed0"
    if not (root / "date2" / "truth" / "plants.csv").is_file():
        from matchplant.simfield import generate_field

        generate_field(preset=preset, seed=0, out=root, vigour=True, second_date=True)
    return FieldPaths(root)


def projected_plants(f: FieldPaths, out: Path) -> Path:
    """Module 8 on the true image boxes: plants.gpkg in ``out``."""
    ds = read_dataset(f.boxes_undistorted, validate=False)
    preds = {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }
    views, _ = project_predictions(ODMProject(f.root), preds)
    plants = merge_views(views)
    crs = json.loads(f.field_json.read_text())["crs"]
    geoms = shapely.box(plants["xmin"], plants["ymin"], plants["xmax"], plants["ymax"])
    gdf = gpd.GeoDataFrame({"plant_id": np.arange(1, len(plants) + 1)}, geometry=geoms, crs=crs)
    return write_vector(gdf, out / "plants.gpkg")


def accuracy(f: FieldPaths, out: Path) -> dict:
    """Run module 9 on the projected plants and score its traits, outlines, plots and growth against the truth."""
    plants = projected_plants(f, out)
    grid = json.loads(f.plots_json.read_text())
    sets = [
        f"polygons={plants}",
        f"output_dir={out / 'stats'}",
        "rasters.date=d1",
        f"rasters.dsm={f.dsm}",
        f"rasters.dtm={f.dtm}",
        f"rasters.multispectral={f.multispectral}",
        f"more_dates=[{{date: d2, dsm: {f.later.dsm}, dtm: {f.later.dtm}}}]",
        f"plots.corners={json.dumps(grid['corners'])}",
        f"plots.columns={grid['columns']}",
        f"plots.ranges={grid['ranges']}",
        f"plots.plant_spacing={grid['plant_spacing']}",
        f"plots.rows_per_plot={grid['rows_per_plot']}",
        f"plots.field_book={f.field_book}",
    ]
    cfg = load_config(SpatialStatExtractorConfig, None, sets)
    t0 = time.perf_counter()
    polygons, table, report, written = extract_and_write(cfg)
    elapsed = time.perf_counter() - t0
    d1 = table.rename(columns=lambda c: c[:-3] if c.endswith("_d1") else c)
    res = {"module9_s": round(elapsed, 2), "traits": trait_scores(d1, f)}
    outl = gpd.read_file(written["outlines_gpkg"])
    first = outl[outl["date"] == "d1"].set_index("plant_id").reindex(table["plant_id"])
    iou = outline_ious(first.geometry.values, d1, f)
    res["outlines"] = {
        "iou_median": float(np.nanmedian(iou)),
        "iou_p10": float(np.nanpercentile(iou, 10)),
        "kept_box": int((first["outline_from"] == "box").sum()),
    }
    res["plots"] = plot_scores(
        pd.read_csv(written["plots_csv"]), pd.read_csv(written["plot_gaps_csv"]), f, grid["plant_spacing"]
    )
    res["growth"] = growth_scores(d1, f, ("top_x_d2", "top_y_d2"))
    return res


def speed(quick: bool, folder: Path) -> dict:
    """Canopy statistics vs box statistics (mean, max, p95) on a synthetic CHM GeoTIFF (paraboloid plants on
    a grid, one per box), both read window by window from the file."""
    size, n = (2000, 1250) if quick else (8000, 20000)
    rng = np.random.default_rng(0)
    res = 0.01
    t = Affine(res, 0, 500000.0, 0, -res, 4000000.0)
    k = int(np.ceil(np.sqrt(n)))
    sp = size / k  # pixels between plant centres
    h = rng.uniform(0.2, 0.6, k * k)
    path = folder / "chm.tif"
    profile = dict(
        driver="GTiff",
        width=size,
        height=size,
        count=1,
        dtype="float32",
        crs="EPSG:32615",
        transform=t,
        nodata=-9999.0,
        tiled=True,
        blockxsize=512,
        blockysize=512,
    )
    with rasterio.open(path, "w", **profile) as dst:
        for r0 in range(0, size, 512):
            rr, cc = np.mgrid[r0 : min(r0 + 512, size), 0:size] + 0.5
            gy, gx = np.clip((rr / sp).astype(int), 0, k - 1), np.clip((cc / sp).astype(int), 0, k - 1)
            rho = np.hypot(cc - (gx + 0.5) * sp, rr - (gy + 0.5) * sp) / (0.35 * sp)
            dst.write(
                np.where(rho < 1, h[gy * k + gx] * (1 - rho**2), 0.0).astype("float32"),
                1,
                window=Window(0, r0, size, rr.shape[0]),
            )
    gy, gx = np.divmod(np.arange(n), k)
    x, y = t @ ((gx + 0.5) * sp, (gy + 0.5) * sp)
    half = 0.4 * sp * res
    boxes = shapely.box(x - half, y - half, x + half, y + half)
    with rasterio.open(path) as ds:
        src = RasterFileSource(ds)
        t0 = time.perf_counter()
        zonal_stats(boxes, src, ["mean", "max"], [95])
        t_box = time.perf_counter() - t0
        t0 = time.perf_counter()
        o = segment(boxes, src, SegmentSettings())
        t_seg = time.perf_counter() - t0
        t0 = time.perf_counter()
        canopy_stats(o, src, ["mean", "max"], [95])
        t_can = time.perf_counter() - t0
    return {
        "raster": f"{size}x{size}",
        "plants": n,
        "outlined": int((o.flag == "").sum()),
        "box_stats_s": round(t_box, 2),
        "outlines_s": round(t_seg, 2),
        "canopy_stats_s": round(t_can, 2),
        "canopy_over_box": round(t_can / t_box, 2),
        "outlines_and_canopy_over_box": round((t_seg + t_can) / t_box, 2),
    }


def main() -> None:
    """Parse the options, score module 9's traits and time canopy against box statistics."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the tiny field (and a small speed test)")
    ap.add_argument("--field", help="an existing field generated with vigour and second_date")
    ap.add_argument("--speed", action="store_true", help="also time canopy vs box statistics")
    ap.add_argument("--no-accuracy", action="store_true", help="only the speed test")
    args = ap.parse_args()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_accuracy:
            f = field("tiny" if args.quick else "small", args.field)
            out["field"] = str(f.root)
            out.update(accuracy(f, Path(tmp)))
        if args.speed or args.no_accuracy:
            out["speed"] = speed(args.quick, Path(tmp))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
