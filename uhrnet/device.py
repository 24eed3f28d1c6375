"""The one place that turns a ``--device`` name into a ``torch.device``."""

from __future__ import annotations

import torch

from uhrnet.errors import ConfigError

__all__ = ["select_device", "synchronize"]


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
