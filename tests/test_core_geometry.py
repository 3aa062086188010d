"""Camera models, poses, frames and ray/DSM intersection against real OpenSfM data and exact geometry."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from affine import Affine
from pyproj import CRS, Geod, Transformer
from scipy.spatial.transform import Rotation

from matchplant.core.formats.reconstruction import read_reconstruction, write_reconstruction
from matchplant.core.geometry.camera import camera_from_opensfm
from matchplant.core.geometry.frames import OffsetFrame, TopocentricFrame, detect_frame, parse_crs, utm_crs_for
from matchplant.core.geometry.ground import ground_to_pixels, pixels_to_ground
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import HIT, NODATA, OUTSIDE, Surface
from matchplant.core.runtime.errors import GeometryError

BERLIN = "opensfm-berlin"


# --------------------------------------------------------------------------------------------------
# real data: OpenSfM's Berlin reconstruction


@pytest.fixture(scope="module")
def berlin(data_dir):
    return read_reconstruction(data_dir / BERLIN / "reconstruction_example.json")


@pytest.mark.independent
def test_berlin_points_reproject_onto_tracks(berlin, data_dir):
    """3D points projected into their images agree with the tracked features: median error < 1 px."""
    points = dict(zip(berlin.point_ids, berlin.points))
    rows = (data_dir / BERLIN / "tracks_example.csv").read_text().splitlines()[1:]
    errors = []
    for row in rows:
        image, track, _, x, y = row.split("\t")[:5]
        if track not in points or image not in berlin.shots:
            continue
        shot = berlin.shots[image]
        uv = shot.project(points[track][None])[0]
        observed = shot.camera.normalized_to_pixel(np.array([float(x), float(y)]))
        errors.append(np.linalg.norm(uv - observed))
    errors = np.array(errors)
    assert len(errors) > 2000
    assert np.median(errors) < 1.0
    # the observation rows mistakenly read as pixels, or the centre taken as translation, fail badly:
    assert np.percentile(errors, 90) < 5.0


@pytest.mark.independent
def test_berlin_camera_centre_is_minus_rt_t_and_lands_on_exif_gps(berlin, data_dir):
    """C = -R^T t mapped through the topocentric frame lands on each image's EXIF GPS (GPS DOP 5 m);
    OpenSfM's own topocentric gps_position maps back onto the EXIF values exactly."""
    exif = json.loads((data_dir / BERLIN / "exif_gps.json").read_text())
    frame = detect_frame(berlin.reference_lla, None, False)
    assert isinstance(frame, TopocentricFrame)
    geod = Geod(ellps="WGS84")
    for name, gps in exif.items():
        if name.startswith("_"):
            continue
        shot = berlin.shots[name]
        lon, lat, _ = frame.to_lla(shot.center[None])[0]
        assert geod.inv(gps["longitude"], gps["latitude"], lon, lat)[2] < 6.0
        wrong = frame.to_lla(np.asarray(shot.translation)[None])[0]  # the published code's mistake
        assert geod.inv(gps["longitude"], gps["latitude"], wrong[0], wrong[1])[2] > 15.0
        glon, glat, galt = frame.to_lla(np.array(shot.gps_position)[None])[0]
        assert geod.inv(gps["longitude"], gps["latitude"], glon, glat)[2] < 1e-6
        assert galt == pytest.approx(gps["altitude"], abs=1e-6)


def test_reconstruction_roundtrip(berlin, tmp_path):
    path = write_reconstruction(tmp_path / "r.json", berlin)
    again = read_reconstruction(path)
    for sid, shot in berlin.shots.items():
        np.testing.assert_allclose(again.shots[sid].center, shot.center, atol=1e-9)
    np.testing.assert_allclose(again.points, berlin.points)


# --------------------------------------------------------------------------------------------------
# camera models

