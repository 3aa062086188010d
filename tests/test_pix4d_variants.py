"""What real Pix4Dmapper projects look like on disk, read exactly or refused by name (docs/DESIGN.md §8).

Every variant is made from the real EasyIDP params folder (tests/data/pix4d-easyidp/NOTE.md) and must read to the
very cameras and poses of the untouched file, or be refused with an InputError naming the file and the fix.
The .p4d files follow Pix4D's ".p4d minimum format" article (support.pix4d.com/hc/en-us/articles/209829943:
``<pix4dmapper><inputs><cameras/><images><image path=.../></images></inputs></pix4dmapper>``), written here.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from matchplant.core.formats.pix4d import read_pix4d
from matchplant.core.formats.projects import detect_project, open_project
from matchplant.core.runtime.errors import InputError

DATA = Path(__file__).parent / "data" / "pix4d-easyidp"
NAME = "pix4d.origin"
CCP = f"{NAME}_calibrated_camera_parameters.txt"
UTM54 = (DATA / "1_initial" / "params" / f"{NAME}_wkt.prj").read_text()
FEET = (
    'PROJCS["NAD83 / UTM zone 15N (ftUS)",GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",'
    '6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION['
    '"Transverse_Mercator"],PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",-93],PARAMETER['
    '"scale_factor",0.9996],PARAMETER["false_easting",1640416.667],PARAMETER["false_northing",0],UNIT['
    '"US survey foot",0.304800609601219]]'
)
EGM96 = 'VERT_CS["EGM96 height",VERT_DATUM["EGM96 geoid",2005],UNIT["metre",1]]'


@pytest.fixture(scope="module")
def original():
    """The untouched project as read: the reference every variant must give."""
    return read_pix4d(DATA)


def project(tmp_path: Path, name: str = "field") -> Path:
    """A copy of the real project folder; returns its params folder."""
    shutil.copytree(DATA, tmp_path / name, ignore=shutil.ignore_patterns("NOTE.md"))
    return tmp_path / name / "1_initial" / "params"


def same(cs, original, rename=lambda k: k) -> None:
    """Every photo of ``original`` in ``cs`` (under its new label), with the same camera and pose to the bit."""
    assert len(cs.posed) == len(original.posed)
    for k, p in original.posed.items():
        q = cs.photos[rename(k)]
        assert np.array_equal(q.shot.center, p.shot.center) and np.array_equal(q.shot.rotation, p.shot.rotation)
        assert q.camera == replace(p.camera, id=q.camera.id)  # ids are numbered as read


def test_layouts_real_exports_have_read_the_same(tmp_path, original):
    """CRLF line ends, a byte-order mark, no blank line after the header or blank lines between blocks, trailing
    spaces and tabs: the same 168 photos, cameras and poses as the untouched file."""
    lines = (DATA / "1_initial" / "params" / CCP).read_text().splitlines()
    head, body = lines[:8], lines[8:]
    variants = {
        "crlf": "\r\n".join(lines) + "\r\n",
        "bom": "\ufeff" + "\n".join(lines),
        "tight": "\n".join(lines[:7] + body),
        "airy": "\n".join(head + [ln + ("\n" if i % 10 == 9 else "") for i, ln in enumerate(body)]) + "\n\n\n",
        "spaces": "\n".join(ln + " \t" for ln in lines),
    }
    for key, text in variants.items():
        params = project(tmp_path, key)
        (params / CCP).write_bytes(text.encode("utf-8"))
        same(read_pix4d(params), original)


def test_image_names_with_spaces_or_folders_keep_their_label(tmp_path, original):
    """A name with spaces is the whole name before 'width height'; a name with folders (Windows or POSIX) is
    labelled as written, its file name is the last part and the folders are kept as its path."""
    params = project(tmp_path)
    text = (params / CCP).read_text()
    text = text.replace("DJI_0172.JPG 5472", "my photo 0172.JPG 5472").replace(
        "DJI_0173.JPG 5472", "flight 2\\DJI_0173.JPG 5472"
    )
    (params / CCP).write_text(text)
    cs = read_pix4d(params)
    renamed = {"DJI_0172.JPG": "my photo 0172.JPG", "DJI_0173.JPG": "flight 2\\DJI_0173.JPG"}
    same(cs, original, lambda k: renamed.get(k, k))
    assert cs.photos["my photo 0172.JPG"].name == "my photo 0172.JPG"
    moved = cs.photos["flight 2\\DJI_0173.JPG"]
    assert moved.name == "DJI_0173.JPG" and moved.path == "flight 2\\DJI_0173.JPG"


def test_a_missing_or_extra_line_is_named_where_it_is(tmp_path):
    """A block short of a line (a hand edit, a copy cut short) is named by its line and what it should hold,
    not read shifted; a file cut in the last block is 'truncated'; a file with no photo, or an empty one, says so."""
    params = project(tmp_path)
    lines = (params / CCP).read_text().splitlines()
    (params / CCP).write_text("\n".join(lines[: 8 + 10 * 5 + 5] + lines[8 + 10 * 5 + 6 :]))  # photo 6's tangential
    with pytest.raises(InputError, match=r"line 64 .*tangential distortion\) holds 3 values, not 2") as err:
        read_pix4d(params)
    assert CCP in str(err.value) and "Camera Internals and Externals" in str(err.value)
    (params / CCP).write_text("\n".join(lines[:-4]))
    with pytest.raises(InputError, match="truncated: the last photo's block"):
        read_pix4d(params)
    (params / CCP).write_text("\n".join(lines[:8]))
    with pytest.raises(InputError, match="lists no calibrated photo"):
        read_pix4d(params)
    (params / CCP).write_text("\n\n")  # Pix4D stopped before writing a line
    with pytest.raises(InputError, match="is empty"):
        read_pix4d(params)


def test_several_camera_models_in_one_project(tmp_path, original):
    """A project with two cameras (a multispectral rig's bands, or two drones: blocks with another size and K) is
    read as two sensors, each photo with its own block's calibration; the poses are untouched."""
    params = project(tmp_path)
    lines = (params / CCP).read_text().splitlines()
    for b in range(8, len(lines), 20):  # every other photo: a 1280x960 band of another focal length
        lines[b] = lines[b].replace("5472 3648", "1280 960")
        lines[b + 1], lines[b + 2] = "1400.5 0 640.25", "0 1400.5 480.75"
    (params / CCP).write_text("\n".join(lines))
    cs = read_pix4d(params)
    assert len(cs.sensors) == 2 and len(cs.posed) == 168
    small = [p for p in cs.photos.values() if p.camera.width == 1280]
    assert len(small) == 84 and all(abs(p.camera.focal_x * 1280 - 1400.5) < 1e-9 for p in small)
    assert all(abs(p.camera.c_y * 1280 - 0.75) < 1e-9 for p in small)  # 480.75 - 960/2
    for k, p in original.posed.items():
        assert np.array_equal(cs.photos[k].shot.center, p.shot.center)


@pytest.mark.parametrize(
    "file, text",
    [
        (f"{NAME}_camera.ssk", "begin camera_parameters x\n    camera_type:   fisheye\nend camera_parameters\n"),
        (f"{NAME}_pix4d_calibrated_internal_camera_parameters.cam", "Pix4D camera calibration file 0\n#Fisheye\n"),
        (f"{NAME}_calibrated_internal_camera_parameters.cam", "#Polynomial coefficients\nPOLY 0 1 0.1 0.01\n"),
        (f"../../{NAME}.p4d", '<pix4dmapper><inputs><cameras><camera name="x"><fisheye/></camera></cameras>'
                              "</inputs></pix4dmapper>"),
    ],
)  # fmt: skip
def test_a_fisheye_project_is_refused_by_name(tmp_path, file, text):
    """Pix4D's fisheye model would read as a pinhole from calibrated_camera_parameters.txt: wherever the project
    says fisheye (camera.ssk's camera_type, the .cam, the .p4d's cameras) it is refused, naming the file."""
    params = project(tmp_path, NAME)
    (params / file).write_text(text)
    with pytest.raises(InputError, match="not a perspective") as err:
        read_pix4d(params)
    assert Path(file).name in str(err.value)


def test_a_frame_camera_ssk_reads(tmp_path, original):
    """camera.ssk with ``camera_type: frame`` (Pix4D's perspective lens, as EasyIDP's maize project) reads."""
    params = project(tmp_path)
    (params / f"{NAME}_camera.ssk").write_text("begin camera_parameters x\r\n    camera_type:  frame\r\nend\r\n")
    same(read_pix4d(params), original)


def test_output_crs_variants(tmp_path, original):
    """A compound CRS (projected + vertical) places the cameras in its projected part; a missing .prj (Pix4D
    writes none in an arbitrary system), a local CRS, an empty file, a geographic CRS and one in feet are refused."""
    params = project(tmp_path)
    prj = params / f"{NAME}_wkt.prj"
    prj.write_text(f'COMPD_CS["WGS 84 / UTM zone 54N + EGM96 height",{UTM54.strip()},{EGM96}]')
    cs = read_pix4d(params)
    assert cs.frame.crs.to_epsg() == 32654 and np.array_equal(cs.centres_map(), original.centres_map())
    refused = {
        "": "is empty",
        'LOCAL_CS["Arbitrary (m)",LOCAL_DATUM["Arbitrary",0],UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH]]': "local",
        'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],'
        'UNIT["degree",0.0174532925199433]]': "not projected",
        FEET: "US survey foot",
        f'COMPD_CS["x",{UTM54.strip()},VERT_CS["h",VERT_DATUM["d",2005],UNIT["foot",0.3048]]]': "foot",
    }
    for text, why in refused.items():
        prj.write_text(text)
        with pytest.raises(InputError, match=why) as err:
            read_pix4d(params)
        assert prj.name in str(err.value) and "projected output coordinate system in metres" in str(err.value)
    prj.unlink()
    with pytest.raises(InputError, match="arbitrary"):
        read_pix4d(params)


def test_offset_file_variants(tmp_path, original):
    """offset.xyz with CRLF, tabs or one number a line reads; two numbers is refused naming the file."""
    params = project(tmp_path)
    off = params / f"{NAME}_offset.xyz"
    x, y, z = off.read_text().split()
    for text in (f"{x} {y} {z}\r\n", f"{x}\t{y}\t{z}", f"{x}\n{y}\n{z}\n"):
        off.write_text(text)
        assert np.array_equal(read_pix4d(params).centres_map(), original.centres_map())
    off.write_text(f"{x} {y}")
    with pytest.raises(InputError, match="holds 2 numbers"):
        read_pix4d(params)


def p4d_text(names: list[str], folder: str) -> str:
    """A .p4d listing ``names`` under ``folder`` (Pix4D's '.p4d minimum format')."""
    images = "".join(f'<image path="{folder}{n}" group="group1" enabled="true"/>' for n in names)
    return (
        '<?xml version="1.0" encoding="UTF-8"?><pix4dmapper><inputs><cameras><camera name="FC6310_8.8_5472x3648">'
        f"<type>perspective</type></camera></cameras><images>{images}</images></inputs></pix4dmapper>"
    )


def test_p4d_lists_the_photos_and_finds_the_project(tmp_path, original):
    """Pix4D writes <name>.p4d beside the project folder <name>/: given the .p4d, the folder holding it, the project
    folder or its params folder, the same project (its root the project folder, so the DSM is found); photos the
    .p4d lists but Pix4D did not calibrate count as without a pose; its relative image paths are used."""
    params = project(tmp_path, NAME)
    root = params.parent.parent
    names = sorted(original.photos) + ["DJI_9001.JPG", "DJI_9002.JPG"]
    (tmp_path / f"{NAME}.p4d").write_text(p4d_text(names, "photos/"))
    (tmp_path / "photos").mkdir()
    for n in names:
        (tmp_path / "photos" / n).write_bytes(b"")
    (root / "3_dsm_ortho" / "1_dsm").mkdir(parents=True)
    (root / "3_dsm_ortho" / "1_dsm" / f"{NAME}_dsm.tif").write_bytes(b"")
    for given in (tmp_path / f"{NAME}.p4d", tmp_path, root, params):
        assert detect_project(given).program == "pix4d"
        proj = open_project(given)
        cs = proj.cameras
        assert Path(cs.source) == root and len(cs.photos) == 170 and sorted(cs.unposed) == names[-2:]
        assert proj.path("dsm") == root / "3_dsm_ortho" / "1_dsm" / f"{NAME}_dsm.tif"
        same(cs, original)
        paths = proj.image_paths(missing_ok=True)
        assert paths["DJI_0172.JPG"] == tmp_path / "photos" / "DJI_0172.JPG"


def test_p4d_with_windows_paths_and_several_projects(tmp_path, original):
    """Absolute Windows paths (the project made on another machine) leave the photos to the usual search; a .p4d
    of another flight is refused; two projects in one folder are refused naming both."""
    params = project(tmp_path, NAME)
    p4d = tmp_path / f"{NAME}.p4d"
    p4d.write_text(p4d_text(sorted(original.photos), "C:\\Users\\me\\flight\\"))
    cs = read_pix4d(p4d)
    assert cs.photos["DJI_0172.JPG"].path == "C:\\Users\\me\\flight\\DJI_0172.JPG" and not cs.unposed
    p4d.write_text(p4d_text(["IMG_0001.JPG", "IMG_0002.JPG"], "C:/x/"))
    with pytest.raises(InputError, match="another project's") as err:
        read_pix4d(params)
    assert p4d.name in str(err.value)
    p4d.write_text("<pix4dmapper><inputs>")
    with pytest.raises(InputError, match="not a readable Pix4D project file"):
        read_pix4d(params)
    p4d.unlink()
    shutil.copytree(params.parent.parent, tmp_path / "second")
    (tmp_path / "second.p4d").write_text(p4d_text(sorted(original.photos), ""))
    (tmp_path / f"{NAME}.p4d").write_text(p4d_text(sorted(original.photos), ""))
    with pytest.raises(InputError, match="2 Pix4D projects in one folder") as err:
        detect_project(tmp_path)
    assert "second.p4d" in str(err.value) and f"{NAME}.p4d" in str(err.value)


def test_external_parameters_check_the_offset_and_list_photos(tmp_path, original):
    """calibrated_external_camera_parameters.txt (X Y Z in the output CRS, 6 decimals as Pix4D writes them) agrees
    with t + offset; an offset.xyz from another run (1 m off) is refused naming both; a photo it lists that the
    camera-parameters file lacks (a file cut between two blocks) is read without a pose."""
    params = project(tmp_path)
    rows = ["imageName X Y Z Omega Phi Kappa"] + [
        f"{k} " + " ".join(f"{v:.6f}" for v in c) + " 0.1 0.2 0.3"
        for k, c in zip(original.posed, original.centres_map())
    ]
    ext = params / f"{NAME}_calibrated_external_camera_parameters.txt"
    ext.write_text("\r\n".join(rows + ["DJI_9999.JPG 1 2 3 0 0 0"]) + "\r\n")
    cs = read_pix4d(params)
    same(cs, original)
    assert cs.unposed == ["DJI_9999.JPG"] and ext in cs.files
    off = params / f"{NAME}_offset.xyz"
    x, y, z = (float(v) for v in off.read_text().split())
    off.write_text(f"{x + 1} {y} {z}")
    with pytest.raises(InputError, match=r"1\.000 m from where") as err:
        read_pix4d(params)
    assert ext.name in str(err.value) and off.name in str(err.value)


def test_p4d_duplicate_names_and_utf16(tmp_path, original):
    """Two images of one name in the .p4d (two folders) are refused: the parameters name photos by file name only.
    A .p4d saved as UTF-16 reads."""
    params = project(tmp_path, NAME)
    p4d = tmp_path / f"{NAME}.p4d"
    text = p4d_text(sorted(original.photos), "a/").replace("</images>", '<image path="b/DJI_0172.JPG"/></images>')
    p4d.write_text(text)
    with pytest.raises(InputError, match="two images named 'DJI_0172.JPG'"):
        read_pix4d(params)
    p4d.write_bytes(p4d_text(sorted(original.photos), "a/").replace("UTF-8", "UTF-16").encode("utf-16"))
    cs = read_pix4d(params)
    assert len(cs.photos) == 168 and cs.photos["DJI_0172.JPG"].path == str(tmp_path / "a" / "DJI_0172.JPG")
