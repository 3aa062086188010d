"""Issue 47: every preset of the demo runs (``python -m matchplant.demo --preset tiny`` stopped at its detection step
with "no plant found": two epochs of the tiny field's 9 iterations, shorter than the warm-up, trained no detector).
Each preset has its own default of epochs, so that each trains a detector that finds plants; the tiny one runs end to
end here (slow tier)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from matchplant.demo import CHOICES, PRESET_EPOCHS, default_epochs
from matchplant.demo_pipeline import pipeline_spec

REPO = Path(__file__).resolve().parents[1]
TINY_ITERATIONS_PER_EPOCH = 9  # 33 training tiles of 128 px in batches of 4 (the tiny field, module 5's split)


def test_every_preset_has_a_default_number_of_epochs():
    assert set(CHOICES["preset"]) <= set(PRESET_EPOCHS)
    assert default_epochs("small") == 2  # the README's figures come from it
    assert default_epochs("tiny", 5) == 5  # --epochs wins


def test_the_tiny_demo_trains_well_past_its_warm_up():
    train = next(
        s["config"]
        for s in pipeline_spec(Path("field"), "", epochs=1, minutes=0, pretrained="none", tile=128)["steps"]
        if s["module"] == "model_train"
    )
    assert default_epochs("tiny") * TINY_ITERATIONS_PER_EPOCH >= 5 * train["warmup_iters"]


@pytest.mark.slow
@pytest.mark.skipif(
    not os.environ.get("MATCHPLANT_LONG_TESTS"),
    reason="the whole tiny demo (training 20 epochs included) takes minutes, past the suite's budget: "
    "MATCHPLANT_LONG_TESTS=1 runs it (docs/development.md, Test tiers)",
)
def test_the_tiny_preset_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    done = subprocess.run(
        [sys.executable, "-m", "matchplant.demo", "--preset", "tiny", "--out", str(out), "--threads", "1"],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=3600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    predictions = json.loads((out / "7_detect" / "predictions.json").read_text())
    assert predictions["predictions"], "the tiny demo's detector found no plant"
    assert (out / "report" / "report.md").is_file()
