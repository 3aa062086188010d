"""Module 6 on a CPU from random weights (issue 28): the light detector, training crops at the detector's scale and
a run as long as the budget, each chosen automatically only for settings left at their defaults, logged, and
overridable."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from matchplant.core.runtime.config import load_config, to_dict
from matchplant.core.runtime.errors import ConfigError
from matchplant.detection.checkpoint import load_detector, save_checkpoint
from matchplant.detection.data import CocoDetection
from matchplant.detection.model import ModelConfig, backbone_stages, build_detector
from matchplant.detection.synth import make_tiles
from matchplant.model_train.budget import Budget
from matchplant.model_train.choose import (
    CPU_CROP,
    LITE,
    MOBILE,
    PAPER,
    SCRATCH_EPOCHS,
    choose_architecture,
    cpu_crop,
    resumed_recipe,
    scratch_budget,
    scratch_recipe,
    validation_interval,
)
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CPU, GPU = torch.device("cpu"), torch.device("meta")  # any device that is not a CPU counts as a GPU here
LITE_ANCHORS = "model.anchor_sizes=[[8,10,13],[16,20,25],[32,40,50]]"


@pytest.fixture(scope="module")
def tiles(train_tiles):
    return train_tiles  # conftest.py: the training set both module-6 test files use


def config(tiles, *extra: str) -> ModelTrainConfig:
    return load_config(ModelTrainConfig, None, [f"train_json={tiles[0]}", "model.pretrained=none", *extra])


def test_the_light_detector_is_small_trains_and_round_trips(tmp_path):
    cfg = ModelConfig(
        architecture=LITE,
        pretrained="none",
        min_size=64,
        max_size=64,
        anchor_sizes=[[8, 10, 13], [16, 20, 25], [32, 40, 50]],
    )
    model = build_detector(cfg, 2)
    # torchvision's parts at the lite widths: a 64-channel FPN at strides 8, 16 (+ pool) and a 256-wide box head
    assert model.backbone.out_channels == 64 and model.roi_heads.box_head.fc6.in_features == 64 * 7 * 7
    assert model.roi_heads.box_head.fc7.out_features == 256 and len(backbone_stages(model, LITE)) == 4
    assert not hasattr(model.backbone.body, "layer4")
    with torch.device("meta"):
        mobile = build_detector(ModelConfig(architecture=MOBILE, pretrained="none"), 2, load_weights=False)
    assert sum(p.numel() for p in model.parameters()) < 0.3 * sum(p.numel() for p in mobile.parameters())
    model.train()
    images = [torch.rand(3, 64, 64) for _ in range(2)]
    targets = [{"boxes": torch.tensor([[10.0, 12.0, 30.0, 33.0]]), "labels": torch.tensor([1])}] * 2
    loss = sum(model(images, targets).values())
    loss.backward()
    assert torch.isfinite(loss)
    save_checkpoint(tmp_path / "lite.pt", model, cfg, ["plant"], [1])
    again, _ = load_detector(tmp_path / "lite.pt")
    assert all(torch.equal(v, again.state_dict()[k]) for k, v in model.state_dict().items())
    with pytest.raises(ConfigError, match="no COCO weights"):
        build_detector(ModelConfig(architecture=LITE, pretrained="coco"), 2)


def test_auto_picks_the_light_detector_from_random_weights_on_a_cpu_only(tiles):
    ds = CocoDetection(tiles[0])

    def choose(*extra, device=CPU):
        cfg = config(tiles, "model.min_size=64", "model.max_size=64", *extra)
        return choose_architecture(cfg, cfg.model, device, ds, 1, 100, tiles[0], Budget.from_config(cfg))

    arch, why, probe = choose()
    assert arch == LITE and probe is None and "random weights on a CPU" in why
    assert choose(LITE_ANCHORS)[0] == LITE  # 3 levels: MobileNetV3 or the light one
    assert choose(device=GPU)[0] == PAPER  # on a GPU without a budget the paper's
    assert choose("model.pretrained=imagenet", "model.checkpoint=null", LITE_ANCHORS)[0] == MOBILE  # not from scratch
    assert choose("model.anchor_sizes=[[8],[16],[32],[64],[128]]")[0] == PAPER  # 5 levels: only ResNet-50


def test_training_crops_are_chosen_on_a_cpu_from_random_weights_logged_and_overridable(tiles, caplog):
    chosen, why = cpu_crop(config(tiles), CPU)  # min_size 800 by default
    assert chosen.augment.crop == CPU_CROP and f"augment.crop: {CPU_CROP}" in why
    for extra, device in (
        ([], GPU),  # a GPU without max_minutes: whole tiles
        (["model.pretrained=coco"], CPU),
        (["model.min_size=224", "model.max_size=224"], CPU),
        ([f"model.architecture={MOBILE}"], CPU),
    ):  # a named architecture trains as set
        kept, why = cpu_crop(config(tiles, *extra), device)
        assert kept.augment.crop == 0 and why is None, extra
    for value in (0, 320):  # set by hand: kept
        kept, why = cpu_crop(config(tiles, f"augment.crop={value}"), CPU)
        assert kept.augment.crop == value and why is None


def test_the_budget_ends_a_from_scratch_cpu_run_and_validation_is_sized(tiles):
    cfg = config(tiles, "max_minutes=15")
    cfg, size, why = scratch_budget(cfg, CPU, Budget.from_config(cfg))
    assert cfg.epochs == SCRATCH_EPOCHS and size and "max_minutes = 15" in why
    for extra, device in (
        (["max_minutes=15", "epochs=40"], CPU),
        (["max_minutes=15", "val_every=3"], CPU),
        ([], CPU),
        (["max_minutes=15", "model.pretrained=coco"], CPU),
        (["max_minutes=15", "model.pretrained=coco"], GPU),
        (["max_minutes=15", f"model.architecture={LITE}"], CPU),
    ):
        kept, size, why = scratch_budget(config(tiles, *extra), device, Budget.from_config(config(tiles, *extra)))
        assert kept == config(tiles, *extra) and not size and why is None, extra
    # validation at most ~10 % of training: 3.8 s against 22.2 s epochs -> every 2nd epoch; cheap -> every epoch
    assert validation_interval(3.8, 22.2) == 2 and validation_interval(1.0, 100.0) == 1
    assert validation_interval(3.0, 8.0) == 4


def test_the_budget_recipe_applies_on_a_gpu_within_max_minutes(tiles, caplog):
    """Issue 38: from random weights with max_minutes, a GPU gets the recipe the CPU's 53 % AP50 came from (the
    light detector, crops, AdamW, epochs ended by the budget), logged with the reason; without a budget, or from
    pretrained weights, the paper's detector on whole tiles as configured."""
    ds = CocoDetection(tiles[0])
    cfg = config(tiles, "max_minutes=3")
    budget = Budget.from_config(cfg)
    arch, why, probe = choose_architecture(cfg, cfg.model, GPU, ds, 1, 100, tiles[0], budget)
    assert arch == LITE and probe is None and "max_minutes = 3" in why
    cropped, why = cpu_crop(cfg, GPU, budget)
    assert cropped.augment.crop == CPU_CROP and "within max_minutes" in why
    extended, size, why = scratch_budget(cfg, GPU, budget)
    assert extended.epochs == SCRATCH_EPOCHS and size and "max_minutes = 3" in why
    chosen, why = scratch_recipe(cfg, GPU)
    assert (chosen.optimizer, chosen.schedule) == ("adamw", "cosine") and "within max_minutes" in why
    for extra in ([], ["model.pretrained=coco"]):  # no budget, or pretrained: as before
        other = config(tiles, *extra, *(["max_minutes=3"] if extra else []))
        other_budget = Budget.from_config(other)
        assert choose_architecture(other, other.model, GPU, ds, 1, 100, tiles[0], other_budget)[0] == PAPER
        assert cpu_crop(other, GPU, other_budget)[0].augment.crop == 0


