"""Module 3 (min_images): footprints, area of interest, selection vs the integer-program optimum, owned areas,
outputs, the numbered folder and the GUI."""

from __future__ import annotations

import csv
import itertools
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
from odm_builder import Raster, write_odm_project
from pyproj import CRS, Transformer
from rasterio.transform import from_origin
from scipy import sparse
from scipy.spatial.transform import Rotation
from shapely.geometry import box

from matchplant.core.geometry.camera import PinholeCamera
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import InputError
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.owned import owned_areas
from matchplant.min_img_finder.run import MinImageFinder
from matchplant.min_img_finder.setcover import CoverageGrid, select_greedy, select_milp

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "3_min_img_finder"
OFFSET = (700000.0, 4500000.0)


# --------------------------------------------------------------------------------------------------
# a small hand-built ODM project: a lawn-mower grid of nadir cameras over a sloped, bumpy DSM


def dsm_height(x, y):
    """Terrain (relative to the offset): 2 % slope east plus bumps (plants) up to 0.4 m."""
    return 300.0 + 0.02 * x + 0.4 * np.clip(np.sin(x * 3.0) * np.sin(y * 2.5), 0, None)


def make_project(
    root: Path,
    nx: int = 4,
    ny: int = 3,
    spacing=(2.0, 1.5),
    altitude: float = 6.0,
    size=(80, 60),
    focal: float = 1.0,
    tilt_deg: float = 0.0,
    ortho_margin: float = 1.2,
) -> Path:
    crs = CRS.from_epsg(32614)
    lon, lat = Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True).transform(*OFFSET)
    w, h = size
    cam = PinholeCamera(id="cam", projection_type="perspective", width=w, height=h, focal_x=focal, focal_y=focal)
    nadir = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    tilt = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    shots = {}
    for j in range(ny):
        for i in range(nx):
            name = f"IMG_{j * nx + i:04d}.JPG"
            cx, cy = 1.0 + i * spacing[0], 1.0 + j * spacing[1]
            centre = np.array([cx, cy, float(dsm_height(cx, cy)) + altitude])
            shots[name] = Shot.from_center(name, cam, tilt @ nadir, centre)
    res = 0.02
    x0, y0 = -4.0, -4.0
    cols, rows = int((nx * spacing[0] + 10) / res), int((ny * spacing[1] + 10) / res)
    xs = x0 + (np.arange(cols) + 0.5) * res
    ys = y0 + rows * res - (np.arange(rows) + 0.5) * res
    X, Y = np.meshgrid(xs, ys)
    transform = from_origin(OFFSET[0] + x0, OFFSET[1] + y0 + rows * res, res, res)
    # orthophoto valid where the cameras' centres are within a margin (a rectangle with a notch)
    valid = (
        (X > 1.0 - ortho_margin)
        & (X < 1.0 + (nx - 1) * spacing[0] + ortho_margin)
        & (Y > 1.0 - ortho_margin)
        & (Y < 1.0 + (ny - 1) * spacing[1] + ortho_margin)
    )
    valid &= ~((X > 1.0 + (nx - 1) * spacing[0] + ortho_margin - 0.8) & (Y < 1.0 - ortho_margin + 0.8))
    rgba = np.zeros((4, rows, cols), dtype="uint8")
    rgba[1] = 140
    rgba[3] = np.where(valid, 255, 0)
    return write_odm_project(
        root,
        crs=crs,
        offset=OFFSET,
        shots=shots,
        reference_lla={"latitude": lat, "longitude": lon, "altitude": 0.0},
        dsm=Raster(dsm_height(X, Y), transform),
        orthophoto=Raster(rgba, transform),
    )


def cfg_for(project: Path, out: Path, *overrides: str) -> MinImgFinderConfig:
    return load_config(MinImgFinderConfig, None, [f"project_dir={project}", f"output_dir={out}", *overrides])


@pytest.fixture(scope="module")
def small_project(tmp_path_factory):
    return make_project(tmp_path_factory.mktemp("mini") / "project with space")


