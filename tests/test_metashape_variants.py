"""Variants of real Metashape camera exports: each read exactly, or refused naming the file, the problem and the fix.

The base is a real Metashape 2.0.2 export (tests/data/metashape-geograypher) and a real multispectral rig's cameras
(tests/data/metashape-multispectral-easyidp); each variant is the real file changed as Metashape writes that variant
(an older layout, a group, a disabled photo, a second component, a chunk matrix, a BOM...), and the poses read from
it are compared with the poses read from the unchanged file.
"""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from matchplant.core.formats.camera_report import summary
from matchplant.core.formats.metashape import read_metashape
from matchplant.core.formats.projects import PhotoProject, open_project
from matchplant.core.runtime.errors import InputError

DATA = Path(__file__).parent / "data"
GEOGRAYPHER = DATA / "metashape-geograypher" / "composite_georef_cameras.xml"
RIG = DATA / "metashape-multispectral-easyidp" / "cameras.xml"
TEXT = GEOGRAYPHER.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def base():
    """The unchanged real export, read once."""
    return read_metashape(GEOGRAYPHER)


def _write(tmp_path: Path, text: str, name: str = "cameras.xml", **kw) -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8") if not kw else kw["data"])
    return path


def _centres(cs) -> dict[str, np.ndarray]:
    """Camera centres in the map CRS by label."""
    return {k: c for k, c in zip(cs.posed, cs.centres_map())}


def _same_poses(a, b, labels=None, tol=1e-6):
    """The posed photos of ``b`` (or ``labels``) have the poses of ``a``: centres (map metres) and rotations from
    geocentric axes (each set's east-north-up frame sits at the mean of its own cameras)."""
    ca, cb = _centres(a), _centres(b)
    labels = labels if labels is not None else list(cb)
    assert labels
    for k in labels:
        assert np.abs(ca[k] - cb[k]).max() < tol, k
        ra = a.posed[k].shot.R @ a.frame.Q
        rb = b.posed[k].shot.R @ b.frame.Q
        assert np.abs(ra - rb).max() < 1e-9, k


def test_rig_reads_the_master_band_and_names_the_bands_left_out(caplog):
    """A DJI multispectral rig's real cameras: the master band (G) keeps its pose; the secondary bands (master_id,
    no transform) and the disabled calibration photos are left out, each reason said once in the log and in the
    cameras summary; the pose is the file's transform through the component's (checked by hand here)."""
    with caplog.at_level(logging.WARNING, logger="matchplant"):
        cs = read_metashape(RIG)
    assert list(cs.photos) == ["DJI_20230901130208_0001_MS_G"]
    (rig_why,) = [k for k in cs.left_out if "multi-camera rig" in k]
    assert sorted(cs.left_out[rig_why]) == sorted(
        [f"DJI_2023090113{t}_0001_MS_{b}" for t in ("2303", "0208") for b in ("R", "RE", "NIR")]
    )
    (off,) = [k for k in cs.left_out if "disabled" in k]
    assert cs.left_out[off] == ["DJI_20230901132303_0001_MS_G"]
    assert "6 photos left out, secondary bands of a multi-camera rig" in caplog.text
    assert "1 photos left out, disabled in Metashape" in caplog.text
    text = summary(PhotoProject(cs))
    assert "left out: 6 photos, secondary bands" in text and "left out: 1 photos, disabled" in text
    # the component is east-north-up at the camera's GPS reference (scale 1): the centre is the transform's
    # translation in that frame, and the camera looks down (its z axis the transform's third column)
    shot = cs.photos["DJI_20230901130208_0001_MS_G"].shot
    frame = cs.frame
    enu = np.array([-29.677549141381292, -8.9185737325389045, -2.5813933981741113])
    geo = shot.center @ frame.Q + frame.origin  # the inverse of frame.from_geocentric
    R = np.array([[-0.873318016260597, 0.25543032333035204, -0.4148144071726625],
                  [-0.48715053369020916, -0.45791164709166216, 0.7436405589955039],
                  [0.0, 0.8515117576294251, 0.5243355095917567]])  # fmt: skip
    origin = np.array([-2648206.930808965, 4747458.256778527, 3324989.496254708])
    assert np.abs(geo - (R @ enu + origin)).max() < 1e-6


