"""Module 7's ``detect.runtime``: ONNX Runtime for the detector's convolutions gives PyTorch's boxes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from matchplant.core.formats.predictions import read_predictions
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.detection.model import build_detector
from matchplant.detection.synth import make_photo
from matchplant.model_test import runtime_onnx
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.run import run
from matchplant.model_train.config import ModelTrainConfig

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def lite_checkpoint(tmp_path_factory):
    """An untrained light detector (the CPU recipe's architecture) as a module 6 checkpoint."""
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            "train_json=x",
            "model.architecture=fasterrcnn_resnet18_fpn_lite",
            "model.pretrained=none",
            "model.min_size=128",
            "model.max_size=256",
        ],
        check_paths=False,
        strict=False,
    )
    torch.manual_seed(0)
    return save_checkpoint(
        tmp_path_factory.mktemp("ck") / "lite.pt", build_detector(cfg.model, 2), cfg.model, ["plant"], [1], epoch=1
    )


def _detect(checkpoint, images, out, runtime: str) -> dict:
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={checkpoint}",
            f"detect.images={images}",
            f"output_dir={out}",
            "detect.tile_size=128",
            "detect.overlap=32",
            "detect.score_threshold=0.0",
            "detect.drawn_images=0",
            f"detect.runtime={runtime}",
            "batch_size=2",
            "device=cpu",
        ],
    )
    run(cfg)
    return read_predictions(out / "predictions.json")


@pytest.mark.skipif(not runtime_onnx.available(), reason="onnxruntime is not installed")
def test_onnx_runtime_gives_pytorchs_boxes(lite_checkpoint, tmp_path):
    """The same photos (tiles in batches of 2, of two sizes) detected by PyTorch and with ONNX Runtime: the same
    boxes in the same order, coordinates within 0.01 px (predictions.json's rounding) and scores within 1e-4."""
    make_photo(tmp_path / "imgs" / "a.png", 300, 200, n_plants=10, seed=1)
    make_photo(tmp_path / "imgs" / "b.png", 170, 260, n_plants=6, seed=2)
    ref = _detect(lite_checkpoint, tmp_path / "imgs", tmp_path / "torch", "torch")["predictions"]
    got = _detect(lite_checkpoint, tmp_path / "imgs", tmp_path / "onnx", "onnx")["predictions"]
    assert len(ref) == len(got) > 20
    assert [p["image_id"] for p in ref] == [p["image_id"] for p in got]
    np.testing.assert_allclose([p["bbox"] for p in got], [p["bbox"] for p in ref], atol=0.011)
    np.testing.assert_allclose([p["score"] for p in got], [p["score"] for p in ref], atol=1e-4)


def test_onnx_without_onnxruntime_is_a_config_error_and_auto_falls_back(monkeypatch, tmp_path):
    monkeypatch.setattr(runtime_onnx, "available", lambda: False)
    monkeypatch.setattr("matchplant.model_test.config.available", lambda: False)
    make_photo(tmp_path / "imgs" / "a.png", 64, 64, n_plants=1, seed=0)
    (tmp_path / "ck.pt").write_bytes(b"")
    args = [f"checkpoint={tmp_path / 'ck.pt'}", f"detect.images={tmp_path / 'imgs'}"]
    with pytest.raises(ConfigError, match="onnxruntime is not installed") as e:
        load_config(ModelTestConfig, None, [*args, "detect.runtime=onnx"])
    assert "detect.runtime: torch" in e.value.fix
    model = torch.nn.Module()
    model.rpn = torch.nn.Identity()
    assert runtime_onnx.with_runtime(model, "auto", torch.device("cpu"), 1) is model  # PyTorch, unchanged