CAMERAS = [
    camera_from_opensfm(
        "persp",
        {"projection_type": "perspective", "width": 4000, "height": 3000, "focal": 0.9, "k1": -0.05, "k2": 0.01},
    ),
    camera_from_opensfm(
        "brown",
        {
            "projection_type": "brown",
            "width": 5472,
            "height": 3648,
            "focal_x": 0.666,
            "focal_y": 0.667,
            "c_x": -0.0015,
            "c_y": 0.0047,
            "k1": -0.264,
            "k2": 0.102,
            "k3": -0.026,
            "p1": 0.0007,
            "p2": 0.00026,
        },
    ),
    camera_from_opensfm(
        "fish", {"projection_type": "fisheye", "width": 4000, "height": 3000, "focal": 0.6, "k1": 0.02, "k2": -0.01}
    ),
    camera_from_opensfm(
        "fishcv",
        {
            "projection_type": "fisheye_opencv",
            "width": 4000,
            "height": 3000,
            "focal_x": 0.6,
            "focal_y": 0.61,
            "c_x": 0.002,
            "c_y": -0.001,
            "k1": 0.01,
            "k2": -0.005,
            "k3": 0.001,
            "k4": -0.0005,
        },
    ),
]


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.projection_type)
def test_pixel_bearing_pixel_roundtrip(cam):
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 23), np.linspace(0, cam.height - 1, 17))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    b = cam.bearings(uv)
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.project(b * 7.3), uv, atol=1e-6)


@pytest.mark.independent
def test_brown_projection_matches_opencv():
    """OpenSfM's brown model is OpenCV's (k1, k2, p1, p2, k3) with focal and principal point scaled by
    max(width, height) around the image centre (docs/DESIGN.md §3): cv2.projectPoints is the reference."""
    cam = CAMERAS[1]
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-0.4, 0.4, (50, 2)), rng.uniform(0.8, 3.0, 50)])
    S = max(cam.width, cam.height)
    K = np.array(
        [
            [cam.focal_x * S, 0, cam.c_x * S + (cam.width - 1) / 2],
            [0, cam.focal_y * S, cam.c_y * S + (cam.height - 1) / 2],
            [0, 0, 1],
        ]
    )
    dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3])
    expect, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(cam.project(X), expect.reshape(-1, 2), rtol=1e-10, atol=1e-8)


def test_points_behind_camera_are_nan():
    assert np.isnan(CAMERAS[0].project(np.array([[0.1, 0.1, -2.0]]))).all()


def test_resized_camera_keeps_normalised_geometry():
    cam = CAMERAS[0]
    small = cam.resized(2000, 1500)
    b = np.array([[0.2, -0.1, 1.0]])
    big_uv, small_uv = cam.project(b)[0], small.project(b)[0]
    np.testing.assert_allclose((small_uv + 0.5) * 2, big_uv + 0.5, atol=1e-9)
    with pytest.raises(GeometryError, match="aspect ratio"):
        cam.resized(2000, 2000)


def test_unsupported_camera_type_is_a_clear_error():
    with pytest.raises(GeometryError, match="spherical"):
        camera_from_opensfm("x", {"projection_type": "spherical", "width": 10, "height": 5})
    with pytest.raises(GeometryError, match="focal"):
        camera_from_opensfm("x", {"projection_type": "perspective", "width": 10, "height": 5})


# --------------------------------------------------------------------------------------------------
# frames

LON, LAT = -96.6, 40.85
CRS14 = utm_crs_for(LON, LAT)


def test_parse_crs_forms():
    assert parse_crs("WGS84 UTM 14N").to_epsg() == 32614
    assert parse_crs("EPSG:32715").to_epsg() == 32715
    assert parse_crs("+proj=utm +zone=14 +datum=WGS84 +units=m +no_defs").to_epsg() in (32614, None)


