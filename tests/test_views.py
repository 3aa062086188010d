"""Plant crops from the raw photos (matchplant.views): checked against the synthetic field's own plants.

The truth is the generator's geometry rebuilt from its seed (tests/views_truth.py): each plant's canopy surface
projected through the photo's camera, with nothing in front of it. The crops read only the project (poses, DSM,
photos) and the polygons.
"""

from __future__ import annotations

import json
import os

import cv2
import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
from project_exports import write_exports
from views_truth import crop_ious, field_plants, map_outlines, photo_points

import matchplant.views.crops as crops_module
from matchplant.core.formats.reconstruction import read_reconstruction
from matchplant.core.runtime.errors import ConfigError
from matchplant.simfield import generate_field
from matchplant.views import CropSettings, cut_crops, survey_cameras


@pytest.fixture(scope="module")
def truth(tiny_field):
    """(plants, terrain, polygons in WGS 84, field.json) of the tiny field."""
    meta = json.loads(tiny_field.field_json.read_text())
    plants, terrain = field_plants("tiny", 0)
    polys = map_outlines(plants, terrain, meta["offset"])
    # any CRS: the polygons come in geographic coordinates and are moved to the project's
    gdf = gpd.GeoDataFrame({"plant_id": plants.ids}, geometry=polys, crs=meta["crs"]).to_crs("EPSG:4326")
    return plants, terrain, gdf, meta


@pytest.fixture(scope="module")
def all_views(tiny_field, truth, tmp_path_factory):
    out = tmp_path_factory.mktemp("crops_all")
    result = cut_crops(truth[2], survey_cameras(tiny_field.root), out, CropSettings())
    return result, pd.read_csv(result.index_csv)


def test_crops_cover_each_plants_true_outline(tiny_field, truth, all_views):
    plants, terrain, _, _ = truth
    result, index = all_views
    shots = read_reconstruction(tiny_field.reconstruction).shots
    ious = crop_ious(index, plants, terrain, shots)
    assert len(ious) > 200 and result.plants_seen == len(plants)
    assert ious.min() >= 0.8, f"IoU min {ious.min():.3f}, median {np.median(ious):.3f}"
    assert np.median(ious) >= 0.9


def test_every_whole_view_is_cut_and_no_other(tiny_field, truth, all_views):
    plants, terrain, _, _ = truth
    _, index = all_views
    got = set(zip(index.plant_id.astype(int), index.photo))
    shots = read_reconstruction(tiny_field.reconstruction).shots
    for name, shot in shots.items():
        for p in range(len(plants)):
            uv = photo_points(plants, terrain, p, shot).reshape(-1, 2)
            if not np.isfinite(uv).all():
                continue
            if shot.camera.in_image(uv, margin=-2).all():  # whole with room to spare: must be cut
                assert (p + 1, name) in got, (p + 1, name)
            elif not shot.camera.in_image(uv, margin=2).all():  # cut by the frame: must not be
                assert (p + 1, name) not in got, (p + 1, name)


