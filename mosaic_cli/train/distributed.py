"""One process or many: the few collective operations the training loop needs.

``torchrun --nproc_per_node=N mosaic train ...`` sets RANK / WORLD_SIZE / LOCAL_RANK; then
every process trains on its own batches, DistributedDataParallel averages the gradients
(gloo on CPU, nccl on GPU), and rank 0 alone writes files.  Run plainly, ``world == 1`` and
every operation here is a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as torch_dist

from mosaic_cli.device import resolve_device

# Rank 0 decodes every clip before the others may start: allow that to take long.
COLLECTIVE_TIMEOUT = timedelta(hours=3)


@dataclass
class Distributed:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    @classmethod
    def start(cls, device: str) -> Distributed:
        """Read the torchrun environment, pick the device, join the process group."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        chosen = resolve_device(device, gpu=local_rank)  # each process its own GPU
        if world > 1 and not torch_dist.is_initialized():
            backend = "nccl" if chosen.type == "cuda" else "gloo"
            if chosen.type == "cuda":
                torch.cuda.set_device(chosen)
            torch_dist.init_process_group(backend, timeout=COLLECTIVE_TIMEOUT)
        return cls(rank, world, local_rank, chosen)

    def barrier(self) -> None:
        if self.active:
            torch_dist.barrier()

    def any_flag(self, *flags: bool) -> list[bool]:
        """Each flag, true if it is true on any process (so all stop or save together)."""
        if not self.active:
            return [bool(f) for f in flags]
        t = torch.tensor([float(f) for f in flags], device=self.device)
        torch_dist.all_reduce(t, op=torch_dist.ReduceOp.MAX)
        return [bool(v) for v in t.tolist()]

    def mean(self, values: list[float]) -> list[float]:
        """Average of each value over the processes (for logging)."""
        if not self.active:
            return list(values)
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        torch_dist.all_reduce(t)
        return (t / self.world).tolist()

    def close(self) -> None:
        if self.active and torch_dist.is_initialized():
            torch_dist.destroy_process_group()