def test_a_resumed_run_keeps_the_crop_epochs_and_validation_auto_chose(tiles):
    cfg = config(tiles, "max_minutes=15")
    chosen, _ = cpu_crop(cfg, CPU)
    chosen, _, _ = scratch_budget(chosen, CPU, Budget.from_config(cfg))
    saved = to_dict(
        load_config(
            ModelTrainConfig,
            None,
            [
                f"train_json={tiles[0]}",
                "model.pretrained=none",
                "max_minutes=15",
                f"augment.crop={chosen.augment.crop}",
                f"epochs={chosen.epochs}",
                "val_every=3",
            ],
        )
    )
    resumed = resumed_recipe(cfg, saved)
    assert (resumed.augment.crop, resumed.epochs, resumed.val_every) == (CPU_CROP, SCRATCH_EPOCHS, 3)
    mine = resumed_recipe(config(tiles, "max_minutes=15", "epochs=40", "augment.crop=0"), saved)
    assert (mine.augment.crop, mine.epochs, mine.val_every) == (0, 40, 1)


def test_crops_keep_the_detectors_scale_hold_a_plant_and_repeat_with_the_seed(tmp_path):
    tiles = make_tiles(tmp_path, n_images=6, size=128, plants=(1, 2), radius=(6, 10), negatives=0, seed=3)
    ds, plain = CocoDetection(tiles), CocoDetection(tiles)
    ds.crop_windows(48, 256, 256, on_plant=1.0)  # 128 px tiles at the detector's 256 px: x2, then 48 px
    ds.set_seed(7)
    for i in range(len(ds)):
        image, target = ds[i]
        assert tuple(image.shape) == (3, 48, 48) and len(target["boxes"]) >= 1  # a plant's centre in every crop
        sizes = 2 * (plain.target(i)["boxes"][:, 2:] - plain.target(i)["boxes"][:, :2])
        b = target["boxes"]
        inside = (b[:, 0] > 0) & (b[:, 1] > 0) & (b[:, 2] < 48) & (b[:, 3] < 48)
        for w, h in (b[inside, 2:] - b[inside, :2]).tolist():  # whole boxes: twice a tile box's size
            assert np.min(np.abs(sizes.numpy() - [w, h]).max(axis=1)) < 1.0
        again, target2 = ds[i]
        assert torch.equal(image, again) and torch.equal(target["boxes"], target2["boxes"])
    assert tuple(ds.plain_image(0).shape) == (3, 128, 128)


def test_a_run_on_crops_trains_at_the_crop_and_times_detection_on_whole_tiles(tiles, tmp_path, caplog):
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            f"train_json={tiles[0]}",
            f"val_json={tiles[1]}",
            f"output_dir={tmp_path}",
            f"model.architecture={LITE}",
            "model.pretrained=none",
            "model.min_size=64",
            "model.max_size=64",
            LITE_ANCHORS,
            "augment.crop=32",
            "batch_size=4",
            "num_workers=0",
            "epochs=1",
            "model.roi.batch_size_per_image=32",
            "model.rpn.post_nms_top_n_train=100",
            "model.rpn.pre_nms_top_n_train=100",
        ],
    )
    with caplog.at_level(logging.INFO):
        summary = train(cfg)
    assert summary["status"] == "finished" and tuple(summary["estimate"]["probe"]["input_px"]) == (32, 32)
    model, ck = load_detector(tmp_path / "checkpoints" / "last.pt")
    assert ck["train_config"]["augment"]["crop"] == 32 and not model.transform._skip_resize  # detection resizes
