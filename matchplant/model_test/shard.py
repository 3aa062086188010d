"""Detection sharded over processes: ``torchrun --nproc_per_node N 7_model_test/model_test.py ...``.

torchrun starts N copies of the script with ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` set. Each takes every
N-th image (one GPU each: ``cuda:LOCAL_RANK``; on the CPU, gloo), and the first gathers every image's
boxes and writes the one ``predictions.json``, in the order a single process would have written it.
Without torchrun (``WORLD_SIZE`` unset or 1) nothing changes.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

from matchplant.core.runtime.log import get_logger


@dataclass
class Shard:
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


def join(device):
    """This process's :class:`Shard` and device; joins the torchrun job when there is one."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Shard(), device
    import torch  # lazy: PyTorch is heavy; configs load without it
    import torch.distributed as dist  # lazy, as above

    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cuda":  # one GPU per process
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")  # nccl's gather: device set above
    rank = dist.get_rank()
    if rank != 0:  # one voice: the other processes report only warnings and errors
        for h in get_logger().handlers:
            h.setLevel(logging.WARNING)
    return Shard(rank, dist.get_world_size()), device
