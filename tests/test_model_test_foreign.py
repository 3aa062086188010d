"""Checkpoints from outside MatchPlant (issue 28 point 5): the paper's layout and bare torchvision weights.

The files are written here the way the paper's code writes them: a torchvision detector built with
``weights=None, weights_backbone=None`` and its box predictor replaced for our classes, saved as
``{'epoch', 'model_state_dict', 'optimizer_state_dict', 'best_map'}`` or as a bare ``state_dict``.
"""

from __future__ import annotations

import urllib.error

import numpy as np
import pytest
import torch
from torchvision.models import detection as tvd
from torchvision.models import get_weight
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor

from matchplant.core.formats.images import read_rgb8
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import InputError
from matchplant.detection import lite
from matchplant.detection.architectures import ARCHITECTURES
from matchplant.detection.checkpoint import load_detector, load_matching_weights
from matchplant.detection.foreign import read_any_checkpoint
from matchplant.detection.model import ModelConfig, build_detector
from matchplant.detection.synth import make_photo
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.run import run

pytestmark = pytest.mark.usefixtures("torch_one_thread")

ARCH = "fasterrcnn_mobilenet_v3_large_fpn"  # the smallest MatchPlant builds (the paper's is ResNet-50: below, meta)


def paper_model(num_classes: int = 2):
    """As the paper's code builds it: torchvision's detector, a new FastRCNNPredictor for our classes."""
    torch.manual_seed(1)
    model = tvd.fasterrcnn_mobilenet_v3_large_fpn(weights=None, weights_backbone=None)
    model.roi_heads.box_predictor = FastRCNNPredictor(model.roi_heads.box_predictor.cls_score.in_features, num_classes)
    return model


@pytest.fixture(scope="module")
def paper_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("foreign")
    model = paper_model()
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9)
    torch.save(
        {
            "epoch": 12,
            "model_state_dict": model.state_dict(),
            "optimizer_state_dict": opt.state_dict(),
            "best_map": 0.61,
        },
        folder / "Pre-trained model_Faster R-CNN.pt",
    )
    torch.save(model.state_dict(), folder / "weights.pth")
    return model, folder / "Pre-trained model_Faster R-CNN.pt", folder / "weights.pth"


@pytest.mark.slow
def test_paper_checkpoint_detects_in_module_7_as_torchvision_does(paper_files, tmp_path):
    model, paper, _ = paper_files
    make_photo(tmp_path / "imgs" / "a.png", 160, 120, n_plants=6, seed=2)
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={paper}",
            f"detect.images={tmp_path / 'imgs'}",
            f"output_dir={tmp_path / 'out'}",
            "class_names=[maize]",
            "detect.tile_size=256",
            "detect.overlap=32",
            "detect.score_threshold=0.0",
            "device=cpu",
        ],
    )
    run(cfg)
    out = read_predictions(tmp_path / "out" / "predictions.json")
    assert [c["name"] for c in out["categories"]] == ["maize"]
    mine = np.array([p["bbox"] for p in out["predictions"]], float)
    mine[:, 2:] += mine[:, :2]
    # independently: torchvision's own model on the whole photo (one tile), every box kept
    model.eval().roi_heads.score_thresh = 0.0
    model.roi_heads.detections_per_img = 300
    img = torch.from_numpy(read_rgb8(tmp_path / "imgs" / "a.png")).permute(2, 0, 1).float() / 255
    with torch.inference_mode():
        ref = model([img])[0]
    ref_boxes = ref["boxes"].numpy()
    assert len(mine) > 5
    dist = np.abs(mine[:, None, :] - ref_boxes[None, :, :]).max(axis=2).min(axis=1)
    assert (dist < 0.02).all()  # every box module 7 gives is torchvision's (nested ones merged away)
    assert np.abs(mine[0] - ref_boxes[0]).max() < 0.02  # the best box kept


def test_bare_state_dict_loads_and_refuses_a_wrong_class_count(paper_files):
    model, _, bare = paper_files
    ck = read_any_checkpoint(bare, class_names=["maize"])
    assert ck["model_config"]["architecture"] == ARCH and ck["class_names"] == ["maize"]
    rebuilt, _ = load_detector(ck, source=bare)
    for k, v in model.state_dict().items():
        assert torch.equal(rebuilt.state_dict()[k], v), k
    with pytest.raises(InputError) as err:
        read_any_checkpoint(bare, class_names=["maize", "weed"])
    assert err.value.path == bare and "(2, 1024)" in err.value.problem and "(3, 1024)" in err.value.problem
    assert "class_names" in err.value.fix
    with pytest.raises(InputError, match="without class names") as err:
        read_any_checkpoint(bare)
    assert "class_names" in err.value.fix


