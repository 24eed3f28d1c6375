"""Timing and memory of a model: wall-clock seconds of calls (GPU-synchronised) and peak memory.

The paper's "speed" is :func:`inference_seconds` (median seconds of one forward pass at batch 1, eval
mode, no gradient); :func:`time_call` times any call; :func:`peak_memory_bytes` measures the peak memory
of one call (CUDA allocator statistics, or on CPU the growth of the process's peak resident set read
from ``/proc/self/status``).
"""

from __future__ import annotations

import ctypes
import re
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import nn

from uhrnet.device import synchronize
from uhrnet.errors import InputError

__all__ = ["time_call", "model_device", "inference_seconds", "peak_memory_bytes"]


def time_call(fn: Callable[[], object], device: torch.device | str, warmup: int = 3, repeats: int = 10) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls of ``fn()`` after ``warmup`` untimed calls, each call
    bracketed by :func:`synchronize` so that GPU time is included."""
    if repeats < 1:
        raise InputError(f"repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return times


def model_device(model: nn.Module) -> torch.device:
    """Device of the model's first parameter (CPU for a model without parameters)."""
    return next((p.device for p in model.parameters()), torch.device("cpu"))


def inference_seconds(
    model: nn.Module,
    input_shape: Sequence[int] = (1, 1, 352, 640),
    device: torch.device | str | None = None,
    warmup: int = 3,
    repeats: int = 10,
    channels_last: bool = False,
) -> float:
    """Median seconds of one forward pass in eval mode without gradient (the paper's "speed").

    The model is moved to ``device`` (default: where it is), run on a random input of ``input_shape``
    (batch 1 in the paper) and put back into its previous train/eval mode afterwards.
    """
    device = torch.device(device) if device is not None else model_device(model)
    model = model.to(device)
    x = torch.randn(*input_shape, device=device)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            return statistics.median(time_call(lambda: model(x), device, warmup, repeats))
    finally:
        model.train(was_training)


def _proc_status_kib(field: str) -> int | None:
    try:
        match = re.search(rf"^{field}:\s+(\d+) kB", Path("/proc/self/status").read_text(), re.M)
    except OSError:
        return None
    return int(match.group(1)) if match else None


def _release_free_heap() -> None:
    """Return freed heap memory to the OS (glibc ``malloc_trim``) so RSS growth is not hidden by it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def peak_memory_bytes(fn: Callable[[], object], device: torch.device | str) -> int | None:
    """Peak memory while running ``fn()`` once, in bytes, or None where it cannot be measured.

    CUDA: ``torch.cuda.max_memory_allocated`` (all tensors alive at the peak, weights included).
    CPU (Linux): growth of the process's peak resident set size over its size before the call, the
    peak being reset first via ``/proc/self/clear_refs`` and freed heap returned to the OS with glibc's
    ``malloc_trim``; an approximation (allocator caching, other
    threads), None where ``/proc`` does not allow it.
    """
    device = torch.device(device)
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        synchronize(device)
        return int(torch.cuda.max_memory_allocated(device))
    if device.type != "cpu":
        fn()
        return None
    _release_free_heap()
    before = _proc_status_kib("VmRSS")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    except OSError:
        before = None
    fn()
    peak = _proc_status_kib("VmHWM")
    if before is None or peak is None:
        return None
    return max(0, peak - before) * 1024
