"""Module 6's numbered checkpoints (issue 39): ``save_every: auto`` keeps the last few when the budget sets the run's
length, a number the user sets keeps them all, and the disk the checkpoints use is logged and summarised."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import pytest

import matchplant.model_train.checkpoint as ck
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError
from matchplant.model_train.budget import Budget
from matchplant.model_train.config import ModelTrainConfig

SIZE = 1000  # bytes of each stand-in checkpoint


@pytest.fixture
def fake_save(monkeypatch):
    """The real save writes a detector; the files' names and sizes are what is checked here."""

    def save(job, state, name, epoch_done, record, partial):
        (job.ck_dir / name).write_bytes(b"x" * SIZE)

    monkeypatch.setattr(ck, "save", save)


def job(tmp_path: Path, save_every, minutes: float) -> SimpleNamespace:
    d = tmp_path / "checkpoints"
    d.mkdir()
    for name in ("best.pt", "last.pt"):
        (d / name).write_bytes(b"x" * SIZE)
    return SimpleNamespace(
        cfg=SimpleNamespace(save_every=save_every), budget=SimpleNamespace(limited=bool(minutes)), ck_dir=d, extras={}
    )


def run_epochs(j, n: int) -> list[str]:
    for epoch in range(1, n + 1):
        ck.save_numbered(j, None, epoch, {})
    return sorted(p.name for p in j.ck_dir.iterdir() if p.suffix == ".pt")


def test_auto_under_a_budget_keeps_the_last_three(tmp_path, fake_save, caplog):
    j = job(tmp_path, "auto", minutes=15)
    with caplog.at_level(logging.INFO, logger="matchplant"):
        names = run_epochs(j, 42)
    assert names == ["best.pt", "epoch_030.pt", "epoch_035.pt", "epoch_040.pt", "last.pt"]
    assert j.extras["checkpoint_disk"] == {"files": 5, "bytes": 5 * SIZE, "folder": str(j.ck_dir)}
    assert "removed epoch_025.pt" in caplog.text and "save_every: N" in caplog.text
    assert "checkpoints: 5 file(s), 0.0 MB" in caplog.text


def test_a_number_set_by_the_user_keeps_them_all(tmp_path, fake_save):
    j = job(tmp_path, 5, minutes=15)
    names = run_epochs(j, 42)
    assert [n for n in names if n.startswith("epoch_")] == [f"epoch_{e:03d}.pt" for e in range(5, 41, 5)]
    assert j.extras["checkpoint_disk"]["files"] == 10


def test_auto_without_a_budget_keeps_every_fifth(tmp_path, fake_save):
    names = run_epochs(job(tmp_path, "auto", minutes=0), 30)
    assert [n for n in names if n.startswith("epoch_")] == [f"epoch_{e:03d}.pt" for e in range(5, 31, 5)]


def test_zero_keeps_only_best_and_last(tmp_path, fake_save):
    assert run_epochs(job(tmp_path, 0, minutes=15), 12) == ["best.pt", "last.pt"]


def test_save_every_reads_auto_or_a_number():
    base = ["train_json=x.json"]
    assert load_config(ModelTrainConfig, None, base, check_paths=False).save_every == "auto"
    assert load_config(ModelTrainConfig, None, [*base, "save_every=7"], check_paths=False).save_every == 7
    with pytest.raises(ConfigError, match="save_every"):
        load_config(ModelTrainConfig, None, [*base, "save_every=often"], check_paths=False)
    with pytest.raises(ConfigError, match="save_every"):
        load_config(ModelTrainConfig, None, [*base, "save_every=-1"], check_paths=False)


# -- the status of a run whose budget is shorter than its least work (issue 39)


def test_a_budget_shorter_than_one_iteration_is_not_reported_finished():
    b = Budget(minutes=1e-6)  # 0.06 ms
    b.plan_for(1, 1)
    while b.elapsed() <= b.seconds:
        pass
    status, message = b.status(1)
    assert status == "finished_over_max_minutes" and "past max_minutes = 1e-06" in message
    b.plan_for(4, 2)
    b.plan.iters = 1
    status, message = b.status(1)
    assert (
        status == "stopped_by_max_minutes" and "past max_minutes: the iteration" in message and "never cut" in message
    )
    b.sets_length = True  # the recipe's ceiling of epochs: the message speaks of iterations done, not of the ceiling
    assert "after 1 iterations (0.5 epochs)" in b.status(1)[1] and "of 4" not in b.status(1)[1]
    relaxed = Budget(minutes=60)
    relaxed.plan_for(1, 1)
    assert relaxed.status(1)[0] == "finished"
