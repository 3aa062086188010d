"""Module 6's reports: ``training_summary.json`` (status, plan, estimate, history) and ``training_curves.png``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path, write_json
from matchplant.model_train.budget import Budget
from matchplant.model_train.config import ModelTrainConfig


def write_summary(
    out: Path,
    cfg: ModelTrainConfig,
    history: list[dict],
    best: dict,
    class_names: list[str],
    device,
    status: str,
    budget: Budget,
    *,
    validation: dict | None = None,
    message: str | None = None,
    extras: dict | None = None,
) -> dict:
    """training_summary.json. ``status``: running, finished, finished_over_max_minutes (all of it, but the budget
    was shorter than one iteration), interrupted or stopped_by_max_minutes (``message``
    says after how many of how many iterations); ``validation``: tiles, boxes and distinct plants, with a warning
    when too few; ``extras``: threads, the probe's estimate, the architecture chosen and why; metrics are
    fractions 0..1. ``budget``: its plan and minutes, and the session's seconds so far."""
    plan, seconds = budget.plan, budget.elapsed()
    times = [h["train_time_s"] for h in history]
    warnings = [validation["warning"]] if validation and validation.get("warning") else []
    total = cfg.epochs * plan.iters_per_epoch if plan is not None else None
    if plan is not None and plan.iters < total:
        warnings.append(
            f"max_minutes ({budget.minutes:g}) fits {plan.iters} of {total} iterations ({plan.source}): "
            f"the learning-rate schedule was laid over {plan.iters} iterations"
        )
    if extras and extras.get("schedule_warning"):
        warnings.append(extras["schedule_warning"])
    if extras and (extras.get("estimate") or {}).get("advice"):
        warnings.append(extras["estimate"]["advice"])
    done = max((h.get("iterations", 0) for h in history), default=0)
    summary = {
        "status": status,
        "message": message or status,
        "epochs_done": sum(1 for h in history if not h.get("partial")),
        "epochs": cfg.epochs,
        "epochs_planned": plan.epochs if plan is not None else cfg.epochs,
        "iterations_done": done,
        "iterations_planned": plan.iters if plan is not None else None,
        "iterations_per_epoch": plan.iters_per_epoch if plan is not None else None,
        "max_minutes": budget.minutes,
        "warnings": warnings,
        "validation": validation,
        "units": "AP, AP50 and the other metrics are fractions 0..1",
        "class_names": class_names,
        "best": best,
        "device": str(device),
        **(extras or {}),
        "checkpoints": {"best": str(out / "checkpoints" / "best.pt"), "last": str(out / "checkpoints" / "last.pt")},
        "mean_train_images_per_s": (float(np.mean([h["train_images_per_s"] for h in history])) if history else None),
        "train_time_s": float(sum(times)),
        "this_session_s": round(seconds, 3),
        "history": history,
        "config": to_dict(cfg),
    }
    write_json(out / "training_summary.json", summary)
    return summary


def plot_curves(history: list[dict], path: Path) -> Path:
    """Loss components and validation AP / AP50 per epoch."""
    from matplotlib.ticker import MaxNLocator  # matplotlib on first use, as core.runtime.gui

    fig = figure(headless=True, figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    epochs = [h["epoch"] for h in history]
    for key in history[0]["losses"]:
        ax1.plot(
            epochs,
            [h["losses"][key] for h in history],
            marker=".",
            lw=2 if key == "loss" else 1,
            label=key.replace("loss_", ""),
        )
    ax1.set(xlabel="epoch", ylabel="training loss", title="losses")
    ax1.legend(fontsize=8)
    val = [h for h in history if "val" in h]
    for key in ("AP50", "AP"):
        ax2.plot([h["epoch"] for h in val], [100 * (h["val"][key] or 0) for h in val], marker="o", label=key)
    ax2.set(xlabel="epoch", ylabel="%", title="validation", ylim=(0, 100))
    if val:
        ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # epochs are whole: no tick at 1.2, 1.4
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path
