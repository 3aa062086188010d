"""The two records module 6's engine passes around: :class:`Job` (what the set-up built: data, model, optimizer,
budget; fixed for the session) and :class:`TrainState` (what training changes: iterations done, history, best
epoch, the random state where an epoch stopped). The parts of :mod:`~matchplant.model_train.engine` take them
instead of two dozen arguments; a GPU variant of a part reads the same records."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from matchplant.model_train.budget import Budget
from matchplant.model_train.config import ModelTrainConfig

if TYPE_CHECKING:  # names for the annotations only: loading the record loads neither PyTorch nor the data code
    import torch
    from torch.utils.data import DataLoader

    from matchplant.detection.data import CocoDetection, EpochSampler
    from matchplant.detection.distributed import Shard
    from matchplant.detection.gpu import Runtime
    from matchplant.detection.model import ModelConfig


@dataclass
class Job:
    """One training session's fixed parts (``cfg`` is the run's settings after auto choices and the probe)."""

    cfg: ModelTrainConfig
    budget: Budget
    out: Path
    device: torch.device
    dist_info: Shard  # this process's place in a torchrun job (one process: rank 0 of 1)
    train_ds: CocoDetection
    val_ds: CocoDetection | None
    class_names: list[str]
    validation: dict
    model: torch.nn.Module  # what trains (DistributedDataParallel under torchrun)
    core: torch.nn.Module  # the detector itself (saved, validated)
    model_cfg: ModelConfig
    geometry: dict
    sampler: EpochSampler
    loader: DataLoader
    iters: int  # iterations per epoch
    optimizer: torch.optim.Optimizer | None = None
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None
    scaler: torch.amp.GradScaler | None = None
    amp: bool = False
    amp_dtype: torch.dtype | None = None  # the autocast dtype on CUDA (model_train/gpu.py), None in fp32
    runtime: Runtime | None = None  # the run's device, precision and feed, chosen once (detection/gpu.py)
    extras: dict = field(default_factory=dict)
    on_epoch_end: Callable[[int, dict], object] | None = None
    on_iteration: Callable[[int], object] | None = None

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
