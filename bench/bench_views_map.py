"""The field map at 20,000 and 100,000 plants (issue 46): file size, load time, a click's popup, a pan's redraw.

    python -m bench.bench_views_map                     # 20,000 and 100,000 plants, 3 loads each
    python -m bench.bench_views_map --plants 20000 --runs 1

Plants are 12-sided polygons in rows with three random traits, plots of 40 plants with two statistics, no
orthophoto. Each load is a fresh headless Chromium (Debian's ``chromium``, driven by Playwright), the file opened
from disk; "load" is from navigation to the plants drawn; "click" from a synthesised click on a plant to its
popup; "redraw" the canvas's redraw after a pan (the plants in view are all drawn again).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import geopandas as gpd
import numpy as np
import shapely

from matchplant.views.fieldmap import write_field_map

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]  # fmt: skip


def field(plants: int) -> tuple[gpd.GeoDataFrame, gpd.GeoDataFrame]:
    """``plants`` plants in rows 0.76 m apart, 0.2 m apart in a row; plots of 40 plants (4 rows of 10)."""
    rows = int(np.ceil(np.sqrt(plants * 0.2 / 0.76)))
    k = np.arange(plants)
    x, y = 500000 + (k % rows) * 0.76, 4500000 + (k // rows) * 0.2
    rng = np.random.default_rng(0)
    polys = shapely.buffer(shapely.points(x, y), 0.08, quad_segs=3)
    gdf = gpd.GeoDataFrame(
        {"plant_id": k + 1, "height": rng.uniform(0.1, 0.6, plants), "ndvi": rng.uniform(0.3, 0.9, plants),
         "area_m2": rng.uniform(0.01, 0.05, plants)}, geometry=polys, crs="EPSG:32614")  # fmt: skip
    px, py = np.meshgrid(np.arange(0, rows, 4), np.arange(0, plants // rows + 1, 10))
    boxes = shapely.box(500000 + px.ravel() * 0.76 - 0.38, 4500000 + py.ravel() * 0.2 - 0.1,
                        500000 + (px.ravel() + 4) * 0.76 - 0.38, 4500000 + (py.ravel() + 10) * 0.2 - 0.1)  # fmt: skip
    plots = gpd.GeoDataFrame(
        {"plot_id": np.arange(1, len(boxes) + 1), "stand_count": rng.integers(30, 41, len(boxes)),
         "height_mean": rng.uniform(0.2, 0.5, len(boxes))}, geometry=boxes, crs="EPSG:32614")  # fmt: skip
    return gdf, plots


def measure(html: Path, plant: shapely.Point, origin) -> dict:
    """One fresh browser: load, click, pan."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=shutil.which("chromium"), args=ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        t = time.perf_counter()
        page.goto(html.as_uri())
        page.wait_for_function("window.fieldmap && fieldmap.ready && fieldmap.redraws > 0", timeout=300_000)
        load = time.perf_counter() - t
        page.evaluate(
            "([lat, lng]) => { fieldmap.map.setView([lat, lng], 6); }", [plant.y - origin[1], plant.x - origin[0]]
        )
        page.wait_for_timeout(200)
        xy = page.evaluate(
            "([lat, lng]) => { const p = fieldmap.map.latLngToContainerPoint([lat, lng]);"
            " const r = fieldmap.map.getContainer().getBoundingClientRect(); return [p.x + r.left, p.y + r.top]; }",
            [plant.y - origin[1], plant.x - origin[0]],
        )
        t = time.perf_counter()
        page.mouse.click(*xy)
        page.wait_for_selector(".plant-popup")
        click = time.perf_counter() - t
        page.evaluate("() => { fieldmap.map.closePopup(); fieldmap.map.setZoom(2); }")
        redraw = page.evaluate(
            "() => { const n = fieldmap.redraws, t = performance.now(); fieldmap.map.panBy([200, 0], {animate: false});"
            " return [performance.now() - t, fieldmap.redraws - n, fieldmap.drawn]; }"
        )
        browser.close()
    return {"load": load, "click": click, "redraw_ms": redraw[0], "drawn": redraw[2]}


def main() -> None:
    """Write each map, then load it ``--runs`` times in a fresh browser."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plants", type=int, nargs="+", default=[20000, 100000])
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_map_"))
    try:
        for n in args.plants:
            plants, plots = field(n)
            t = time.perf_counter()
            html = write_field_map(work / f"map_{n}.html", plants, plots=plots)
            written = time.perf_counter() - t
            origin = np.floor(plants.total_bounds[:2])
            runs = [measure(html, plants.geometry.iloc[n // 2].centroid, origin) for _ in range(args.runs)]
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            spread = f"{min(r['load'] for r in runs):.2f}-{max(r['load'] for r in runs):.2f}"
            print(f"{n} plants: file {html.stat().st_size / 1e6:.1f} MB written in {written:.1f} s;"
                  f" load {med['load']:.2f} s ({spread}), click to popup {1000 * med['click']:.0f} ms,"
                  f" pan redraw {med['redraw_ms']:.0f} ms"
                  f" ({med['drawn']:.0f} plants in view)")  # fmt: skip
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