def test_rig_camera_with_a_transform_is_still_left_out(tmp_path):
    """A secondary band's camera is posed through its master whatever it carries: never read on its own."""
    text = RIG.read_text().replace(
        '<camera id="581" sensor_id="1" component_id="0" master_id="580" label="DJI_20230901130208_0001_MS_R">',
        '<camera id="581" sensor_id="1" component_id="0" master_id="580" label="DJI_20230901130208_0001_MS_R">'
        "<transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform>",
    )
    cs = read_metashape(_write(tmp_path, text))
    assert "DJI_20230901130208_0001_MS_R" not in cs.photos


def test_photoscan_layout_before_1_4_is_refused_by_name(tmp_path):
    """PhotoScan's fx/fy/skew layout (cx, cy from the corner) is named, not read as focal length 0."""
    old = re.sub(r"<f>([^<]*)</f>", r"<fx>\1</fx><fy>\1</fy><skew>0</skew>", TEXT)
    old = old.replace('<document version="2.0.0">', '<document version="1.2.0">')
    path = _write(tmp_path, old)
    with pytest.raises(InputError) as err:
        read_metashape(path)
    msg = str(err.value)
    assert "before version 1.4" in msg and "<fx>, <fy>, <skew>" in msg and "Metashape 1.4 or later" in msg
    assert str(path) in msg


def test_calibration_without_f_is_refused(tmp_path):
    path = _write(tmp_path, re.sub(r"<f>[^<]*</f>", "", TEXT))
    with pytest.raises(InputError, match="has no focal length <f>"):
        read_metashape(path)


def test_initial_calibration_alone_is_refused_unless_fixed(tmp_path, base):
    """Only the initial calibration: not what the alignment used, refused; with the sensor's calibration fixed it
    is, and the photos read as with the adjusted one."""
    initial = TEXT.replace('class="adjusted"', 'class="initial"')
    with pytest.raises(InputError, match="only its initial calibration"):
        read_metashape(_write(tmp_path, initial))
    fixed = initial.replace(
        '<property name="layer_index" value="0" />',
        '<property name="layer_index" value="0" />\n        <property name="fixed" value="true" />',
    )
    cs = read_metashape(_write(tmp_path, fixed, "fixed.xml"))
    _same_poses(base, cs)
    cam, ref = next(iter(cs.sensors.values())), next(iter(base.sensors.values()))
    assert (cam.focal_x, cam.c_x, cam.k1, cam.p1) == (ref.focal_x, ref.c_x, ref.k1, ref.p1)


def test_adjusted_is_preferred_over_initial(tmp_path, base):
    """Both calibrations (EasyIDP's two_calib project keeps both): the adjusted one is read, whatever the order."""
    both = TEXT.replace(
        '<calibration type="frame" class="adjusted">',
        '<calibration type="frame" class="initial"><resolution width="4864" height="3648" /><f>3000</f></calibration>'
        '\n        <calibration type="frame" class="adjusted">',
    )
    cs = read_metashape(_write(tmp_path, both))
    _same_poses(base, cs)
    assert next(iter(cs.sensors.values())).focal_y == next(iter(base.sensors.values())).focal_y


def test_disabled_cameras_are_left_out(tmp_path, base):
    labels = list(base.posed)[:3]
    text = TEXT
    for k in labels:
        text = text.replace(f'label="{k}">', f'label="{k}" enabled="false">', 1)
    cs = read_metashape(_write(tmp_path, text))
    assert not set(labels) & set(cs.photos)
    assert sorted(next(v for k, v in cs.left_out.items() if "disabled" in k)) == sorted(labels)
    _same_poses(base, cs)


def test_cameras_in_group_folders_and_empty_transforms(tmp_path, base):
    """Cameras inside <group> folders read as at top level; an empty <transform/> is a photo without a pose."""
    start = TEXT.index("<camera ", TEXT.index("<cameras"))
    mid = TEXT.index("<camera ", TEXT.index("</camera>", start))
    text = TEXT[:start] + '<group id="0" label="Folder" type="folder">' + TEXT[start:mid] + "</group>" + TEXT[mid:]
    cs = read_metashape(_write(tmp_path, text))
    _same_poses(base, cs)
    assert len(cs.photos) == len(base.photos)
    first = list(base.posed)[0]
    blank = re.sub(r"<transform>[-0-9. e]+</transform>", "<transform />", TEXT, count=1)
    cs = read_metashape(_write(tmp_path, blank, "blank.xml"))
    assert cs.photos[first].shot is None and len(cs.posed) == len(base.posed) - 1


