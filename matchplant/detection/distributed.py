"""Joining a torchrun job, shared by training (module 6) and detection (module 7).

``torchrun --nproc_per_node N <script> ...`` starts N copies of the script with ``RANK``, ``WORLD_SIZE`` and
``LOCAL_RANK`` set. Each process joins the job (one GPU each, ``cuda:LOCAL_RANK``, over nccl; on the CPU,
gloo); rank 0 is the one voice of the job: the other processes log only warnings and errors. Without
torchrun (``WORLD_SIZE`` unset or 1) nothing changes.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

from matchplant.core.runtime.log import get_logger


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


def world_size() -> int:
    """How many processes the torchrun job has (1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def join(device):
    """This process's :class:`Shard` and device; joins the torchrun job when there is one. A CUDA
    ``device`` becomes this process's own GPU, ``cuda:LOCAL_RANK``."""
    if world_size() <= 1:
        return Shard(), device
    import torch  # lazy: PyTorch is heavy; configs load without it
    import torch.distributed as dist  # lazy, as above

    if device.type == "cuda":  # one GPU per process
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")  # nccl's gather: device set above
    rank = dist.get_rank()
    if rank != 0:  # one voice: the other processes report only warnings and errors
        for h in get_logger().handlers:
            h.setLevel(logging.WARNING)
    return Shard(rank, dist.get_world_size()), device


__all__ = ["Shard", "join", "world_size"]
