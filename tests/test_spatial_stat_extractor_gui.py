"""Module 9's window: headless (Agg, synthesised events) and in a real window under Xvfb."""

from __future__ import annotations

import textwrap

import numpy as np
import pandas as pd
import pytest
import shapely
from affine import Affine
from conftest import run_in_xvfb, xvfb_available
from gui_events import click

CRS = "EPSG:32615"


@pytest.fixture()
def small_field(tmp_path):
    """A 1600 x 2000 CHM with 40 plants of known height (a cone each), and their boxes."""
    import geopandas as gpd
    import rasterio

    t = Affine(0.005, 0, 400000.0, 0, -0.005, 5000000.0)
    h, w = 1600, 2000
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.arange(8), np.arange(5))  # plants in rows, 1.2 m apart: boxes never overlap
    cx = 400000.0 + 0.6 + 1.2 * gx.ravel() + rng.uniform(-0.2, 0.2, 40)
    cy = 5000000.0 - 0.6 - 1.5 * gy.ravel() + rng.uniform(-0.2, 0.2, 40)
    heights = rng.uniform(0.1, 0.6, 40)
    chm = np.zeros((h, w), np.float32)
    for px, py, hh in zip(cx, cy, heights):  # a cone per plant, drawn in its own small window
        c0, r0 = int((px - 0.2 - t.c) / t.a), int((py + 0.2 - t.f) / t.e)
        rows, cols = np.mgrid[r0 : r0 + 80, c0 : c0 + 80]
        x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
        r = np.hypot(x - px, y - py) / 0.15
        np.maximum(
            chm[r0 : r0 + 80, c0 : c0 + 80], np.where(r < 1, hh * (1 - r), 0), out=chm[r0 : r0 + 80, c0 : c0 + 80]
        )
    with rasterio.open(
        tmp_path / "chm.tif",
        "w",
        driver="GTiff",
        width=w,
        height=h,
        count=1,
        dtype="float32",
        crs=CRS,
        transform=t,
        nodata=-9999.0,
        tiled=True,
    ) as dst:
        dst.write(chm, 1)
    boxes = shapely.box(cx - 0.16, cy - 0.16, cx + 0.16, cy + 0.16)
    gpd.GeoDataFrame({"plant_id": np.arange(1, 41)}, geometry=boxes, crs=CRS).to_file(tmp_path / "plants.gpkg")
    pd.DataFrame({"a": [1]}).to_csv(tmp_path / "bad.csv", index=False)
    return {"dir": tmp_path, "heights": heights}


