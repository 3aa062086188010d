"""Module 1 (gcp_finder): image metadata, survey, predicted pixels, target detection, gcp_list.txt, GUI."""

from __future__ import annotations

import csv
import io
import json
import math
import struct
import subprocess
import sys
import textwrap
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import piexif
import pytest
from gui_events import click, drag, key  # noqa: E402  (tests/ is on sys.path under pytest)
from PIL import Image
from pyproj import Transformer

from matchplant.core.formats.exif import gps_ifd, jpeg_segments
from matchplant.core.formats.gcp_list import read_gcp_list, write_gcp_list
from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.gcp_finder.candidates import find_candidates
from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.marks import MarkStore
from matchplant.gcp_finder.metadata import parse_dji_xmp, read_image_info
from matchplant.gcp_finder.pose import camera_rotation, track_yaw
from matchplant.gcp_finder.run import run
from matchplant.gcp_finder.target import detect_target

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data" / "gcp_lists"
UTM = "EPSG:32614"
W, H, GSD = 600, 400, 0.01  # image size, metres per pixel at the GCPs
FOCAL_MM, SENSOR_MM = 8.8, 13.2  # DJI FC6310 (Phantom 4 Pro): in the built-in sensor table
HEIGHT = GSD * FOCAL_MM / SENSOR_MM * W  # camera height above the GCPs giving that GSD: 4 m
GROUND = 350.0
TARGET = 0.5  # side of the 2x2 checker target, m
GCPS = {"G1": (700000.0, 4500000.0), "G2": (700001.2, 4500000.5), "G3": (700003.5, 4500002.5)}


def pixel_of(gx, gy, cam, yaw_deg):
    """Where a ground point appears in a nadir image: image right = (cos yaw, -sin yaw), top = (sin yaw, cos yaw)
    on the map (an independent statement of the convention, not the module's rotation code)."""
    psi = math.radians(yaw_deg)
    dx, dy = gx - cam[0], gy - cam[1]
    right = dx * math.cos(psi) - dy * math.sin(psi)
    up = dx * math.sin(psi) + dy * math.cos(psi)
    return (W - 1) / 2 + right / GSD, (H - 1) / 2 - up / GSD


def render(cam, yaw_deg, rng, ss=2) -> np.ndarray:
    """A nadir view of textured soil with the checker targets (anti-aliased by supersampling)."""
    psi = math.radians(yaw_deg)
    v, u = np.mgrid[0 : H * ss, 0 : W * ss]
    u = (u + 0.5) / ss - 0.5 - (W - 1) / 2
    v = (v + 0.5) / ss - 0.5 - (H - 1) / 2
    right, up = u * GSD, -v * GSD
    gx = cam[0] + right * math.cos(psi) + up * math.sin(psi)
    gy = cam[1] - right * math.sin(psi) + up * math.cos(psi)
    val = np.full(gx.shape, np.nan)
    for tx, ty in GCPS.values():
        a, b = gx - tx, gy - ty
        inside = (np.abs(a) < TARGET / 2) & (np.abs(b) < TARGET / 2)
        val[inside] = np.where(a[inside] * b[inside] > 0, 235.0, 20.0)
    val = val.reshape(H, ss, W, ss)
    mask = np.isfinite(val).mean(axis=(1, 3))
    tgt = np.nan_to_num(val).mean(axis=(1, 3))
    soil = 120 + 25 * rng.standard_normal((H, W))
    img = tgt + (1 - mask) * soil
    return np.clip(np.repeat(img[..., None], 3, axis=2) * [1.0, 0.85, 0.7], 0, 255).astype(np.uint8)


