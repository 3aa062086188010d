"""Joining a torchrun job, shared by training (module 6) and detection (module 7).

``torchrun --nproc_per_node N <script> ...`` starts N copies of the script with ``RANK``, ``WORLD_SIZE`` and
``LOCAL_RANK`` set. Each process joins the job (one GPU each, ``cuda:LOCAL_RANK``, over nccl; on the CPU,
gloo); rank 0 is the one voice of the job: the other processes log only warnings and errors. Without
torchrun (``WORLD_SIZE`` unset or 1) nothing changes.
"""

from __future__ import annotations

import datetime
import logging
import os
import socket
import time
from dataclasses import dataclass

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("distributed")

TIMEOUT_VAR = "MATCHPLANT_JOIN_TIMEOUT"  # seconds a process waits for the others to join (and per collective)
DEFAULT_TIMEOUT_S = 600.0
RENDEZVOUS = ("RANK", "MASTER_ADDR", "MASTER_PORT")  # what torchrun sets beside WORLD_SIZE
UNSET = "unset WORLD_SIZE RANK LOCAL_RANK MASTER_ADDR MASTER_PORT"


@dataclass
class Shard:
    """This process's place in the job: its rank among ``world`` processes."""

    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    def take(self, items: list) -> list[int]:
        """Indices of the items this process handles (every ``world``-th, starting at ``rank``)."""
        return list(range(self.rank, len(items), self.world))

    def gather(self, part: list) -> list:
        """Every process's list, concatenated on the main process (empty elsewhere)."""
        if self.world == 1:
            return part
        import torch.distributed as dist  # lazy: PyTorch is heavy; configs load without it

        parts = [None] * self.world if self.main else None
        dist.gather_object(part, parts, dst=0)
        return [x for p in parts for x in p] if self.main else []

    def barrier(self) -> None:
        if self.world > 1:
            import torch.distributed as dist  # lazy: PyTorch is heavy; configs load without it

            dist.barrier()


def _int_var(name: str, default: str) -> int:
    value = os.environ.get(name, default).strip()
    try:
        return int(value)
    except ValueError:
        raise InputError(
            f"the environment variable {name}={value!r} is not a whole number",
            fix=f"{UNSET} to run as one process, or start the command with torchrun "
            "--nproc_per_node N, which sets them",
        ) from None


def world_size() -> int:
    """How many processes the torchrun job has (1 without torchrun)."""
    return _int_var("WORLD_SIZE", "1")


def join_timeout() -> float:
    """Seconds to wait for the other processes (``MATCHPLANT_JOIN_TIMEOUT``, default 600)."""
    value = os.environ.get(TIMEOUT_VAR, str(DEFAULT_TIMEOUT_S))
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise InputError(
            f"the environment variable {TIMEOUT_VAR}={value!r} is not a positive number of seconds",
            fix=f"set {TIMEOUT_VAR}=600 (or unset it)",
        )
    return seconds


def check_environment() -> int:
    """The torchrun variables, before any wait: a ``WORLD_SIZE`` > 1 left in the shell without the rest of a
    rendezvous (``RANK``, ``MASTER_ADDR``, ``MASTER_PORT``) is an error naming them, not a crash or a hang.
    Returns the world size."""
    world = world_size()
    if world <= 1:
        return world
    missing = [v for v in RENDEZVOUS if not os.environ.get(v, "").strip()]
    if missing:
        raise InputError(
            f"WORLD_SIZE={world} is set in the environment but {', '.join(missing)} "
            f"{'is' if len(missing) == 1 else 'are'} not: this is not a torchrun job (a variable left "
            "in the shell from an earlier job?)",
            fix=f"run as one process with `{UNSET}` first, or start the command with `torchrun "
            "--standalone --nproc_per_node N ...`, which sets them all",
        )
    rank = _int_var("RANK", "0")
    if not 0 <= rank < world:
        raise InputError(
            f"RANK={rank} is outside 0..{world - 1} (WORLD_SIZE={world})", fix=f"{UNSET}, or let torchrun set them"
        )
    return world


def _wait_for_master(addr: str, port: int, seconds: float) -> None:
    """Wait up to ``seconds`` for the job's first process to listen at ``addr:port``; an error saying so."""
    end = time.monotonic() + seconds
    while True:
        try:
            with socket.create_connection((addr, port), timeout=min(2.0, seconds)):
                return
        except OSError as exc:
            if time.monotonic() >= end:
                raise InputError(
                    f"no process of the distributed job listens at MASTER_ADDR:MASTER_PORT = {addr}:"
                    f"{port} after {seconds:g} s ({exc.strerror or exc}); this process is RANK="
                    f"{os.environ.get('RANK')} of WORLD_SIZE={os.environ.get('WORLD_SIZE')}",
                    fix=f"start every process (torchrun --nproc_per_node N starts them together), or "
                    f"`{UNSET}` to run as one process; {TIMEOUT_VAR} sets the wait in seconds",
                ) from None
            time.sleep(0.5)


def join(device):
    """This process's :class:`Shard` and device; joins the torchrun job when there is one. A CUDA
    ``device`` becomes this process's own GPU, ``cuda:LOCAL_RANK``. The wait for the other processes is
    bounded (:func:`join_timeout`): a job whose other processes never come is an error saying so."""
    if check_environment() <= 1:
        return Shard(), device
    import torch  # lazy: PyTorch is heavy; configs load without it
    import torch.distributed as dist  # lazy, as above

    if device.type == "cuda":  # one GPU per process
        device = torch.device("cuda", _int_var("LOCAL_RANK", "0"))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        seconds = join_timeout()
        if _int_var("RANK", "0") != 0:  # a plain wait first: c10d's own timeout prints pages of C++ frames
            _wait_for_master(os.environ["MASTER_ADDR"], _int_var("MASTER_PORT", "0"), seconds)
        try:  # nccl's gather: device set above
            dist.init_process_group(
                "nccl" if device.type == "cuda" else "gloo", timeout=datetime.timedelta(seconds=seconds)
            )
        except (RuntimeError, TimeoutError, OSError, ValueError) as exc:  # DistStoreError is a RuntimeError
            env = ", ".join(f"{v}={os.environ.get(v)}" for v in ("WORLD_SIZE", *RENDEZVOUS))
            raise InputError(
                f"could not join the distributed job ({env}) within {seconds:g} s: "
                f"{str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__} (are the "
                f"other {_int_var('WORLD_SIZE', '1') - 1} process(es) running and can they reach "
                f"MASTER_ADDR:MASTER_PORT?)",
                fix=f"start every process (torchrun --nproc_per_node N starts them together), or "
                f"`{UNSET}` to run as one process; {TIMEOUT_VAR} sets the wait in seconds",
            ) from exc
    rank = dist.get_rank()
    log.info("joined the distributed job: rank %d of %d (%s)", rank, dist.get_world_size(), dist.get_backend())
    if rank != 0:  # one voice: the other processes report only warnings and errors
        for h in get_logger().handlers:
            h.setLevel(logging.WARNING)
    return Shard(rank, dist.get_world_size()), device


__all__ = ["Shard", "check_environment", "join", "join_timeout", "world_size"]