def test_crops_are_the_photos_pixels_and_views_are_measured(tiny_field, truth, all_views):
    plants, _, _, meta = truth
    result, index = all_views
    rec = read_reconstruction(tiny_field.reconstruction)
    offset = np.array(meta["offset"] + [0.0])
    centres = truth[2].to_crs(meta["crs"]).geometry.centroid
    for r in index.sample(20, random_state=0).itertuples():
        photo = cv2.imread(str(tiny_field.images / r.photo), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        crop = cv2.imread(str(result.index_csv.parent / r.crop))

        errors = {
            s: _window_error(photo, crop, r.x0 + s[0], r.y0 + s[1]) for s in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
        }
        assert crop.shape == (r.height, r.width, 3) and errors[0, 0] < 6  # JPEG again, nothing else
        assert errors[0, 0] < 0.8 * min(v for k, v in errors.items() if k != (0, 0))
        shot = rec.shots[r.photo]
        eye = shot.center + offset
        c = centres.iloc[int(r.plant_id) - 1]
        d = eye - [c.x, c.y, plants.z[int(r.plant_id) - 1]]  # to the ground under the plant's centre
        assert r.distance_m == pytest.approx(np.linalg.norm(d), abs=0.02)
        assert r.off_nadir_deg == pytest.approx(np.degrees(np.arctan2(np.hypot(d[0], d[1]), d[2])), abs=0.5)
        # a pixel of a pinhole camera at this distance, widened on the ground by the obliquity (at most)
        focal_px = shot.camera.focal_x * max(shot.camera.width, shot.camera.height)
        cos = np.cos(np.radians(r.off_nadir_deg))
        assert 0.85 * r.distance_m / focal_px * 100 < r.gsd_cm < 1.15 * r.distance_m / focal_px / cos**1.5 * 100


def _window_error(photo, crop, x0, y0) -> float:
    """Mean absolute difference between ``crop`` and the photo's window of its size at (x0, y0)."""
    window = photo[y0 : y0 + crop.shape[0], x0 : x0 + crop.shape[1]].astype(float)
    return float(np.abs(crop - window).mean()) if window.shape == crop.shape else np.inf


def test_best_views_are_the_most_nadir(tiny_field, truth, all_views, tmp_path):
    _, every = all_views
    result = cut_crops(truth[2], survey_cameras(tiny_field.root), tmp_path, CropSettings(best=2))
    best = pd.read_csv(result.index_csv)
    assert set(best["rank"]) == {1, 2}
    for pid, rows in best.groupby("plant_id"):
        angles = np.sort(every.loc[every.plant_id == pid, "off_nadir_deg"].to_numpy())[:2]
        assert np.allclose(np.sort(rows.off_nadir_deg.to_numpy()), angles)
    gpkg = gpd.read_file(result.index_gpkg, layer="crops")
    assert len(gpkg) == len(best) and gpkg.crs.to_epsg() == 32614


def test_interrupted_run_resumes_to_the_same_index(tiny_field, truth, all_views, tmp_path, monkeypatch):
    _, every = all_views
    real = crops_module.cut_photo
    calls = []

    def stop_at_third(*args, **kwargs):
        calls.append(args[0].name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    survey = survey_cameras(tiny_field.root)
    monkeypatch.setattr(crops_module, "cut_photo", stop_at_third)
    with pytest.raises(KeyboardInterrupt):
        cut_crops(truth[2], survey, tmp_path, CropSettings())
    assert len([p for p in (tmp_path / "crops").iterdir() if p.is_dir()]) == 2
    (tmp_path / "crops" / ".partial-x").mkdir()  # as a kill mid-photo leaves it
    calls.clear()
    monkeypatch.setattr(crops_module, "cut_photo", lambda *a, **k: (calls.append(a[0].name), real(*a, **k))[1])
    result = cut_crops(truth[2], survey, tmp_path, CropSettings())
    assert len(calls) == len(survey.cameras) - 2
    assert not list((tmp_path / "crops").glob(".partial-*"))
    again = pd.read_csv(result.index_csv)
    pd.testing.assert_frame_equal(again, every)
    with pytest.raises(ConfigError, match="another run"):
        cut_crops(truth[2], survey, tmp_path, CropSettings(best=1))


@pytest.mark.slow
@pytest.mark.skipif(
    not os.environ.get("MATCHPLANT_LONG_TESTS"),
    reason="the demo field's 16,366 crops take ~5 min per camera source, past the suite's budget: "
    "MATCHPLANT_LONG_TESTS=1 runs it (docs/development.md, Test tiers); the tiny field's crops are checked the same "
    "way in every run",
)
@pytest.mark.parametrize("program", ["odm", "metashape", "pix4d"])
def test_demo_field_crops_cover_each_plants_true_outline(tmp_path, program):
    """The demo's field (``small``: 40 photos, 1,292 plants, every whole view), its poses read from ODM's project or
    from our Metashape and Pix4D exports of it: IoU >= 0.8 in every crop (truth: the generator's own cameras)."""
    paths = generate_field(preset="small", seed=0, out=tmp_path / "field")
    meta = json.loads(paths.field_json.read_text())
    plants, terrain = field_plants("small", 0)
    gdf = gpd.GeoDataFrame(
        {"plant_id": plants.ids}, geometry=map_outlines(plants, terrain, meta["offset"]), crs=meta["crs"]
    )
    if program == "odm":
        survey = survey_cameras(paths.root)
    else:
        project = write_exports(paths.root, tmp_path / "exports")[program]
        survey = survey_cameras(project, paths.images, paths.dsm)
    result = cut_crops(gdf, survey, tmp_path / "crops", CropSettings())
    ious = crop_ious(pd.read_csv(result.index_csv), plants, terrain, read_reconstruction(paths.reconstruction).shots)
    print(f"{program}: {len(ious)} crops, IoU min {ious.min():.4f}, median {np.median(ious):.4f}")
    assert len(ious) > 15000 and result.plants_seen == len(plants)
    assert ious.min() >= 0.8 and np.median(ious) >= 0.9, (ious.min(), np.median(ious))


@pytest.mark.parametrize("program", ["metashape", "pix4d"])
def test_crops_through_metashape_and_pix4d_cover_the_same_views(
    tiny_field, truth, all_views, camera_exports, program, tmp_path
):
    """The tiny field's poses exported as Metashape and Pix4D write them (conftest's ``camera_exports``): the
    crops are cut from the same original photos, through each program's distortion model, for the same
    (plant, photo) views as through ODM, and cover the true outline as well. The truth is the generator's own
    cameras (its reconstruction.json), never what our Metashape/Pix4D readers make of the export."""
    plants, terrain, gdf, _ = truth
    _, odm_index = all_views
    project = camera_exports / ("meta/cameras.xml" if program == "metashape" else "p4d")
    survey = survey_cameras(project, tiny_field.images, tiny_field.dsm)  # project_type auto: told from the files
    assert survey.source == program and survey.crs.to_epsg() == 32614
    assert {c.shot.camera.projection_type for c in survey.cameras} == {"brown"}  # original photos, distorted
    result = cut_crops(gdf, survey, tmp_path, CropSettings())
    index = pd.read_csv(result.index_csv)
    assert set(zip(index.plant_id, index.photo)) == set(zip(odm_index.plant_id, odm_index.photo))
    ious = crop_ious(index, plants, terrain, read_reconstruction(tiny_field.reconstruction).shots)
    print(f"{program}: {len(ious)} crops, IoU min {ious.min():.4f}, median {np.median(ious):.4f}")
    assert ious.min() >= 0.8, f"IoU min {ious.min():.3f}, median {np.median(ious):.3f}"
    assert np.median(ious) >= 0.9
