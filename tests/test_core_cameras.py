"""Metashape and Pix4D projects read into one camera record, checked on real exports (tests/data/*/NOTE.md)."""

from __future__ import annotations

import shutil
import time
import zipfile
from dataclasses import replace
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pyproj
import pytest

from matchplant.core.formats.gcp_list import Mark
from matchplant.core.formats.gcp_marks import write_metashape_markers, write_pix4d_gcps, write_pix4d_marks
from matchplant.core.formats.metashape import read_metashape
from matchplant.core.formats.pix4d import read_pix4d, read_pmatrix
from matchplant.core.geometry.frame_camera import FrameCamera
from matchplant.core.geometry.geodetic import DatumTopocentricFrame, TangentFrame
from matchplant.core.runtime.errors import InputError

DATA = Path(__file__).parent / "data"
WHEAT = DATA / "metashape-wheat" / "wheat_tanashi.psx"
GEOGRAYPHER = DATA / "metashape-geograypher" / "composite_georef_cameras.xml"
PIX4D = DATA / "pix4d-easyidp"
PARAMS = PIX4D / "1_initial" / "params"


def _marker_points(cs):
    """Each marker's reference position in the set's frame, with its marks."""
    out = []
    for m in cs.markers:
        tr = pyproj.Transformer.from_crs(m.crs.to_3d(), cs.frame.crs.to_3d(), always_xy=True)
        out.append((m, cs.frame.from_map(np.array(tr.transform(*m.xyz))[None])[0]))
    return out


def _triangulate(shots, uvs) -> np.ndarray:
    """The point nearest to every ray through the marks (least squares)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for shot, uv in zip(shots, uvs):
        d = shot.ray_directions(np.array([uv]))[0]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ shot.center
    return np.linalg.solve(A, b)


@pytest.mark.independent
def test_metashape_markers_reproject_onto_the_operators_marks():
    """The wheat project's six surveyed markers, projected into the 23 photos an operator marked them on.

    Two figures. (1) Each marker triangulated from its own marks and projected back: this checks the camera
    model and the poses without the georeferencing. Metashape's own tie-point RMS for this chunk is 1.05 px
    (meta OptimizeCameras/sigma0) and a hand-placed mark adds about as much, so per axis σ ≈ 1.5 px: a 2D
    distance then has median 1.18σ ≈ 1.8 px and 95th percentile 2.45σ ≈ 3.7 px; we hold 2.5 and 4.5 px (a
    principal point with the wrong sign gives 45 px, checked below). (2) The surveyed coordinates projected
    directly: this adds the georeferencing (chunk transform, WGS 84 -> geocentric -> UTM). The markers sit
    where the bundle puts them to within the bundle's own vertical disagreement with the survey (triangulated
    minus surveyed: 9-24 cm, mostly height, from three nearly nadir views 30 m up); at the 6.3 mm ground pixel
    and the 15-30° view angles of the marks that is 3-10 px, so we hold median 8 px and 95th percentile 12 px.
    A datum or height error (the geoid here is 37 m) or a swapped axis would put the markers hundreds of
    pixels off."""
    cs = read_metashape(WHEAT)
    assert len(cs.posed) == 138 and not cs.unposed and len(cs.markers) == 6
    assert cs.photos["DJI_0001"].name == "DJI_0001.JPG"  # from the photo's path in frame.zip
    assert cs.frame.crs.to_epsg() == 32654
    direct, back, flipped = [], [], []
    for marker, ref in _marker_points(cs):
        shots = [cs.photos[k].shot for k in marker.marks]
        uvs = list(marker.marks.values())
        x = _triangulate(shots, uvs)
        for shot, uv in zip(shots, uvs):
            direct.append(np.hypot(*(shot.project(ref[None])[0] - uv)))
            back.append(np.hypot(*(shot.project(x[None])[0] - uv)))
        wrong = [s.with_camera(replace(s.camera, c_x=-s.camera.c_x)) for s in shots]
        xw = _triangulate(wrong, uvs)
        flipped += [np.hypot(*(s.project(xw[None])[0] - uv)) for s, uv in zip(wrong, uvs)]
    assert len(direct) == 23
    assert np.median(back) < 2.5 and np.percentile(back, 95) < 4.5, (np.median(back), np.percentile(back, 95))
    assert np.median(direct) < 8 and np.percentile(direct, 95) < 12, (np.median(direct), np.percentile(direct, 95))
    assert np.median(flipped) > 20  # the check above can tell a wrong convention


@pytest.mark.independent
def test_metashape_export_xml_places_cameras_at_their_gps():
    """Metashape 2.0's export (component transforms, a WGS 84 chunk): the aligned camera centres land within GPS
    error of the cameras' own (unused) GPS tags; the 7 unaligned photos are named, not placed."""
    cs = read_metashape(GEOGRAYPHER)
    assert len(cs.photos) == 47 and len(cs.unposed) == 7 and "oblique-v3/202MEDIA/DJI_0078.JPG" in cs.unposed
    assert cs.photos["nadir/102MEDIA/DJI_0002.JPG"].name == "DJI_0002.JPG"
    refs = {
        c.get("label"): [float(c.find("reference").get(k)) for k in "xyz"]
        for c in ElementTree.parse(GEOGRAYPHER).getroot().iter("camera")
    }
    tr = pyproj.Transformer.from_crs("EPSG:4979", cs.frame.crs.to_3d(), always_xy=True)
    gps = np.array([tr.transform(*refs[k]) for k in cs.posed])
    off = np.hypot(*(cs.centres_map() - gps)[:, :2].T)
    assert np.median(off) < 5, np.median(off)  # consumer GPS: metres; a wrong datum or axis: kilometres