@pytest.fixture(scope="module")
def finder(small_project, tmp_path_factory):
    return MinImageFinder(cfg_for(small_project, tmp_path_factory.mktemp("out"), "dsm_resolution=0"))


# --------------------------------------------------------------------------------------------------
# footprints


def brute_force_ground(shot, uv, frame, dsm_path):
    """Independent ray-DSM intersection: fine steps along the ray, the DSM read with rasterio (nearest
    cell, no interpolation), the crossing refined linearly. Tolerance is set by the 2 cm DSM cells."""
    import rasterio

    with rasterio.open(dsm_path) as src:
        data = src.read(1)
        inv = ~src.transform
    c = frame.to_map(shot.center[None, :])[0]
    d = shot.ray_directions(uv)
    out = []
    for di in d:
        s = np.arange(0, 40, 0.0005)
        p = c + s[:, None] * di
        col, row = inv @ (p[:, 0], p[:, 1])
        z = data[np.clip(row.astype(int), 0, data.shape[0] - 1), np.clip(col.astype(int), 0, data.shape[1] - 1)]
        k = int(np.argmax(p[:, 2] <= z))
        out.append(p[k])
    return np.array(out)


@pytest.mark.independent
def test_footprint_corners_are_ray_dsm_intersections(finder, small_project):
    fp = finder.footprints[5]
    w, h = fp.shot.camera.width, fp.shot.camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    truth = brute_force_ground(fp.shot, corners, finder.frame, small_project / "odm_dem/dsm.tif")
    verts = np.asarray(fp.polygon.exterior.coords)[:-1]
    for t in truth:  # each corner is a vertex of the footprint polygon
        assert np.min(np.hypot(*(verts - t[:2]).T)) < 0.01
    # every border vertex lies on the DSM and projects back onto the image border
    assert fp.hit.all()
    from matchplant.core.geometry.ground import ground_to_pixels

    np.testing.assert_allclose(ground_to_pixels(fp.shot, fp.border, finder.frame), fp.border_uv, atol=1e-6)
    z = finder.surface.sample(fp.border[:, 0], fp.border[:, 1])
    np.testing.assert_allclose(fp.border[:, 2], z, atol=2e-3)
    # not a rectangle: the relief bends the outline (bumps up to 0.4 m at 6 m altitude)
    assert fp.polygon.area < box(*fp.polygon.bounds).area


def test_footprint_of_tilted_camera_is_a_trapezoid(tmp_path):
    project = make_project(tmp_path / "p", nx=2, ny=2, tilt_deg=20.0)
    f = MinImageFinder(cfg_for(project, tmp_path / "o", "dsm_resolution=0", "uncovered_threshold=50"))
    xy = np.asarray(f.footprints[0].polygon.exterior.coords)[:-1]
    far = xy[:, 1] > np.median(xy[:, 1])
    width_far = np.ptp(xy[far, 0])
    width_near = np.ptp(xy[~far, 0])
    assert abs(width_far - width_near) > 0.1  # a box around an orthophoto would hide this


# --------------------------------------------------------------------------------------------------
# area of interest


def test_aoi_is_the_orthophoto_valid_area(finder):
    nx, ny, sp, m = 4, 3, (2.0, 1.5), 1.2
    expected = box(
        OFFSET[0] + 1 - m, OFFSET[1] + 1 - m, OFFSET[0] + 1 + (nx - 1) * sp[0] + m, OFFSET[1] + 1 + (ny - 1) * sp[1] + m
    )
    notch = box(expected.bounds[2] - 0.8, expected.bounds[1], expected.bounds[2], expected.bounds[1] + 0.8)
    expected = expected.difference(notch)
    assert finder.aoi.symmetric_difference(expected).area / expected.area < 0.02