@pytest.mark.independent
def test_topocentric_frame_matches_independent_enu_math():
    """ENU -> ECEF done by hand (rotation matrix) -> geodetic with pyproj agrees with the frame."""
    frame = TopocentricFrame(LAT, LON, 350.0, CRS14)
    enu = np.array([[0.0, 0.0, 0.0], [150.0, -80.0, 12.0], [-200.0, 190.0, 40.0]])
    lat, lon = np.radians(LAT), np.radians(LON)
    to_ecef = Transformer.from_crs(CRS.from_epsg(4979), CRS.from_epsg(4978), always_xy=True)
    x0 = np.array(to_ecef.transform(LON, LAT, 350.0))
    R = np.array(
        [
            [-np.sin(lon), np.cos(lon), 0],
            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
        ]
    )
    ecef = x0 + enu @ R
    lon_, lat_, h_ = to_ecef.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE")
    e, n = Transformer.from_crs(4326, CRS14, always_xy=True).transform(lon_, lat_)
    np.testing.assert_allclose(frame.to_map(enu), np.stack([e, n, h_], 1), atol=1e-6)
    np.testing.assert_allclose(frame.from_map(frame.to_map(enu)), enu, atol=1e-6)
    # treating ENU as UTM shifted to the reference point is off by decimetres to metres at 200 m
    e0, n0 = Transformer.from_crs(4326, CRS14, always_xy=True).transform(LON, LAT)
    naive = enu[:, :2] + [e0, n0]
    assert np.abs(naive - frame.to_map(enu)[:, :2]).max() > 0.5


def test_detect_frame_cases():
    e0, n0 = 688000.0, 4525000.0
    lon0, lat0 = Transformer.from_crs(CRS14, 4326, always_xy=True).transform(e0, n0)
    ref = {"latitude": lat0, "longitude": lon0, "altitude": 0.0}
    coords = (CRS14, np.array([e0, n0, 0.0]))
    f1 = detect_frame(ref, coords, False)
    assert isinstance(f1, OffsetFrame) and f1.offset[0] == e0
    f2 = detect_frame({"latitude": lat0 + 1e-4, "longitude": lon0, "altitude": 0}, coords, False)
    assert isinstance(f2, TopocentricFrame)  # older ODM: offset differs from reference_lla
    f3 = detect_frame({"latitude": lat0 + 1e-4, "longitude": lon0, "altitude": 0}, coords, True)
    assert isinstance(f3, OffsetFrame)  # a topocentric copy beside it means converted
    assert isinstance(detect_frame(ref, None, False), OffsetFrame)  # reference at whole UTM metres


# --------------------------------------------------------------------------------------------------
# ray / DSM intersection on a sloped DSM with bumps, nadir and oblique, every camera model


def sloped_surface(res=0.05, size=1600, hole=True):
    x0, y0 = 688000.0 - 40, 4525000.0 + 40
    xs = x0 + (np.arange(size) + 0.5) * res
    ys = y0 - (np.arange(size) + 0.5) * res
    X, Y = np.meshgrid(xs, ys)
    Z = (
        300
        + 0.08 * (X - x0)
        + 0.03 * (y0 - Y)
        + 0.4 * np.sin((X - x0) / 5.0)
        + 0.5 * np.exp(-((X - 688000) ** 2 + (Y - 4525000) ** 2) / 0.3)
    )  # a "plant" bump
    if hole:
        Z[200:230, 1300:1340] = np.nan
    return Surface(Z, Affine(res, 0, x0, 0, -res, y0), crs=CRS14)


def looking_down(tilt_deg: float, heading_deg: float = 20.0) -> np.ndarray:
    """World->camera rotation of a camera looking down, pitched ``tilt_deg`` off nadir."""
    cam_to_world = (
        Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
        @ Rotation.from_euler("x", 180 + tilt_deg, degrees=True).as_matrix()
    )
    return cam_to_world.T


FRAMES = {
    "utm_offset": OffsetFrame(CRS14, np.array([688000.0, 4525000.0, 0.0])),
    "topocentric": TopocentricFrame(*Transformer.from_crs(CRS14, 4326).transform(688000.0, 4525000.0), 0.0, CRS14),
}


