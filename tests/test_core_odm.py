"""The ODM project reader (matchplant.core.formats.odm): a minimal project around the real Berlin
reconstruction, and the synthetic field."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from matchplant.core.formats.odm import ODMProject
from matchplant.core.runtime.errors import InputError


def test_odm_project_reports_missing_outputs_with_options(tmp_path, data_dir):
    root = tmp_path / "proj"
    (root / "opensfm").mkdir(parents=True)
    shutil.copy(data_dir / "opensfm-berlin" / "reconstruction_example.json", root / "opensfm" / "reconstruction.json")
    project = ODMProject(root)
    with pytest.raises(InputError) as info:
        project.require("reconstruction", "dsm", "dtm", "undistorted_images")
    msg = str(info.value)
    assert "odm_dem/dsm.tif" in msg and "--dsm" in msg and "--dtm" in msg and "optimize-disk-space" in msg
    assert "reconstruction.json" not in msg.split("\n")[1]
    rec = project.reconstruction()
    assert len(rec.shots) == 3
    frame = project.frame()
    assert frame.kind == "topocentric" and frame.crs.to_epsg() == 32633
    with pytest.raises(InputError, match="not found"):
        ODMProject(tmp_path / "missing")


def test_odm_project_reads_real_undistorted_size(tmp_path, data_dir):
    root = tmp_path / "proj"
    (root / "opensfm" / "undistorted" / "images").mkdir(parents=True)
    shutil.copy(
        data_dir / "opensfm-berlin" / "reconstruction_example.json",
        root / "opensfm" / "undistorted" / "reconstruction.json",
    )
    Image.new("RGB", (1632, 1224)).save(root / "opensfm" / "undistorted" / "images" / "01.jpg.tif")
    project = ODMProject(root)
    shot = project.shot("01.jpg", undistorted=True)
    assert (shot.camera.width, shot.camera.height) == (1632, 1224)
    full = project.reconstruction(undistorted=True).shots["01.jpg"]
    X = full.center + full.R[2] * 10 + full.R[0] * 2  # a point in front of the camera
    np.testing.assert_allclose((shot.project(X[None])[0] + 0.5) * 2, full.project(X[None])[0] + 0.5, atol=1e-9)
    with pytest.raises(InputError, match="02.jpg"):
        project.shot("02.jpg")
    with pytest.raises(InputError, match="not in the reconstruction"):
        project.reconstruction(undistorted=True).shot("nope.jpg")


def test_odm_project_on_synthetic_field(tiny_field):
    project = ODMProject(tiny_field.root)
    assert project.missing() == []
    frame = project.frame()
    assert frame.kind == "utm_offset"
    field = json.loads(tiny_field.field_json.read_text())
    assert frame.crs.to_epsg() == int(str(field["crs"]).split(":")[-1])
