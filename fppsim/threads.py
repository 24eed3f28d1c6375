"""One helper thread per process, for work that overlaps the main thread's (fork-safe).

numpy, scipy and the GL driver release the GIL in their heavy loops, so two threads share the work of
a sample on two cores. The helper is made anew in a forked worker process: threads do not survive a
fork, and an executor inherited from the parent would never run its jobs. Jobs run in a copy of the
caller's context (numpy's ``errstate`` lives there), and a job started from the helper itself runs in
place rather than waiting for a thread that is busy running its caller.
"""

from __future__ import annotations

import contextvars
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar


def machine_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` where there is none):
    the bound of every resource option that starts threads or processes (``--threads``, ``--workers``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def check_cores(value: int, flag: str, what: str, error) -> int:
    """``value`` if it is at most :func:`machine_cores`, else ``error`` (one line saying the cost)."""
    cores = machine_cores()
    if int(value) > cores:
        raise error(f"{flag} {value}: this machine has {cores} CPU core(s); more {what} than cores only slow the run "
                    f"down (each waits for a core: an epoch took 60x longer at 1000 threads on 2 cores); give at most "
                    f"{cores}")
    return value

T = TypeVar("T")

_PREFIX = "fppsim-helper"
_POOL: dict = {"pid": None, "pool": None}
_LOCK = threading.Lock()


def _forget_pool() -> None:
    global _LOCK
    _LOCK = threading.Lock()  # another thread may have held it at the fork
    _POOL.update(pid=None, pool=None)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def helper_pool() -> ThreadPoolExecutor:
    """This process's helper thread (one worker)."""
    with _LOCK:
        if _POOL["pid"] != os.getpid() or _POOL["pool"] is None:
            _POOL["pool"] = ThreadPoolExecutor(1, thread_name_prefix=_PREFIX)
            _POOL["pid"] = os.getpid()
        return _POOL["pool"]


def on_helper() -> bool:
    """Whether the calling thread is the helper."""
    return threading.current_thread().name.startswith(_PREFIX)


def beside(fn: Callable[..., T], *args) -> Future:
    """Start ``fn(*args)`` on the helper, in a copy of the caller's context; run it at once (and return
    its finished future) when the caller is the helper itself."""
    if on_helper():
        future: Future = Future()
        try:
            future.set_result(fn(*args))
        except BaseException as exc:  # handed over like the pool's own futures do
            future.set_exception(exc)
        return future
    return helper_pool().submit(contextvars.copy_context().run, fn, *args)


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
    if len(bands) <= 1 or on_helper():
        return [fn(b) for b in bands]
    futures = [beside(fn, b) for b in bands[1:]]
    try:
        first = fn(bands[0])
    finally:
        for f in futures:
            f.exception()  # waits
    return [first, *(f.result() for f in futures)]