def make_image(path: Path, cam, yaw_deg: float | None, rng, t: int, xmp: bool = True, model=b"FC6310") -> None:
    lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(cam[0], cam[1])
    exif = {
        "0th": {piexif.ImageIFD.Make: b"DJI", piexif.ImageIFD.Model: model},
        "Exif": {
            piexif.ExifIFD.FocalLength: (int(FOCAL_MM * 100), 100),
            piexif.ExifIFD.DateTimeOriginal: f"2024:06:05 15:30:{t:02d}".encode(),
        },
        "GPS": gps_ifd(lat, lon, GROUND + HEIGHT),
    }
    buf = io.BytesIO()
    Image.fromarray(render(cam, yaw_deg or 0.0, rng)).save(buf, "jpeg", quality=95, exif=piexif.dump(exif))
    data = buf.getvalue()
    if xmp and yaw_deg is not None:
        payload = (
            b"http://ns.adobe.com/xap/1.0/\x00<x:xmpmeta xmlns:x='adobe:ns:meta/'><rdf:Description "
            b'drone-dji:RelativeAltitude="+4.00" drone-dji:GimbalPitchDegree="-90.0" '
            b'drone-dji:FlightYawDegree="+' + f"{yaw_deg:.1f}".encode() + b'"/></x:xmpmeta>'
        )
        end = [e for m, s, e in jpeg_segments(data)[0] if m == 0xE1][0]
        data = data[:end] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[end:]
    path.write_bytes(data)


CAMS = {
    "IMG_0001.JPG": ((700000.3, 4500000.2), 0.0),
    "IMG_0002.JPG": ((700001.0, 4500000.9), 90.0),
    "IMG_0003.JPG": ((700002.2, 4500001.0), 200.0),
    "IMG_0004.JPG": ((700008.0, 4500008.0), 30.0),
}


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    root = tmp_path_factory.mktemp("gcpflight")
    rng = np.random.default_rng(3)
    (root / "images").mkdir()
    for t, (name, (cam, yaw)) in enumerate(CAMS.items()):
        make_image(root / "images" / name, cam, yaw, rng, t)
    with open(root / "survey.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y", "z"])
        for gid, (x, y) in GCPS.items():
            w.writerow([gid, x, y, GROUND])
    truth = {}
    for name, (cam, yaw) in CAMS.items():
        for gid, (x, y) in GCPS.items():
            u, v = pixel_of(x, y, cam, yaw)
            if 0 <= u < W and 0 <= v < H:
                truth[(gid, name)] = (u, v)
    return root, truth


def cfg_for(root: Path, out: Path, **kw) -> GcpFinderConfig:
    return GcpFinderConfig(
        **{"images": root / "images", "survey": root / "survey.csv", "survey_crs": UTM, "output_dir": out, **kw}
    )


def test_image_info_and_xmp(flight):
    root, _ = flight
    info = read_image_info(root / "images" / "IMG_0002.JPG")
    assert (info.width, info.height, info.model, info.focal_mm) == (W, H, "FC6310", FOCAL_MM)
    assert info.yaw == 90.0 and info.pitch == -90.0 and info.relative_alt == 4.0
    assert abs(info.alt - (GROUND + HEIGHT)) < 1e-3
    assert parse_dji_xmp(
        '<drone-dji:GimbalYawDegree>-12.5</drone-dji:GimbalYawDegree> drone-dji:FlightYawDegree="+3"'
    ) == {"gimbal_yaw": -12.5, "flight_yaw": 3.0}


def test_tiff_images(flight, tmp_path):
    root, truth = flight
    (tmp_path / "images").mkdir()
    src = root / "images" / "IMG_0001.JPG"
    with Image.open(src) as im:  # the same picture and EXIF as a TIFF
        im.save(tmp_path / "images" / "IMG_0001.tif", exif=piexif.dump(piexif.load(str(src))))
    (tmp_path / "survey.csv").write_bytes((root / "survey.csv").read_bytes())
    info = read_image_info(tmp_path / "images" / "IMG_0001.tif")
    assert (info.width, info.height, info.model) == (W, H, "FC6310")
    finder = find_candidates(cfg_for(tmp_path, tmp_path / "o"))
    got = {(c.gcp, c.image) for v in finder.candidates.values() for c in v}
    assert got == {(g, "IMG_0001.tif") for g, im in truth if im == "IMG_0001.JPG"}


def test_rotation_convention_matches_independent_formula():
    for yaw in (0.0, 37.0, 90.0, 200.0):
        R = camera_rotation(yaw, -90.0)
        cam = (10.0, 20.0)
        for g in ((11.0, 20.0), (10.0, 21.5), (8.3, 19.1)):
            d = R @ np.array([g[0] - cam[0], g[1] - cam[1], -HEIGHT])
            f = FOCAL_MM / SENSOR_MM * W
            u, v = d[0] / d[2] * f + (W - 1) / 2, d[1] / d[2] * f + (H - 1) / 2
            assert np.allclose((u, v), pixel_of(*g, cam, yaw), atol=1e-9)


