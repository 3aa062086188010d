"""Module 3 through Metashape and Pix4D exports of the demo field: the same images chosen as through ODM."""

from __future__ import annotations

import shutil

import pytest

from matchplant.core.formats.metashape import write_metashape
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.pix4d import write_pix4d
from matchplant.min_img_finder import MinImgFinderConfig
from matchplant.min_img_finder.run import MinImageFinder


@pytest.fixture(scope="module")
def exports(tiny_field, tmp_path_factory):
    """The tiny field as a Metashape export and a Pix4D project, each with the photos, DSM and orthophoto."""
    out = tmp_path_factory.mktemp("m3_exports")
    odm = ODMProject(tiny_field.root)
    shots = odm.reconstruction().shots
    meta, p4d = out / "meta", out / "p4d"
    for folder in (meta, p4d):
        shutil.copytree(tiny_field.root / "images", folder / "images")
    write_metashape(meta / "cameras.xml", shots, odm.frame())
    shutil.copy(tiny_field.root / "odm_dem" / "dsm.tif", meta / "field_dsm.tif")
    shutil.copy(tiny_field.root / "odm_orthophoto" / "odm_orthophoto.tif", meta / "field_orthomosaic.tif")
    write_pix4d(p4d / "1_initial" / "params", "field", shots, odm.frame())
    (p4d / "3_dsm_ortho" / "1_dsm").mkdir(parents=True)
    (p4d / "3_dsm_ortho" / "2_mosaic").mkdir(parents=True)
    shutil.copy(tiny_field.root / "odm_dem" / "dsm.tif", p4d / "3_dsm_ortho" / "1_dsm" / "field_dsm.tif")
    shutil.copy(
        tiny_field.root / "odm_orthophoto" / "odm_orthophoto.tif",
        p4d / "3_dsm_ortho" / "2_mosaic" / "field_transparent_mosaic_group1.tif",
    )
    return out


def test_same_image_set_through_each_program(tiny_field, exports, tmp_path):
    """The selection through Metashape's and Pix4D's original photos is ODM's through its undistorted ones."""
    chosen = {}
    projects = {"odm": tiny_field.root, "metashape": exports / "meta" / "cameras.xml", "pix4d": exports / "p4d"}
    for name, project in projects.items():
        finder = MinImageFinder(MinImgFinderConfig(project_dir=project, output_dir=tmp_path / name))
        names = [f.name for f in finder.footprints]
        chosen[name] = sorted(names[i] for i in finder.select().indices)
    assert chosen["metashape"] == chosen["odm"] == chosen["pix4d"], chosen
