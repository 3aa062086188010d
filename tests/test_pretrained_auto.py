"""``model.pretrained: auto`` (issue 40, point 4): COCO weights when they are in the torch cache or downloadable,
else the from-scratch recipe (``none``), logged with the reason, and decided in milliseconds to seconds before any
model is built (offline, the default once spent ~70 s timing MobileNetV3 before failing on the download)."""

from __future__ import annotations

import dataclasses
import logging
import socket
import threading
import time
from pathlib import Path

import pytest
from log_records import log_records, messages

from matchplant.core.runtime.errors import ConfigError
from matchplant.detection import model as detection_model
from matchplant.detection.architectures import get_architecture
from matchplant.detection.model import ModelConfig, build_detector, coco_weights_at_hand
from matchplant.model_train.choose import MOBILE, PAPER, resolve_pretrained
from matchplant.model_train.config import ModelTrainConfig

pytest.importorskip("torchvision")


@pytest.fixture
def empty_cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    return tmp_path / "torch" / "hub" / "checkpoints"


def _offline(monkeypatch):
    def refuse(*args, **kwargs):
        raise OSError("network unreachable (test)")

    monkeypatch.setattr(socket, "create_connection", refuse)


def _cache(folder: Path, *architectures: str) -> None:
    from torchvision.models import get_weight

    folder.mkdir(parents=True, exist_ok=True)
    for name in architectures:
        (folder / get_weight(get_architecture(name).coco_weights).url.rsplit("/", 1)[-1]).write_bytes(b"")


def _cfg(**model) -> ModelTrainConfig:
    cfg = ModelTrainConfig(train_json=Path("train.json"))
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **model))


def test_auto_is_the_default():
    assert ModelConfig().pretrained == "auto"


def _resolved(cfg, resume=None) -> tuple[str, str]:
    with log_records("matchplant.model_train", logging.INFO) as records:
        cfg = resolve_pretrained(cfg, resume)
    return cfg.model.pretrained, " ".join(messages(records))


def test_offline_and_not_cached_gives_the_from_scratch_recipe(empty_cache, monkeypatch):
    _offline(monkeypatch)
    t0 = time.perf_counter()
    choice, logged = _resolved(_cfg())
    assert time.perf_counter() - t0 < 2.0
    assert choice == "none"
    assert "pretrained: auto -> none" in logged and "does not answer" in logged, logged


def test_cached_weights_are_used_without_asking_the_network(empty_cache, monkeypatch):
    _cache(empty_cache, PAPER, MOBILE)

    def no_network(*args, **kwargs):
        raise AssertionError("the network was asked although the weights are cached")

    monkeypatch.setattr(socket, "create_connection", no_network)
    choice, logged = _resolved(_cfg())
    assert choice == "coco" and "in the torch cache" in logged, logged


def test_a_fixed_architecture_needs_only_its_own_weights(empty_cache, monkeypatch):
    _offline(monkeypatch)
    _cache(empty_cache, MOBILE)
    assert resolve_pretrained(_cfg(architecture=MOBILE), None).model.pretrained == "coco"
    assert resolve_pretrained(_cfg(), None).model.pretrained == "none"  # auto may pick the paper's: not cached


def test_a_reachable_host_means_downloadable(empty_cache, monkeypatch):
    class Connection:
        def close(self):
            pass

    monkeypatch.setattr(socket, "create_connection", lambda *a, **k: Connection())
    assert coco_weights_at_hand([PAPER])[0]


def test_a_silent_host_is_given_up_after_the_timeout(empty_cache, monkeypatch):
    release = threading.Event()

    def silent(*args, **kwargs):  # a lookup that hangs; let go (as a timeout) when the test ends, not 30 s later
        release.wait(30)
        raise OSError("timed out")

    monkeypatch.setattr(socket, "create_connection", silent)
    t0 = time.perf_counter()
    try:
        assert not coco_weights_at_hand([PAPER], timeout=0.5)[0]
        assert time.perf_counter() - t0 < 2.0
    finally:
        release.set()


def test_resume_keeps_the_runs_weights_and_a_checkpoint_needs_none(empty_cache, monkeypatch):
    _offline(monkeypatch)
    assert resolve_pretrained(_cfg(), {"model_config": {"pretrained": "coco"}}).model.pretrained == "coco"
    assert resolve_pretrained(_cfg(checkpoint=Path("best.pt")), None).model.pretrained == "none"
    assert resolve_pretrained(_cfg(pretrained="imagenet"), None).model.pretrained == "imagenet"  # as set


def test_an_unresolved_auto_is_never_built():
    with pytest.raises(ConfigError, match="pretrained is 'auto'"):
        build_detector(ModelConfig(architecture=MOBILE), 2)
    assert detection_model.AUTO in detection_model.PRETRAINED