def test_track_yaw_lawnmower():
    # two lines north then south, with a sideways turn between them
    pts = [(0, y) for y in range(5)] + [(3, y) for y in range(4, -1, -1)]
    yaw = track_yaw(np.array(pts, float))
    assert np.allclose(yaw[:5], 0.0) and np.allclose(yaw[5:], 180.0)


def test_candidates_predicted_near_truth_and_ranked(flight, tmp_path, monkeypatch):
    from figure_checks import outside_figure

    import matchplant.gcp_finder.candidates as candidates
    from matchplant.core.runtime import gui

    figs = []  # candidates.png, checked below for clipped labels
    monkeypatch.setattr(candidates, "figure", lambda *a, **k: figs.append(gui.figure(*a, **k)) or figs[-1])
    root, truth = flight
    finder = run(cfg_for(root, tmp_path / "out"))
    assert len(figs) == 1 and outside_figure(figs[0]) == []
    got = {(c.gcp, c.image): c for lst in finder.candidates.values() for c in lst}
    assert set(got) == set(truth)  # exactly the images that see each GCP (IMG_0004 sees none)
    for k, c in got.items():
        assert math.dist((c.u, c.v), truth[k]) < 0.5  # same geometry, no noise: nearly exact
    for lst in finder.candidates.values():
        d = [c.center_distance for c in lst]
        assert d == sorted(d) and [c.rank for c in lst] == list(range(1, len(lst) + 1))
    rows = list(csv.DictReader(open(tmp_path / "out" / "candidates.csv")))
    assert len(rows) == len(truth) and (tmp_path / "out" / "candidates.png").stat().st_size > 0
    # the distance threshold is honoured
    near = find_candidates(cfg_for(root, tmp_path / "o2", max_center_distance=0.3))
    for lst in near.candidates.values():
        assert all(c.center_distance <= 0.3 for c in lst)
    n_near = sum(len(v) for v in near.candidates.values())
    assert n_near == sum(1 for c in got.values() if c.center_distance <= 0.3) < len(got)


def test_lonlat_survey_gives_utm_output(flight, tmp_path):
    root, truth = flight
    t = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)
    with open(tmp_path / "ll.csv", "w") as fh:
        fh.write("name,lat,lon,elevation\n")
        for gid, (x, y) in GCPS.items():
            lon, lat = t.transform(x, y)
            fh.write(f"{gid},{lat:.10f},{lon:.10f},{GROUND}\n")
    finder = find_candidates(
        GcpFinderConfig(
            images=root / "images", survey=tmp_path / "ll.csv", survey_crs="EPSG:4326", output_dir=tmp_path / "o"
        )
    )
    assert finder.crs.to_epsg() == 32614
    assert abs(finder.gcps["G2"].x - GCPS["G2"][0]) < 1e-3
    assert {(c.gcp, c.image) for v in finder.candidates.values() for c in v} == set(truth)


def test_auto_finds_targets_subpixel(flight, tmp_path):
    root, truth = flight
    run(cfg_for(root, tmp_path / "out", auto=True))
    header, crs, marks = read_gcp_list(tmp_path / "out" / "gcp_list.txt")
    assert header == "EPSG:32614" and crs.to_epsg() == 32614
    found = {(m.gcp, m.image): m for m in marks}
    assert len(found) >= len(truth) - 1  # a target cut by the image edge may be missed
    for k, m in found.items():
        assert math.dist((m.u, m.v), truth[k]) < 0.5, k
        assert (m.x, m.y, m.z) == pytest.approx((*GCPS[m.gcp], GROUND))
    # the same marks in Metashape's and Pix4D's import formats (their pixels count from the image's corner)
    rows = [ln.split(",") for ln in (tmp_path / "out" / "pix4d_marks.csv").read_text().splitlines()]
    pix4d = {(g, im): (float(x) - 0.5, float(y) - 0.5) for im, g, x, y, _ in rows}
    assert set(pix4d) == set(found)
    for k, m in found.items():  # gcp_list.txt keeps 3 decimals
        assert pix4d[k] == pytest.approx((m.u, m.v), abs=6e-4)
    doc = ElementTree.parse(tmp_path / "out" / "metashape_markers.xml").getroot().find("chunk")
    assert len(doc.findall("frames/frame/markers/marker/location")) == len(marks)
    assert parse_crs(doc.findtext("reference")).equals(crs)


