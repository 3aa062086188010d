"""The artifacts every bad-input case starts from, made once per session from the tiny synthetic field:
the field itself (an ODM project with photos, GNSS log, GCP survey and truth), module 5 tiles, an untrained
module 6 checkpoint, module 7-style predictions (the true boxes) and module 8 plants. Read-only: a case
copies what it breaks (``Work.copy``)."""

from __future__ import annotations

import json
import shutil

import pytest
from harness import Work

from matchplant.cli import run_module
from matchplant.core.formats.coco import read_dataset
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.io import write_json
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.detection.model import build_detector
from matchplant.model_train.config import ModelTrainConfig


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
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            "train_json=x",
            "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
            "model.pretrained=none",
            "model.min_size=64",
            "model.max_size=128",
        ],
        check_paths=False,
        strict=False,
    )
    save_checkpoint(root / "model.pt", build_detector(cfg.model, 2), cfg.model, ["plant"], [1], epoch=1)
    (root / "README").write_text(json.dumps({"made_from": str(tiny_field.root)}))
    return root


@pytest.fixture
def work(artifacts, tmp_path):
    return Work(tmp_path, artifacts)
