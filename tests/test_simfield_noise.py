"""The synthetic field made imperfect like a real one (issue 26, point 8): ``noise: realistic`` and a skewed
plot grid, each checked on the written files against the generator's truth by an independent computation
(numpy over the same pixels, shapely, module 9's own plot grid)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import rasterio
import shapely
from PIL import Image
from scipy import ndimage

from matchplant.core.runtime.io import read_json
from matchplant.simfield import generate_field


@pytest.fixture(scope="module")
def noisy_field(tmp_path_factory):
    """The tiny field (seed 0) with noise: realistic and per-plant vigour: the same scene as ``tiny_field``."""
    return generate_field(preset="tiny", seed=0, out=tmp_path_factory.mktemp("noisy"), noise="realistic", vigour=True)


def _read(path, band=1):
    with rasterio.open(path) as src:
        return src.read(band, masked=True)


def _bare_ground(field, clear=0.05):
    """Soil cells at least ``clear`` m from any plant, weed or target, from truth/plant_ids.tif."""
    with rasterio.open(field.plant_ids) as src:
        label, res = src.read(1), src.res[0]
    return ~ndimage.binary_dilation(label != 0, iterations=int(np.ceil(clear / res)))


def test_chm_has_the_noise_of_a_photogrammetric_chm(noisy_field, tiny_field):
    dsm, dtm = _read(noisy_field.dsm), _read(noisy_field.dtm)
    chm = (dsm - dtm).filled(np.nan)
    ground = _bare_ground(noisy_field) & np.isfinite(chm)
    g = chm[ground]
    p50, p95 = np.percentile(g, [50, 95])
    # a real ODM CHM's bare ground: p50 about 1.6 cm, p95 about 7 cm, 44 % above 2 cm (issue 26)
    assert 0.010 < p50 < 0.022 and 0.055 < p95 < 0.085, (p50, p95)
    assert 0.35 < np.mean(g > 0.02) < 0.55
    # spatially correlated (bumps, not white noise): neighbouring ground cells agree
    a, b = chm[:, :-1], chm[:, 1:]
    both = ground[:, :-1] & ground[:, 1:]
    assert np.corrcoef(a[both], b[both])[0, 1] > 0.7
    # the exact field's bare ground is exactly 0 (so the noise is what the realistic field adds)
    exact = (_read(tiny_field.dsm) - _read(tiny_field.dtm)).filled(np.nan)
    assert np.nanmax(np.abs(exact[_bare_ground(tiny_field)])) < 1e-3
    # small holes in the DSM only, as ODM leaves them; the DTM is whole
    holes = np.ma.getmaskarray(dsm)
    assert 0.001 < holes.mean() < 0.01 and not np.ma.getmaskarray(dtm).any()
    assert ndimage.label(holes)[1] > 20  # many small holes, not one big one
    measured = read_json(noisy_field.noise_json)
    assert measured["bare_ground_chm_m"]["p50"] == pytest.approx(p50, abs=0.003)
    assert measured["dsm_holes"]["cells"] == holes.sum()


def test_plant_tops_are_smoothed(noisy_field, tiny_field):
    """At each plant's true top the exact CHM is the plant's height; the noisy CHM there is lower than the
    ground noise alone would make it (ODM's smoothing rounds the tops), and the plants' highest cells still
    follow their heights."""
    plants = pd.read_csv(tiny_field.plants_csv)
    with rasterio.open(tiny_field.plant_ids) as src:
        label, transform = src.read(1), src.transform
    rows, cols = rasterio.transform.rowcol(transform, plants["x"], plants["y"])
    exact = (_read(tiny_field.dsm) - _read(tiny_field.dtm)).filled(np.nan)
    noisy = (_read(noisy_field.dsm) - _read(noisy_field.dtm)).filled(np.nan)
    top_exact, top_noisy = exact[rows, cols], noisy[rows, cols]
    err = np.abs(top_exact - plants["height"])  # (the cell centre is up to 3 mm off the plant's centre)
    assert np.median(err) < 0.003 and err.max() < 0.03
    p50 = read_json(noisy_field.noise_json)["model"]["chm_p50"]
    assert np.nanmedian(top_noisy - top_exact) < p50 - 0.01  # lowered by the smoothing beyond the noise's +1.6 cm
    ids = plants["id"].to_numpy()
    highest = np.asarray(ndimage.labeled_comprehension(noisy, label, ids, np.nanmax, float, np.nan))
    assert np.corrcoef(highest, plants["height"])[0, 1] > 0.9
    assert 0.8 < np.nanmedian(highest / plants["height"]) < 1.2


def test_multispectral_is_five_bands_labelled_like_a_generic_writer(noisy_field):
    with rasterio.open(noisy_field.multispectral) as src:
        assert src.count == 5 and src.dtypes[0] == "float32"
        interp = [c.name for c in src.colorinterp]
        assert interp == ["red", "green", "blue", "undefined", "undefined"]  # GDAL's labels: band 1 is blue
        assert all(d is None for d in src.descriptions)
        bands = src.read().astype(float)
    assert read_json(noisy_field.noise_json)["multispectral_bands"] == ["blue", "green", "red", "rededge", "nir"]
    traits = pd.read_csv(noisy_field.traits_csv)
    with rasterio.open(noisy_field.plant_ids) as src:
        label = src.read(1)
    core = ndimage.binary_erosion(label > 0, iterations=2) * label  # away from the blurred edges
    ids = traits["id"].to_numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        ndvi = (bands[4] - bands[2]) / (bands[4] + bands[2])  # NIR band 5, red band 3
        wrong = (bands[4] - bands[0]) / (bands[4] + bands[0])  # "red" by GDAL's label: band 1, the blue
    mean = np.asarray(ndimage.mean(ndvi, core, ids))
    ok = np.bincount(core.ravel(), minlength=ids.max() + 1)[ids] > 5
    assert ok.sum() > 30
    assert np.abs(mean[ok] - traits["ndvi"].to_numpy()[ok]).max() < 0.05
    assert np.corrcoef(mean[ok], traits["ndvi"].to_numpy()[ok])[0, 1] > 0.95
    # the blue band taken for red gives a far higher NDVI (what issue 26 saw: 50 % too high)
    assert np.nanmean(np.asarray(ndimage.mean(wrong, core, ids))[ok]) > np.nanmean(mean[ok]) + 0.03
    soil = label == 0
    assert 0.05 < np.median(ndvi[soil]) < 0.3


def test_masks_are_antialiased_png_jpeg_and_gif(noisy_field):
    truth = pd.read_csv(noisy_field.mask_objects)
    names = sorted(p.name.removesuffix(".png") for p in noisy_field.masks_antialiased.glob("SIM_*.png"))
    assert names == sorted(truth["image"]) and len(names) == 9
    for name, plants, parts, pixels in truth.itertuples(index=False):
        ids = np.asarray(Image.open(noisy_field.masks_undistorted / f"{name}.png"))
        png = np.asarray(Image.open(noisy_field.masks_antialiased / f"{name}.png"))
        assert png.dtype == np.uint8 and png.shape == ids.shape
        levels = np.unique(png)
        assert len(levels) > 50  # anti-aliased: many grey levels, not 2
        grey = (png > 0) & (png < 255)
        box = np.ones((3, 3), bool)
        edge = ndimage.binary_dilation(ids > 0, box, 3) & ~ndimage.binary_erosion(ids > 0, box, 3)
        assert grey[edge].sum() / grey.sum() > 0.99  # the grey levels sit on the plants' edges
        assert np.array_equal(png >= 128, ids > 0) or np.mean((png >= 128) == (ids > 0)) > 0.995
        gif = np.asarray(Image.open(noisy_field.masks_antialiased_gif / f"{name}.gif").convert("L"))
        assert np.array_equal(gif, png)  # GIF keeps the 256 grey levels
        jpg = np.asarray(Image.open(noisy_field.masks_antialiased_jpg / f"{name}.jpg").convert("L"))
        assert jpg.shape == png.shape and np.abs(jpg.astype(int) - png).mean() < 3 and len(np.unique(jpg)) > 50
        # the truth: plants in the instance mask, 8-connected parts of the binary one
        assert plants == len(np.unique(ids[ids > 0]))
        assert parts == ndimage.label(ids > 0, structure=np.ones((3, 3)))[1] and pixels == (ids > 0).sum()


def test_the_photos_are_the_exact_fields(noisy_field, tiny_field):
    """The noise is what photogrammetry makes of the scene: photos, boxes and plants are the exact field's."""
    for name in ("plants_csv", "boxes_raw", "boxes_undistorted", "reconstruction", "plant_ids"):
        assert getattr(noisy_field, name).read_bytes() == getattr(tiny_field, name).read_bytes(), name
    for img in sorted(tiny_field.images.iterdir())[:3]:
        assert (noisy_field.images / img.name).read_bytes() == img.read_bytes()
    assert read_json(noisy_field.field_json)["noise"] == "realistic"
    assert not tiny_field.noise_json.exists() and not tiny_field.masks_antialiased.exists()


def test_exact_run_over_a_noisy_one_leaves_no_noisy_truth(tmp_path):
    small = {"image_width": 96, "field_width": 1.6, "field_length": 1.2}
    p = generate_field("tiny", out=tmp_path / "f", noise="realistic", **small)
    assert p.noise_json.is_file() and any(p.masks_antialiased_gif.iterdir())
    generate_field("tiny", out=tmp_path / "f", **small)
    assert not p.noise_json.exists() and not p.mask_objects.exists() and not any(p.masks_antialiased_gif.iterdir())
    with rasterio.open(p.multispectral) as src:
        assert src.count == 2


@pytest.mark.parametrize("skew", [12.0])
def test_skewed_plot_grid_truth_agrees_with_module_9s_grid_and_the_plants(tmp_path, skew):
    """A parallelogram grid: module 9's plot_grid from truth/plots.json's corners gives truth/plots.csv's
    outlines; every plant of a plot stands inside it, every gap lies inside its plot and on its row, and no
    plant grows at a gap."""
    from matchplant.spatial_stat_extractor.plots import PlotsConfig, plot_grid

    field = generate_field("tiny", seed=1, out=tmp_path / "skew", plot_skew_deg=skew, image_width=200)
    grid = read_json(field.plots_json)
    plots = pd.read_csv(field.plots_csv)
    gaps = pd.read_csv(field.gaps_csv)
    plants = pd.read_csv(field.plants_csv)
    assert grid["skew_deg"] == skew and grid["row_direction"] == [0.0, 1.0]
    c = np.array(grid["corners"])
    across = c[1] - c[0]
    assert np.degrees(np.arctan2(across[1], across[0])) == pytest.approx(skew)
    built = plot_grid(PlotsConfig(corners=grid["corners"], columns=grid["columns"], ranges=grid["ranges"]))
    truth = shapely.from_wkt(plots["geometry"].to_numpy())
    assert len(built) == len(truth)
    for a, b in zip(built.geometry.values, truth):
        assert a.symmetric_difference(b).area < 1e-6 * b.area
    assert (plots["stand_count"] + plots["gaps"] == plots["expected"]).all()
    for outline, count, pid in zip(truth, plots["stand_count"], plots["plot_id"]):
        assert shapely.contains_xy(outline, plants["x"], plants["y"]).sum() == count
        g = gaps[gaps["plot_id"] == pid]
        assert shapely.contains_xy(outline, g["x"], g["y"]).all()  # every gap inside its own plot
    d = np.hypot(
        gaps["x"].to_numpy()[:, None] - plants["x"].to_numpy()[None],
        gaps["y"].to_numpy()[:, None] - plants["y"].to_numpy()[None],
    )
    assert len(gaps) and d.min() > 0.1
    # the seeds of one row follow the grid: row r's seeds start (x_r - x_0) tan(skew) further north
    first = plants.sort_values("y").groupby("row").first()
    rise = (first["x"] - first["x"].iloc[0]) * np.tan(np.radians(skew))
    phase = np.mod(first["y"] - first["y"].iloc[0] - rise + 0.1, 0.2) - 0.1
    assert np.abs(phase).max() < 0.08  # within the sowing jitter


def test_bad_noise_settings_are_named(tmp_path):
    from matchplant.core.runtime.errors import ConfigError

    with pytest.raises(ConfigError, match="noise"):
        generate_field("tiny", out=tmp_path / "x", noise="foggy")
    with pytest.raises(ConfigError, match="plot_skew_deg"):
        generate_field("tiny", out=tmp_path / "x", plot_skew_deg=50)
    assert not (tmp_path / "x").exists()
