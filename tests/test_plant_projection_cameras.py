"""Module 8 through Metashape and Pix4D projects: the demo field exported by our writers in both formats gives
the plants the ODM project gives (the boxes on the original photos)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.metashape import read_metashape, write_metashape
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.pix4d import write_pix4d
from matchplant.core.formats.projects import PhotoProject, detect_project, open_project
from matchplant.core.runtime.errors import InputError
from matchplant.plant_projection.merge import merge_views
from matchplant.plant_projection.views import project_predictions


@pytest.fixture(scope="module")
def exports(tiny_field, tmp_path_factory):
    """The tiny field's ODM poses written as a Metashape camera export and a Pix4D params folder."""
    out = tmp_path_factory.mktemp("exports")
    odm = ODMProject(tiny_field.root)
    shots = odm.reconstruction().shots
    (out / "meta").mkdir()
    write_metashape(out / "meta" / "cameras.xml", shots, odm.frame())
    write_pix4d(out / "p4d" / "1_initial" / "params", "demo", shots, odm.frame())
    return out


def _raw_predictions(field) -> dict:
    ds = read_dataset(field.boxes_raw, validate=False)
    preds = [dict(a, score=1.0) for a in ds["annotations"]]
    return {"images": ds["images"], "categories": ds["categories"], "predictions": preds}


def test_auto_says_what_it_found(tiny_field, exports, tmp_path):
    """auto names the program and the files; a folder of none of the three is refused, naming what was looked for."""
    assert detect_project(tiny_field.root).program == "odm"
    found = detect_project(exports / "meta")
    assert found.program == "metashape" and found.evidence == [exports / "meta" / "cameras.xml"]
    assert detect_project(exports / "p4d").program == "pix4d"
    (tmp_path / "photos").mkdir()
    with pytest.raises(InputError, match="looked for ODM: opensfm/reconstruction.json"):
        detect_project(tmp_path / "photos")
    with pytest.raises(InputError, match="not a pix4d project"):
        detect_project(exports / "meta", "pix4d")


@pytest.mark.parametrize("program", ["metashape", "pix4d"])
def test_demo_field_gives_the_same_plants_through_each_program(tiny_field, exports, program):
    """Pix4D's frame is ODM's (map minus an offset): the same rays, to the bit. Metashape's chunk is rigid in
    geocentric space while the demo's truth is straight in UTM; the writer turns each pose by the rotation
    nearest to the projection's Jacobian at the camera (docs/DESIGN.md §3), which leaves UTM's scale (1.0001
    here) on each ray's horizontal run: hits agree to 0.05 mm (median), and a box edge set by a ray grazing a
    plant top may land on the other side of it, as in ODM's own topocentric reconstruction
    (test_topocentric_reconstruction_gives_the_same_plants)."""
    preds = _raw_predictions(tiny_field)
    ref, _ = project_predictions(ODMProject(tiny_field.root), preds)
    src = exports / ("meta/cameras.xml" if program == "metashape" else "p4d")
    project = open_project(src, program, dsm=tiny_field.root / "odm_dem" / "dsm.tif")
    assert isinstance(project, PhotoProject) and project.program == program
    got, rejected = project_predictions(project, preds)
    assert len(rejected) == 0 and len(got.table) == len(ref.table)
    ray = np.linalg.norm(got.outlines() - ref.outlines(), axis=-1)
    a, b = merge_views(got), merge_views(ref)
    assert len(a) == len(b)
    cols = ["xmin", "ymin", "xmax", "ymax", "cx", "cy"]
    plants = np.abs(a[cols].to_numpy() - b[cols].to_numpy()).max(axis=1)
    if program == "pix4d":
        assert ray.max() < 1e-6 and plants.max() < 1e-6
    else:
        assert np.median(ray) < 1e-4 and np.percentile(ray, 99) < 1e-3 and (ray < 0.01).mean() >= 0.995
        assert np.median(plants) < 1e-3 and (plants < 1e-3).mean() >= 0.9, np.sort(plants)[-5:]


def test_metashape_writer_round_trips(tiny_field, exports):
    """What the Metashape writer writes, the reader reads back: centres and rays of every photo."""
    odm = ODMProject(tiny_field.root)
    cs = read_metashape(exports / "meta" / "cameras.xml")
    for sid, shot in odm.reconstruction().shots.items():
        got = cs.photos[sid].shot
        c_map = odm.frame().to_map(shot.center[None, :])[0]
        assert np.linalg.norm(cs.frame.to_map(got.center[None, :])[0] - c_map) < 1e-6
        uv = np.array([[0.0, 0.0], [399.0, 299.0], [200.0, 150.0]])
        far = odm.frame().to_map(shot.center + 30 * shot.ray_directions(uv))
        mine = cs.frame.to_map(got.center + 30 * got.ray_directions(uv))
        assert np.abs(mine - far).max() < 0.005  # 30 m rays: UTM scale 1e-4 and convergence aside, the same


def test_bad_project_inputs(tiny_field, exports, tmp_path):
    """Photos missing on disk, and a DSM of another place, are refused with the file and the fix."""
    project = open_project(exports / "meta" / "cameras.xml", images=tmp_path)
    with pytest.raises(InputError, match="not on disk") as err:
        project.image_paths()
    assert "set 'images'" in str(err.value)
    far = tmp_path / "far_dsm.tif"
    shutil.copy(tiny_field.root / "odm_dem" / "dsm.tif", far)
    with rasterio.open(far, "r+") as dst:
        t = dst.transform
        dst.transform = Affine(t.a, t.b, t.c + 50_000, t.d, t.e, t.f)
    project = open_project(exports / "p4d", dsm=far)
    with pytest.raises(InputError, match="does not overlap the cameras") as err:
        project.frame()
    assert str(far) in str(err.value)