def test_foreign_weights_start_a_module_6_fine_tune(paper_files):
    """Module 6 takes every tensor but the box predictor (another class count) from the paper's file."""
    _, paper, _ = paper_files
    src = read_any_checkpoint(paper, architecture=ARCH, fit_classes=False)
    assert src["foreign"]["epoch"] == 12 and src["foreign"]["best_map"] == 0.61
    model = build_detector(ModelConfig(architecture=ARCH, pretrained="none"), 4, load_weights=False)
    loaded, skipped = load_matching_weights(model, src["model_state"])
    assert sorted({k.rsplit(".", 1)[0] for k in skipped}) == [
        "roi_heads.box_predictor.bbox_pred",
        "roi_heads.box_predictor.cls_score",
    ]
    assert len(loaded) == len(src["model_state"]) - 4


@pytest.mark.parametrize(
    "arch", [pytest.param(a, marks=[] if a == "fasterrcnn_resnet50_fpn" else pytest.mark.slow) for a in ARCHITECTURES]
)
def test_every_architecture_is_recognised_from_its_weights(arch, tmp_path):
    """Bare weights of each architecture, as torchvision builds it for 4 classes (shapes only: meta tensors)."""
    builder = getattr(lite, ARCHITECTURES[arch].builder, None) or getattr(tvd, ARCHITECTURES[arch].builder)
    with torch.device("meta"):
        model = builder(weights=None, weights_backbone=None, num_classes=4)
    torch.save({f"module.{k}": v for k, v in model.state_dict().items()}, tmp_path / "w.pt")  # DataParallel's
    ck = read_any_checkpoint(tmp_path / "w.pt", class_names=["a", "b", "c"])
    assert ck["model_config"]["architecture"] == arch and ck["foreign"]["classes_in_weights"] == 3
    with pytest.raises(InputError, match="3 class") as err:
        read_any_checkpoint(tmp_path / "w.pt", class_names=["plant"])
    assert err.value.path == tmp_path / "w.pt"


def test_weights_of_other_anchors_or_another_model_are_refused_by_name(tmp_path):
    with torch.device("meta"):
        odd = tvd.fasterrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=2)
        odd.rpn.head = tvd.rpn.RPNHead(256, 5)  # five aspect ratios
    torch.save(odd.state_dict(), tmp_path / "odd.pt")
    with pytest.raises(InputError, match="another shape") as err:
        read_any_checkpoint(tmp_path / "odd.pt", class_names=["plant"])
    assert "rpn.head.cls_logits.bias (5,) in the file, (3,) in MatchPlant's" in err.value.problem
    torch.save({"conv.weight": torch.zeros(3, 3)}, tmp_path / "other.pt")
    with pytest.raises(InputError, match="no architecture MatchPlant builds"):
        read_any_checkpoint(tmp_path / "other.pt", class_names=["plant"])


def test_torchvision_weights_in_the_hub_cache_work_offline(tmp_path, monkeypatch):
    """A COCO weight file copied by hand into torch's cache is used without any download."""
    weights = get_weight(ARCHITECTURES[ARCH].coco_weights)
    torch.manual_seed(3)
    coco = tvd.fasterrcnn_mobilenet_v3_large_fpn(weights=None, weights_backbone=None, num_classes=91)
    # through TORCH_HOME, not torch.hub.set_dir: set_dir cannot be undone (restoring the old path still pins it,
    # and later tests that set TORCH_HOME would read this machine's cache)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    (tmp_path / "hub" / "checkpoints").mkdir(parents=True)
    torch.save(coco.state_dict(), tmp_path / "hub" / "checkpoints" / weights.url.rsplit("/", 1)[-1])

    def offline(*args, **kwargs):
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    model = build_detector(ModelConfig(architecture=ARCH, pretrained="coco"), 2)
    key = "backbone.body.0.0.weight"
    assert torch.equal(model.state_dict()[key], coco.state_dict()[key])