def test_reference_as_authority_code(tmp_path, base):
    """The chunk's CRS as Metashape's short authority code (EPSG::4326) reads as its WKT."""
    text = re.sub(r"<reference>GEOGCS[^<]*</reference>", "<reference>EPSG::4326</reference>", TEXT, count=1)
    assert text != TEXT
    cs = read_metashape(_write(tmp_path, text))
    _same_poses(base, cs)


def _component_text(second_transform: str | None) -> str:
    """The real file with its first three cameras moved to a second component (id 1), whose transform is the first
    one composed with a rigid motion A (the cameras' transforms carry A⁻¹), or none."""
    rot = [float(v) for v in re.search(r"<rotation locked=\"true\">([^<]*)<", TEXT).group(1).split()]
    tr = [float(v) for v in re.search(r"<translation locked=\"true\">([^<]*)<", TEXT).group(1).split()]
    s = float(re.search(r"<scale locked=\"true\">([^<]*)<", TEXT).group(1))
    R0, t0 = np.array(rot).reshape(3, 3), np.array(tr)
    a = np.radians(30.0)
    A = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    b = np.array([5.0, -3.0, 2.0])
    # X_geo = s R0 (A X' + b) + t0 = s (R0 A) X' + (s R0 b + t0); X' = A^T (X - b)
    R1, t1 = R0 @ A, s * R0 @ b + t0
    text = TEXT
    for m in list(re.finditer(r'component_id="0"([^>]*)>\s*<transform>([^<]*)</transform>', TEXT))[:3]:
        T = np.array(m.group(2).split(), dtype=float).reshape(4, 4)
        T2 = np.eye(4)
        T2[:3, :3], T2[:3, 3] = A.T @ T[:3, :3], A.T @ (T[:3, 3] - b)
        new = f'component_id="1"{m.group(1)}>\n        <transform>' + " ".join(repr(float(v)) for v in T2.ravel())
        text = text.replace(m.group(0), new + "</transform>")
    comp = (
        '<component id="1" label="Component 2">'
        + (
            "<transform><rotation>" + " ".join(map(repr, R1.ravel().tolist())) + "</rotation><translation>"
            + " ".join(map(repr, t1.tolist())) + f"</translation><scale>{s!r}</scale></transform>"
            if second_transform
            else ""
        )
        + "</component>"
    )  # fmt: skip
    return text.replace("</components>", comp + "</components>")


def test_several_components_each_with_its_transform(tmp_path, base):
    """Cameras in a second component with its own transform land where they were (within a micrometre)."""
    cs = read_metashape(_write(tmp_path, _component_text("yes")))
    _same_poses(base, cs, tol=1e-6)
    assert len(cs.posed) == len(base.posed)


def test_component_without_a_transform_leaves_its_cameras_without_a_pose(tmp_path, base):
    cs = read_metashape(_write(tmp_path, _component_text(None)))
    (why,) = [k for k in cs.left_out if "component 1" in k]
    assert len(cs.left_out[why]) == 3 and all(cs.photos[k].shot is None for k in cs.left_out[why])
    assert len(cs.posed) == len(base.posed) - 3


def test_unknown_component_is_refused(tmp_path):
    text = TEXT.replace('component_id="0"', 'component_id="7"', 1)
    with pytest.raises(InputError, match="names component 7"):
        read_metashape(_write(tmp_path, text))


