"""Single-process or multi-process (DDP) training plumbing.

`torchrun --nproc_per_node N -m ago_runtime.cli train ...` sets RANK / WORLD_SIZE / LOCAL_RANK /
MASTER_ADDR / MASTER_PORT; `setup()` reads them and starts a process group (gloo on CPU, nccl
on GPU). Without them it is a plain single process (rank 0 of 1). Only rank 0 writes files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    started_group: bool = False   # True when setup() created the process group (and cleanup ends it)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def pick_device(spec: str, local_rank: int = 0) -> torch.device:
    """"auto" -> cuda:<local_rank> when a GPU is there, else cpu; "cpu" / "cuda" / "cuda:N" as asked;
    anything else (e.g. "tpu9") is refused."""
    from .config_checks import check_device

    check_device(spec)
    if spec == "auto":
        spec = "cuda" if torch.cuda.is_available() else "cpu"
    if spec.startswith("cuda"):
        if not torch.cuda.is_available():
            from ago_runtime.errors import AgoInputError

            raise AgoInputError(None, "device cuda asked for but no GPU is available")
        return torch.device(f"cuda:{local_rank}") if spec == "cuda" else torch.device(spec)
    return torch.device("cpu")


def setup(device_spec: str = "auto") -> DistInfo:
    """Join the process group described by the torchrun environment, if any."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    device = pick_device(device_spec, local)
    if world <= 1:
        return DistInfo(0, 1, 0, device, False)
    started = False
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group(backend=backend, rank=rank, world_size=world)
        started = True
    return DistInfo(rank, world, local, device, started)


def cleanup(info: DistInfo) -> None:
    if info.started_group and dist.is_initialized():
        dist.destroy_process_group()


def barrier(info: DistInfo) -> None:
    if info.distributed and dist.is_initialized():
        dist.barrier()


def mean_over_ranks(value: float, info: DistInfo) -> float:
    """The mean of a python float over all ranks (the value itself when single-process)."""
    if not info.distributed:
        return float(value)
    t = torch.tensor([float(value)], dtype=torch.float64, device=info.device if info.device.type == "cuda" else "cpu")
    dist.all_reduce(t)
    return float(t.item()) / info.world_size
