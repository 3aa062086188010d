"""Module 1's marks for Pix4D and Metashape (core/formats/gcp_marks.py), checked against the formats' documentation.

Each written file is read back by a parser written here from the programs' documentation (columns, no header,
comma separators, pixel origin at the image's top-left corner), not by our own code, so a mistake in the writer
cannot cancel itself; the Metashape markers XML is also compared with a real project's marks
(tests/data/metashape-markers-easyidp/NOTE.md).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from xml.etree import ElementTree

import pytest
from gui_events import click, key
from pyproj import CRS
from test_gcp_finder import GCPS, GROUND, cfg_for, flight  # noqa: F401  (flight: the module's synthetic flight)

from matchplant.cli import run_module
from matchplant.core.formats.gcp_list import Mark, read_gcp_list
from matchplant.core.formats.gcp_marks import check_names, read_metashape_cameras, write_marks
from matchplant.core.runtime.errors import InputError
from matchplant.gcp_finder.candidates import find_candidates
from matchplant.gcp_finder.gui import GcpFinderGUI
from matchplant.gcp_finder.marks import store_for
from matchplant.gcp_finder.run import run

REAL = Path(__file__).parent / "data" / "metashape-markers-easyidp"
UTM = CRS.from_epsg(32614)
W, H = 4000, 3000


def marks_example() -> list[Mark]:
    """Two GCPs; marks on the centre of the top-left pixel and of the bottom-right pixel, and one in between."""
    return [
        Mark(700000.0, 4500000.0, 350.0, 0.0, 0.0, "DJI_0007.JPG", "G1"),
        Mark(700000.0, 4500000.0, 350.0, W - 1.0, H - 1.0, "DJI_0003.JPG", "G1"),
        Mark(700010.5, 4500020.25, 351.5, 1234.25, 987.75, "DJI_0003.JPG", "G2"),
    ]


def cameras_xml(path: Path, ids: dict[str, str]) -> Path:
    """A Metashape Export Cameras XML: <document><chunk><cameras><camera id label/>, labels without extension."""
    cams = "".join(f'<camera id="{i}" sensor_id="0" label="{label}"/>' for label, i in ids.items())
    path.write_text(
        f'<?xml version="1.0"?><document version="2.0.0"><chunk><cameras>{cams}</cameras></chunk></document>'
    )
    return path


def plain_rows(path: Path) -> list[list[str]]:
    """Rows of a comma-separated file with no header (Pix4D's and Metashape's import files)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [row for row in csv.reader(fh) if row]


def parse_metashape_markers(path: Path) -> dict[str, dict[str, tuple[float, float]]]:
    """Metashape's markers XML as documented by its exports: {label: {camera_id: (x, y)}} of pinned locations."""
    chunk = ElementTree.parse(path).getroot().find("chunk")
    labels = {m.get("id"): m.get("label") for m in chunk.find("markers").findall("marker")}
    out: dict[str, dict[str, tuple[float, float]]] = {label: {} for label in labels.values()}
    for m in chunk.find("frames").find("frame").find("markers").findall("marker"):
        for loc in m.findall("location"):
            assert loc.get("pinned") == "true"
            out[labels[m.get("marker_id")]][loc.get("camera_id")] = (float(loc.get("x")), float(loc.get("y")))
    return out


def test_pix4d_files_follow_the_documented_columns_and_pixel_origin(tmp_path):
    files = write_marks(tmp_path, "EPSG:32614", UTM, marks_example(), ["pix4d"])
    assert sorted(p.name for p in files) == ["pix4d_gcps.csv", "pix4d_marks.csv"]
    marks = plain_rows(tmp_path / "pix4d_marks.csv")  # image name, GCP label, x, y: no header
    assert all(len(r) == 4 for r in marks)
    # Pix4D's origin is the top-left corner of the image: the top-left pixel's centre is (0.5, 0.5)
    assert marks[0][:2] == ["DJI_0007.JPG", "G1"] and [float(v) for v in marks[0][2:]] == [0.5, 0.5]
    assert [float(v) for v in marks[1][2:]] == [W - 0.5, H - 0.5]
    assert marks[2][:2] == ["DJI_0003.JPG", "G2"] and [float(v) for v in marks[2][2:]] == [1234.75, 988.25]
    gcps = plain_rows(tmp_path / "pix4d_gcps.csv")  # label, easting, northing, z (UTM's axis order): no header
    assert [r[0] for r in gcps] == ["G1", "G2"]
    assert [float(v) for v in gcps[1][1:]] == [700010.5, 4500020.25, 351.5]


def test_pix4d_gcps_in_northing_first_axis_order(tmp_path):
    crs = CRS.from_epsg(31467)  # DHDN / 3-degree Gauss-Kruger zone 3: its axes are northing, easting
    assert crs.axis_info[0].direction.lower() == "north"
    write_marks(tmp_path, "EPSG:31467", crs, marks_example(), ["pix4d"])
    assert [float(v) for v in plain_rows(tmp_path / "pix4d_gcps.csv")[1][1:]] == [4500020.25, 700010.5, 351.5]