def test_aoi_from_user_polygon_file(small_project, tmp_path):
    import geopandas as gpd

    field = box(OFFSET[0] + 1.5, OFFSET[1] + 1.2, OFFSET[0] + 5.0, OFFSET[1] + 3.5)
    wgs = gpd.GeoDataFrame(geometry=[field], crs="EPSG:32614").to_crs("EPSG:4326")  # another CRS on purpose
    wgs.to_file(tmp_path / "field.geojson", driver="GeoJSON")
    f = MinImageFinder(cfg_for(small_project, tmp_path / "o", f"aoi_file={tmp_path / 'field.geojson'}"))
    assert f.aoi.symmetric_difference(field).area / field.area < 1e-3
    sel = f.select()
    assert f.exact_coverage(sel.indices) >= 0.95 - 1e-9


def test_bad_aoi_file_is_a_clear_error(small_project, tmp_path):
    (tmp_path / "empty.geojson").write_text('{"type": "FeatureCollection", "features": []}')
    with pytest.raises(InputError, match="no polygon"):
        MinImageFinder(cfg_for(small_project, tmp_path / "o", f"aoi_file={tmp_path / 'empty.geojson'}"))


# --------------------------------------------------------------------------------------------------
# selection


@pytest.mark.parametrize("uncovered", [0.0, 5.0, 20.0])
def test_coverage_at_least_requested_and_near_the_optimum(finder, uncovered):
    target = 1 - uncovered / 100
    grid = finder.grid
    greedy = select_greedy(grid, target, max_overlap=1.0, overlap_penalty=0.2)
    best = select_milp(grid, target, max_overlap=1.0, time_limit=30)
    assert best.optimal
    reach = min(target, finder.exact_coverage(range(len(finder.footprints))))
    assert greedy.coverage >= target - 1e-9 or greedy.coverage >= reach - 1e-9
    assert best.coverage >= min(target, grid.coverage(range(len(finder.footprints)))) - 1e-9
    assert len(greedy.indices) <= 1.1 * len(best.indices) + 1e-9, (len(greedy.indices), len(best.indices))
    # the optimum is a lower bound no selection can beat: all subsets one smaller miss the target
    assert len(best.indices) <= len(greedy.indices)


def test_overlap_cap_is_respected_or_reported(finder):
    grid = finder.grid
    frac = grid.overlap_fraction()
    sel = select_greedy(grid, 0.8, max_overlap=0.5, overlap_penalty=0.2)
    pairs = [frac[i, j] for i in sel.indices for j in sel.indices if i < j]
    assert sel.relaxed or max(pairs, default=0) <= 0.5 + 1e-9
    best = select_milp(grid, 0.8, max_overlap=0.5, time_limit=30)
    if not best.relaxed:
        assert max((frac[i, j] for i in best.indices for j in best.indices if i < j), default=0) <= 0.5 + 1e-9
        assert len(sel.indices) <= 1.1 * len(best.indices) + 1e-9


@pytest.mark.slow
def test_selection_on_generated_flights_vs_milp(tmp_path):
    """Several flight layouts and thresholds (not chosen to pass): in total the greedy selection uses at most
    10 % more images than the integer-program optimum, never more than one extra, and always reaches the
    requested coverage. (Optima here are 2-6 images, where one extra image is already +17-50 %.)"""
    greedy_total = optimum_total = 0
    for k, (nx, ny, spacing) in enumerate([(5, 3, (1.2, 1.1)), (8, 6, (1.0, 0.8)), (10, 7, (0.6, 0.5))]):
        project = make_project(tmp_path / f"p{k}", nx=nx, ny=ny, spacing=spacing, size=(40, 30))
        f = MinImageFinder(cfg_for(project, tmp_path / "o", "max_overlap=100", "cell_size=0.04"))
        for uncovered in (0, 2, 10):
            f.cfg.uncovered_threshold = uncovered
            g = f.select()
            best = select_milp(f.grid, 1 - uncovered / 100, 1.0, time_limit=30)
            assert best.optimal
            assert f.exact_coverage(g.indices) >= 1 - uncovered / 100 - 1e-9
            assert len(best.indices) <= len(g.indices) <= len(best.indices) + 1, (nx, ny, uncovered)
            greedy_total += len(g.indices)
            optimum_total += len(best.indices)
    assert greedy_total <= 1.1 * optimum_total, (greedy_total, optimum_total)