def test_detect_target_none_on_flat():
    assert detect_target(np.full((100, 100), 120, np.float32), 50, 50, 30) is None


@pytest.mark.independent
def test_real_gcp_lists_parse():
    header, crs, marks = read_gcp_list(DATA / "copr" / "gcp_list.txt")
    assert header.startswith("+proj=utm") and crs.utm_zone == "11N"
    assert len(marks) == 27 and len({m.gcp for m in marks}) == 10
    assert marks[0].image == "IMG_0037.jpg" and marks[0].gcp == "gcp02"
    assert marks[0].u == pytest.approx(3609.3727839973153) and marks[0].x == 235269.88
    header, crs, marks = read_gcp_list(DATA / "bellus" / "gcp_list.txt")
    assert header == "WGS84 UTM 17N" and crs.to_epsg() == 32617
    assert len(marks) == 4 and marks[0].gcp == "" and marks[0].image == "IMG_1356_RGB.jpg"
    assert (marks[0].u, marks[0].v) == (2648, 2147)
    with pytest.raises(InputError, match="line 2"):  # an EPSG:4326 point list without pixels
        read_gcp_list(DATA / "copr" / "gcp_list_noimg.txt")


def test_gcp_list_roundtrip(tmp_path):
    _, _, marks = read_gcp_list(DATA / "copr" / "gcp_list.txt")
    write_gcp_list(tmp_path / "g.txt", "EPSG:32611", marks)
    header, crs, again = read_gcp_list(tmp_path / "g.txt")
    assert header == "EPSG:32611" and len(again) == 27
    for a, b in zip(marks, again):
        assert (a.image, a.gcp) == (b.image, b.gcp) and abs(a.u - b.u) < 1e-3 and abs(a.x - b.x) < 1e-4


def test_survey_errors(flight, tmp_path):
    root, _ = flight
    bad = tmp_path / "s.csv"
    bad.write_text("id,x,y\nG1,700000,4500000\n")
    with pytest.raises(InputError, match="no column .z."):
        find_candidates(GcpFinderConfig(images=root / "images", survey=bad, survey_crs=UTM, output_dir=tmp_path))
    with pytest.raises(ConfigError, match="survey_crs.*coordinate reference system"):
        find_candidates(cfg_for(root, tmp_path, survey_crs="EPSG:123456789"))
    far = tmp_path / "far.csv"
    far.write_text("id,x,y,z\nA,690000,4510000,350\nB,690010,4510000,350\n")
    with pytest.raises(InputError, match="none of the 2 GCPs"):
        find_candidates(GcpFinderConfig(images=root / "images", survey=far, survey_crs=UTM, output_dir=tmp_path))
    with pytest.raises(ConfigError, match="survey_crs"):
        load_config(GcpFinderConfig, None, [f"images={root / 'images'}", f"survey={root / 'survey.csv'}"])


def test_unknown_camera_needs_sensor_width(tmp_path):
    (tmp_path / "images").mkdir()
    make_image(
        tmp_path / "images" / "a.jpg", (700000.3, 4500000.2), 0.0, np.random.default_rng(0), 1, model=b"MysteryCam"
    )
    (tmp_path / "survey.csv").write_text("id,x,y,z\nG1,700000,4500000,350\n")
    with pytest.raises(InputError, match="sensor_width_mm"):
        find_candidates(cfg_for(tmp_path, tmp_path / "o"))
    f = find_candidates(cfg_for(tmp_path, tmp_path / "o", sensor_width_mm=SENSOR_MM))
    assert len(f.candidates["G1"]) == 1


def _gui(root, out, headless=True):
    from matchplant.gcp_finder.gui import GcpFinderGUI

    cfg = cfg_for(root, out)
    finder = find_candidates(cfg)
    store = MarkStore(finder, out / "gcp_list.txt")
    return GcpFinderGUI(finder, store, zoom_px=cfg.zoom_px, headless=headless), store