def test_metashape_camera_model_matches_the_manual(tmp_path):
    """Our camera against Metashape's formulas written out (manual, appendix "Camera models"), with the real
    calibration of EasyIDP's goya project (b1, b2, k1..k4, p1, p2 all non-zero)."""
    cal = dict(f=3013.7286896854812, cx=219.81021538195535, cy=-41.698648463345691, b1=2.1663197269770209,
               b2=1.3172242107907306, k1=0.024049145279139067, k2=-0.062259130075893766, k3=0.080114191207232066,
               k4=-0.042086840510821462, p1=0.022622306021091419, p2=-0.0004632318923652631)  # fmt: skip
    w, h = 4000, 3000
    xml = "".join(f"<{k}>{v!r}</{k}>" for k, v in cal.items())
    doc = (
        f'<document version="1.5.0"><chunk label="c"><sensors><sensor id="0" label="s" type="frame">'
        f'<resolution width="{w}" height="{h}"/><calibration type="frame" class="adjusted">'
        f'<resolution width="{w}" height="{h}"/>{xml}</calibration></sensor></sensors><cameras>'
        f'<camera id="0" sensor_id="0" label="a.jpg"><transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform>'
        f"</camera></cameras><transform><rotation>1 0 0 0 1 0 0 0 1</rotation><translation>6378137 0 0"
        f"</translation><scale>1</scale></transform><reference>EPSG:4326</reference></chunk></document>"
    )
    (tmp_path / "cameras.xml").write_text(doc)
    cam = read_metashape(tmp_path / "cameras.xml").photos["a.jpg"].camera
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.45, 0.45, 500)
    r2 = x * x + y * y
    rad = 1 + cal["k1"] * r2 + cal["k2"] * r2**2 + cal["k3"] * r2**3 + cal["k4"] * r2**4
    xp = x * rad + cal["p1"] * (r2 + 2 * x * x) + 2 * cal["p2"] * x * y
    yp = y * rad + cal["p2"] * (r2 + 2 * y * y) + 2 * cal["p1"] * x * y
    u = w * 0.5 + cal["cx"] + xp * cal["f"] + xp * cal["b1"] + yp * cal["b2"]
    v = h * 0.5 + cal["cy"] + yp * cal["f"]
    ours = cam.project(np.stack([x, y, np.ones_like(x)], axis=1))
    np.testing.assert_allclose(ours, np.stack([u - 0.5, v - 0.5], axis=1), atol=1e-9)  # pixel centres at integers
    back = cam.bearings(ours)
    np.testing.assert_allclose(back[:, :2] / back[:, 2:], np.stack([x, y], axis=1), atol=1e-12)


