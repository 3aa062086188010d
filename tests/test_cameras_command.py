"""``matchplant cameras PROJECT``: the summary of real Metashape and Pix4D projects, and map points found in photos."""

from __future__ import annotations

import csv
import io
import shutil

import numpy as np

from matchplant.cli import main
from matchplant.core.formats.metashape import read_metashape
from tests.test_core_cameras import PIX4D, WHEAT


def test_summary_of_a_metashape_project(capsys):
    """Program, photos with and without a pose, the sensor, the CRS and the extent."""
    assert main(["cameras", str(WHEAT)]) == 0
    out = capsys.readouterr().out
    assert "program: metashape" in out and "photos: 138 (138 with a pose, 0 without)" in out
    assert "FC550, DJI MFT 15mm F1.7 ASPH (15mm): 4608x3456 px" in out and "EPSG:32654" in out
    assert "cameras' extent: x 3679" in out


def test_points_are_found_in_the_photos_they_were_marked_on(tmp_path, capsys):
    """The wheat project's markers as map points (WGS 84, ellipsoidal heights): every photo an operator marked a
    marker on is listed for it, at a pixel within the marker test's 12 px (tests/test_core_cameras.py)."""
    cs = read_metashape(WHEAT)
    pts = tmp_path / "markers.csv"
    pts.write_text("x,y,z\n" + "".join(",".join(repr(float(v)) for v in m.xyz) + "\n" for m in cs.markers))
    out = tmp_path / "pixels.csv"
    code = main(["cameras", str(WHEAT), "--points", str(pts), "--points-crs", "EPSG:4979", "--output", str(out)])
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    got = {(int(r["point"]), r["photo"]): (float(r["u"]), float(r["v"])) for r in rows}
    for k, m in enumerate(cs.markers):
        for label, uv in m.marks.items():
            assert np.hypot(*(np.array(got[(k, cs.photos[label].name)]) - uv)) < 12


def test_points_to_standard_output_in_the_projects_crs(tmp_path, capsys):
    """Without --points-crs the points are in the project's CRS; '-' writes the CSV to standard output."""
    shutil.copytree(PIX4D, tmp_path / "p4d")
    pts = tmp_path / "points.csv"
    pts.write_text("x,y,z\n368109,3956043,96\n")
    assert main(["cameras", str(tmp_path / "p4d"), "--points", str(pts), "--output", "-"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "point,x,y,z,photo,u,v" and len(lines) > 10


def test_bad_inputs_exit_non_zero_and_write_nothing(tmp_path, capsys):
    """A folder that is no project, and points without x/y/z columns: exit 2, a message naming the file."""
    assert main(["cameras", str(tmp_path)]) == 2
    assert "looked for ODM" in capsys.readouterr().err
    bad = tmp_path / "pts.csv"
    bad.write_text("a,b\n1,2\n")
    out = tmp_path / "out.csv"
    assert main(["cameras", str(WHEAT), "--points", str(bad), "--output", str(out)]) == 2
    assert str(bad) in capsys.readouterr().err and not out.exists()
