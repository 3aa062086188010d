"""The artifacts every bad-input case starts from, made once per session from the tiny synthetic field:
the field itself (an ODM project with photos, GNSS log, GCP survey and truth), module 5 tiles, an untrained
module 6 checkpoint, module 7-style predictions (the true boxes) and module 8 plants. Read-only: a case
copies what it breaks (``Work.copy``)."""

from __future__ import annotations

import json
import shutil

import pytest
from harness import Work
from small_detector import save_small, small_detector

from matchplant.cli import run_module
from matchplant.core.formats.coco import read_dataset
from matchplant.core.runtime.io import write_json


@pytest.fixture(scope="session")
def artifacts(tiny_field, tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_inputs_artifacts")
    shutil.copytree(tiny_field.root, root / "field")
    field = root / "field"
    ds = read_dataset(field / "truth" / "boxes_undistorted.json", validate=False)
    write_json(
        root / "predictions.json",
        {
            "images": ds["images"],
            "categories": ds["categories"],
            "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
        },
    )
    assert (
        run_module(
            "img_splitter",
            [
                "--set",
                f"images={field / 'opensfm/undistorted/images'}",
                "--set",
                f"annotations={field / 'truth/boxes_undistorted.json'}",
                "--set",
                f"output_dir={root / 'tiles'}",
                "--set",
                "tile_size=128",
                "--set",
                "overlap=32",
                "--set",
                "workers=1",
                "--quiet",
            ],
        )
        == 0
    )
    assert (
        run_module(
            "plant_projection",
            [
                "--set",
                f"project={field}",
                "--set",
                f"predictions={root / 'predictions.json'}",
                "--set",
                f"output_dir={root / 'plants'}",
                "--quiet",
            ],
        )
        == 0
    )
    save_small(root / "model.pt", *small_detector())
    (root / "README").write_text(json.dumps({"made_from": str(tiny_field.root)}))
    return root


@pytest.fixture
def work(artifacts, tmp_path):
    return Work(tmp_path, artifacts)
