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

TIMEOUT_VAR = "MATCHPLANT_JOIN_TIMEOUT"  # seconds a process waits for the others to join
# torchrun starts the processes together: they meet within seconds (their imports differ by a few), so half a
# minute without them is an error (a variable left in the shell, a process that died), not a reason to wait
DEFAULT_TIMEOUT_S = 30.0
# once joined, one process may wait for another in a collective while that one validates or reads a big
# image: that wait is bounded apart, and longer
COLLECTIVE_TIMEOUT_S = 1800.0
RENDEZVOUS = ("RANK", "MASTER_ADDR", "MASTER_PORT")  # what torchrun sets beside WORLD_SIZE
UNSET = "unset WORLD_SIZE RANK LOCAL_RANK LOCAL_WORLD_SIZE MASTER_ADDR MASTER_PORT"
FIX = f"run as one process with `{UNSET}` first, or start the command with `torchrun --nproc_per_node N ...`, \
which sets them all consistently"


@dataclass
class Shard:
    """This process's place in the job: its rank among ``world`` processes."""

    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        """Whether this is the main process (rank 0), the one that validates and writes checkpoints."""
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
        """Wait until every process of the job reaches this point (nothing to wait for in a single process)."""
        if self.world > 1:
            import torch.distributed as dist  # lazy: PyTorch is heavy; configs load without it

            dist.barrier()

    def leave(self) -> None:
        """Leave the job at the end of a run that succeeded: every process meets, then the process group is
        taken down. A process that exits without it leaves gloo's worker threads to the interpreter's
        teardown, which can abort it (SIGABRT, "terminate called without an active exception") after its
        work is done, so that torchrun reports a failed job. Not called on an error: the others may be
        inside a collective and would wait for this one until the collective timeout."""
        if self.world > 1:
            import torch.distributed as dist  # lazy: PyTorch is heavy; configs load without it

            if dist.is_initialized():
                dist.barrier()
                dist.destroy_process_group()


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
    """Seconds to wait for the other processes (``MATCHPLANT_JOIN_TIMEOUT``, default 30)."""
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


def _env(name: str) -> str | None:
    value = os.environ.get(name, "").strip()
    return value or None


def check_environment() -> int:
    """The torchrun variables, before any wait, checked against each other: a ``WORLD_SIZE`` > 1 left in the
    shell without the rest of a rendezvous (``RANK``, ``MASTER_ADDR``, ``MASTER_PORT``), a ``RANK`` or
    ``LOCAL_RANK`` outside the job, a ``LOCAL_WORLD_SIZE`` larger than the job, a port that is no port, a value
    that is not a whole number: each is an error naming the variables, not a crash or a hang. Returns the
    world size."""
    world = world_size()
    given = {v: _int_var(v, "0") for v in ("RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_PORT") if _env(v)}
    rank, local = given.get("RANK", 0), given.get("LOCAL_RANK", 0)

    def bad(problem: str) -> InputError:
        env = ", ".join(f"{v}={os.environ[v].strip()}" for v in ("WORLD_SIZE", *given) if _env(v))
        return InputError(f"inconsistent distributed settings in the environment ({env}): {problem}", fix=FIX)

    if world < 1:
        raise bad(f"WORLD_SIZE={world} is not a number of processes (1 or more)")
    if world == 1:
        if rank != 0 or local != 0:
            raise bad("a job of one process (WORLD_SIZE 1 or unset) has only RANK 0 and LOCAL_RANK 0")
        return world
    missing = [v for v in RENDEZVOUS if not _env(v)]
    if missing:
        raise InputError(
            f"WORLD_SIZE={world} is set in the environment but {', '.join(missing)} "
            f"{'is' if len(missing) == 1 else 'are'} not: this is not a torchrun job (a variable left "
            "in the shell from an earlier job?)",
            fix=FIX,
        )
    local_world = given.get("LOCAL_WORLD_SIZE", world)
    if not 0 <= rank < world:
        raise bad(f"RANK={rank} is outside 0..{world - 1} (WORLD_SIZE={world})")
    if not 1 <= local_world <= world:
        raise bad(f"LOCAL_WORLD_SIZE={local_world} must be 1..WORLD_SIZE={world}")
    if not 0 <= local < local_world or local > rank:
        raise bad(f"LOCAL_RANK={local} must be 0..{local_world - 1} (LOCAL_WORLD_SIZE) and at most RANK={rank}")
    if not 0 < given["MASTER_PORT"] < 2**16:
        raise bad(f"MASTER_PORT={given['MASTER_PORT']} is not a port (1..65535)")
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


def _meet(seconds: float):
    """The job's store (torch's env:// rendezvous: rank 0's, or torchrun's agent's) once every process has
    arrived; a TimeoutError after ``seconds`` saying how many did. Counting here bounds the wait for the
    others apart from the process group's own timeout, which also bounds every later collective."""
    import torch.distributed as dist  # lazy: PyTorch is heavy; configs load without it

    world = world_size()
    store, _, _ = next(dist.rendezvous("env://", timeout=datetime.timedelta(seconds=seconds)))
    key = f"matchplant/joined/{os.environ.get('TORCHELASTIC_RESTART_COUNT', '0')}"
    arrived = store.add(key, 1)
    end = time.monotonic() + seconds
    while arrived < world:
        if time.monotonic() >= end:
            raise TimeoutError(f"{arrived} of WORLD_SIZE={world} process(es) joined")
        time.sleep(0.1)
        arrived = store.add(key, 0)
    return store


def join(device):
    """This process's :class:`Shard` and device; joins the torchrun job when there is one. A CUDA
    ``device`` becomes this process's own GPU, ``cuda:LOCAL_RANK``. The wait for the other processes is
    bounded (:func:`join_timeout`): a job whose other processes never come is an error saying so."""
    if check_environment() <= 1:
        return Shard(), device
    import torch  # lazy: PyTorch is heavy; configs load without it
    import torch.distributed as dist  # lazy, as above

    if device.type == "cuda":  # one GPU per process
        local, gpus = _int_var("LOCAL_RANK", "0"), torch.cuda.device_count()
        if local >= gpus:
            raise InputError(
                f"LOCAL_RANK={local} but this machine has {gpus} GPU(s) (cuda:0..cuda:{gpus - 1})",
                fix=f"start at most {gpus} process(es) per machine (torchrun --nproc_per_node {gpus}), or {UNSET}",
            )
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        seconds = join_timeout()
        end = time.monotonic() + seconds  # one bound for the whole join
        if _int_var("RANK", "0") != 0:  # a plain wait first: c10d's own timeout prints pages of C++ frames
            _wait_for_master(os.environ["MASTER_ADDR"], _int_var("MASTER_PORT", "0"), seconds)
        try:  # nccl's gather: device set above
            store = _meet(max(end - time.monotonic(), 1.0))
            dist.init_process_group(
                "nccl" if device.type == "cuda" else "gloo",
                store=store,
                rank=_int_var("RANK", "0"),
                world_size=world_size(),
                timeout=datetime.timedelta(seconds=max(seconds, COLLECTIVE_TIMEOUT_S)),
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