def _click_all(gui, truth, offset=(0.0, 0.0)):
    """Visit every candidate of every GCP with the keyboard and click the truth pixel."""
    clicks = {}
    for _ in gui.gcp_ids:
        for _ in gui.candidates:
            c = gui.candidate
            u, v = truth[(gui.gcp, c.image)]
            u, v = u + offset[0], v + offset[1]
            (x0, x1), (y1, y0) = gui.ax.get_xlim(), gui.ax.get_ylim()
            if not (x0 < u < x1 and y0 < v < y1):
                key(gui.fig, "f")  # whole image
            click(gui.fig, gui.ax, u, v)
            clicks[(gui.gcp, c.image)] = (u, v)
            key(gui.fig, "right")
        key(gui.fig, "down")
    return clicks


@pytest.mark.slow
@pytest.mark.gui
def test_gui_clicks_write_gcp_list(flight, tmp_path):
    root, truth = flight
    gui, store = _gui(root, tmp_path)
    clicks = _click_all(gui, truth, offset=(0.37, -0.21))
    assert len(clicks) == len(truth)
    header, _, marks = read_gcp_list(tmp_path / "gcp_list.txt")  # autosaved, no explicit save
    assert header == "EPSG:32614"
    got = {(m.gcp, m.image): (m.u, m.v) for m in marks}
    assert set(got) == set(clicks)
    for k, uv in clicks.items():
        assert np.allclose(got[k], uv, atol=2e-3)
        assert (marks[0].x, marks[0].y) == pytest.approx(GCPS[marks[0].gcp])
    # drag the current mark 5 px right, then undo the move, then delete it
    gcp, image = gui.gcp, gui.candidate.image
    u, v = store.marks[(gcp, image)]
    drag(gui.fig, gui.ax, u, v, u + 5, v)
    assert store.marks[(gcp, image)] == pytest.approx((u + 5, v))
    key(gui.fig, "u")
    assert store.marks[(gcp, image)] == pytest.approx((u, v))
    key(gui.fig, "d")
    assert (gcp, image) not in store.marks
    assert (gcp, image) not in {(m.gcp, m.image) for m in read_gcp_list(tmp_path / "gcp_list.txt")[2]}
    # a right-drag pans without marking; zoom with the keyboard
    lims = gui.ax.get_xlim()
    drag(gui.fig, gui.ax, u, v, u + 20, v, button=3)
    assert gui.ax.get_xlim()[0] < lims[0] - 5 and (gcp, image) not in store.marks  # grabbed and moved right
    key(gui.fig, "+")
    assert gui.ax.get_xlim()[1] - gui.ax.get_xlim()[0] < lims[1] - lims[0]
    key(gui.fig, "h")  # the full list of keys, and back
    assert "delete" in gui.help.get_text()
    key(gui.fig, "h")
    # choose a GCP by clicking its line in the list on the right
    step = min(0.05, 0.9 / len(gui.gcp_ids))
    click(gui.fig, gui.side, 0.1, 0.95 - 2 * step - 0.01)
    assert gui.gcp == gui.gcp_ids[2] and gui.ci == 0
    key(gui.fig, "[")
    key(gui.fig, "[")
    assert gui.gcp == gcp
    gui.ci = [c.image for c in gui.candidates].index(image)
    gui.open()
    # 'a' finds the target itself
    key(gui.fig, "a")
    assert math.dist(store.marks[(gcp, image)], truth[(gcp, image)]) < 0.5
    gui.fig.savefig(tmp_path / "shot.png")


@pytest.mark.gui
def test_gui_continues_existing_list(flight, tmp_path):
    root, truth = flight
    gui, store = _gui(root, tmp_path)
    click(gui.fig, gui.ax, gui.candidate.u, gui.candidate.v)
    first = (gui.gcp, gui.candidate.image)
    finder = store.finder
    again = MarkStore(finder, tmp_path / "gcp_list.txt")
    assert again.load(tmp_path / "gcp_list.txt") == 1 and first in again.marks
    # an unnamed line (as in ODM's example lists) is matched to the GCP at its coordinates
    g = finder.gcps["G3"]
    (tmp_path / "other.txt").write_text(f"EPSG:32614\n{g.x} {g.y} {g.z} 10 20 IMG_0003.JPG\n")
    assert again.load(tmp_path / "other.txt") == 1 and again.marks[("G3", "IMG_0003.JPG")] == (10, 20)
    assert set(again.warn_few()) == {first[0], "G3"}


