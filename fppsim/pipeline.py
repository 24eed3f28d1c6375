"""Overlapping output with rendering: a background writer thread and figshare rows streamed from memory.

:class:`BackgroundWriter` runs sample writes (PNG encoding, deflate, file IO: all release the GIL) on
one thread while the caller synthesises the next sample. :class:`FigshareRows` fills ``f1_80.npy`` and
``Z.npy`` from the in-memory arrays as samples finish, so a figshare run need not read every native
sample back at the end; the rows are computed by the very functions :func:`fppsim.formats.export_figshare`
uses (:func:`fppsim.formats.figshare_rows`), so the files are identical.
"""

from __future__ import annotations

import os
import queue
import threading
from pathlib import Path

import numpy as np

from ._fs import tmp_path
from .errors import DatasetError
from .formats import figshare_rows  # noqa: F401  (re-exported: the rows export_figshare writes)

__all__ = ["BackgroundWriter", "FigshareRows", "figshare_rows"]


class BackgroundWriter:
    """Run ``fn(*args)`` jobs in order on one background thread.

    At most ``depth`` jobs wait behind the running one (``submit`` blocks beyond that, which bounds the
    memory held by pending samples). The first error a job raises is re-raised by the next
    :meth:`submit`, :meth:`flush` or :meth:`close`; later jobs are skipped until then.
    """

    def __init__(self, depth: int = 1):
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="fppsim-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    fn, args = job
                    fn(*args)
            except BaseException as exc:  # handed to the caller's thread
                self._error = exc
            finally:
                self._queue.task_done()

    def _reraise(self) -> None:
        if self._error is not None:
            exc, self._error = self._error, None
            raise exc

    def submit(self, fn, *args) -> None:
        self._reraise()
        if not self._thread.is_alive():
            raise RuntimeError("background writer is closed")
        self._queue.put((fn, args))

    def flush(self) -> None:
        """Wait until every submitted job has finished; re-raise a job's error."""
        self._queue.join()
        self._reraise()

    def close(self) -> None:
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._reraise()


class FigshareRows:
    """``f1_80.npy`` + ``Z.npy`` (N, H, W, 1) float32 filled row by row, published atomically.

    ``put(k, fringe, label)`` writes row ``k``; :meth:`commit` renames the temporary files into place
    once every row is there; :meth:`discard` removes them.
    """

    def __init__(self, out: str | os.PathLike, n: int, height: int, width: int):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.shape = (int(n), int(height), int(width), 1)
        self._tmp = {name: tmp_path(self.out / name) for name in ("f1_80.npy", "Z.npy")}
        self._maps = {}
        try:
            for name, p in self._tmp.items():
                self._maps[name] = np.lib.format.open_memmap(p, mode="w+", dtype=np.float32, shape=self.shape)
                # reserve the blocks now: a full disk then fails here with ENOSPC, where writes into a
                # sparse memmap would kill the process with SIGBUS
                with open(p, "r+b") as fh:
                    os.posix_fallocate(fh.fileno(), 0, os.path.getsize(p))
        except OSError as exc:
            self.discard()
            raise DatasetError(f"cannot write the figshare arrays in {self.out}: {exc.strerror or exc}") from None
        self._filled = np.zeros(n, dtype=bool)

    def put(self, k: int, fringe: np.ndarray, label: np.ndarray) -> None:
        if fringe.shape != self.shape[1:3] or label.shape != self.shape[1:3]:
            raise ValueError(f"figshare row {k}: image size {fringe.shape} differs from {self.shape[1:3]}")
        self._maps["f1_80.npy"][k, :, :, 0] = fringe
        self._maps["Z.npy"][k, :, :, 0] = label
        self._filled[k] = True

    @property
    def complete(self) -> bool:
        return bool(self._filled.all())

    def commit(self) -> int:
        if not self.complete:
            raise ValueError(f"figshare arrays: {int((~self._filled).sum())} of {self.shape[0]} rows missing")
        for m in self._maps.values():
            m.flush()
        self._maps.clear()
        for name, p in self._tmp.items():
            os.replace(p, self.out / name)
        return self.shape[0]

    def discard(self) -> None:
        self._maps.clear()
        for p in self._tmp.values():
            Path(p).unlink(missing_ok=True)
