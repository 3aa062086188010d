"""Module 8 (plant projection): boxes on photos -> plants on the map, against exact geometry.

Two kinds of ground truth: a small ODM-shaped project built here from first principles (dome-shaped
plants on a sloped DSM, brown raw camera, nadir and oblique shots, map boxes known exactly), and the
synthetic field of matchplant.simfield (tiny preset) when it is available.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from affine import Affine
from odm_builder import Raster, write_odm_project
from pyproj import CRS
from scipy.spatial.transform import Rotation

from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.formats.reconstruction import write_reconstruction
from matchplant.core.geometry.boxes import iou_pairs, match_boxes
from matchplant.core.geometry.camera import FisheyeCamera, PinholeCamera
from matchplant.core.geometry.frames import write_coords_txt
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import HIT, OUTSIDE, STATUS_TEXT
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import MatchPlantError
from matchplant.plant_projection import dsm
from matchplant.plant_projection.config import PlantProjectionConfig
from matchplant.plant_projection.evaluation import evaluate_boxes, read_boxes
from matchplant.plant_projection.geometry import box_outline, outline_boxes
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.relief import Scene, skimmed
from matchplant.plant_projection.run import run
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.views import NOT_IN_RECONSTRUCTION, project_predictions, resolve_images

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "8_plant_projection"
CRS14 = CRS.from_epsg(32614)
OFFSET = np.array([700000.0, 4500000.0, 0.0])
RES = 0.01


# --------------------------------------------------------------------------------------------------
# a small ODM project with exact truth, built from first principles


def terrain(x, y):
    return 350.0 + 0.06 * x + 0.025 * y  # a 6.5 % slope


def make_plants(rng, nx=6, ny=8):
    xs, ys = np.meshgrid(1.2 + 0.76 * np.arange(nx), 1.0 + 0.45 * np.arange(ny))
    x = xs.ravel() + rng.normal(0, 0.02, xs.size)
    y = ys.ravel() + rng.normal(0, 0.02, xs.size)
    r = rng.uniform(0.08, 0.18, x.size)
    h = rng.uniform(0.1, 0.45, x.size)
    return x, y, r, h


def dsm_array(plants, size=(700, 600)):
    """Terrain plus paraboloid plants ``h (1 - (d/r)^2)`` (leaf tips reach the soil)."""
    x, y, r, h = plants
    rows, cols = size
    X, Y = np.meshgrid((np.arange(cols) + 0.5) * RES, 7.0 - (np.arange(rows) + 0.5) * RES)
    Z = terrain(X, Y)
    for xi, yi, ri, hi in zip(x, y, r, h):
        d2 = ((X - xi) ** 2 + (Y - yi) ** 2) / ri**2
        Z = np.maximum(Z, np.where(d2 < 1, terrain(X, Y) + hi * (1 - d2), -np.inf))
    return Z, Affine(RES, 0, OFFSET[0], 0, -RES, OFFSET[1] + 7.0)


def surface_points(plants, n_theta=90, n_rho=12):
    x, y, r, h = plants
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    rho = np.linspace(0, 1, n_rho)
    R, T = np.meshgrid(rho, th)
    px = x[:, None] + r[:, None] * (R * np.cos(T)).ravel()
    py = y[:, None] + r[:, None] * (R * np.sin(T)).ravel()
    pz = terrain(px, py) + h[:, None] * (1 - R.ravel() ** 2)
    return np.stack([px, py, pz], axis=-1)


def pose(tilt_deg, heading_deg):
    cam_to_world = (
        Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
        @ Rotation.from_euler("x", 180 + tilt_deg, degrees=True).as_matrix()
    )
    return cam_to_world.T


def build_project(root: Path, *, tilt=0.0, heading=0.0, seed=0, fisheye=False):
    """Write an ODM-shaped project; return the truth (map boxes) and GT boxes on undistorted and raw images."""
    rng = np.random.default_rng(seed)
    plants = make_plants(rng)
    Z, transform = dsm_array(plants)
    w, h = 480, 360
    if fisheye:
        raw = FisheyeCamera(
            id="cam", projection_type="fisheye", width=w, height=h, focal_x=0.7, focal_y=0.7, k1=-0.02, k2=0.003
        )
    else:
        raw = PinholeCamera(
            id="cam",
            projection_type="brown",
            width=w,
            height=h,
            focal_x=0.85,
            focal_y=0.86,
            c_x=0.004,
            c_y=-0.003,
            k1=-0.08,
            k2=0.02,
            p1=0.001,
            p2=-0.0005,
        )
    und = PinholeCamera(id="cam", projection_type="perspective", width=w, height=h, focal_x=0.85, focal_y=0.85)
    shots_raw, shots_und = {}, {}
    for i, (cx, cy) in enumerate([(a, b) for b in (2.0, 3.2, 4.4) for a in (2.0, 3.2)]):
        back = 4.0 * np.tan(np.radians(tilt))  # oblique: stand back so the field stays in view
        c = np.array(
            [cx - back * np.sin(np.radians(heading)), cy - back * np.cos(np.radians(heading)), terrain(cx, cy) + 4.0]
        )
        R = pose(tilt, heading) @ Rotation.from_euler("xyz", rng.normal(0, 1.0, 3), degrees=True).as_matrix().T
        name = f"IMG_{i:03d}.JPG"
        shots_raw[name] = Shot.from_center(name, raw, R, c)
        shots_und[name] = Shot.from_center(name, und, R, c)
    ref = {"latitude": 40.6, "longitude": -96.6, "altitude": 0.0}
    write_odm_project(
        root,
        crs=CRS14,
        offset=OFFSET,
        reference_lla=ref,
        shots=shots_raw,
        undistorted_shots=shots_und,
        dsm=Raster(Z, transform),
        topocentric_copy=True,
        image_color=(90, 70, 50),
    )

    pts = surface_points(plants)
    x, y, r, _ = plants
    truth = np.stack([x - r, y - r, x + r, y + r], axis=1) + np.tile(OFFSET[:2], 2)
    gt = {}
    for kind, shots in (("undistorted", shots_und), ("raw", shots_raw)):
        images, anns = [], []
        for k, (name, shot) in enumerate(shots.items()):
            uv = shot.project(pts.reshape(-1, 3)).reshape(len(x), -1, 2)
            lo, hi = uv.min(axis=1) + 0.5, uv.max(axis=1) + 0.5  # centre coordinates -> COCO edges
            inside = np.isfinite(lo).all(1) & (lo > 0).all(1) & (hi[:, 0] < w) & (hi[:, 1] < h)
            fname = f"{name}.tif" if kind == "undistorted" else name
            images.append({"id": k + 1, "file_name": fname, "width": w, "height": h})
            for pid in np.flatnonzero(inside):
                anns.append(
                    {
                        "id": len(anns) + 1,
                        "image_id": k + 1,
                        "category_id": 1,
                        "score": 1.0,
                        "bbox": [*lo[pid], *(hi[pid] - lo[pid])],
                        "plant_id": int(pid + 1),
                    }
                )
        gt[kind] = {"images": images, "categories": [{"id": 1, "name": "maize"}], "predictions": anns}
    return truth, gt


def tiles_of(gt: dict, tile=240, overlap=40) -> dict:
    """The same boxes as seen on overlapping tiles (with source_image, x0, y0), boxes cut at tile borders."""
    images, preds = [], []
    by_image = {}
    for a in gt["predictions"]:
        by_image.setdefault(a["image_id"], []).append(a)
    for im in gt["images"]:
        for y0 in range(0, im["height"] - overlap, tile - overlap):
            for x0 in range(0, im["width"] - overlap, tile - overlap):
                tw, th = min(tile, im["width"] - x0), min(tile, im["height"] - y0)
                tid = len(images) + 1
                images.append(
                    {
                        "id": tid,
                        "file_name": f"{im['file_name']}_{x0}_{y0}.png",
                        "width": tw,
                        "height": th,
                        "source_image": im["file_name"],
                        "x0": x0,
                        "y0": y0,
                    }
                )
                for a in by_image.get(im["id"], []):
                    x, y, bw, bh = a["bbox"]
                    x1, y1 = max(x, x0), max(y, y0)
                    x2, y2 = min(x + bw, x0 + tw), min(y + bh, y0 + th)
                    if x2 - x1 > 3 and y2 - y1 > 3:
                        preds.append(dict(a, image_id=tid, bbox=[x1 - x0, y1 - y0, x2 - x1, y2 - y1]))
    return {"images": images, "categories": gt["categories"], "predictions": preds}


def project_and_score(root: Path, preds: dict, truth: np.ndarray, **kw):
    settings = ProjectionSettings.from_config(PlantProjectionConfig(**{k: v for k, v in kw.items() if k != "merge"}))
    views, rejected = project_predictions(ODMProject(root), preds, settings)
    plants = merge_views(views, merge=kw.get("merge", "nadir"))
    m = evaluate_boxes(truth, plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy())
    return views, rejected, plants, m


@pytest.fixture(scope="module")
def nadir_project(tmp_path_factory):
    root = tmp_path_factory.mktemp("nadir")
    truth, gt = build_project(root, tilt=0.0, heading=0.0)
    return root, truth, gt


# --------------------------------------------------------------------------------------------------
# geometry units


def test_ground_under_plants_is_the_terrain():
    """The ground estimated from the DSM (morphological opening) is the sloped terrain wherever the soil
    shows, within a cm or so under the plants, and keeps nothing of the plants (away from the raster's edges,
    where the window runs out of terrain)."""
    from matchplant.core.geometry.surface import Surface

    plants = make_plants(np.random.default_rng(3))
    Z, transform = dsm_array(plants)
    Z[300:304, 200:204] = np.nan  # a hole stays a hole: rays meeting the ground there are reported
    ground = Surface(Z, transform).ground(1.0)
    assert np.isnan(ground.sample(*(transform @ (202.0, 302.0))))
    rows, cols = np.mgrid[50:650:7, 50:550:7]  # half a window from the raster's edges
    x, y = transform @ (cols + 0.5, rows + 0.5)
    err = ground.sample(x, y) - terrain(x - OFFSET[0], y - OFFSET[1])
    soil = Z[rows, cols] - terrain(x - OFFSET[0], y - OFFSET[1]) < 1e-6
    assert np.isfinite(err).all()
    assert np.abs(err[soil]).max() < 0.004  # the ground cell is 2 cm: its lowest DSM cell, 6.5 % slope
    assert np.abs(err[~soil]).max() < 0.015 and err[~soil].max() < 0.015  # plants up to 0.45 m tall are gone


def test_settle_moves_exact_hits_and_keeps_grazing_ones():
    """A ray stopped 2 cm above the surface settles onto it when it meets it within 4 cm further down (the
    soil, a plant's side) and stays when it only grazed a top (the soil lies much further down)."""
    from matchplant.core.geometry.surface import Surface

    Z = np.zeros((200, 200))
    Z[90:110, 90:110] = 0.5  # a 20 cm block, 0.5 m tall
    s = Surface(Z, Affine(0.01, 0, 0, 0, -0.01, 2.0))
    d = np.array([[0.5, 0.0, -1.0], [0.5, 0.0, -1.0]])
    # one ray to flat soil at x = 0.51, one passing 1 cm over the block's far top edge (x = 1.095)
    o = np.array([[0.0, 1.0, 1.02], [0.585, 1.0, 1.53]])
    stopped, _, st = s.intersect(o, d, clearance=0.02)
    settled, _, st2 = s.intersect(o, d, clearance=0.02, settle=0.04)
    assert (st == HIT).all() and (st2 == HIT).all()
    np.testing.assert_allclose(stopped[0], [0.5, 1.0, 0.02], atol=1e-6)  # 2 cm above the soil
    np.testing.assert_allclose(settled[0], [0.51, 1.0, 0.0], atol=1e-6)  # on it
    assert stopped[1, 2] == pytest.approx(0.52, abs=1e-6) and stopped[1, 0] < 1.1  # grazing the top's edge
    np.testing.assert_allclose(settled[1], stopped[1])  # the soil is 0.5 m further down: it stays


@pytest.mark.slow
def test_rays_that_skimmed_a_plant_are_flagged():
    """A far-edge ray that passed just over a plant's top and landed on the soil behind it did not mark the
    plant's edge; one that landed on open soil did."""
    from matchplant.core.geometry.surface import Surface

    Z = np.zeros((200, 200))
    Z[90:110, 90:110] = 0.5  # a 20 cm plant, 0.5 m tall, x and y from 0.9 to 1.1
    s = Surface(Z, Affine(0.01, 0, 0, 0, -0.01, 2.0))
    cam = np.array([1.0, 1.0, 10.0])
    # the ray that clears the plant's last full-height point (the centre of its last cell, x = 1.095, z = 0.5)
    # by 5 cm lands on the soil just behind it
    skimmed_hit = np.array([1.0 + 0.095 * 10.0 / 9.45, 1.0, 0.0])
    open_hit = np.array([0.2, 0.2, 0.0])
    out = skimmed(np.array([skimmed_hit, open_hit]), Scene(s.raster, s.ground(1.0).raster, cam, 0.05, 0.1, 0.5))
    assert out.tolist() == [True, False]


def test_box_outline_runs_around_the_box():
    o = box_outline(np.array([[10, 20, 30, 60]]), 1)[0]
    assert o.shape == (8, 2)
    assert o[0].tolist() == [9.5, 19.5] and o[2].tolist() == [29.5, 19.5] and o[4].tolist() == [29.5, 59.5]
    assert o[:, 0].min() == 9.5 and o[:, 1].max() == 59.5


def test_inscribed_box_of_a_rotated_square_is_the_round_plants_box():
    a = np.radians(30)
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) @ np.array(
        [[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]
    )
    sq += [700000.0, 4500000.0]  # UTM-sized numbers must not lose precision
    box, c, area = outline_boxes(sq[None], "inscribed")
    assert np.allclose(box[0] - [700000, 4500000, 700000, 4500000], [-1, -1, 1, 1], atol=1e-6)
    assert area[0] == pytest.approx(4.0)
    env, _, _ = outline_boxes(sq[None], "outline")
    assert env[0, 2] - env[0, 0] == pytest.approx(2 * (np.cos(a) + np.sin(a)))


def test_iou_and_matching():
    a = np.array([[0, 0, 2, 2], [10, 10, 11, 11]], float)
    b = np.array([[1, 0, 3, 2], [0, 0, 2, 2]], float)
    assert iou_pairs(a[:1], b[:1])[0] == pytest.approx(1 / 3)
    match, iou = match_boxes(a, b)
    assert match.tolist() == [1, -1] and iou[0] == 1.0


# --------------------------------------------------------------------------------------------------
# projection against exact truth


def test_nadir_undistorted_boxes_land_on_the_plants(nadir_project):
    root, truth, gt = nadir_project
    views, rejected, plants, m = project_and_score(root, gt["undistorted"], truth)
    assert len(rejected) == 0
    assert m["iou_median"] >= 0.9, m
    assert m["share_iou_above_0.5"] >= 0.99, m
    assert len(plants) == len(truth)  # every plant once: many views merged, no duplicates
    assert plants["views"].min() >= 1 and plants["views"].max() > 2
    # the representative is the view closest to nadir among its plant's views
    best = views.table.groupby("plant_id")["off_nadir_deg"].min()
    assert np.allclose(plants.set_index("plant_id")["off_nadir_deg"], best)
    # truth ids travel through: each plant record holds views of one true plant only
    purity = views.table.groupby("plant_id")["truth_plant_id"].nunique()
    assert (purity == 1).mean() > 0.97
    # a side is seen across the plant when it faces away from the camera's nadir point: views well east of it
    # see their east side across the plant and their west side from its own side (and so on for each axis)
    project = ODMProject(root)
    t = views.table
    cam = np.array(
        [project.frame_of(s).to_map(project.shot(s, undistorted=True).center[None, :])[0, :2] for s in t["shot_id"]]
    )
    half = np.column_stack([t["xmax"] - t["xmin"], t["ymax"] - t["ymin"]]) / 2
    off = t[["cx", "cy"]].to_numpy() - cam
    for axis, (low, high) in enumerate([("across_w", "across_e"), ("across_s", "across_n")]):
        beyond = off[:, axis] > 2 * half[:, axis]  # the camera's nadir west (south) of the whole box
        before = off[:, axis] < -2 * half[:, axis]
        assert beyond.sum() > 20 and before.sum() > 20
        assert t[high][beyond].all() and not t[low][beyond].any()
        assert t[low][before].all() and not t[high][before].any()


@pytest.mark.parametrize("tilt,heading", [(25.0, 0.0), (20.0, 35.0)], ids=["oblique", "oblique-rotated"])
def test_oblique_flight_over_slope(tmp_path, tilt, heading):
    truth, gt = build_project(tmp_path, tilt=tilt, heading=heading, seed=1)
    views, rejected, plants, m = project_and_score(tmp_path, gt["undistorted"], truth)
    seen = np.unique([a["plant_id"] for a in gt["undistorted"]["predictions"]]) - 1
    m = evaluate_boxes(truth[seen], plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy())
    assert m["iou_median"] >= 0.9, m
    assert m["share_iou_above_0.5"] >= 0.99, m


def test_original_brown_images_give_the_same_plants(nadir_project):
    root, truth, gt = nadir_project
    _, rejected, plants, m = project_and_score(root, gt["raw"], truth)
    assert len(rejected) == 0
    assert m["iou_median"] >= 0.9 and m["share_iou_above_0.5"] >= 0.99, m


def test_original_fisheye_images(tmp_path):
    truth, gt = build_project(tmp_path, fisheye=True, seed=2)
    _, rejected, plants, m = project_and_score(tmp_path, gt["raw"], truth, image_type="original")
    assert len(rejected) == 0
    assert m["iou_median"] >= 0.9 and m["share_iou_above_0.5"] >= 0.99, m


def test_tiles_of_one_photo_become_one_plant(nadir_project):
    root, truth, gt = nadir_project
    tiled = tiles_of(gt["undistorted"])
    assert len(tiled["predictions"]) > len(gt["undistorted"]["predictions"])  # plants cut by tile borders
    views, rejected, plants, m = project_and_score(root, tiled, truth)
    assert len(plants) == len(truth)
    assert m["iou_median"] >= 0.9 and m["share_iou_above_0.5"] >= 0.99, m
    assert not plants["cut"].any()  # a whole view was preferred to a cut one


def test_fuse_and_none(nadir_project):
    root, truth, gt = nadir_project
    _, _, fused, m = project_and_score(root, gt["undistorted"], truth, merge="fuse")
    assert len(fused) == len(truth) and m["share_iou_above_0.5"] >= 0.99
    _, _, every, _ = project_and_score(root, gt["undistorted"], truth, merge="none")
    assert len(every) == len(gt["undistorted"]["predictions"])


# --------------------------------------------------------------------------------------------------
# boxes that cannot be projected are reported with the reason


def test_missing_image_nodata_and_outside_are_reported(tmp_path, nadir_project):
    import rasterio
    from rasterio.windows import Window

    src, truth, gt = nadir_project
    root = tmp_path / "copy"
    shutil.copytree(src, root)
    # remove one shot from the reconstruction
    rec_path = root / "opensfm" / "undistorted" / "reconstruction.json"
    rec = json.loads(rec_path.read_text())
    gone = "IMG_002.JPG"
    del rec[0]["shots"][gone]
    rec_path.write_text(json.dumps(rec))
    # punch a nodata hole just larger than one plant
    k = 10
    x, y = (truth[k, :2] + truth[k, 2:]) / 2
    half = int(np.ceil((truth[k, 2] - truth[k, 0]) / 2 / RES)) + 3
    with rasterio.open(root / "odm_dem" / "dsm.tif", "r+") as dst:
        z = dst.read(1)
        r, c = dst.index(x, y)
        z[r - half : r + half, c - half : c + half] = -9999
        dst.write(z, 1)
    preds = gt["undistorted"]
    views, rejected, plants, _ = project_and_score(root, preds, truth)
    truth_id = np.array([a["plant_id"] for a in preds["predictions"]])
    name = {im["id"]: im["file_name"] for im in preds["images"]}
    in_gone = np.array([name[a["image_id"]] == gone + ".tif" for a in preds["predictions"]])
    miss = rejected[rejected["reason"] == NOT_IN_RECONSTRUCTION]
    assert sorted(miss["pred_index"]) == list(np.flatnonzero(in_gone))
    hole = rejected[rejected["reason"].str.contains("nodata")]
    assert sorted(hole["pred_index"]) == list(np.flatnonzero((truth_id == k + 1) & ~in_gone))
    assert len(views.table) + len(rejected) == len(preds["predictions"])  # nothing dropped silently
    assert len(plants) == len(truth) - 1

    # a DSM that covers only the western half: boxes beyond it are reported as outside
    with rasterio.open(root / "odm_dem" / "dsm.tif") as full:
        half_w = full.width // 2
        profile = dict(full.profile, width=half_w, transform=full.window_transform(Window(0, 0, half_w, full.height)))
        data = full.read(1, window=Window(0, 0, half_w, full.height))
    with rasterio.open(tmp_path / "west.tif", "w", **profile) as dst:
        dst.write(data, 1)
    views, rejected, _, _ = project_and_score(root, preds, truth, dsm=tmp_path / "west.tif")
    east = truth[:, 0] > OFFSET[0] + half_w * RES + 0.3  # plants well beyond the DSM's edge
    out = rejected[rejected["reason"] == STATUS_TEXT[OUTSIDE]]
    assert set(np.flatnonzero(east) + 1) <= set(truth_id[out["pred_index"]])
    assert not (set(views.table["truth_plant_id"]) & set(np.flatnonzero(east) + 1))


def test_run_writes_outputs_and_reports(tmp_path, nadir_project):
    import geopandas as gpd

    src, truth, gt = nadir_project
    preds = dict(gt["undistorted"])
    preds["images"] = preds["images"] + [{"id": 99, "file_name": "NOT_FLOWN.JPG.tif", "width": 480, "height": 360}]
    preds["predictions"] = preds["predictions"] + [
        {"image_id": 99, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9},
        {"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.1},
    ]
    (tmp_path / "preds.json").write_text(json.dumps(preds))
    pd.DataFrame(truth, columns=["xmin", "ymin", "xmax", "ymax"]).to_csv(tmp_path / "ref.csv", index=False)
    cfg = load_config(
        PlantProjectionConfig,
        None,
        [
            f"project={src}",
            f"predictions={tmp_path / 'preds.json'}",
            f"output_dir={tmp_path / 'out'}",
            "mode=both",
            f"evaluate.reference={tmp_path / 'ref.csv'}",
            "vector_formats=[gpkg, shp]",
        ],
    )
    result = run(cfg)
    out = tmp_path / "out"
    gdf = gpd.read_file(out / "plants.gpkg", layer="plants")
    assert gdf.crs.to_epsg() == 32614 and len(gdf) == len(truth)
    assert {"plant_id", "source_image", "score", "category", "views", "spread_m"} <= set(gdf.columns)
    assert gdf.geometry.is_valid.all()
    csv = pd.read_csv(out / "plants.csv")
    assert list(csv["plant_id"]) == list(gdf["plant_id"])
    assert (out / "plants.shp").is_file() and (out / "plants.prj").is_file()
    rep = pd.read_csv(out / "unprojected_boxes.csv")
    assert rep["reason"].tolist() == [NOT_IN_RECONSTRUCTION]
    summary = json.loads((out / "projection_summary.json").read_text())
    assert summary["below_min_score"] == 1 and summary["not_projected"] == 1
    ev = json.loads((out / "evaluation.json").read_text())
    assert ev["share_iou_above_0.5"] >= 0.99 and (out / "evaluation.png").stat().st_size > 10_000
    assert result["evaluation"]["iou_median"] >= 0.9


def test_coco_reference_over_orthophoto(tmp_path, nadir_project):
    """Reference boxes drawn in orthophoto pixels are placed on the map through its transform."""
    import rasterio

    _, truth, _ = nadir_project
    t = Affine(0.005, 0, OFFSET[0], 0, -0.005, OFFSET[1] + 7.0)
    ortho = tmp_path / "ortho.tif"
    with rasterio.open(
        ortho, "w", driver="GTiff", width=1200, height=1400, count=3, dtype="uint8", crs=CRS14, transform=t
    ) as dst:
        dst.write(np.full((3, 1400, 1200), 120, np.uint8))
    inv = ~t
    anns = []
    for k, (x1, y1, x2, y2) in enumerate(truth):
        c1, r1 = inv @ (x1, y2)
        c2, r2 = inv @ (x2, y1)
        anns.append({"id": k + 1, "image_id": 1, "category_id": 1, "bbox": [c1, r1, c2 - c1, r2 - r1]})
    coco = {
        "images": [{"id": 1, "file_name": "ortho.tif", "width": 1200, "height": 1400}],
        "annotations": anns,
        "categories": [{"id": 1, "name": "maize"}],
    }
    (tmp_path / "ref.json").write_text(json.dumps(coco))
    boxes = read_boxes(tmp_path / "ref.json", orthophoto=ortho)
    assert np.allclose(boxes, truth, atol=1e-6)


# --------------------------------------------------------------------------------------------------
# errors and the folder


def test_bad_inputs_are_clear_errors(tmp_path, nadir_project):
    root, _, _ = nadir_project
    with pytest.raises(MatchPlantError, match="predictions"):
        load_config(PlantProjectionConfig, None, [f"project={root}", f"output_dir={tmp_path}"])
    (tmp_path / "p.json").write_text("[1, 2")
    cfg = load_config(
        PlantProjectionConfig, None, [f"project={root}", f"predictions={tmp_path / 'p.json'}", f"output_dir={tmp_path}"]
    )
    with pytest.raises(MatchPlantError, match="truncated|not valid JSON"):
        run(cfg)
    with pytest.raises(MatchPlantError, match="evaluate.reference"):
        load_config(PlantProjectionConfig, None, ["mode=evaluate", f"output_dir={tmp_path}"])


def test_resolve_images_matches_names_that_differ_by_case_or_extension():
    und = orig = {"IMG_1.JPG", "IMG_2.JPG", "IMG_2.DNG", "A"}
    names = ["IMG_1.JPG.tif", "IMG_1.tif", "img_1.jpg.tif", "IMG_1.jpg", "A.tif", "IMG_2.tif", "IMG_9.JPG.tif"]
    got, hints = resolve_images(names, und, orig)
    assert got["IMG_1.JPG.tif"] == ("IMG_1.JPG", True)  # ODM's own name
    assert got["IMG_1.tif"] == got["img_1.jpg.tif"] == ("IMG_1.JPG", True)  # extension or case differ
    assert got["IMG_1.jpg"] == ("IMG_1.JPG", False)  # an original photo
    assert got["A.tif"] == ("A", True)
    assert got["IMG_2.tif"][0] is None and got["IMG_9.JPG.tif"][0] is None  # ambiguous (JPG, DNG); unknown
    assert "did you mean" in hints["IMG_9.JPG.tif"]
    got, _ = resolve_images(["IMG_1.jpg.tif"], und, orig, image_type="original")
    assert got["IMG_1.jpg.tif"][0] is None  # boxes said to be on originals are not moved to undistorted images


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: {"images": d["images"], "annotations": d["predictions"]}, "COCO dataset"),
        (lambda d: d["predictions"], "images_from"),
        (lambda d: dict(d, predictions=[]), "no detections"),
        (lambda d: dict(d, predictions=[dict(d["predictions"][0], bbox=[1, 2, float("nan"), 3])]), r"predictions\[0\]"),
        (lambda d: dict(d, predictions=[dict(d["predictions"][0], bbox=[10, 10, -3, 3])]), "negative"),
        (lambda d: dict(d, predictions=[dict(d["predictions"][0], score=87)]), "percentage"),
    ],
)
def test_read_predictions_names_what_is_wrong(tmp_path, nadir_project, change, message):
    _, _, gt = nadir_project
    path = tmp_path / "p.json"
    path.write_text(json.dumps(change(json.loads(json.dumps(gt["undistorted"])))))
    with pytest.raises(MatchPlantError, match=message) as err:
        read_predictions(path, every_box=True)
    assert "p.json" in str(err.value) and "fix:" in str(err.value)


