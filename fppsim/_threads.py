"""One helper thread per process, for work that overlaps the main thread's (fork-safe).

numpy, scipy and the GL driver release the GIL in their heavy loops, so two threads share the work of
a sample on two cores. The helper is made anew in a forked worker process: threads do not survive a
fork, and an executor inherited from the parent would never run its jobs.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

_POOL: dict = {"pid": None, "pool": None}


def helper_pool() -> ThreadPoolExecutor:
    """This process's helper thread (one worker)."""
    if _POOL["pid"] != os.getpid():
        _POOL["pool"] = ThreadPoolExecutor(1, thread_name_prefix="fppsim-helper")
        _POOL["pid"] = os.getpid()
    return _POOL["pool"]


def row_bands(height: int, count: int, multiple: int = 16) -> list[slice]:
    """``count`` (at most) contiguous row slices covering ``range(height)``, their starts multiples of
    ``multiple`` (so that the element counts, and the tails that SIMD loops handle apart, of every band
    but the last are multiples of it); one band when ``height`` is too small to split."""
    count = max(1, int(count))
    step = -(-height // count)
    step = -(-step // multiple) * multiple
    starts = list(range(0, height, step)) if step < height else [0]
    return [slice(a, min(a + step, height)) for a in starts]


def map_bands(fn: Callable[[slice], T], bands: Sequence[slice]) -> list[T]:
    """``[fn(band) for band in bands]``: the first band on the calling thread, the others on the helper
    (one after another). Every job finishes before the first error (if any) is raised."""
    if len(bands) <= 1 or threading.current_thread().name.startswith("fppsim-helper"):
        return [fn(b) for b in bands]  # (on the helper itself: it would wait for itself)
    futures = [helper_pool().submit(fn, b) for b in bands[1:]]
    try:
        first = fn(bands[0])
    finally:
        for f in futures:
            f.exception()  # waits
    return [first, *(f.result() for f in futures)]
