"""Data-parallel training under ``torchrun`` (gloo, CPU only): which process this is, the gradient all-reduce,
process 0's decisions broadcast to the others, and leaving the process group when training returns. Without
``torchrun`` every helper here is the single-process case unchanged.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import ParamSpec, TypeVar

import torch


@dataclass(frozen=True)
class Ranks:
    """Data-parallel training under ``torchrun`` (one process per core or machine).

    Each process takes its share (every ``world``-th scene) of the same shuffled global batch, gradients are
    averaged with an all-reduce before clipping and the Adam step, so every process holds the same weights;
    process 0 alone validates, writes checkpoints and the log, and tells the others when to stop. Without
    ``torchrun`` (``WORLD_SIZE`` unset or 1) this is the single-process loop unchanged.

    Attributes:
        rank: this process (0 = the one that writes).
        world: number of processes.
    """

    rank: int = 0
    world: int = 1

    @classmethod
    def from_env(cls) -> Ranks:
        """Join the process group torchrun describes in the environment (gloo: CPU only)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        import torch._dynamo  # noqa: F401  (see below)
        import torch.distributed as dist

        # torch._dynamo, imported lazily by the first optimizer, holds C++ references to any process group that
        # exists when it loads, so destroy_process_group cannot free that group's gloo threads, and about one
        # torchrun exit in six then aborts ("terminate called without an active exception"). Imported before
        # the group exists, it holds none.
        if not dist.is_initialized():
            dist.init_process_group("gloo")
        return cls(rank=dist.get_rank(), world=dist.get_world_size())

    @property
    def main(self) -> bool:
        return self.rank == 0

    def average_gradients(self, net: torch.nn.Module) -> None:
        if self.world == 1:
            return
        import torch.distributed as dist

        for param in net.parameters():
            if param.grad is None:
                param.grad = torch.zeros_like(param)
            dist.all_reduce(param.grad)
            param.grad /= self.world

    def agree(self, flag: bool) -> bool:
        """Process 0's ``flag`` on every process."""
        if self.world == 1:
            return flag
        import torch.distributed as dist

        value = torch.tensor([1 if flag else 0])
        dist.broadcast(value, src=0)
        return bool(value.item())


_Params = ParamSpec("_Params")
_Result = TypeVar("_Result")


def leaves_process_group(train: Callable[_Params, _Result]) -> Callable[_Params, _Result]:
    """``train``, leaving the torchrun process group it joined when it returns.

    Why: a gloo group alive at interpreter exit keeps its threads running into teardown. Not on an exception,
    where another process may still be inside a collective and the teardown could hang (torchtitan's rule too);
    torchrun ends the others then.
    """

    @functools.wraps(train)
    def wrapper(*args: _Params.args, **kwargs: _Params.kwargs) -> _Result:
        import torch.distributed as dist

        joined_here = not dist.is_initialized()
        result = train(*args, **kwargs)
        if joined_here and dist.is_initialized():
            dist.destroy_process_group()
        return result

    return wrapper
