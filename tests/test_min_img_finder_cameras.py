"""Module 3 through Metashape and Pix4D exports of the demo field: the same images chosen as through ODM."""

from __future__ import annotations

import re

import pytest
from project_exports import write_exports

from matchplant.min_img_finder import MinImgFinderConfig
from matchplant.min_img_finder.run import MinImageFinder


@pytest.fixture(scope="module")
def exports(tiny_field, tmp_path_factory):
    """The tiny field as a Metashape export and a Pix4D project, each with the photos, DSM and orthophoto; and the
    Metashape export as Metashape labels cameras by default (the photo's name without its extension)."""
    found = write_exports(tiny_field.root, tmp_path_factory.mktemp("m3_exports"))
    xml = found["metashape"]
    bare = xml.with_name("cameras_bare_labels.xml")
    bare.write_text(re.sub(r'label="(SIM_\d+)\.JPG"', r'label="\1"', xml.read_text()))
    return {**found, "metashape, labels without extension": bare}


def test_same_image_set_through_each_program(tiny_field, exports, tmp_path):
    """The selection through Metashape's and Pix4D's original photos is ODM's through its undistorted ones."""
    chosen = {}
    for name, project in {"odm": tiny_field.root, **exports}.items():
        finder = MinImageFinder(MinImgFinderConfig(project_dir=project, output_dir=tmp_path / name))
        names = [f.name for f in finder.footprints]
        chosen[name] = sorted(names[i] for i in finder.select().indices)
    assert len(chosen) == 4 and len({tuple(v) for v in chosen.values()}) == 1, chosen
