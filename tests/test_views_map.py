"""The field map in a real headless Chromium: no request leaves the map's folder, the plants are drawn, a click
opens the right plant's popup with its crops, a screenshot shows each plant in its trait's colour."""

from __future__ import annotations

import cv2
import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import shapely
from browser import open_page, why_not
from views_truth import true_plants

from matchplant.views import CropSettings, cut_crops, survey_cameras
from matchplant.views.fieldmap import write_field_map

pytestmark = pytest.mark.skipif(why_not() is not None, reason=str(why_not()))

VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)


def ramp(t: float) -> np.ndarray:
    """The map's colour ramp (viridis in five stops), independently of its JavaScript."""
    s = min(max(t, 0.0), 1.0) * 4
    i = min(int(s), 3)
    return VIRIDIS[i] + (s - i) * (VIRIDIS[i + 1] - VIRIDIS[i])


@pytest.fixture(scope="module")
def field_map(tiny_field, tmp_path_factory):
    """The tiny field's map, with its crops beside it: (html, plants GeoDataFrame, plots)."""
    folder = tmp_path_factory.mktemp("map")
    gdf = true_plants(tiny_field).drop(columns="ndvi")
    table = pd.read_csv(tiny_field.plots_csv)
    plots = gpd.GeoDataFrame(table.drop(columns="geometry"), geometry=shapely.from_wkt(table.geometry), crs=gdf.crs)
    crops = cut_crops(gdf, survey_cameras(tiny_field.root), folder / "crops", CropSettings(best=3))
    html = write_field_map(
        folder / "map.html", gdf, plots=plots, orthophoto=tiny_field.orthophoto, crops=crops.index_csv, trait="height"
    )
    return html, gdf, plots


def container_point(page, x: float, y: float) -> tuple[float, float]:
    """The page pixel of map point (x, y), as Leaflet places it."""
    origin = page.evaluate("DATA.origin")
    pt = page.evaluate(
        "([lat, lng]) => { const p = fieldmap.map.latLngToContainerPoint([lat, lng]);"
        " const r = fieldmap.map.getContainer().getBoundingClientRect(); return [p.x + r.left, p.y + r.top]; }",
        [y - origin[1], x - origin[0]],
    )
    return float(pt[0]), float(pt[1])


def test_map_opens_offline_draws_every_plant_and_clicks_open_the_right_popup(field_map, tmp_path):
    html, plants, plots = field_map
    with open_page(html.parent) as (page, requests, outside):
        page.goto(html.as_uri())
        page.wait_for_function("window.fieldmap && window.fieldmap.ready && window.fieldmap.redraws > 0")
        assert page.evaluate("fieldmap.plants") == len(plants)
        assert page.evaluate("fieldmap.drawn") == len(plants)  # the whole field is in view
        with_plants = np.asarray(cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR), float)
        page.evaluate("document.querySelector('canvas.plants').style.visibility = 'hidden'")
        ortho_only = np.asarray(cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR), float)
        page.evaluate("document.querySelector('canvas.plants').style.visibility = 'visible'")

        # every plant's inner point shows its height's colour, drawn at 75 % over the orthophoto
        lo, hi = plants["height"].min(), plants["height"].max()
        errors = []
        for g, h in zip(plants.geometry, plants["height"]):
            inner = g.buffer(-0.02).representative_point() if g.buffer(-0.02).area > 0 else g.representative_point()
            u, v = (int(round(c)) for c in container_point(page, inner.x, inner.y))
            colour = (with_plants[v, u, ::-1] - 0.25 * ortho_only[v, u, ::-1]) / 0.75
            errors.append(np.abs(colour - ramp((h - lo) / (hi - lo))).max())
        assert np.median(errors) < 6 and np.percentile(errors, 90) < 15, errors
        # outside every plant the screenshot is the orthophoto
        union = shapely.union_all(plants.geometry.values)
        for x, y in np.random.default_rng(0).uniform(plants.total_bounds[:2], plants.total_bounds[2:], (200, 2)):
            if not union.buffer(0.02).contains(shapely.Point(x, y)):
                u, v = (int(round(c)) for c in container_point(page, x, y))
                assert np.abs(with_plants[v, u] - ortho_only[v, u]).max() <= 2

        # a click on a plant: its popup, its traits, its crops (loaded from beside the map)
        big = plants.iloc[int(np.argmax(plants.geometry.area))]
        inner = big.geometry.buffer(-0.02).representative_point()
        page.mouse.click(*container_point(page, inner.x, inner.y))
        popup = page.wait_for_selector(".plant-popup")
        assert popup.get_attribute("data-plant") == str(big.plant_id)
        assert f"{big.height:.4g}" in popup.inner_text()
        images = page.eval_on_selector_all(".plant-popup image", "els => els.map(e => e.getAttribute('href'))")
        assert 1 <= len(images) <= 3 and all(i.startswith("crops/crops/") for i in images)
        page.wait_for_timeout(300)
        assert any("/crops/crops/" in r for r in requests)

        # a click on soil inside a plot: the plot's statistics
        plot = plots.iloc[0]
        free = plot.geometry.difference(union.buffer(0.05)).representative_point()
        page.mouse.click(*container_point(page, free.x, free.y))
        popup = page.wait_for_selector(".plot-popup")
        assert popup.get_attribute("data-plot") == str(plot.plot_id)
        assert f"stand_count{plot.stand_count}" in popup.inner_text().replace("\t", "").replace("\n", "")

        # search by id
        page.fill("#search", str(plants.plant_id.iloc[5]))
        page.press("#search", "Enter")
        page.wait_for_function(f"document.querySelector('.plant-popup[data-plant=\"{plants.plant_id.iloc[5]}\"]')")
        assert page.eval_on_selector_all(".plant-popup", "els => els.length") == 1
        page.fill("#search", "no-such-id")
        page.press("#search", "Enter")
        assert "no plant or plot" in page.inner_text("#search-msg")
        page.screenshot(path=str(tmp_path / "map.png"))
    assert not outside, f"requests outside the map's folder: {outside}"
