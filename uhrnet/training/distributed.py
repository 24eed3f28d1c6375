"""Distributed training helpers: process layout under torchrun and sums reduced over processes."""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist

__all__ = ["DistInfo", "init_distributed", "all_reduce", "MetricSums"]


@dataclass
class DistInfo:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device_name: str) -> DistInfo:
    """torchrun sets WORLD_SIZE/RANK/LOCAL_RANK; without them this is a single process."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = device_name != "cpu" and torch.cuda.is_available()
    if use_cuda:
        torch.cuda.set_device(local)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo", timeout=timedelta(minutes=30))
    return DistInfo(rank, world, local)


def all_reduce(values: torch.Tensor, info: DistInfo, device, op=None) -> torch.Tensor:
    if not info.enabled:
        return values
    t = values.to(device)
    dist.all_reduce(t, op=op or dist.ReduceOp.SUM)
    return t.cpu()


class MetricSums:
    """Sums and counts of per-image values (NaN skipped), reducible across ranks."""

    def __init__(self, keys):
        self.keys = list(keys)
        self.v = torch.zeros(2 * len(self.keys), dtype=torch.float64)

    def add(self, key: str, values: torch.Tensor) -> None:
        values = values.double().flatten()
        ok = torch.isfinite(values)
        i = self.keys.index(key)
        self.v[2 * i] += values[ok].sum()
        self.v[2 * i + 1] += ok.sum()

    def reduce(self, info: DistInfo, device) -> dict:
        v = all_reduce(self.v.clone(), info, device)
        return {k: (float(v[2 * i] / v[2 * i + 1]) if v[2 * i + 1] > 0 else float("nan"))
                for i, k in enumerate(self.keys)}