def test_metashape_reference_and_markers_xml(tmp_path):
    ids = {"DJI_0003": "7", "DJI_0007": "3"}  # not in file order: a wrong look-up shows
    files = write_marks(tmp_path, "EPSG:32614", UTM, marks_example(), ["metashape"], ids, "cameras.xml")
    assert sorted(p.name for p in files) == ["metashape_markers.xml", "metashape_reference.csv"]
    ref = plain_rows(tmp_path / "metashape_reference.csv")  # label, x (easting), y (northing), z
    assert ref == [["G1", "700000.0000", "4500000.0000", "350.0000"], ["G2", "700010.5000", "4500020.2500", "351.5000"]]
    got = parse_metashape_markers(tmp_path / "metashape_markers.xml")
    assert got == {"G1": {"3": (0.5, 0.5), "7": (W - 0.5, H - 0.5)}, "G2": {"7": (1234.75, 988.25)}}


def test_metashape_without_camera_ids_writes_the_reference_only(tmp_path):
    files = write_marks(tmp_path, "EPSG:32614", UTM, marks_example(), ["metashape"])
    assert [p.name for p in files] == ["metashape_reference.csv"]


def test_metashape_markers_match_a_real_project(tmp_path):
    """The real project's pinned marks, taken to our pixels and written again, give its camera ids and pixels."""
    real = parse_metashape_markers(REAL / "markers.xml")
    ids = read_metashape_cameras(REAL / "cameras.xml")
    assert len(ids) == 138 and ids["DJI_0001"] == "0"
    label_of = {v: k for k, v in ids.items()}
    refs = {
        m.get("label"): [float(m.find("reference").get(k)) for k in "xyz"]
        for m in ElementTree.parse(REAL / "markers.xml").getroot().iter("marker")
        if m.get("label") is not None
    }
    ours = [
        Mark(*refs[label], x - 0.5, y - 0.5, label_of[cid] + ".JPG", label)
        for label, locs in real.items()
        for cid, (x, y) in locs.items()
    ]
    assert len(ours) == 23
    write_marks(tmp_path, "EPSG:4326", CRS.from_epsg(4326), ours, ["metashape"], ids, REAL / "cameras.xml")
    got = parse_metashape_markers(tmp_path / "metashape_markers.xml")
    assert got.keys() == real.keys()
    for label, locs in real.items():
        assert got[label].keys() == locs.keys(), label
        for cid, xy in locs.items():
            assert got[label][cid] == pytest.approx(xy, abs=5e-4), (label, cid)


@pytest.mark.parametrize(
    ("mark", "names"),
    [
        (Mark(0, 0, 0, 1, 1, "a.JPG", "G,1"), "survey.csv"),
        (Mark(0, 0, 0, 1, 1, "a.JPG", "G 1"), "survey.csv"),
        (Mark(0, 0, 0, 1, 1, "a.JPG", ""), "survey.csv"),
        (Mark(0, 0, 0, 1, 1, "my photo.JPG", "G1"), "images"),
    ],
)
def test_names_the_formats_cannot_hold_are_refused(mark, names):
    with pytest.raises(InputError) as e:
        check_names([mark], "survey.csv", "images")
    assert names in str(e.value) and "fix" in str(e.value).lower()


def test_commas_are_refused_only_where_a_comma_separates():
    check_names([Mark(0, 0, 0, 1, 1, "a,b.JPG", "G,1")], formats=["odm"])  # gcp_list.txt is whitespace-separated
    with pytest.raises(InputError, match="comma"):
        check_names([Mark(0, 0, 0, 1, 1, "a.JPG", "G,1")], formats=["odm", "pix4d"])


def test_a_photo_not_in_the_metashape_chunk_is_refused(tmp_path):
    ids = {"DJI_0003": "7"}
    with pytest.raises(InputError, match=r"DJI_0007\.JPG is not a camera of the Metashape chunk") as e:
        write_marks(tmp_path, "EPSG:32614", UTM, marks_example(), ["metashape"], ids, tmp_path / "cams.xml")
    assert "cams.xml" in str(e.value)
    assert not any(tmp_path.iterdir())  # not even the reference CSV


@pytest.mark.parametrize("text", ["not xml", "<document><chunk/><chunk/></document>", "<document><chunk/></document>"])
def test_bad_metashape_cameras_file(tmp_path, text):
    (tmp_path / "c.xml").write_text(text)
    with pytest.raises(InputError, match="Export Cameras"):
        read_metashape_cameras(tmp_path / "c.xml")


def flight_cameras(root: Path, path: Path, drop: str | None = None) -> Path:
    """A cameras XML for the synthetic flight's photos (ids in reverse order), without ``drop``."""
    names = sorted(p.stem for p in (root / "images").iterdir() if p.stem != drop)
    return cameras_xml(path, {n: str(100 - i) for i, n in enumerate(names)})