def test_gui_headless(small_field, tmp_path):
    from matchplant.core.runtime.config import load_config
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
    from matchplant.spatial_stat_extractor.gui import SpatialStatExtractorGUI

    d = small_field["dir"]
    gui = SpatialStatExtractorGUI(SpatialStatExtractorConfig(), headless=True)
    gui.boxes["polygons"].set_val(str(d / "plants.gpkg"))
    gui.boxes["rasters.chm"].set_val(str(d / "chm.tif"))
    gui.boxes["percentiles"].set_val("10, 90")
    gui.boxes["output_dir"].set_val(str(d / "out"))
    assert gui.cfg.percentiles == [10.0, 90.0] and gui.cfg.rasters.chm == d / "chm.tif"
    gui.stat_checks.set_active(
        list(gui.stat_checks.labels).index(next(lb for lb in gui.stat_checks.labels if lb.get_text() == "nodata"))
    )
    assert "nodata" in gui.cfg.stats

    click(gui.fig, gui.btn_preview.ax, 0.5, 0.5)
    arr = gui.image_artist.get_array()
    assert max(arr.shape) <= 800, "the preview must be a reduced-resolution read"
    assert "EPSG:32615" in gui.crs_text.get_text() and "40 plants" in gui.status.get_text()

    click(gui.fig, gui.btn_run.ax, 0.5, 0.5)
    gui.wait(60)
    assert gui.status.get_text().startswith("done"), gui.status.get_text()
    assert gui.bar.get_width() == 1.0
    table = pd.read_csv(d / "out" / "stats.csv")
    assert {"chm_p10", "chm_p90", "chm_nodata", "chm_max"} <= set(table.columns)
    np.testing.assert_allclose(table["chm_max"], small_field["heights"], rtol=0.04)  # cone tip between pixels
    assert (d / "out" / "polygons.shp").is_file() and (d / "out" / "stats.gpkg").is_file()
    assert gui.colorbar is not None and gui.colorbar.ax.get_ylabel() == "chm_max (m)"  # the map's scale, with unit
    gui.fig.savefig(tmp_path / "gui.png")
    # the colour bar, its ticks and label stay left of the form (it once lay over the form's labels)
    renderer = gui.fig.canvas.get_renderer()
    bar = gui.colorbar.ax.get_tightbbox(renderer)
    form = [box.ax.get_tightbbox(renderer) for box in gui.boxes.values()] + [gui.crs_text.get_window_extent(renderer)]
    form_left = min(b.x0 for b in form)
    assert bar.x1 <= form_left and bar.x0 >= gui.ax.get_window_extent().x1 - 1, (bar, form_left)
    # the window covers RGB indices, plots, the field book and a later date; every field stays in the window
    for key in ("rasters.rgb", "plots.polygons", "plots.field_book", "later_chm"):
        assert key in gui.boxes and key in gui.pickers
    renderer = gui.fig.canvas.get_renderer()
    for box in gui.boxes.values():
        bb = box.ax.get_window_extent(renderer)
        assert 0 <= bb.y0 and bb.y1 <= gui.fig.bbox.y1 and bb.x1 <= gui.fig.bbox.x1
    gui.boxes["later_chm"].set_val(str(d / "chm.tif"))
    gui._set("later_chm", str(d / "chm.tif"))
    assert [r.date for r in gui.cfg.more_dates] == ["later"] and gui.cfg.more_dates[0].chm == d / "chm.tif"
    assert gui.cfg.rasters.date == "first"
    gui._set("later_chm", "")
    assert gui.cfg.more_dates == []
    gui.cfg.rasters.date = ""
    gui._set("rasters.red_band", "")  # empty: from the raster's band names or band_order
    assert gui.cfg.rasters.red_band is None

    # an unusable file: the error is shown in the window, in red, not raised
    gui.boxes["polygons"].set_val(str(d / "bad.csv"))
    click(gui.fig, gui.btn_run.ax, 0.5, 0.5)
    gui.wait(60)
    assert gui.status.get_text().startswith("error") and "xmin,ymin,xmax,ymax" in gui.status.get_text()
    assert gui.status.get_color() == "#c62828"
    # a missing file is refused before any work starts
    gui.boxes["rasters.chm"].set_val(str(d / "nope.tif"))
    assert not gui.run() and "not found" in gui.status.get_text()

    gui.boxes["rasters.chm"].set_val(str(d / "chm.tif"))
    gui.boxes["polygons"].set_val(str(d / "plants.gpkg"))
    saved = gui.save_config()
    cfg = load_config(SpatialStatExtractorConfig, saved)
    assert cfg.rasters.chm == d / "chm.tif" and cfg.percentiles == [10.0, 90.0] and "nodata" in cfg.stats