@pytest.mark.independent
def test_pix4d_projection_agrees_with_its_p_matrices():
    """Pix4D's own P matrices (pmatrix.txt: offset coordinates to undistorted pixels) against our K, R, t read
    from calibrated_camera_parameters.txt: < 0.01 px over a 9x7 grid of every one of the 168 photos, with the
    ground 15 m below (the flight's height above the offset's origin)."""
    cs = read_pix4d(PIX4D)
    pm = read_pmatrix(PARAMS / "pix4d.origin_pmatrix.txt")
    assert len(cs.photos) == 168 and set(pm) == set(cs.photos)
    worst = 0.0
    for name, P in pm.items():
        shot = cs.photos[name].shot
        cam = shot.camera
        gu, gv = np.meshgrid(np.linspace(0, cam.width - 1, 9), np.linspace(0, cam.height - 1, 7))
        d = shot.ray_directions(np.stack([gu.ravel(), gv.ravel()], axis=1))
        X = shot.center + d * ((0.0 - shot.center[2]) / d[:, 2:])
        ours = cam.undistorted_project(shot.world_to_camera(X)) + 0.5  # Pix4D: pixel corners at integers
        hom = np.c_[X, np.ones(len(X))] @ P.T
        worst = max(worst, float(np.abs(ours - hom[:, :2] / hom[:, 2:]).max()))
    assert worst < 0.01, worst


@pytest.mark.independent
def test_pix4d_principal_point_is_measured_from_the_image_corner():
    """Pix4D's .cam file gives the principal point offset from the image centre in pixels: w/2 - cx and
    h/2 - cy of K, so Pix4D's image centre is (w/2, h/2) and its pixel origin the image's corner."""
    cs = read_pix4d(PIX4D)
    cam = next(iter(cs.sensors.values()))
    text = (PARAMS / "pix4d.origin_pix4d_calibrated_internal_camera_parameters.cam").read_text()
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if "offset xpoff ypoff in pixel" in ln.lower())
    xpoff, ypoff = (float(lines[i + j].split()[1]) for j in (1, 2))
    s = max(cam.width, cam.height)
    # ours: c = (cx - w/2)/S, so the .cam's offsets are -c*S (with pixel centres as origin they would differ by 0.5)
    assert abs(-cam.c_x * s - xpoff) < 1e-6 and abs(-cam.c_y * s - ypoff) < 1e-6


def test_datum_topocentric_frame_is_the_geocentric_frame_moved():
    """Points in the frame convert to the map exactly as PROJ converts their geocentric coordinates, on WGS 84
    and on another datum (NAD83, GRS 1980)."""
    for geo, proj in ((4326, 32610), (4269, 26910)):
        crs = pyproj.CRS.from_epsg(geo)
        frame = DatumTopocentricFrame(38.97, -120.09, 10.0, crs, pyproj.CRS.from_epsg(proj))
        cart = pyproj.Transformer.from_crs(
            pyproj.CRS({"proj": "geocent", "ellps": "WGS84" if geo == 4326 else "GRS80"}),
            pyproj.CRS.from_epsg(proj).to_3d(),
            always_xy=True,
        )
        geoc = frame.origin + np.random.default_rng(2).normal(size=(20, 3)) * 300
        want = np.stack(cart.transform(*geoc.T), axis=1)
        np.testing.assert_allclose(frame.to_map(frame.from_geocentric(geoc)), want, atol=1e-6)


def test_frame_camera_round_trip_with_k4_and_skew():
    """Pixels -> bearings -> pixels returns the pixels (the Newton inverse with k4 and skew)."""
    cam = FrameCamera("c", "brown", 4000, 3000, 0.75, 0.76, 0.01, -0.02, k1=0.02, k2=-0.06, k3=0.08, p1=-4e-4,
                      p2=0.02, k4=-0.04, skew=3e-4)  # fmt: skip
    uv = np.random.default_rng(3).uniform([0, 0], [3999, 2999], size=(2000, 2))
    np.testing.assert_allclose(cam.project(cam.bearings(uv)), uv, atol=1e-7)


# -- bad input -----------------------------------------------------------------------------------------------
def _copy_wheat(tmp_path: Path) -> Path:
    shutil.copytree(WHEAT.parent, tmp_path / "wheat")
    return tmp_path / "wheat" / WHEAT.name


def _rewrite_chunk(psx: Path, edit) -> None:
    """Apply ``edit`` to the chunk's doc.xml inside chunk.zip."""
    z = psx.with_suffix(".files") / "0" / "chunk.zip"
    with zipfile.ZipFile(z) as f:
        text = f.read("doc.xml").decode()
    with zipfile.ZipFile(z, "w") as f:
        f.writestr("doc.xml", edit(text))