def test_folder_config_and_help():
    cfg = load_config(PlantProjectionConfig, FOLDER / "config.yaml", check_paths=False, strict=False)
    assert cfg.mode == "project" and cfg.merge == "nadir"
    r = subprocess.run(
        [sys.executable, str(FOLDER / "plant_projection.py"), "--help"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0 and "--predictions" in r.stdout


# --------------------------------------------------------------------------------------------------
# the synthetic field (matchplant.simfield): projecting its ground-truth image boxes


def gt_predictions(field, raw=False) -> dict:
    from matchplant.core.formats.coco import read_dataset

    ds = read_dataset(field.boxes_raw if raw else field.boxes_undistorted, validate=False)
    return {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }


def score_field(field, raw=False, merge="nadir"):
    views, rejected = project_predictions(ODMProject(field.root), gt_predictions(field, raw))
    plants = merge_views(views, merge=merge)
    truth = pd.read_csv(field.map_boxes)[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
    return rejected, plants, evaluate_boxes(truth, plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy()), truth


@pytest.mark.parametrize("raw", [False, True], ids=["undistorted", "raw-brown"])
def test_synthetic_field_nadir(tiny_field, raw):
    rejected, plants, m, truth = score_field(tiny_field, raw)
    assert len(rejected) == 0
    assert m["iou_median"] >= 0.9, m
    assert m["share_iou_above_0.5"] >= 0.99, m
    assert len(plants) == len(truth)  # one record per plant


def test_dsm_read_per_image_gives_the_same_plants(tiny_field, monkeypatch):
    """A DSM too large for memory is read image by image (each window padded for the ground estimate): the
    boxes agree with those from the DSM read once."""
    preds = gt_predictions(tiny_field)
    ref, _ = project_predictions(ODMProject(tiny_field.root), preds)
    monkeypatch.setattr(dsm, "MAX_SURFACE_CELLS", 1000)
    got, rejected = project_predictions(ODMProject(tiny_field.root), preds)
    assert len(rejected) == 0 and len(got.table) == len(ref.table)
    cols = ["xmin", "ymin", "xmax", "ymax"]
    err = np.abs(got.table[cols].to_numpy() - ref.table[cols].to_numpy()).max(axis=1)
    assert np.median(err) < 0.001 and (err < 0.01).mean() >= 0.98, np.quantile(err, [0.5, 0.9, 1.0])


def test_topocentric_reconstruction_gives_the_same_plants(tiny_field, tmp_path):
    """Plain OpenSfM / older ODM: the reconstruction is topocentric (its reference_lla does not match the
    coords.txt offset). The reader must detect it, and the plants must land where the UTM-offset
    reconstruction puts them, within 1 cm."""
    from dataclasses import replace

    from matchplant.core.formats.reconstruction import read_reconstruction
    from matchplant.core.geometry.frames import TopocentricFrame, read_coords_txt

    root = tmp_path / "topo"
    shutil.copytree(tiny_field.root, root, ignore=shutil.ignore_patterns("images*", "*.JPG", "multispectral"))
    osfm = root / "opensfm"
    topo = read_reconstruction(osfm / "reconstruction.topocentric.json")
    und = read_reconstruction(osfm / "undistorted" / "reconstruction.json")
    ucam = next(iter(und.cameras.values()))
    (osfm / "reconstruction.topocentric.json").replace(osfm / "reconstruction.json")
    write_reconstruction(
        osfm / "undistorted" / "reconstruction.json",
        replace(topo, cameras={ucam.id: ucam}, shots={k: v.with_camera(ucam) for k, v in topo.shots.items()}),
    )
    crs, offset = read_coords_txt(root / "odm_georeferencing" / "coords.txt")
    write_coords_txt(root / "odm_georeferencing" / "coords.txt", crs, offset + [1.0, 1.0, 0.0])  # older ODM
    assert isinstance(ODMProject(root).frame(), TopocentricFrame)
    for raw in (False, True):
        preds = gt_predictions(tiny_field, raw)
        ref, _ = project_predictions(ODMProject(tiny_field.root), preds)
        got, rejected = project_predictions(ODMProject(root), preds)
        assert len(rejected) == 0 and len(got.table) == len(ref.table)
        # the ray hits agree within 1 cm (in fact to a fraction of a mm)...
        ray_err = np.linalg.norm(got.outlines() - ref.outlines(), axis=-1)
        assert np.median(ray_err) < 0.001 and (ray_err < 0.01).mean() >= 0.995
        # ...and so do the boxes, bar a rare grazing ray that stops on the other side of the clearance
        cols = ["xmin", "ymin", "xmax", "ymax", "cx", "cy"]
        box_err = np.abs(got.table[cols].to_numpy() - ref.table[cols].to_numpy()).max(axis=1)
        assert (box_err < 0.01).mean() >= 0.97 and np.median(box_err) < 0.001  # 1 box in 49 may graze
        assert got.crs.equals(ref.crs)


def test_plain_coco_results_list_with_images_from(tiny_field, tmp_path, nadir_project):
    """A plain COCO results list has no image names: images_from (the dataset it was run on) gives them."""
    root, truth, gt = nadir_project
    preds = gt["undistorted"]
    dataset = {"images": preds["images"], "categories": preds["categories"], "annotations": []}
    (tmp_path / "images.json").write_text(json.dumps(dataset))
    results = [{k: a[k] for k in ("image_id", "category_id", "bbox", "score")} for a in preds["predictions"]]
    (tmp_path / "results.json").write_text(json.dumps(results))
    over = [f"project={root}", f"predictions={tmp_path / 'results.json'}", f"output_dir={tmp_path / 'out'}"]
    cfg = load_config(PlantProjectionConfig, None, over + [f"images_from={tmp_path / 'images.json'}"])
    summary = run(cfg)["projection"]
    assert summary["projected_boxes"] == len(results) and summary["plants"] == len(truth)
    plants = pd.read_csv(tmp_path / "out" / "plants.csv")
    m = evaluate_boxes(truth, plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy())
    assert m["share_iou_above_0.5"] >= 0.99, m
    with pytest.raises(MatchPlantError, match="plain COCO results list"):
        run(load_config(PlantProjectionConfig, None, over))


@pytest.fixture(scope="module", params=[1, 2], ids=["seed1", "seed2"])
def oblique_field(tmp_path_factory, request):
    from matchplant.simfield import generate_field

    return generate_field(
        preset="tiny", seed=request.param, out=tmp_path_factory.mktemp("oblique"), tilt_deg=20, slope_pct=10
    )


@pytest.mark.slow
def test_synthetic_field_oblique_over_slope(oblique_field):
    """Forward-tilted camera (20 degrees) over a 10 % slope, a 3 m flight over plants up to 0.6 m tall: plants
    are seen 15-38 degrees off nadir, their far sides lie behind their tops and many are partly hidden behind a
    taller neighbour. Edges facing the nadir meet the ground; hidden sides come from other views or mirroring."""
    field = oblique_field
    rejected, plants, m, truth = score_field(field)
    assert len(rejected) == 0
    assert m["iou_median"] >= 0.9, m
    assert m["share_iou_above_0.5"] >= 0.99, m
    # one record per plant, bar at most one duplicate at the field's edge (seen only 27-38 degrees off nadir)
    assert len(truth) <= len(plants) <= len(truth) + 1
