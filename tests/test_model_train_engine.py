"""Module 6's engine parts on their own (issue 37): the budget record's seconds and stop decision, one training
step, one epoch's stop, and a checkpoint's round trip, each against values worked out by hand."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import MatchPlantError
from matchplant.detection.checkpoint import read_checkpoint
from matchplant.detection.model import build_detector
from matchplant.model_train import budget as budget_mod
from matchplant.model_train.budget import LONG_RUN_S, Budget, Costs
from matchplant.model_train.checkpoint import restore, save
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.engine import train_one_epoch, train_step
from matchplant.model_train.setup import build_optimizer, build_scheduler
from matchplant.model_train.state import TrainState


class _Clock:
    now = 0.0

    @classmethod
    def perf_counter(cls):
        return cls.now


def config(*extra: str) -> ModelTrainConfig:
    return load_config(ModelTrainConfig, None, ["train_json=x", *extra], check_paths=False)


@pytest.fixture
def clock(monkeypatch):
    _Clock.now = 100.0
    monkeypatch.setattr(budget_mod, "time", _Clock)
    return _Clock


def _running(minutes: float, clock, *, validated=True) -> Budget:
    """A budget of ``minutes`` planned for 10 epochs of 10 iterations at 1 s, 5 s validations, 2 s checkpoints."""
    budget = Budget.from_config(config(f"max_minutes={minutes}"))
    budget.plan_for(100, 10)
    budget.costs, budget.validated = Costs(iteration=1.0, validation=5.0, checkpoint=2.0), validated
    budget.stop_flag = SimpleNamespace(requested=False)
    return budget


def test_the_budget_reads_max_minutes_once_and_gives_seconds_and_the_fallback(clock):
    b = Budget.from_config(config("max_minutes=2.5"))
    assert b.minutes == 2.5 and b.limited and b.seconds == 150.0 and b.horizon_s == 150.0
    assert b.horizon_words() == "max_minutes = 2.5"
    clock.now += 40.0
    assert b.elapsed() == 40.0 and b.left() == 110.0
    none = Budget.from_config(config())
    assert none.minutes == 0 and not none.limited and none.seconds == 0.0
    assert none.horizon_s == LONG_RUN_S and none.horizon_words() == "3.0 h (no max_minutes)"


def test_the_stop_decision_keeps_time_for_the_last_validation_and_checkpoint(clock):
    b = _running(1, clock)  # 60 s; the reserve is 5 + 2 = 7 s
    assert b.reserve() == 7.0
    clock.now += 51.0  # 51 s spent: the next 1 s iteration + 7 s = 59 s <= 60: go on
    assert b.after_step(1, 1.0) is None
    clock.now += 1.5  # 52.5 + 1 + 7 = 60.5 s > 60: stop
    assert b.after_step(2, 1.0) == "budget"
    assert b.out_of_time_for(0.0) and not _running(10, clock).out_of_time_for(5.0)
    b.stop_flag.requested = True
    assert b.after_step(3, 1.0) == "interrupt"
    unlimited = _running(0, clock)
    clock.now += 10**6
    assert unlimited.after_step(1, 1.0) is None and not unlimited.out_of_time_for(10**6)


def test_the_first_refit_follows_the_measured_speed(clock):
    b = _running(1, clock, validated=False)  # 60 s, reserve 2 s
    b.fit(0, b.costs, 60.0, "probe")
    # by hand: n iterations cost n + 2 x (epochs begun) s; 50 + 5 x 2 = 60 fits, 51 + 6 x 2 = 63 does not
    assert b.plan.iters == 50 and b.plan.source == "probe"
    for done in range(1, 11):  # 10 steps at 2 s: the refit comes at min(10, 50 // 10) = 5
        clock.now += 2.0
        b.after_step(done, 2.0)
        if done == 5:
            # 10 s spent, 50 s left at 2 s per iteration (the mean of steps 2-5): n iterations cost 2n + 2 s per
            # epoch begun, 12 s for the 5 done; 28: 56 + 6 - 12 = 50 s fits, 29: 58 + 6 - 12 = 52 s does not
            assert b.plan.fitted and b.plan.source == "measured on the first iterations"
            assert b.plan.iters == 28


def test_status_messages(clock):
    b = _running(1.5, clock)
    assert b.status(100) == ("finished", "finished all 10 epochs (100 iterations)")
    b.plan.iters = 40
    assert b.status(40) == (
        "stopped_by_max_minutes",
        "stopped by max_minutes (1.5) after 40 of 100 iterations (4 of "
        "10 epochs), the end of the plan fitted to the budget (the learning-rate schedule ran "
        "its course)",
    )
    assert b.status(25)[1].endswith(
        "after 25 of 100 iterations (2.5 of 10 epochs), before the end of the plan fitted to it (40 iterations at the "
        "pace measured before: training ran slower); --resume trains the 15 left"
    )
    assert b.status(25, interrupted=True) == (
        "interrupted",
        "interrupted (Ctrl-C) after 25 of 100 iterations (2.5 of 10 epochs); --resume continues exactly there",
    )


class _Toy(torch.nn.Module):
    """A 'detector' whose two losses are (w - 3)^2 and w^2 / 2: the gradient is 2(w - 3) + w."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))

    def forward(self, images, targets):
        return {"loss_a": ((self.w - 3) ** 2).sum(), "loss_b": (self.w**2 / 2).sum()}