def hand_grid(A: np.ndarray, weights=None) -> CoverageGrid:
    """A coverage grid from a dense 0/1 matrix (images x cells), cells laid out left to right."""
    m = A.shape[1]
    return CoverageGrid(
        x=np.arange(m, dtype=float),
        y=np.zeros(m),
        cell=1.0,
        A=sparse.csr_matrix(A.astype(bool)),
        weights=np.ones(m) if weights is None else np.asarray(weights, float),
    )


def brute_force_cover(A: np.ndarray, w: np.ndarray, target: float, cap: float = 1.0) -> list[int] | None:
    """The fewest rows of ``A`` covering ``target`` of the weight (or all the rows can cover), no two chosen
    rows sharing more than ``cap`` of the smaller one's weight: every subset, smallest first."""
    A = A.astype(bool)
    area = A @ w
    shared = (A * w) @ A.T
    need = min(target, w[A.any(axis=0)].sum() / w.sum()) * w.sum() * (1 - 1e-9)
    for k in range(1, A.shape[0] + 1):
        for rows in itertools.combinations(range(A.shape[0]), k):
            if w[A[list(rows)].any(axis=0)].sum() >= need and all(
                shared[i, j] <= (cap + 1e-9) * min(area[i], area[j]) for i, j in itertools.combinations(rows, 2)
            ):
                return list(rows)
    return None


def test_solver_on_hand_made_arrays_greedy_trap():
    """The textbook case where plain greedy is not optimal: two rows of 7 cells (R1, R2) are the optimum, but
    S1 (4 + 4 cells) is larger than either, then S2 (2 + 2) and S3 (1 + 1) - three images."""
    A = np.zeros((5, 14), dtype=int)
    A[0, 0:7] = 1  # R1
    A[1, 7:14] = 1  # R2
    A[2, [0, 1, 2, 3, 7, 8, 9, 10]] = 1  # S1
    A[3, [4, 5, 11, 12]] = 1  # S2
    A[4, [6, 13]] = 1  # S3
    grid = hand_grid(A)
    assert sorted(brute_force_cover(A, grid.weights, 1.0)) == [0, 1]
    best = select_milp(grid, 1.0)
    assert best.optimal and sorted(best.indices) == [0, 1] and best.coverage == pytest.approx(1.0)
    plain = select_greedy(grid, 1.0, overlap_penalty=0.0, restarts=False)
    assert sorted(plain.indices) == [2, 3, 4] and plain.coverage == pytest.approx(1.0)
    assert sorted(select_greedy(grid, 1.0).indices) == [0, 1]  # restarts from other images find the optimum


@pytest.mark.slow
@pytest.mark.independent
def test_solver_on_random_arrays_matches_brute_force():
    """Small random incidence matrices and weights, with and without an overlap cap, against every subset:
    both solvers return valid selections (coverage reached; cap kept unless they say they relaxed it, which the
    integer program does only when no subset keeps it), neither beats the brute-force optimum, and the
    integer program finds it (but for the HiGHS miss of the next test)."""
    rng = np.random.default_rng(7)
    checked, misses = 0, []
    for _ in range(40):
        n, m = int(rng.integers(4, 9)), int(rng.integers(6, 18))
        A = (rng.random((n, m)) < 0.35).astype(int)
        grid = hand_grid(A, rng.uniform(0.5, 2.0, m))
        w = grid.weights
        frac = grid.overlap_fraction()
        reach = w[A.any(axis=0)].sum() / w.sum()
        for target, cap in itertools.product((1.0, 0.9, 0.7), (1.0, 0.5)):
            need = min(target, reach) - 1e-6
            free = brute_force_cover(A, w, target)
            capped = brute_force_cover(A, w, target, cap)
            best = select_milp(grid, target, max_overlap=cap)
            greedy = select_greedy(grid, target, max_overlap=cap)
            assert best.relaxed == (capped is None)
            for sel in (best, greedy):
                assert sel.coverage >= need and len(sel.indices) >= len(free)
                if not sel.relaxed:
                    assert len(sel.indices) >= len(capped)
                    assert all(frac[i, j] <= cap + 1e-9 for i, j in itertools.combinations(sel.indices, 2))
            if len(best.indices) != len(capped or free):
                misses.append((A.tolist(), target, cap))
            checked += 1
    assert checked == 240 and len(misses) <= 2, misses


