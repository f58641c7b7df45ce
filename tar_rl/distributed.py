"""Training across processes with ``torch.distributed``: what a rank needs to know and to exchange.

A job started by ``torchrun --nproc_per_node=N -m tar_rl train ...`` has ``WORLD_SIZE``, ``RANK``
and ``LOCAL_RANK`` in its environment; :func:`init` opens the process group (gloo on CPU, NCCL
on CUDA) and returns a :class:`Dist`. Without those variables, or with ``WORLD_SIZE=1``, it returns
the single-process ``Dist`` whose collectives are no-ops, so the training loop has one code path.

TAR needs no communication of its own: its weights are computed within each segment, and a rank's
segments are whole segments, so each rank weights its own share of the batch exactly as a single
process would weight the same segments. DistributedDataParallel averages the gradients over ranks;
with the same number of segments per rank that is the gradient of the mean over all segments.
The one weighting with a state learnt across batches, ``dro_time``, sums its batch statistics over
the ranks inside ``TARLoss`` on each training step, so that every rank holds the same state.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as torch_dist

__all__ = ["Dist", "close_group", "data_parallel", "init", "shutdown"]

# Long enough for rank 0 to collect a demonstration dataset while the others wait at a barrier.
# A rank that dies does not leave the others waiting this long: torchrun stops the whole group.
TIMEOUT = datetime.timedelta(hours=2)


def data_parallel(module: torch.nn.Module, device_ids: list[int] | None = None) -> torch.nn.Module:
    """``DistributedDataParallel(module)`` without buffer syncing at each forward.

    Every rank holds the same buffers (observation statistics, the TAR schedule step), updated
    identically, so there is nothing to broadcast. torch 2.13 names the switch
    ``forward_sync_buffers``; earlier releases ``broadcast_buffers``.
    """
    import inspect

    from torch.nn.parallel import DistributedDataParallel

    params = inspect.signature(DistributedDataParallel.__init__).parameters
    switch = "forward_sync_buffers" if "forward_sync_buffers" in params else "broadcast_buffers"
    return DistributedDataParallel(module, device_ids=device_ids, **{switch: False})


@dataclass(frozen=True)
class Dist:
    """This process's place in the job.

    Attributes:
        rank: global rank (0 is the main process: it alone writes files and prints).
        world: number of processes.
        local_rank: rank on this machine (selects the CUDA device).
    """

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.active:
            torch_dist.barrier()

    def all_gather_object(self, obj: Any) -> list[Any]:
        """Every rank's ``obj``, in rank order, on every rank."""
        if not self.active:
            return [obj]
        out: list[Any] = [None] * self.world
        torch_dist.all_gather_object(out, obj)
        return out

    def all_sum(self, values: list[float]) -> list[float]:
        """Element-wise sums over the ranks (float64)."""
        if not self.active:
            return list(values)
        t = torch.tensor(values, dtype=torch.float64)
        if torch_dist.get_backend() == "nccl":
            t = t.cuda()
        torch_dist.all_reduce(t)
        return t.cpu().tolist()

    def all_true(self, flag: bool) -> bool:
        """True when ``flag`` is true on every rank."""
        if not self.active:
            return bool(flag)
        return self.all_sum([0.0 if flag else 1.0])[0] == 0.0


def init(device_type: str = "cpu") -> Dist:
    """Open the process group described by torchrun's environment (or return the single-process ``Dist``).

    Args:
        device_type: ``cpu`` (gloo) or ``cuda`` (NCCL; each rank uses ``cuda:LOCAL_RANK``).
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not torch_dist.is_initialized():
        backend = "nccl" if device_type == "cuda" else "gloo"
        if device_type == "cuda":
            torch.cuda.set_device(local_rank)
        torch_dist.init_process_group(backend=backend, timeout=TIMEOUT)
    return Dist(rank=rank, world=world, local_rank=local_rank)


def close_group() -> None:
    """On the normal path: a barrier, then ``destroy_process_group()``.

    gloo's worker threads release completed collectives (DDP's gradient all-reduces) after they
    complete, and that release may need the GIL; if the process group is destroyed (by dropping the
    last DDP model, which holds it) while the main thread holds the GIL, the two wait for each other
    forever. Drop the DDP model first, then call this: the barrier waits without the GIL, so those
    releases finish first. Not on an error path: a barrier there would wait for ranks that are
    still inside a collective the failing rank never joined.
    """
    if torch_dist.is_initialized():
        torch_dist.barrier()
        torch_dist.destroy_process_group()


def shutdown(d: Dist) -> None:
    """Destroy the process group opened by :func:`init` (no-op for a single process), without a
    barrier: it also runs when a rank fails (see :func:`close_group` for the normal path)."""
    if d.active and torch_dist.is_initialized():
        torch_dist.destroy_process_group()