def test_chunk_transform_as_matrix(tmp_path, base):
    """Metashape 1.x's chunk <transform><matrix> (4x4, scale in it), no components: the same poses."""
    rot = np.array(re.search(r"<rotation locked=\"true\">([^<]*)<", TEXT).group(1).split(), dtype=float)
    tr = np.array(re.search(r"<translation locked=\"true\">([^<]*)<", TEXT).group(1).split(), dtype=float)
    s = float(re.search(r"<scale locked=\"true\">([^<]*)<", TEXT).group(1))
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = s * rot.reshape(3, 3), tr
    text = re.sub(r"<components.*</components>", "", TEXT, flags=re.S).replace(' component_id="0"', "")
    text = text.replace("</cameras>", "</cameras><transform><matrix>" + " ".join(map(repr, M.ravel().tolist()))
                        + "</matrix></transform>")  # fmt: skip
    cs = read_metashape(_write(tmp_path, text))
    _same_poses(base, cs, tol=1e-5)
    bad = text.replace("<matrix>", "<matrix>2 ", 1).replace(" 1</matrix>", "</matrix>")
    with pytest.raises(InputError, match="matrix"):
        read_metashape(_write(tmp_path, bad, "bad.xml"))


def test_bom_and_crlf(tmp_path, base):
    """A file saved by a Windows editor (UTF-8 BOM, CRLF line ends) reads the same."""
    data = b"\xef\xbb\xbf" + TEXT.replace("\n", "\r\n").encode("utf-8")
    cs = read_metashape(_write(tmp_path, "", data=data))
    _same_poses(base, cs)


def test_sensor_without_calibration_of_unaligned_photos(tmp_path, base):
    """A second sensor never calibrated (its photos not aligned; EasyIDP met one) does not stop the file."""
    unaligned = [k for k in base.photos if base.photos[k].shot is None]
    text = TEXT.replace(
        "</sensors>",
        '<sensor id="1" label="other" type="frame"><resolution width="100" height="80" /></sensor></sensors>',
    )
    text = text.replace(f'sensor_id="0" label="{unaligned[0]}"', f'sensor_id="1" label="{unaligned[0]}"')
    cs = read_metashape(_write(tmp_path, text))
    _same_poses(base, cs)
    assert unaligned[0] not in cs.photos
    assert any(unaligned[0] in v for v in cs.left_out.values())


def test_reference_as_compound_crs(tmp_path, base):
    """A compound CRS (WGS 84 + EGM96 height, as WKT): the chunk's transform is geocentric, so the cameras land
    where they did (the map is the UTM zone, ellipsoidal heights); a projected compound CRS whose geoid grid PROJ
    lacks here is refused naming the ballpark shift, never read with heights off by the geoid."""
    pyproj = pytest.importorskip("pyproj")
    wkt = pyproj.CRS.from_user_input("EPSG:4326+5773").to_wkt("WKT1_GDAL")
    text = re.sub(r"<reference>GEOGCS[^<]*</reference>", "<reference>" + wkt + "</reference>", TEXT, count=1)
    cs = read_metashape(_write(tmp_path, text))
    assert cs.frame.crs.name == base.frame.crs.name == "WGS 84 / UTM zone 10N"
    _same_poses(base, cs)
    navd = pyproj.CRS.from_user_input("EPSG:32610+5703")
    if navd.to_wkt() and not pyproj.network.is_network_enabled():
        wkt = navd.to_wkt()
        text = re.sub(r"<reference>GEOGCS[^<]*</reference>", "<reference>" + wkt + "</reference>", TEXT, count=1)
        try:
            read_metashape(_write(tmp_path, text, "navd.xml"))
        except Exception as exc:  # noqa: BLE001 - which error class PROJ's refusal takes is checked by its text
            assert "ballpark" in str(exc)


def test_psx_photo_paths_are_relative_to_the_frame_document(tmp_path, data_dir):
    """A .psx stores each photo's path relative to its frame.zip (``../../../<folder>/DJI_0001.JPG`` in EasyIDP's
    real wheat project): the photos beside the project are found there, not by guessing a folder."""
    shutil.copytree(data_dir / "metashape-wheat", tmp_path / "wheat")
    psx = tmp_path / "wheat" / "wheat_tanashi.psx"
    photos = tmp_path / "wheat" / "wheat_tanashi_kato3N_20190314_Ins1RGB_30m"
    photos.mkdir()
    project = open_project(psx, "metashape")
    for sid in project.shot_ids(False):
        (photos / sid).write_bytes(b"")
    found = project.image_paths()
    assert len(found) == len(project.shot_ids(False)) > 100
    assert {p.parent for p in found.values()} == {photos} and all(p.name == sid for sid, p in found.items())
