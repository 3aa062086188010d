"""Module 6 (model_train), resume (issue 27): ``--resume`` into a folder whose run no longer matches the config (a
changed ``model.architecture``, input size, class list, or batch size mid-epoch) is refused, naming the key and the
checkpoint, with the two ways on; ``resume: fresh`` starts a new run there instead (must work).

The earlier run is the artifacts' untrained checkpoint (MobileNetV3 FPN, 64..128 px, class 'plant') placed as
``output_dir/checkpoints/last.pt``.
"""

from __future__ import annotations

import json

import torch
from cases_model_train import args, splits
from harness import Case, Work


def earlier_run(w: Work, **change) -> None:
    """The artifacts' checkpoint as an earlier run's last.pt in the output folder (edited by ``change``)."""
    data = torch.load(w.artifacts / "model.pt", map_location="cpu", weights_only=False)
    data.update(change)
    (w.out / "checkpoints").mkdir(parents=True)
    torch.save(data, w.out / "checkpoints" / "last.pt")


def architecture_changed(w: Work) -> list[str]:
    train, _, val, _ = splits(w)
    earlier_run(w)
    return [*args(w, train, val, "model.architecture=fasterrcnn_resnet50_fpn", "resume=true")]


def input_size_changed(w: Work) -> list[str]:
    train, _, val, _ = splits(w)
    earlier_run(w)
    return [*args(w, train, val, "model.min_size=96", "resume=true")]


def classes_changed(w: Work) -> list[str]:
    train, _, val, _ = splits(w)
    earlier_run(w, class_names=["weed"])
    return [*args(w, train, val), "--resume"]


def batch_size_changed_mid_epoch(w: Work) -> list[str]:
    train, _, val, _ = splits(w)
    earlier_run(w, epoch=0, iteration=3, iters_per_epoch=7, epoch_progress={"batches": 3, "sums": {}})
    return [*args(w, train, val), "--resume"]


def fresh_after_architecture_change(w: Work) -> list[str]:
    train, _, val, _ = splits(w)
    earlier_run(w)
    torch.save({"stale": True}, w.out / "checkpoints" / "epoch_009.pt")
    return [
        *args(
            w,
            train,
            val,
            "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
            "model.min_size=96",
            "model.max_size=96",
        ),
        "--fresh",
    ]


def started_fresh(w: Work) -> None:
    summary = json.loads((w.out / "training_summary.json").read_text())
    assert summary["status"] == "finished" and summary["epochs_done"] == 1
    ck = torch.load(w.out / "checkpoints" / "last.pt", map_location="cpu", weights_only=False)
    assert ck["model_config"]["min_size"] == 96 and ck["iteration"] == summary["iterations_done"] > 0
    assert not (w.out / "checkpoints" / "epoch_009.pt").exists()  # the earlier run's checkpoints are gone


CASES = [
    Case(
        "m6-resume-architecture-changed",
        "model_train",
        architecture_changed,
        mentions=("model.architecture", "last.pt", "fasterrcnn_mobilenet_v3_large_fpn", "--fresh"),
    ),
    Case(
        "m6-resume-input-size-changed",
        "model_train",
        input_size_changed,
        mentions=("model.min_size", "last.pt", "64", "--fresh"),
    ),
    Case(
        "m6-resume-classes-changed", "model_train", classes_changed, mentions=("classes", "weed", "last.pt", "--fresh")
    ),
    Case(
        "m6-resume-batch-size-changed-mid-epoch",
        "model_train",
        batch_size_changed_mid_epoch,
        mentions=("batch_size", "last.pt", "7 iterations per epoch"),
    ),
    Case(
        "m6-resume-fresh-after-architecture-change",
        "model_train",
        fresh_after_architecture_change,
        expect="ok",
        check=started_fresh,
    ),
]