@pytest.mark.parametrize("frame_name", list(FRAMES))
@pytest.mark.parametrize("tilt", [0.0, 35.0], ids=["nadir", "oblique"])
@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.projection_type)
def test_pixel_dsm_pixel_roundtrip(cam, tilt, frame_name):
    frame = FRAMES[frame_name]
    surface = sloped_surface()
    centre_map = np.array([688003.0, 4524998.0, 345.0])
    shot = Shot.from_center("img", cam, looking_down(tilt), frame.from_map(centre_map[None])[0])
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 31), np.linspace(0, cam.height - 1, 21))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    points, status = pixels_to_ground(shot, uv, frame, surface)
    ok = status == HIT
    assert ok.mean() > 0.5
    back = ground_to_pixels(shot, points[ok], frame)
    assert np.abs(back - uv[ok]).max() < 0.01
    dz = np.abs(points[ok, 2] - surface.sample(points[ok, 0], points[ok, 1]))
    assert dz.max() < 1e-3
    # rays that miss are explained: they leave the DSM or fall into its hole
    assert set(np.unique(status[~ok])) <= {OUTSIDE, NODATA}


def test_intersection_finds_first_surface_not_a_flat_plane():
    """A ray grazing over a bump hits the bump's near side, not the ground behind it."""
    res = 0.05
    Z = np.zeros((200, 200))
    Z[:, 100:110] = 2.0  # a 2 m wall across the ray's path
    s = Surface(Z, Affine(res, 0, 0, 0, -res, 10.0))
    origin = np.array([[1.0, 5.0, 3.5]])  # reaches z = 1.5 at the wall (x = 5), the ground at x = 8
    d = np.array([[1.0, 0.0, -0.5]])
    p, _, st = s.intersect(origin, d)
    assert st[0] == HIT
    assert p[0, 0] == pytest.approx(5.0, abs=0.05)  # the wall's face, within a cell of bilinear blending
    assert 1.0 < p[0, 2] < 2.0


