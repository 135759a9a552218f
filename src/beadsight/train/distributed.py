"""Single-process or data-parallel (DDP) training: the process group and the device.

Under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins one process group (NCCL on
GPUs, gloo on CPUs); otherwise :class:`Distributed` is a single process whose
collectives are no-ops, so the trainer has one code path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as torch_dist

from beadsight.config import ConfigError


def _env_int(name: str, default: int) -> int:
    return int(os.environ.get(name, str(default)))


@dataclass
class Distributed:
    """This process's place among the training processes (rank 0 writes files)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1
    owned: bool = False  # we initialised the process group (and destroy it)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def start(cls, device: torch.device) -> Distributed:
        """Join the process group ``torchrun`` describes (or the one already running)."""
        env_world = _env_int("WORLD_SIZE", 1)
        local_rank = _env_int("LOCAL_RANK", 0)
        local_world = _env_int("LOCAL_WORLD_SIZE", 1)
        if torch_dist.is_available() and torch_dist.is_initialized():
            return cls(torch_dist.get_rank(), torch_dist.get_world_size(), local_rank, local_world)
        if env_world <= 1:
            return cls()
        backend = "nccl" if device.type == "cuda" else "gloo"
        torch_dist.init_process_group(backend=backend)
        return cls(torch_dist.get_rank(), env_world, local_rank, local_world, owned=True)

    def barrier(self) -> None:
        if self.world > 1:
            torch_dist.barrier()

    def all_reduce(self, tensor: torch.Tensor) -> torch.Tensor:
        """Sum ``tensor`` over all processes, in place; returns it."""
        if self.world > 1:
            torch_dist.all_reduce(tensor)
        return tensor

    def any(self, flag: bool, device: torch.device) -> bool:
        """True on every process when ``flag`` is true on any (a collective: all call it)."""
        if self.world == 1:
            return flag
        value = torch.tensor(float(flag), device=device)
        return bool(self.all_reduce(value).item() > 0)

    def gather(self, obj: Any) -> list[Any]:
        """``obj`` of every process, by rank (a collective: all call it)."""
        if self.world == 1:
            return [obj]
        out: list[Any] = [None] * self.world
        torch_dist.all_gather_object(out, obj)
        return out

    def close(self) -> None:
        if self.owned and torch_dist.is_initialized():
            torch_dist.destroy_process_group()


def resolve_device(name: str, precision: str = "fp32") -> torch.device:
    """The device by :func:`beadsight.torch_device.resolve_device`; a plain ``cuda`` under
    torchrun is the process's ``LOCAL_RANK`` GPU."""
    from beadsight.torch_device import resolve_device as resolve_torch_device

    device = resolve_torch_device(name, "device")
    world = _env_int("WORLD_SIZE", 1)
    if device.type == "cuda":
        if device.index is None:
            device = torch.device(f"cuda:{_env_int('LOCAL_RANK', 0) if world > 1 else 0}")
        torch.cuda.set_device(device)
        return device
    if precision == "fp16":
        raise ConfigError(f"precision fp16 needs a CUDA device; use bf16 or fp32 on {device}")
    if device.type == "mps" and world > 1:
        raise ConfigError("device mps: one process only (distributed training needs cuda or cpu)")
    return device
