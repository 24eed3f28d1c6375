"""What the stages of every workflow share (``uhrnet sim2real``, ``pipelines/few_scans.py``, ``pipelines/scaling.py``)
and only workflows need: running a stage with its printed output in a log, counting a figshare dataset's
samples, reading an experiment's YAML/JSON file. What a run folder holds and the resume checks on it
(history, finished epochs, ``fresh``, the default meshes) are :mod:`uhrnet.run_folder`'s.
"""

from __future__ import annotations

import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Callable

from fppsim.errors import DatasetError, FppsimError
from fppsim.dataio.encoding import load_npy
from fppsim.dataio.formats import FIGSHARE_PAIRS
from uhrnet.errors import Sim2RealError, UhrnetError

__all__ = ["run_stage", "dataset_count", "read_config_file"]


def dataset_count(folder: str | Path) -> int:
    """Samples of the figshare-format dataset in ``folder`` (its ``Z.npy``); 0 when there is none (or it
    cannot be read)."""
    z = Path(folder) / FIGSHARE_PAIRS[0][1]
    if not z.is_file():
        return 0
    try:
        arr = load_npy(z)
    except DatasetError:  # damaged, empty, an .npz under the name: no dataset here (generate then says why)
        return 0
    return int(arr.shape[0]) if arr.ndim else 0


def run_stage(name: str, fn: Callable[[], object], log: Path, header: str) -> float:
    """Run ``fn()`` with its printed output appended to ``log``; seconds taken. A failure is raised as
    :class:`Sim2RealError` naming the stage, its first line and the log."""
    t0 = time.perf_counter()
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write(header.rstrip("\n") + "\n")
        fh.flush()
        try:
            with redirect_stdout(fh), redirect_stderr(fh):
                fn()
        except (UhrnetError, FppsimError, ValueError, OSError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            fh.write(f"error: {first}\n")
            raise Sim2RealError(f"{name} failed: {first} (log {log})") from exc
    return time.perf_counter() - t0


def read_config_file(path: str | Path, what: str, error: type[Exception] = Sim2RealError):
    """The parsed YAML/JSON document of an experiment's file (an ablation, an arms file); ``error`` names,
    in one line, ``what`` is missing, a folder or other non-file given for it, or the file that cannot be
    read or is not (UTF-8 text) YAML/JSON."""
    import yaml  # PyYAML: only experiments read such files

    p = Path(path)
    if p.is_dir():
        raise error(f"{p}: is a folder; give the YAML/JSON file")
    if not p.exists():
        raise error(f"{what} not found: {p}")
    if not p.is_file():
        raise error(f"{p}: not a regular file; give the YAML/JSON file")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{p}: not a text YAML/JSON file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc})") from None
    try:
        return yaml.safe_load(text)
    except (yaml.YAMLError, ValueError, RecursionError) as exc:  # a value YAML cannot build, e.g. 2020-13-45
        raise error(f"{p}: not valid YAML/JSON ({(str(exc).splitlines() or [type(exc).__name__])[0]})") from None