@pytest.mark.skipif(not xvfb_available(), reason="Xvfb not installed")
def test_gui_real_window(small_field, tmp_path):
    d = small_field["dir"]
    code = textwrap.dedent(f"""
        import matplotlib.pyplot as plt
        from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
        from matchplant.spatial_stat_extractor.gui import SpatialStatExtractorGUI
        cfg = SpatialStatExtractorConfig()
        cfg.polygons = __import__("pathlib").Path({str(d / "plants.gpkg")!r})
        cfg.rasters.chm = __import__("pathlib").Path({str(d / "chm.tif")!r})
        cfg.output_dir = __import__("pathlib").Path({str(d / "xout")!r})
        gui = SpatialStatExtractorGUI(cfg, headless=False)
        assert plt.get_backend().lower().startswith("tk"), plt.get_backend()
        assert gui.preview()
        gui.run()
        def check():
            if not gui.busy and gui.status.get_text().startswith("done"):
                gui.fig.savefig({str(tmp_path / "window.png")!r})
                print("DONE", gui.status.get_text())
                plt.close("all")
        t = gui.fig.canvas.new_timer(interval=200)
        t.add_callback(check)
        t.start()
        killer = gui.fig.canvas.new_timer(interval=60000)
        killer.add_callback(lambda: plt.close("all"))
        killer.start()
        plt.show()
    """)
    r = run_in_xvfb(code, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "DONE done" in r.stdout, r.stdout + r.stderr[-2000:]
    assert (d / "xout" / "stats.csv").is_file() and (tmp_path / "window.png").stat().st_size > 20_000


def test_window_opened_before_the_previous_modules_ran_shows_no_error(small_field, tmp_path):
    """Issue 29 (seen under Xvfb): the folder's config names module 8's plants.gpkg and the ODM rasters, which do
    not exist before those modules ran; the window then asks for the files instead of opening on a red error. With
    the files present it opens on their preview."""
    from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
    from matchplant.spatial_stat_extractor.gui import launch

    d = small_field["dir"]
    missing = SpatialStatExtractorConfig()
    missing.polygons, missing.rasters.chm = tmp_path / "runs" / "plants.gpkg", d / "chm.tif"
    gui = launch(missing, headless=True)
    assert gui.status.get_text().startswith("choose the plant polygons") and not hasattr(gui, "preview_polygons")
    present = SpatialStatExtractorConfig()
    present.polygons, present.rasters.chm, present.output_dir = d / "plants.gpkg", d / "chm.tif", d / "out"
    gui = launch(present, headless=True)
    assert len(gui.preview_polygons) == 40 and "40 plants" in gui.status.get_text()


def test_the_map_is_coloured_by_a_height_or_a_mean_not_a_minimum():
    from matchplant.spatial_stat_extractor.gui import colour_column

    assert colour_column(["exg_min", "exg_max", "exg_mean", "red_mean"]) == "exg_mean"  # an RGB-only run
    assert colour_column(["ndvi_min", "chm_min", "chm_max", "ndvi_mean"]) == "chm_max"
    assert colour_column(["chm_canopy_p95", "ndvi_canopy_mean"]) == "chm_canopy_p95"
    assert colour_column(["red_min", "red_max"]) == "red_min"  # nothing better: the first


def test_the_folders_picture_of_the_window_shows_its_current_form():
    """``9_spatial_stat_extractor/gui.png`` (drawn by docs/gui/folder_windows.py) records the form it shows and
    the map's colour bar (the picture once showed ten of the fields and a map without its colour bar)."""
    import json
    from pathlib import Path

    from PIL import Image

    from matchplant.spatial_stat_extractor.gui import PICKERS, TEXT_FIELDS
    from matchplant.spatial_stat_extractor.zonal import BASIC_STATS, MODES

    with Image.open(Path(__file__).resolve().parents[1] / "9_spatial_stat_extractor" / "gui.png") as im:
        shown = json.loads(im.text.get("widgets", "{}"))
    fix = "9_spatial_stat_extractor/gui.png is older than the window: python docs/gui/folder_windows.py <demo output>"
    assert shown.get("fields") == [list(f) for f in TEXT_FIELDS], fix
    assert shown.get("pickers") == sorted(PICKERS), fix
    assert shown.get("stats") == list(BASIC_STATS) and shown.get("modes") == list(MODES), fix
    assert shown.get("colour_bar"), "the picture shows the map coloured by a trait after a run, with its colour bar"