@pytest.mark.xfail(
    reason="HiGHS 1.12 (scipy 1.17) proves 5 images optimal where 4 cover everything (its dual "
    "bound is above the LP relaxation's 3.5); with the area variables integer it finds 4"
)
def test_milp_finds_the_brute_force_optimum_where_highs_misses():
    A = np.array(
        [
            [0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 1, 1, 0],
            [0, 0, 0, 0, 0, 0, 1, 1, 0, 1, 1, 0, 0],
            [0, 0, 0, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1],
            [1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1],
            [0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 1, 0, 1],
            [0, 1, 0, 1, 0, 1, 0, 0, 1, 0, 0, 0, 0],
            [1, 1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 1, 0],
            [0, 0, 1, 0, 1, 0, 1, 1, 0, 0, 0, 0, 0],
        ]
    )
    w = np.array(
        [
            1.016316,
            1.38543647,
            1.52552656,
            1.03312067,
            1.27864773,
            1.64787107,
            1.86376897,
            0.72659342,
            1.90012909,
            0.5077683,
            1.62946626,
            1.71579025,
            0.70514608,
        ]
    )
    assert brute_force_cover(A, w, 1.0) == [0, 1, 2, 6]
    assert len(select_milp(hand_grid(A, w), 1.0).indices) == 4


def test_grid_coverage_matches_polygon_coverage(finder):
    sel = finder.select()
    assert abs(sel.coverage - finder.exact_coverage(sel.indices)) < 0.02


# --------------------------------------------------------------------------------------------------
# owned areas


def test_owned_areas_partition_the_covered_field(finder):
    sel = finder.select()
    result = finder.evaluate(sel)
    owned = list(result.owned.values())
    covered = shapely.union_all([fp.polygon for fp in result.selected]).intersection(finder.aoi)
    total = sum(o.area for o in owned)
    assert total == pytest.approx(covered.area, rel=1e-6)  # nothing lost
    for a in range(len(owned)):  # nothing owned twice
        for b in range(a + 1, len(owned)):
            assert owned[a].intersection(owned[b]).area < 1e-6
    for fp in result.selected:  # an image owns only what it sees
        assert result.owned[fp.name].difference(fp.polygon).area < 1e-6


def test_owned_area_in_pixels_maps_back_to_the_ground(finder):
    from matchplant.core.geometry.ground import pixels_to_ground

    result = finder.evaluate(finder.select())
    for fp in result.selected:
        uv = result.owned_pixels[fp.name]
        assert len(uv) >= 3
        w = fp.shot.camera.width
        assert (uv[:, 0] >= -0.5).all() and (uv[:, 0] <= w - 0.5).all()
        ground, status = pixels_to_ground(fp.shot, uv, finder.frame, finder.surface)
        owned = result.owned[fp.name]
        d = shapely.distance(owned.boundary, shapely.points(ground[:, :2]))
        # the pixel outline lands back on the owned area's outline; where a 0.4 m bump hides the ground point
        # from the camera the ray stops on the bump first, a few cm away
        assert np.nanpercentile(d, 90) < 0.005 and np.nanmax(d) < 0.05


def test_each_point_of_the_field_owned_once():
    """Voronoi part plus leftover pieces on a case where the nearest centre does not see everything."""
    aoi = box(0, 0, 10, 4)
    fps = [box(0, 0, 6, 4), box(5, 0, 10, 2), box(5.5, 1.5, 10, 4)]
    own = owned_areas(aoi, fps)
    assert sum(o.area for o in own) == pytest.approx(40.0)
    assert shapely.union_all(own).area == pytest.approx(40.0)
    for o, f in zip(own, fps):
        assert o.difference(f).area < 1e-9