def test_nodata_hole_is_reported():
    s = sloped_surface()
    hole_x = s.transform.c + 1320 * 0.05
    hole_y = s.transform.f - 215 * 0.05
    p, _, st = s.intersect(np.array([[hole_x, hole_y, 400.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert st[0] == NODATA and np.isnan(p).all()


def test_minus_9999_is_nodata_when_reading(tmp_path):
    import rasterio

    data = np.full((20, 20), 10.0, dtype="float32")
    data[5:8, 5:8] = -9999
    path = tmp_path / "dsm.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=20,
        height=20,
        count=1,
        dtype="float32",
        crs=CRS14,
        transform=Affine(0.1, 0, 0, 0, -0.1, 2),
    ) as dst:
        dst.write(data, 1)
    s = Surface.open(path)
    assert np.isnan(s.data[6, 6]) and s.zmin == 10.0
    win = Surface.open(path, bounds=(0.5, 0.5, 1.0, 1.0))
    assert win.data.shape[0] < 20 and win.data.shape[1] < 20


@pytest.mark.parametrize("how", ["nodata", "mask band"])
def test_holes_from_a_declared_nodata_or_a_mask_band(tmp_path, how):
    """Holes come from the file's own nodata value (not only ODM's -9999) or from its mask band."""
    import rasterio

    data = np.full((20, 20), 10.0, dtype="float32")
    data[2:4, 2:4] = -32767 if how == "nodata" else 55.0  # under a mask, any value is a hole
    path = tmp_path / "dsm.tif"
    profile = dict(
        driver="GTiff",
        width=20,
        height=20,
        count=1,
        dtype="float32",
        crs=CRS14,
        transform=Affine(0.1, 0, 0, 0, -0.1, 2),
    )
    if how == "nodata":
        profile["nodata"] = -32767
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
        if how == "mask band":
            mask = np.full((20, 20), 255, dtype="uint8")
            mask[2:4, 2:4] = 0
            dst.write_mask(mask)
    s = Surface.open(path)
    assert np.isnan(s.data[2:4, 2:4]).all() and np.isfinite(s.data).sum() == 396
    assert s.zmin == s.zmax == 10.0
    win = Surface.open(path, bounds=(0.1, 1.5, 0.6, 1.9))  # a window over the hole
    assert np.isnan(win.data).sum() == 4


@pytest.mark.slow
def test_march_does_not_step_over_a_thin_first_crossing():
    """A one-cell spike (a leaf tip on a 1 cm DSM) that a ray grazes between two half-cell samples: the first
    crossing is found, as a brute-force march 1,000 times finer finds it, whatever the samples' phase."""
    res = 0.01
    data = np.zeros((41, 201), dtype=np.float32)
    data[20, 100] = 1.0  # the spike: a bilinear tent 2 cells wide
    surface = Surface(data=data, transform=Affine(res, 0, 0, 0, -res, 0.41))
    d = np.array([1.0, 0.0, -0.5])
    d /= np.linalg.norm(d)
    x_tip = 100.5 * res
    rng = np.random.default_rng(0)
    # rays passing 1 to 15 cm below the tip, at random phases: the part of the ray under the tent is 0.02 to
    # 0.3 cells long, so half-cell samples straddle it
    below = rng.uniform(0.01, 0.15, 200)
    x0 = rng.uniform(0.2, 0.6, 200)
    z0 = 1.0 - below + (x_tip - x0) * 0.5
    o = np.column_stack([x0, np.full(200, 0.205), z0])
    pts, s, status = surface.intersect(o, np.repeat(d[None], 200, axis=0))
    fine = np.linspace(0, 3.0, 300_001)
    for k in range(200):
        p = o[k] + fine[:, None] * d
        f = p[:, 2] - surface.sample(p[:, 0], p[:, 1])
        first = np.flatnonzero(f <= 0)[0]
        assert status[k] == HIT
        assert s[k] == pytest.approx(fine[first], abs=2e-5)


def _first_crossing_brute(surface, o, d, clearance, s_max, n=400_001):
    """The first ray parameter where a march 1,000 times finer than a cell comes down to ``clearance`` above
    the surface from above it (NaN samples break a bracket, as holes do), or NaN."""
    s = np.linspace(0.0, s_max, n)
    p = o + s[:, None] * d
    f = p[:, 2] - surface.sample(p[:, 0], p[:, 1]) - clearance
    down = np.flatnonzero((f[:-1] > 0) & (f[1:] <= 0))
    return s[down[0] + 1] if down.size else np.nan, s[1] - s[0]


@pytest.mark.slow
@pytest.mark.parametrize("clearance", [0.0, 0.02])
def test_walk_finds_the_brute_force_first_crossing_on_rough_ground_with_holes(clearance):
    """Rays in every direction over a rough 1 cm surface (plants as spikes and domes, holes): the first crossing
    is where a brute-force march finds it, within its step, and a ray stopped by a hole says so."""
    rng = np.random.default_rng(7)
    data = rng.uniform(0.0, 0.05, (60, 80)).astype(np.float32)
    data[rng.integers(0, 60, 40), rng.integers(0, 80, 40)] += rng.uniform(0.1, 0.6, 40).astype(np.float32)
    yy, xx = np.mgrid[0:60, 0:80]
    data += (0.3 * np.exp(-((xx - 40) ** 2 + (yy - 30) ** 2) / 60.0)).astype(np.float32)
    data[10:14, 60:66] = np.nan  # a hole
    surface = Surface(data=data, transform=Affine(0.01, 0, 0, 0, -0.01, 0.6))
    n = 300
    o = np.column_stack([rng.uniform(0.05, 0.75, n), rng.uniform(0.05, 0.55, n), rng.uniform(0.7, 1.0, n)])
    d = np.column_stack([rng.normal(0, 0.25, n), rng.normal(0, 0.25, n), -np.ones(n)])
    d[:20, :2] = 0.0  # straight down
    d[20:40, 1] = 0.0  # along a row
    pts, s, status = surface.intersect(o, d, clearance=clearance)
    checked = 0
    for k in range(n):
        s_max = (o[k, 2] + 0.1) / -d[k, 2]
        truth, step = _first_crossing_brute(surface, o[k], d[k], clearance, s_max)
        if np.isfinite(truth):
            assert status[k] == HIT, k
            assert s[k] == pytest.approx(truth, abs=1.5 * step), k
            checked += 1
        else:
            assert status[k] in (OUTSIDE, NODATA), k
    assert checked > 0.6 * n  # the others leave the raster or meet the hole
    hit = status == HIT
    above = pts[hit, 2] - surface.sample(pts[hit, 0], pts[hit, 1])
    np.testing.assert_allclose(above, clearance, atol=1e-6)
