"""The two records module 6's engine passes around: :class:`Job` (what the set-up built: data, model, optimizer,
budget; fixed for the session) and :class:`TrainState` (what training changes: iterations done, history, best
epoch, the random state where an epoch stopped). The parts of :mod:`~matchplant.model_train.engine` take them
instead of two dozen arguments; a GPU variant of a part reads the same records."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from matchplant.model_train.budget import Budget
from matchplant.model_train.config import ModelTrainConfig


@dataclass
class Job:
    """One training session's fixed parts (``cfg`` is the run's settings after auto choices and the probe)."""

    cfg: ModelTrainConfig
    budget: Budget
    out: Path
    device: Any
    dist_info: Any
    train_ds: Any
    val_ds: Any
    class_names: list[str]
    validation: dict
    model: Any  # what trains (DistributedDataParallel under torchrun)
    core: Any  # the detector itself (saved, validated)
    model_cfg: Any
    geometry: dict
    sampler: Any
    loader: Any
    iters: int  # iterations per epoch
    optimizer: Any = None
    scheduler: Any = None
    scaler: Any = None
    amp: bool = False
    amp_dtype: Any = None  # the autocast dtype on CUDA (model_train/gpu.py), None in fp32
    runtime: Any = None  # the run's device, precision and feed, chosen once (detection/gpu.py's Runtime)
    extras: dict = field(default_factory=dict)
    on_epoch_end: Callable[[int, dict], Any] | None = None
    on_iteration: Callable[[int], Any] | None = None

    @property
    def ck_dir(self) -> Path:
        """Folder of the run's checkpoints (``<output_dir>/checkpoints``)."""
        return self.out / "checkpoints"


@dataclass
class TrainState:
    """What training has done so far (saved in every checkpoint, restored on resume)."""

    done: int = 0  # iterations
    history: list[dict] = field(default_factory=list)
    best: dict = field(default_factory=lambda: {"epoch": None, "value": None})
    progress: dict | None = None  # resumed mid-epoch: {"batches", "sums"} of that epoch
    rng: dict | None = None  # ... and the random state it stopped with
    stop_rng: dict | None = None  # the random state where the last epoch stopped (partial epochs)