def test_module_writes_every_format_from_the_same_marks(flight, tmp_path):  # noqa: F811
    root, truth = flight
    out = tmp_path / "out"
    cams = flight_cameras(root, tmp_path / "cams.xml")
    run(cfg_for(root, out, auto=True, formats=["pix4d", "metashape"], metashape_cameras=cams))
    _, _, marks = read_gcp_list(out / "gcp_list.txt")  # always written: sessions continue from it
    assert marks
    p4d = {(r[1], r[0]): (float(r[2]), float(r[3])) for r in plain_rows(out / "pix4d_marks.csv")}
    assert p4d.keys() == {(m.gcp, m.image) for m in marks}
    for m in marks:
        assert p4d[(m.gcp, m.image)] == pytest.approx((m.u + 0.5, m.v + 0.5), abs=1e-3)
        assert math.dist((m.u, m.v), truth[(m.gcp, m.image)]) < 0.5  # and the mark is the target's centre
    ids = read_metashape_cameras(cams)
    xml = parse_metashape_markers(out / "metashape_markers.xml")
    for m in marks:
        assert xml[m.gcp][ids[Path(m.image).stem]] == pytest.approx((m.u + 0.5, m.v + 0.5), abs=1e-3)
    ref = {r[0]: [float(v) for v in r[1:]] for r in plain_rows(out / "metashape_reference.csv")}
    assert ref == {g: [*GCPS[g], GROUND] for g in xml}


def test_module_refuses_a_flight_photo_missing_from_the_chunk_and_writes_nothing(flight, tmp_path):  # noqa: F811
    root, truth = flight
    out = tmp_path / "out"
    image = sorted({img for _, img in truth})[0]
    cams = flight_cameras(root, tmp_path / "cams.xml", drop=Path(image).stem)
    argv = [
        "--set",
        f"images={root / 'images'}",
        "--set",
        f"survey={root / 'survey.csv'}",
        "--set",
        "survey_crs=EPSG:32614",
    ]
    argv += ["--set", f"output_dir={out}", "--set", "auto=true", "--set", "formats=[metashape]"]
    argv += ["--set", f"metashape_cameras={cams}", "--quiet"]
    assert run_module("gcp_finder", argv) != 0
    assert {p.name for p in out.iterdir()} <= {"logs"}  # the run's log only: no marks file


def test_module_refuses_a_label_with_a_comma(flight, tmp_path):  # noqa: F811
    root, _ = flight
    survey = tmp_path / "survey.csv"
    survey.write_text("id,x,y,z\n" + "".join(f'"{g},a",{x},{y},{GROUND}\n' for g, (x, y) in GCPS.items()))
    with pytest.raises(InputError, match="comma") as e:
        run(cfg_for(root, tmp_path / "out", survey=survey, auto=True, formats=["pix4d"]))
    assert "survey.csv" in str(e.value)
    assert not (tmp_path / "out" / "pix4d_marks.csv").exists()


def test_a_gcp_with_no_mark_is_left_out_of_every_file(tmp_path):
    marks = [m for m in marks_example() if m.gcp == "G2"]  # G1 surveyed but not marked
    write_marks(tmp_path, "EPSG:32614", UTM, marks, ["odm", "pix4d", "metashape"], {"DJI_0003": "0"})
    assert [r[0] for r in plain_rows(tmp_path / "pix4d_gcps.csv")] == ["G2"]
    assert [r[0] for r in plain_rows(tmp_path / "metashape_reference.csv")] == ["G2"]
    assert list(parse_metashape_markers(tmp_path / "metashape_markers.xml")) == ["G2"]
    assert {m.gcp for m in read_gcp_list(tmp_path / "gcp_list.txt")[2]} == {"G2"}


@pytest.mark.gui
def test_gui_saves_every_format_after_each_change(flight, tmp_path):  # noqa: F811
    root, truth = flight
    cfg = cfg_for(
        root, tmp_path, formats=["pix4d", "metashape"], metashape_cameras=flight_cameras(root, tmp_path / "c.xml")
    )
    finder = find_candidates(cfg)
    gui = GcpFinderGUI(finder, store_for(cfg, finder, autosave=True), zoom_px=cfg.zoom_px, headless=True)
    gcp, image = gui.gcp, gui.candidate.image
    u, v = truth[(gcp, image)]
    key(gui.fig, "f")  # whole image
    click(gui.fig, gui.ax, u, v)
    (row,) = plain_rows(tmp_path / "pix4d_marks.csv")  # saved at once, no explicit save
    assert row[:2] == [image, gcp] and [float(x) for x in row[2:]] == pytest.approx([u + 0.5, v + 0.5], abs=2e-3)
    cid = read_metashape_cameras(tmp_path / "c.xml")[Path(image).stem]
    assert parse_metashape_markers(tmp_path / "metashape_markers.xml")[gcp][cid] == pytest.approx(
        (u + 0.5, v + 0.5), abs=2e-3
    )
    key(gui.fig, "d")
    assert plain_rows(tmp_path / "pix4d_marks.csv") == []