# --------------------------------------------------------------------------------------------------
# outputs, CLI and folder


@pytest.mark.slow
def test_run_writes_every_output(small_project, tmp_path, monkeypatch):
    import matchplant.min_img_finder.output as output
    from matchplant.core.runtime import gui
    from matchplant.min_img_finder.run import run

    figs = []  # coverage.png, checked below as a reader sees it
    monkeypatch.setattr(output, "figure", lambda *a, **k: figs.append(gui.figure(*a, **k)) or figs[-1])
    out = tmp_path / "out"
    result = run(cfg_for(small_project, out, "copy_images=link"))
    rows = list(csv.DictReader(open(out / "selected_images.csv")))
    assert [r["image"] for r in rows] == [fp.name for fp in result.selected]
    for r in rows:
        assert (out / "images" / r["file"]).is_file()
        assert (out / "images" / r["file"]).read_bytes() == (
            small_project / "opensfm/undistorted/images" / r["file"]
        ).read_bytes()
    assert float(rows[-1]["cumulative_coverage_pct"]) >= 95.0 - 0.5
    owned = json.loads((out / "owned_areas.json").read_text())
    assert set(owned) == {r["file"] for r in rows} and all(len(v) >= 3 for v in owned.values())
    summary = json.loads((out / "selection.json").read_text())
    assert summary["coverage_pct"] >= 95.0 - 1e-6 and summary["images_selected"] == len(rows)
    import geopandas as gpd
    import pyogrio

    layers = {name for name, _ in pyogrio.list_layers(out / "footprints.gpkg")}
    assert layers == {"footprints", "owned", "aoi", "uncovered"}
    fps = gpd.read_file(out / "footprints.gpkg", layer="footprints")
    assert len(fps) == 12 and fps.selected.sum() == len(rows) and fps.crs.to_epsg() == 32614
    from PIL import Image

    with Image.open(out / "coverage.png") as im:
        assert im.width > 400 and len(np.unique(np.asarray(im.convert("RGB")).reshape(-1, 3), axis=0)) > 20
    from figure_checks import outside_figure

    assert len(figs) == 1 and outside_figure(figs[0]) == []  # no label clipped


def test_rerun_into_one_folder_leaves_exactly_the_selection(small_project, tmp_path):
    """A second run with another coverage target (fewer photos) removes the first run's extra photos from
    images/, and leaves a file the user put there alone."""
    from matchplant.min_img_finder.run import run

    out = tmp_path / "out"
    first = run(cfg_for(small_project, out, "copy_images=copy", "uncovered_threshold=1"))
    (out / "images" / "my_notes.txt").write_text("mine")
    second = run(cfg_for(small_project, out, "copy_images=link", "uncovered_threshold=40"))
    assert len(second.selected) < len(first.selected)
    listed = {r["file"] for r in csv.DictReader(open(out / "selected_images.csv"))}
    assert listed == {fp.file.name for fp in second.selected}
    assert {p.name for p in (out / "images").iterdir()} == listed | {"my_notes.txt"}


