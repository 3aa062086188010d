"""Module 8 on a photogrammetric DSM (simfield's ``noise: realistic``: noisy bare soil, smoothed tops, small
holes): one record per plant, no box lost to a small hole, the ground at the soil's level, checked against the
generator's truth (its plant boxes, plant map and measured noise)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest
import rasterio
from affine import Affine

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.odm import ODMProject
from matchplant.core.geometry.surface import Surface
from matchplant.plant_projection.dsm_noise import soil_level, soil_surface
from matchplant.plant_projection.evaluation import evaluate_boxes
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.views import project_predictions
from matchplant.simfield import generate_field
from matchplant.simfield.layout import FieldPaths


@pytest.fixture(scope="module")
def noisy_field(tmp_path_factory) -> FieldPaths:
    """The tiny field (seed 0) with a photogrammetric DSM: soil noise p50 1.6 cm / p95 7 cm, 0.4 % holes."""
    root = tmp_path_factory.mktemp("tiny_noisy")
    generate_field(preset="tiny", seed=0, out=root, noise="realistic")
    return FieldPaths(root)


def test_small_holes_are_filled_from_their_rims_and_large_ones_kept():
    """Holes up to ``fill_holes`` take values between their rim's lowest and highest; a larger hole stays a
    hole (its rays are reported)."""
    rng = np.random.default_rng(0)
    z = (350 + 0.03 * rng.standard_normal((200, 200))).astype(np.float32)
    z[50:56, 50:54] = np.nan  # 3 cm x 2 cm at 5 mm
    z[120:170, 120:170] = np.nan  # 25 cm
    filled, count = soil_surface(Surface(z, Affine(0.005, 0, 0, 0, -0.005, 1.0)), 0.1)
    rim = z[48:58, 48:56]
    assert count == 24
    small = filled.data[50:56, 50:54]
    assert np.isfinite(small).all() and np.nanmin(rim) <= small.min() and small.max() <= np.nanmax(rim)
    assert np.isnan(filled.data[120:170, 120:170]).all()
    assert soil_surface(Surface(z, Affine(0.005, 0, 0, 0, -0.005, 1.0)), 0.0)[1] == 0  # 0: fill none


def test_ground_is_lifted_to_the_noisy_soil(noisy_field):
    """The DSM's opening rests on the soil noise's troughs, centimetres below the soil; the lifted ground lies at
    the soil's median (cells at least 5 cm from any plant in the generator's plant map), and the spread measured
    is the generator's soil noise."""
    dsm = Surface.open(noisy_field.dsm)
    with rasterio.open(noisy_field.plant_ids) as src:
        ids = src.read(1)
    soil = cv2.erode((ids == 0).astype(np.uint8), np.ones((21, 21), np.uint8)) > 0  # 5 cm from plants, weeds
    surface, _ = soil_surface(dsm, 0.1)
    opened = Surface.ground(surface, 1.5)  # the plain opening
    noise = soil_level(surface, opened)
    rows, cols = np.nonzero(soil & np.isfinite(dsm.data))
    x, y = dsm.transform @ (cols + 0.5, rows + 0.5)
    z = dsm.data[rows, cols]
    below = np.median(z - opened.sample(x, y))
    assert below > 0.05  # what made every soil hit look like a plant's top
    assert abs(np.median(z - surface.ground(1.5).sample(x, y))) < 0.015
    bare = json.loads(noisy_field.noise_json.read_text())["bare_ground_chm_m"]
    sigma = (bare["p95"] - bare["p50"]) / 1.6449
    assert noise.spread == pytest.approx(sigma, rel=0.3)
    assert noise.lift == pytest.approx(below, abs=0.015)


def test_noisy_dsm_gives_one_record_per_plant(noisy_field):
    """The generator's boxes of every photo on the noisy DSM: no box lost to a hole, one record per plant, and
    the plants' map boxes where the truth has them."""
    ds = read_dataset(noisy_field.boxes_undistorted, validate=False)
    preds = {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }
    views, rejected = project_predictions(ODMProject(noisy_field.root), preds)
    plants = merge_views(views)
    truth = pd.read_csv(noisy_field.map_boxes)
    assert len(rejected) == 0, rejected["reason"].value_counts()
    per_truth = views.table.groupby("truth_plant_id")["plant_id"].nunique()
    assert len(plants) == len(truth) and (per_truth == 1).all(), per_truth.value_counts()
    m = evaluate_boxes(
        truth[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
    )
    assert m["share_iou_above_0.5"] >= 0.97 and m["iou_median"] >= 0.85, m


def test_soil_level_under_a_canopy_that_covers_most_of_the_field():
    """Rows of a closing canopy (flat tops 0.2 m high, as noisy as the soil) cover 70 % of the field, so the
    canopy's height is the commonest: the soil, the lowest well-filled height, is still the level measured,
    within a centimetre of the soil cells' own median."""
    rng = np.random.default_rng(1)
    res, n = 0.01, 600
    noise = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 4)
    noise *= 0.03 / noise.std()  # 3 cm of correlated noise, on soil and canopy alike
    across = (np.arange(n) * res % 0.5) - 0.25  # rows every 0.5 m, 0.35 m wide
    canopy = np.clip((0.175 - np.abs(across)) / 0.02, 0, 1) * 0.2
    z = 350 + noise + canopy[None, :].astype(np.float32)
    surface, _ = soil_surface(Surface(z, Affine(res, 0, 0, 0, -res, n * res)), 0.1)
    opened = Surface.ground(surface, 1.5)
    level = soil_level(surface, opened)
    bare = np.broadcast_to(canopy[None, :] == 0, z.shape)
    rows, cols = np.nonzero(bare)
    x, y = surface.transform @ (cols + 0.5, rows + 0.5)
    assert (canopy > 0).mean() > 0.6
    assert level.lift == pytest.approx(np.median(z[bare] - opened.sample(x, y)), abs=0.01)
    assert np.median(z[bare] - surface.ground(1.5).sample(x, y)) == pytest.approx(0.0, abs=0.01)
