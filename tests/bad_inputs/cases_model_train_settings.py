"""Module 6 settings that would silently change another or do nothing (issue 39): a crop larger than the detector's
input (which would raise the input itself), crop_on_plant without crops, and a max_minutes shorter than the run's
one iteration (trained, but not reported as 'finished' within its budget)."""

from __future__ import annotations

import json

from cases_model_train import args, splits
from harness import Case, Work


def train(*extra: str):
    def prepare(w: Work) -> list[str]:
        tr, _, val, _ = splits(w, n_train=2, n_val=1)  # one training step
        return args(w, tr, val, *extra)

    return prepare


def over_budget(w: Work) -> None:
    summary = json.loads((w.out / "training_summary.json").read_text())
    assert summary["status"] == "finished_over_max_minutes", summary["status"]
    assert "past max_minutes = 1e-05" in summary["message"] and summary["iterations_done"] == 1


CASES = [
    Case(
        "m6-crop-larger-than-input",
        "model_train",
        train("augment.crop=1024"),
        mentions=("augment.crop (1024)", "model.min_size = 64", "at most 64"),
    ),
    Case(
        "m6-crop-on-plant-without-crops",
        "model_train",
        train("augment.crop=0", "augment.crop_on_plant=0.5"),
        mentions=("augment.crop_on_plant", "augment.crop: 0"),
    ),
    Case("m6-max-minutes-below-one-iteration", "model_train", train("max_minutes=0.00001"), "ok", check=over_budget),
]
