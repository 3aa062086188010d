"""Resuming a run exactly where it stopped, refusing one that no longer matches, and Ctrl-C that keeps the work.

``resume: true`` continues ``output_dir/checkpoints/last.pt``: at an epoch's end or inside one (after Ctrl-C or
``max_minutes``), with the same samples in the same order (:class:`~matchplant.detection.data.EpochSampler`,
augmentation seeded per tile), the same learning-rate position (the scheduler counts iterations, the plan is
stored) and the random state the interrupted run had (:func:`random_state`), so the resumed run computes what
the uninterrupted one would have. A changed ``model.architecture``, input size or class list is refused
(:func:`check_resumable`) with the key, the checkpoint and the two ways on; ``resume: fresh`` (``--fresh``)
starts a new run in the folder instead.

:class:`StopOnInterrupt`: the first Ctrl-C asks training to stop after the current iteration (a checkpoint is
written, then the command prints its one line and exits 130); a second one stops at once.
"""

from __future__ import annotations

import random
import signal
import threading
from pathlib import Path

import numpy as np

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.checkpoint import read_checkpoint
from matchplant.detection.gpu import as_runtime
from matchplant.detection.model import AUTO

log = get_logger("model_train")

CHECKED = ("architecture", "min_size", "max_size")  # model settings a resumed run cannot change
# settings that change what the next epochs train on (the data, its order, the augmentation): a resumed run with
# another value trains on something else than the run did, which the resume says (they may be changed on purpose)
DATA_KEYS = ("train_json", "train_images", "batch_size", "seed")


def open_resume(cfg, ck_dir: Path, class_names: list[str]) -> dict | None:
    """The checkpoint to resume from (``resume: true``), or None for a new run (``false``, ``fresh``)."""
    last = ck_dir / "last.pt"
    if cfg.resume == "fresh":
        old = sorted(ck_dir.glob("*.pt")) if ck_dir.is_dir() else []
        for p in old:
            p.unlink()
        if old:
            log.info(
                "resume: fresh: a new run in %s; the earlier run's %d checkpoint(s) were removed",
                cfg.output_dir,
                len(old),
            )
        return None
    if not cfg.resume:
        if last.is_file():
            log.info(
                "%s holds an earlier run's checkpoints; this new run replaces them (resume: true would continue it)",
                ck_dir,
            )
        return None
    if not last.is_file():
        raise InputError(
            "nothing to resume: no checkpoint of an earlier run here",
            path=last,
            fix="set output_dir to the crashed run's folder, or start without --resume",
        )
    ck = read_checkpoint(last)
    check_resumable(cfg, ck, class_names, last)
    return ck


def check_resumable(cfg, ck: dict, class_names: list[str], path: Path) -> None:
    """Refuse to resume a run whose classes or model settings differ from the config's."""
    ways = (
        "start a new run with --fresh (resume: fresh; it replaces the checkpoints in output_dir), or set "
        "another output_dir"
    )
    if ck.get("class_names") != class_names:
        raise ConfigError(
            f"cannot resume: the checkpoint's classes {ck.get('class_names')} differ from the "
            f"training set's {class_names}",
            path=path,
            fix=f"resume with the same dataset, or {ways}",
        )
    saved = ck.get("model_config") or {}
    for key in CHECKED:
        now = getattr(cfg.model, key)
        if key == "architecture" and now == AUTO:
            log.info("model.architecture: auto; the resumed run keeps its %s", saved.get(key))
            continue
        if saved.get(key) is not None and saved.get(key) != now:
            raise ConfigError(
                f"cannot resume: model.{key} is {now} but the run in this folder was trained with {saved.get(key)}",
                path=path,
                fix=f"set model.{key}: {saved.get(key)} to continue it, or {ways}",
            )
    changed = changed_data_settings(cfg, ck.get("train_config") or {})
    if changed:
        log.warning(
            "resuming %s with training data settings other than the run's: %s; the next epochs train on that, "
            "after %s iteration(s) on the run's settings (set the run's values to continue it exactly as it was, "
            "or resume: fresh to start over)",
            path,
            "; ".join(changed),
            ck.get("iteration", "its"),
        )
    if ck.get("epoch", 0) >= cfg.epochs and not ck.get("epoch_progress"):
        log.warning(
            "the run in %s already finished its %d epochs; raise 'epochs' to train longer", cfg.output_dir, ck["epoch"]
        )


def changed_data_settings(cfg, saved: dict) -> list[str]:
    """``key: run's value -> this config's`` for each setting of :data:`DATA_KEYS` and ``augment`` that this config
    sets to another value than the checkpoint's run had (an auto value, null, takes the run's and is no change)."""
    now = to_dict(cfg)
    pairs = [(k, saved.get(k), now.get(k)) for k in DATA_KEYS]
    pairs += [(f"augment.{k}", v, now["augment"].get(k)) for k, v in (saved.get("augment") or {}).items()]
    out = []
    for key, was, new in pairs:
        if was is None or new is None:
            continue
        if key in ("train_json", "train_images"):
            was, new = str(Path(was).resolve()), str(Path(new).resolve())
        if was != new:
            out.append(f"{key}: {was} -> {new}")
    return out


def random_state(device) -> dict:
    """Every random state training draws from (torch's CPU and CUDA generators, NumPy, Python)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    runtime = as_runtime(device)
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if runtime.own_rng:
        state["cuda"] = torch.cuda.get_rng_state(runtime.device)
    return state


def set_random_state(state: dict, device) -> None:
    """Restore :func:`random_state`'s generators (``device``: the run's Runtime, or a bare device)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    runtime = as_runtime(device)
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if runtime.own_rng and state.get("cuda") is not None:
        torch.cuda.set_rng_state(state["cuda"], runtime.device)


def ignore_sigint(_worker_id: int) -> None:
    """DataLoader workers leave Ctrl-C to the main process (which stops cleanly after the iteration)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class StopOnInterrupt:
    """While training: the first Ctrl-C sets ``requested`` (training stops after the iteration and saves), the
    second raises KeyboardInterrupt at once. Outside the main thread (a GUI's worker) it does nothing."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.debug(  # the command's own line says it (one line on Ctrl-C)
            "Ctrl-C: stopping after this iteration and writing a checkpoint that --resume continues "
            "from (Ctrl-C again stops at once, without it)"
        )

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False
