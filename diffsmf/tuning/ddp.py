"""Data-parallel helpers on ``torch.distributed`` (gloo on CPU, NCCL on GPU).

The tuning loop shards each global mini-batch of trajectories across processes; every process
computes the gradient of its share of the *global* mean loss, and an all-reduce (sum) of the
gradients gives every process the exact single-process gradient (what
``DistributedDataParallel`` does, written out because a filter's parameters are few and not
all of them are used by every filter). Parameters are broadcast from rank 0 at the start so
every process starts from the same point.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import torch
import torch.distributed as dist
from torch import Tensor, nn

__all__ = [
    "all_reduce_grads",
    "all_reduce_sum",
    "broadcast_parameters",
    "init_from_env",
    "is_distributed",
    "rank",
    "shard",
    "world_size",
]


def is_distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


def rank() -> int:
    return dist.get_rank() if is_distributed() else 0


def world_size() -> int:
    return dist.get_world_size() if is_distributed() else 1


def init_from_env(backend: str | None = None) -> bool:
    """Initialise the process group when launched by ``torchrun`` (``WORLD_SIZE > 1``).

    Backend: ``backend`` or NCCL when CUDA is available, else gloo. Returns True if a group
    is (now) initialised.
    """
    if is_distributed():
        return True
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return False
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend=backend)
    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    return True


def shard(indices: Tensor) -> Tensor:
    """This process's share of ``indices`` (round robin: rank r takes r, r + W, ...)."""
    return indices[rank() :: world_size()]


def broadcast_parameters(module: nn.Module) -> None:
    """Copy rank 0's parameters and buffers to every process."""
    if not is_distributed():
        return
    with torch.no_grad():
        for t in list(module.parameters()) + list(module.buffers()):
            dist.broadcast(t.data, src=0)


def all_reduce_grads(params: Iterable[nn.Parameter]) -> None:
    """Sum the gradients of ``params`` over processes (missing grads count as zero)."""
    if not is_distributed():
        return
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        dist.all_reduce(p.grad, op=dist.ReduceOp.SUM)


def all_reduce_sum(t: Tensor) -> Tensor:
    """Sum of ``t`` over processes (returns ``t`` itself when not distributed)."""
    if not is_distributed():
        return t
    t = t.clone()
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t
