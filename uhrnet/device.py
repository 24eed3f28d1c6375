"""The one place that turns a ``--device`` name into a ``torch.device``."""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
import torch

from uhrnet.errors import ConfigError

__all__ = ["select_device", "synchronize", "keep_freed_memory"]


def select_device(name: str = "auto", local_rank: int | None = None) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is a :class:`ConfigError`.

    ``local_rank`` picks the GPU of this process under torchrun.
    """
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError("--device cuda requested but no CUDA device is available")
        if local_rank is not None and name == "cuda":
            return torch.device("cuda", local_rank)
    return torch.device(name)


def synchronize(device: torch.device | str) -> None:
    """Wait for queued GPU work (for honest timings); a no-op on CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc's mallopt parameters


def keep_freed_memory() -> bool:
    """Linux (glibc): keep the memory that large tensors free inside the process instead of giving it back to
    the system, for CPU training. glibc serves every allocation over its mmap threshold (32 MB at most) with
    a fresh mapping and unmaps it on free, so each training step page-faults its large feature maps in again:
    a U-Net base 16 at 448 x 640, batch 2, has 37 MB maps, and half its CPU time went to the kernel
    (``munmap`` and zeroed pages). ``mallopt(M_MMAP_MAX, 0)`` takes everything from the heap and a high
    ``M_TRIM_THRESHOLD`` keeps it there: the same numbers, the process holds its peak heap. Process-wide and
    for good; returns whether it was applied (False on other C libraries)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2 ** 31 - 1))
    except (OSError, AttributeError):
        return False