@pytest.mark.gui
def test_gui_real_window_xvfb(flight, tmp_path):
    from conftest import run_in_xvfb, xvfb_available

    if not xvfb_available():
        pytest.skip("Xvfb not installed")
    root, truth = flight
    code = textwrap.dedent(f"""
        import sys, math
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        import matplotlib
        from pathlib import Path
        from matchplant.gcp_finder.candidates import find_candidates
        from matchplant.gcp_finder.config import GcpFinderConfig
        from matchplant.gcp_finder.marks import MarkStore
        from matchplant.gcp_finder.gui import GcpFinderGUI
        from gui_events import click, key
        root, out = Path({str(root)!r}), Path({str(tmp_path)!r})
        cfg = GcpFinderConfig(images=root / "images", survey=root / "survey.csv", survey_crs="EPSG:32614",
                              output_dir=out)
        finder = find_candidates(cfg)
        gui = GcpFinderGUI(finder, MarkStore(finder, out / "gcp_list.txt"), headless=False)
        assert matplotlib.get_backend().lower() == "tkagg", matplotlib.get_backend()
        def act():
            c = gui.candidate
            click(gui.fig, gui.ax, c.u + 1.5, c.v - 2.0)
            gui.fig.canvas.draw()
            gui.fig.savefig(out / "window.png")
            key(gui.fig, "q")
        timer = gui.fig.canvas.new_timer(interval=300)
        timer.single_shot = True
        timer.add_callback(act)
        timer.start()
        gui.show()
        print("closed", gui.gcp, gui.candidate.image, gui.candidate.u + 1.5, gui.candidate.v - 2.0)
    """)
    r = run_in_xvfb(code, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    _, gcp, image, u, v = r.stdout.split()[-5:]
    marks = read_gcp_list(tmp_path / "gcp_list.txt")[2]
    assert [(m.gcp, m.image) for m in marks] == [(gcp, image)]
    assert abs(marks[0].u - float(u)) < 2e-3 and abs(marks[0].v - float(v)) < 2e-3
    assert (tmp_path / "window.png").stat().st_size > 10_000


def test_folder_config_and_help():
    cfg = load_config(GcpFinderConfig, ROOT / "1_gcp_finder" / "config.yaml", check_paths=False, strict=False)
    assert 0 < cfg.max_center_distance <= 1
    r = subprocess.run(
        [sys.executable, str(ROOT / "1_gcp_finder" / "gcp_finder.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--gui" in r.stdout


# -- the synthetic field ---------------------------------------------------------------------------


def _field_cfg(field, out, **kw) -> GcpFinderConfig:
    meta = json.loads(field.field_json.read_text())
    return GcpFinderConfig(images=field.images, survey=field.gcp_survey, survey_crs=meta["crs"], output_dir=out, **kw)


def _field_truth(field) -> dict:
    with open(field.gcp_pixels) as fh:
        return {(r["gcp_id"], r["image"]): (float(r["u"]), float(r["v"])) for r in csv.DictReader(fh)}


def test_field_predictions_and_auto(tiny_field, tmp_path):
    truth = _field_truth(tiny_field)
    finder = run(_field_cfg(tiny_field, tmp_path, auto=True, max_center_distance=1.0, edge_margin_px=0))
    width = next(iter(finder.images.values())).width
    preds = {(c.gcp, c.image): (c.u, c.v) for v in finder.candidates.values() for c in v}
    common = set(preds) & set(truth)
    assert len(common) >= 0.8 * len(truth)
    for k in common:
        assert math.dist(preds[k], truth[k]) < 0.05 * width, k
    marks = read_gcp_list(tmp_path / "gcp_list.txt")[2]
    auto = {(m.gcp, m.image): (m.u, m.v) for m in marks}
    inside = [k for k in truth if k in auto]
    assert len(inside) >= 0.7 * len(truth)
    for k in inside:
        assert math.dist(auto[k], truth[k]) < 2.0, (k, auto[k], truth[k])


@pytest.mark.slow
@pytest.mark.gui
def test_field_gui_clicks(tiny_field, tmp_path):
    from matchplant.gcp_finder.gui import GcpFinderGUI

    truth = _field_truth(tiny_field)
    cfg = _field_cfg(tiny_field, tmp_path)
    finder = find_candidates(cfg)
    store = MarkStore(finder, tmp_path / "gcp_list.txt")
    gui = GcpFinderGUI(finder, store, headless=True)
    for gid in finder.candidates:  # the two best images of each GCP whose target centre is in the image
        finder.candidates[gid] = [c for c in finder.candidates[gid] if (gid, c.image) in truth][:2]
    gui.open()
    clicks = _click_all(gui, truth)
    got = {(m.gcp, m.image): (m.u, m.v) for m in read_gcp_list(tmp_path / "gcp_list.txt")[2]}
    assert got.keys() == clicks.keys() and clicks
    for k in clicks:
        assert np.allclose(got[k], clicks[k], atol=2e-3)


def test_survey_values_checked_with_their_line(flight, tmp_path):
    root, _ = flight
    rows = (root / "survey.csv").read_text().splitlines()

    def survey(lines, **kw):
        p = tmp_path / "s.csv"
        p.write_text("\n".join(lines) + "\n")
        return find_candidates(cfg_for(root, tmp_path, survey=p, **kw))

    with pytest.raises(InputError, match="on lines 3 and 4"):
        survey([rows[0], rows[1], rows[2], rows[2].replace(rows[2].split(",")[1], "1")])
    with pytest.raises(InputError, match="line 2: column 'x' is 'n/a'"):
        survey([rows[0], "G9,n/a,4500000,300", *rows[1:]])
    lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(*map(float, rows[1].split(",")[1:3]))
    with pytest.raises(InputError, match="look like degrees"):  # lon/lat in a survey said to be UTM
        survey([rows[0], f"G1,{lon},{lat},300", f"G2,{lon + 1e-5},{lat},300"])
    with pytest.raises(InputError, match="swapped"):  # lat in x, lon in y
        survey([rows[0], f"G1,{lat},{lon},300", f"G2,{lat},{lon + 1e-5},300"], survey_crs="EPSG:4326")
    with pytest.raises(ConfigError, match="output_crs.*not a projected"):
        survey(rows, output_crs="EPSG:4326")


def test_continued_list_drops_foreign_images_and_outside_marks(flight, tmp_path):
    root, truth = flight
    finder = find_candidates(cfg_for(root, tmp_path))
    (gid, image), (u, v) = next(iter(truth.items()))
    g = finder.gcps[gid]
    earlier = tmp_path / "earlier.txt"
    earlier.write_text(
        f"EPSG:32614\n{g.x} {g.y} {g.z} {u} {v} {image} {gid}\n"
        f"{g.x} {g.y} {g.z} 10 10 OTHER_FLIGHT_0001.JPG {gid}\n"
        f"{g.x} {g.y} {g.z} 10 99999 {image} {gid}\n"
    )
    store = MarkStore(finder, tmp_path / "gcp_list.txt", autosave=False)
    assert store.load(earlier) == 1 and list(store.marks) == [(gid, image)]
    earlier.write_text(f"EPSG:32614\n{g.x} {g.y} {g.z} nan {v} {image} {gid}\n")
    with pytest.raises(InputError, match="line 2"):
        store.load(earlier)
    # run() writes the continued list back without them, even without 'auto'
    earlier.write_text(
        f"EPSG:32614\n{g.x} {g.y} {g.z} {u} {v} {image} {gid}\n{g.x} {g.y} {g.z} 10 10 OTHER_FLIGHT_0001.JPG {gid}\n"
    )
    run(cfg_for(root, tmp_path / "out", gcp_list=earlier))
    assert [(m.gcp, m.image) for m in read_gcp_list(tmp_path / "out" / "gcp_list.txt")[2]] == [(gid, image)]


def test_the_folders_picture_of_the_window_shows_its_current_help():
    """``1_gcp_finder/gui.png`` is drawn by docs/gui/folder_windows.py, which records the help line it shows."""
    import hashlib

    from matchplant.gcp_finder.gui import HELP

    with Image.open(ROOT / "1_gcp_finder" / "gui.png") as im:
        shown = im.text.get("help_sha1")
    assert shown == hashlib.sha1(HELP.encode()).hexdigest(), (
        "1_gcp_finder/gui.png shows an older window: python docs/gui/folder_windows.py <demo output>"
    )