def _toy_parts(lr=0.1):
    model = _Toy()
    opt = torch.optim.SGD(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda it: 1.0)
    return model, opt, sched, torch.amp.GradScaler("cuda", enabled=False)


BATCH = ([torch.zeros(3, 4, 4)], [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.int64)}])


def test_one_step_updates_the_weights_and_the_schedule_by_hand():
    model, opt, sched, scaler = _toy_parts()
    names, values = train_step(model, *BATCH, opt, sched, scaler, torch.device("cpu"), False, "step")
    assert names == ("loss_a", "loss_b", "loss") and values == pytest.approx([9.0, 0.0, 9.0])
    # gradient at w = 0: 2 (0 - 3) + 0 = -6; SGD at 0.1: w = 0.6
    assert model.w.item() == pytest.approx(0.6) and sched.last_epoch == 1
    names, values = train_step(model, *BATCH, opt, sched, scaler, torch.device("cpu"), False, "step")
    assert values == pytest.approx([(0.6 - 3) ** 2, 0.18, (0.6 - 3) ** 2 + 0.18])
    model.w.data.fill_(math.inf)
    with pytest.raises(MatchPlantError, match="training loss became"):
        train_step(model, *BATCH, opt, sched, scaler, torch.device("cpu"), False, "step")


def test_one_epoch_stops_when_asked_and_sums_the_losses():
    model, opt, sched, scaler = _toy_parts(lr=0.0)  # the losses stay 9 and 0
    sums, seen = {"loss": 9.0, "loss_a": 9.0, "loss_b": 0.0}, []  # resumed after one batch
    reason, batches = train_one_epoch(
        model,
        [BATCH] * 5,
        opt,
        sched,
        scaler,
        torch.device("cpu"),
        False,
        "e",
        sums,
        1,
        lambda s: seen.append(s) or ("budget" if len(seen) == 2 else None),
        slow=False,
        limit=4,
    )
    assert reason == "budget" and batches == 3 and len(seen) == 2
    assert sums == pytest.approx({"loss": 27.0, "loss_a": 27.0, "loss_b": 0.0})
    reason, batches = train_one_epoch(
        model,
        [BATCH] * 5,
        opt,
        sched,
        scaler,
        torch.device("cpu"),
        False,
        "e",
        {},
        0,
        lambda s: None,
        slow=False,
        limit=4,
    )
    assert reason is None and batches == 4  # the limit (the plan's end inside the epoch)


FAST = [
    "model.architecture=fasterrcnn_mobilenet_v3_large_fpn",
    "model.pretrained=none",
    "model.min_size=64",
    "model.max_size=64",
    "model.anchor_sizes=[[8,16,32],[8,16,32],[8,16,32]]",
]


def test_a_checkpoint_round_trip_restores_the_state_mid_epoch(tmp_path: Path):
    torch.manual_seed(0)
    cfg = config(*FAST)
    core = build_detector(cfg.model, 2, load_weights=False)
    budget = Budget.from_config(cfg)
    plan = budget.plan_for(30, 10)
    plan.iters = 17
    opt = build_optimizer(cfg, core)
    sched = build_scheduler(cfg, opt, 10, plan)
    for _ in range(3):
        opt.step()  # no gradients: nothing moves but the schedule
        sched.step()

    def job(optimizer, scheduler):
        return SimpleNamespace(
            optimizer=optimizer,
            scheduler=scheduler,
            scaler=None,
            amp=False,
            cfg=cfg,
            iters=10,
            geometry={"tile_size": 64},
            budget=budget,
            ck_dir=tmp_path,
            core=core,
            model_cfg=cfg.model,
            class_names=["plant"],
            train_ds=SimpleNamespace(category_ids=[1]),
        )

    state = TrainState(
        done=13,
        history=[{"epoch": 1, "iterations": 10}],
        best={"epoch": 1, "value": 0.5},
        stop_rng={"torch": torch.get_rng_state()},
    )
    save(job(opt, sched), state, "last.pt", 1, {"val": {"AP50": 0.5}}, {"batches": 3, "sums": {"loss": 2.0}})
    ck = read_checkpoint(tmp_path / "last.pt")
    assert (ck["epoch"], ck["iteration"], ck["planned_iters"], ck["iters_per_epoch"]) == (1, 13, 17, 10)
    assert ck["metrics"] == {"AP50": 0.5} and ck["epoch_progress"] == {"batches": 3, "sums": {"loss": 2.0}}
    assert torch.equal(ck["random_state"]["torch"], state.stop_rng["torch"])
    # a new session of the same run: its plan and schedule come back from the checkpoint
    budget = Budget.from_config(cfg)
    budget.plan_for(30, 10)
    opt2 = build_optimizer(cfg, core)
    sched2 = build_scheduler(cfg, opt2, 10, budget.plan)
    back = restore(job(opt2, sched2), ck)
    assert (back.done, back.history, back.best) == (13, state.history, state.best)
    assert back.progress == {"batches": 3, "sums": {"loss": 2.0}} and torch.equal(
        back.rng["torch"], state.stop_rng["torch"]
    )
    assert (budget.plan.iters, budget.plan.fitted, budget.plan.source) == (17, True, "resumed")
    assert sched2.last_epoch == 3 and opt2.param_groups[0]["lr"] == opt.param_groups[0]["lr"]
    assert restore(job(opt2, sched2), None) == TrainState()