@pytest.mark.slow
def test_folder_config_loads_and_help_works():
    cfg = load_config(MinImgFinderConfig, FOLDER / "config.yaml", check_paths=False)
    assert cfg.method == "greedy"
    text = (FOLDER / "config.yaml").read_text()
    keys = [ln for ln in text.splitlines() if re.match(r"^[a-z_]+:", ln)]
    assert all(text.splitlines()[text.splitlines().index(k) - 1].startswith("#") for k in keys)
    res = subprocess.run([sys.executable, str(FOLDER / "min_img_finder.py"), "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "--gui" in res.stdout


@pytest.mark.slow
def test_missing_dsm_is_a_clear_cli_error(small_project, tmp_path):
    import shutil

    copy = tmp_path / "p"
    shutil.copytree(small_project, copy)
    (copy / "odm_dem/dsm.tif").unlink()
    res = subprocess.run(
        [
            sys.executable,
            str(FOLDER / "min_img_finder.py"),
            "--set",
            f"project_dir={copy}",
            "--set",
            f"output_dir={tmp_path / 'o'}",
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 2 and "Traceback" not in res.stderr and "--dsm" in res.stderr


# --------------------------------------------------------------------------------------------------
# GUI


@pytest.mark.slow
@pytest.mark.gui
def test_gui_headless_toggle_select_save(small_project, tmp_path):
    from gui_events import click

    from matchplant.min_img_finder.gui import MinImgFinderGUI

    gui = MinImgFinderGUI(cfg_for(small_project, tmp_path / "out"), headless=True)
    first = list(gui.result.selection.indices)
    assert gui.finder.exact_coverage(first) >= 0.95 - 1e-9

    # click inside a selected image's owned area: it is removed, coverage drops
    def marks():  # number drawn on each selected image -> its colour
        return {t.get_text(): t.get_bbox_patch().get_edgecolor() for t in gui.ax.texts if t.get_bbox_patch()}

    before = marks()
    assert set(before) == {str(i + 1) for i in first}
    name = gui.finder.footprints[first[0]].name
    p = gui.result.owned[name].representative_point()
    click(gui.fig, gui.ax, p.x, p.y)
    assert first[0] not in gui.result.selection.indices and len(gui.result.selection.indices) == len(first) - 1
    # every other image keeps its number and its colour
    after = marks()
    assert after == {k: v for k, v in before.items() if k != str(first[0] + 1)}
    assert gui.result.exact_coverage < gui.finder.exact_coverage(first)
    # click there again: the smallest unselected footprint under the pointer comes back in
    click(gui.fig, gui.ax, p.x, p.y)
    assert len(gui.result.selection.indices) == len(first)
    # a stricter threshold typed in the panel and Select: at least as many images
    gui.boxes["uncovered_threshold"].set_val("0")
    click(gui.fig, gui.select_btn.ax, 0.5, 0.5)
    assert len(gui.result.selection.indices) >= len(first)
    assert gui.result.exact_coverage >= 1 - 1e-4  # up to slivers thinner than a grid cell
    # a bad value is reported in the status line, not raised (text set without events: each event redraws)
    gui.boxes["max_overlap"].text_disp.set_text("abc")
    gui.run_selection()
    assert "invalid" in gui.status.get_text()
    gui.boxes["max_overlap"].text_disp.set_text("30")
    click(gui.fig, gui.save_btn.ax, 0.5, 0.5)
    assert (tmp_path / "out" / "selected_images.csv").is_file()
    assert (tmp_path / "out" / "min_img_finder_config.yaml").is_file()
    rows = list(csv.DictReader(open(tmp_path / "out" / "selected_images.csv")))
    assert len(rows) == len(gui.result.selection.indices)


@pytest.mark.gui
def test_gui_real_window_under_xvfb(small_project, tmp_path):
    from conftest import run_in_xvfb, xvfb_available

    if not xvfb_available():
        pytest.skip("Xvfb is not installed")
    shot = tmp_path / "gui.png"
    code = f"""
import matplotlib
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.gui import close, show
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.gui import MinImgFinderGUI
cfg = load_config(MinImgFinderConfig, None, ["project_dir={small_project}", "output_dir={tmp_path / "o"}"])
gui = MinImgFinderGUI(cfg, headless=False)
assert matplotlib.get_backend().lower() == "tkagg", matplotlib.get_backend()
timer = gui.fig.canvas.new_timer(interval=1500)
def done():
    gui.fig.savefig({str(shot)!r})
    print("title", gui.fig.canvas.manager.get_window_title())
    close(gui.fig)
timer.add_callback(done)
timer.start()
show(gui.fig)
print("images", len(gui.result.selection.indices))
"""
    res = run_in_xvfb(code, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "images" in res.stdout and shot.is_file()
    assert "title MatchPlant - 3 Minimum image finder" in res.stdout  # the step, not "Figure 1"


# --------------------------------------------------------------------------------------------------
# the synthetic field


def test_synthetic_field_selection_and_footprints(tiny_field, tmp_path):

    f = MinImageFinder(cfg_for(tiny_field.root, tmp_path / "o", "dsm_resolution=0", "uncovered_threshold=5"))
    # footprint corners are the ray-DSM intersections (independent brute force on the real DSM file)
    fp = f.footprints[0]
    w, h = fp.shot.camera.width, fp.shot.camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    truth = brute_force_ground(fp.shot, corners, f.frame, tiny_field.dsm)
    verts = np.asarray(fp.polygon.exterior.coords)[:-1]
    assert max(np.min(np.hypot(*(verts - t[:2]).T)) for t in truth) < 0.01
    # every plant centre the truth says is fully inside an undistorted image lies in that image's footprint
    coco = json.loads(tiny_field.boxes_undistorted.read_text())
    plants = {int(r["id"]): (float(r["x"]), float(r["y"])) for r in csv.DictReader(open(tiny_field.plants_csv))}
    images = {im["id"]: im for im in coco["images"]}
    by_name = {x.name: x for x in f.footprints}
    checked = 0
    for ann in coco["annotations"]:
        im = images[ann["image_id"]]
        x, y, bw, bh = ann["bbox"]
        if x > 2 and y > 2 and x + bw < im["width"] - 2 and y + bh < im["height"] - 2:
            checked += 1
            assert by_name[im["shot_id"]].polygon.buffer(0.02).contains(shapely.Point(plants[ann["plant_id"]]))
    assert checked > 20
    # selection: the requested coverage (or all that the flight can give) with at most 1.1 x the optimum
    reach = f.exact_coverage(range(len(f.footprints)))
    sel = f.select()
    assert f.exact_coverage(sel.indices) >= min(0.95, reach) - 1e-4
    best = select_milp(f.grid, 0.95, f.cfg.max_overlap / 100, time_limit=30)
    assert len(sel.indices) <= 1.1 * len(best.indices)


def test_the_folders_picture_of_the_window_shows_its_current_form():
    """``3_min_img_finder/gui.png`` (drawn by docs/gui/folder_windows.py) records its fields and methods: the
    window's parameters and every method the config accepts."""
    import typing

    from PIL import Image

    from matchplant.min_img_finder.gui import FIELDS

    with Image.open(Path(__file__).resolve().parents[1] / "3_min_img_finder" / "gui.png") as im:
        shown = json.loads(im.text.get("widgets", "{}"))
    fix = "3_min_img_finder/gui.png is older than the window: python docs/gui/folder_windows.py <demo output>"
    assert shown.get("fields") == [label for _, label in FIELDS], fix
    assert shown.get("methods") == list(typing.get_args(typing.get_type_hints(MinImgFinderConfig)["method"])), fix


def test_the_status_line_says_when_the_asked_coverage_cannot_be_reached(finder):
    """Module 3's window once said "overlap cap relaxed to reach the coverage" for a selection that covered 92 %
    of 95 % asked: every image together covered no more. The line now says so; the reachable share is the union
    of every footprint (the exact polygon coverage of all images, within the grid's cells)."""
    from types import SimpleNamespace

    from matchplant.min_img_finder.gui import selection_words

    every = list(range(len(finder.footprints)))
    assert finder.reachable == pytest.approx(finder.exact_coverage(every), abs=0.02)
    sel = SimpleNamespace(method="greedy", indices=[1, 2], seconds=0.2, relaxed=True)
    short = selection_words(sel, 0.92, 95)
    assert short.endswith("cover only 92.0% (asked 95%) - overlap cap relaxed to reach that"), short
    sel.relaxed = False
    assert selection_words(sel, 1.0, 95) == "greedy: 2 images in 0.20 s"