def test_bad_metashape_inputs_name_the_file_and_the_fix(tmp_path):
    """Truncated, foreign, unaligned-only and local (unreferenced) exports are refused, naming file and fix."""
    text = GEOGRAYPHER.read_text()
    cases = {
        "truncated": (text[: len(text) // 2], "not complete XML"),
        "other XML": ('<?xml version="1.0"?><gpx><trk/></gpx>', "not a Metashape camera export"),
        "pix4d file": ((PARAMS / "pix4d.origin_calibrated_camera_parameters.txt").read_text(), "not complete XML"),
        "unaligned": (_strip(text, "<transform>", "</transform>", only_cameras=True), "none of the 47 photos"),
        "local": (_strip(text, "<reference>", "</reference>"), "local coordinate system"),
    }
    for name, (body, words) in cases.items():
        f = tmp_path / f"{name}.xml"
        f.write_text(body)
        with pytest.raises(InputError) as err:
            read_metashape(f)
        msg = str(err.value)
        assert words in msg and str(f) in msg and "fix:" in msg, (name, msg)
    psx = _copy_wheat(tmp_path)
    _rewrite_chunk(psx, lambda t: _strip(t, "<reference>", "</reference>"))
    with pytest.raises(InputError, match="local coordinate system"):
        read_metashape(psx)


def _strip(text: str, start: str, end: str, *, only_cameras: bool = False) -> str:
    """``text`` without every ``start ... end`` (with only_cameras: only one-line camera transforms)."""
    out, i = [], 0
    while (j := text.find(start, i)) >= 0:
        k = text.find(end, j) + len(end)
        if only_cameras and "\n" in text[j:k]:
            out.append(text[i:k])
        else:
            out.append(text[i:j])
        i = k
    return "".join(out) + text[i:]


def test_bad_pix4d_inputs_name_the_file_and_the_fix(tmp_path):
    """A missing offset or .prj file, and a truncated parameters file, are refused by name."""
    for missing in ("pix4d.origin_offset.xyz", "pix4d.origin_wkt.prj"):
        shutil.copytree(PARAMS, tmp_path / missing / "params")
        (tmp_path / missing / "params" / missing).unlink()
        with pytest.raises(InputError) as err:
            read_pix4d(tmp_path / missing / "params")
        assert missing in str(err.value) and "Camera Internals and Externals" in str(err.value)
    shutil.copytree(PARAMS, tmp_path / "cut")
    ccp = tmp_path / "cut" / "pix4d.origin_calibrated_camera_parameters.txt"
    ccp.write_text("\n".join(ccp.read_text().splitlines()[:-3]))
    with pytest.raises(InputError, match="truncated"):
        read_pix4d(ccp)


# -- speed ---------------------------------------------------------------------------------------------------
def test_reading_2000_photos_takes_under_two_seconds(tmp_path):
    """A 2,000-photo Metashape export and Pix4D parameters file (real ones, their photos repeated) read in < 2 s."""
    text = GEOGRAYPHER.read_text()
    a, b = text.index("<camera id="), text.index("</cameras>")
    cams = [c for c in text[a:b].split("</camera>") if "<transform>" in c]
    many = "".join(
        c.replace(c[c.index("<camera id=") : c.index(">", c.index("<camera id=")) + 1],
                  f'<camera id="{k}" sensor_id="0" component_id="0" label="p{k}.JPG">') + "</camera>"
        for k, c in zip(range(2000), cams * 50)
    )  # fmt: skip
    (tmp_path / "big.xml").write_text(text[:a] + many + text[b:])
    lines = (PARAMS / "pix4d.origin_calibrated_camera_parameters.txt").read_text().splitlines()
    head, blocks = lines[:8], [lines[8 + 10 * k : 18 + 10 * k] for k in range(168)]
    body = [f"p{k}.JPG 5472 3648\n" + "\n".join(blocks[k % 168][1:]) for k in range(2000)]
    (tmp_path / "params").mkdir()
    for f in ("pix4d.origin_offset.xyz", "pix4d.origin_wkt.prj"):
        shutil.copy(PARAMS / f, tmp_path / "params" / f)
    (tmp_path / "params" / "pix4d.origin_calibrated_camera_parameters.txt").write_text("\n".join(head + body))
    read_metashape(GEOGRAYPHER)  # PROJ's database opened once, as in any run
    for reader, src in ((read_metashape, tmp_path / "big.xml"), (read_pix4d, tmp_path / "params")):
        t0 = time.perf_counter()
        cs = reader(src)
        took = time.perf_counter() - t0
        assert len(cs.posed) == 2000 and took < 2.0, (reader.__name__, took)


def test_gcp_marks_are_written_as_metashape_and_pix4d_import_them(tmp_path):
    """The wheat project's real markers and marks, read by our Metashape reader and written by module 1's writers
    in Metashape's marker XML and Pix4D's marks file: the pixels come out as Metashape stored them (both programs
    count from the image's corner, our reader from the centre of the first pixel), the coordinates as surveyed."""
    cs = read_metashape(WHEAT)
    marks = [
        Mark(*m.xyz, u, v, cs.photos[label].name, m.label) for m in cs.markers for label, (u, v) in m.marks.items()
    ]
    frame = zipfile.ZipFile(WHEAT.with_suffix(".files") / "0" / "0" / "frame.zip").read("doc.xml")
    stored = {
        (m.get("marker_id"), loc.get("camera_id")): (float(loc.get("x")), float(loc.get("y")))
        for m in ElementTree.fromstring(frame).findall("markers/marker")
        for loc in m.findall("location")
    }
    chunk = ElementTree.fromstring(zipfile.ZipFile(WHEAT.with_suffix(".files") / "0" / "chunk.zip").read("doc.xml"))
    cam_id = {c.get("label"): c.get("id") for c in chunk.findall("cameras/camera")}
    marker_id = {m.get("label"): m.get("id") for m in chunk.findall("markers/marker")}
    write_pix4d_marks(tmp_path / "pix4d_marks.csv", marks)
    write_pix4d_gcps(tmp_path / "pix4d_gcps.csv", cs.markers[0].crs, marks)
    ids = {cs.photos[label].name: cam_id[label] for label in cs.photos if label in cam_id}
    write_metashape_markers(tmp_path / "metashape_markers.xml", marks, ids)
    rows = [ln.split(",") for ln in (tmp_path / "pix4d_marks.csv").read_text().splitlines()]
    assert len(rows) == len(stored) == 23
    for image, gcp, x, y in rows:  # module 1's writer rounds to 3 decimals
        want = stored[(marker_id[gcp], cam_id[image.rsplit(".", 1)[0]])]
        assert abs(float(x) - want[0]) < 6e-4 and abs(float(y) - want[1]) < 6e-4
    doc = ElementTree.parse(tmp_path / "metashape_markers.xml").getroot().find("chunk")
    names = {m.get("id"): m.get("label") for m in doc.findall("markers/marker")}
    for m in doc.findall("frames/frame/markers/marker"):
        for loc in m.findall("location"):
            key = (marker_id[names[m.get("marker_id")]], loc.get("camera_id"))
            assert (float(loc.get("x")), float(loc.get("y"))) == pytest.approx(stored[key], abs=6e-4)
    coords = (tmp_path / "pix4d_gcps.csv").read_text().splitlines()
    assert len(coords) == 6


def test_tangent_frame_departs_from_the_exact_conversion_by_the_earths_curvature():
    """A photo's tangent frame against the exact conversion (the wheat project's ENU frame to UTM): rays 60 m long
    in any direction within 60° of nadir stay within 0.4 mm (0.33 mm here: r²/2R and the turn of the map's grid); the
    camera centre is exact."""
    cs = read_metashape(WHEAT)
    shot = cs.photos["DJI_0040"].shot
    tangent = TangentFrame(cs.frame, shot.center)
    np.testing.assert_allclose(tangent.to_map(shot.center[None]), cs.frame.to_map(shot.center[None]), atol=1e-9)
    rng = np.random.default_rng(4)
    d = rng.normal(size=(500, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 1.2  # downward, within about 60° of nadir
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = shot.center + 60 * d
    err = np.linalg.norm(tangent.to_map(p) - cs.frame.to_map(p), axis=1)
    assert err.max() < 4e-4, err.max()
    np.testing.assert_allclose(tangent.from_map(tangent.to_map(p)), p, atol=1e-9)
    md = tangent.map_directions(d)
    np.testing.assert_allclose(np.linalg.norm(md, axis=1), 1.0)


def test_a_project_of_several_chunks_is_refused_by_name(tmp_path):
    """Two chunks in one file: both named, and the fix; a chosen one is read."""
    text = GEOGRAYPHER.read_text()
    a, b = text.index("<chunk "), text.index("</chunk>") + len("</chunk>")
    chunk = text[a:b]
    (tmp_path / "two.xml").write_text(text[:b] + chunk.replace('label="Chunk 1"', 'label="Chunk 2"', 1) + text[b:])
    with pytest.raises(InputError, match="2 chunks \\(Chunk 1, Chunk 2\\)") as err:
        read_metashape(tmp_path / "two.xml")
    assert "Export Cameras exports the active chunk" in str(err.value)
    assert len(read_metashape(tmp_path / "two.xml", chunk="Chunk 2").photos) == 47
