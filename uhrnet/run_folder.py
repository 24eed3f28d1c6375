"""A run folder and its protocol, the one home of both: what a training run (``uhrnet train``), an
adaptation (``uhrnet adapt``) and imported weights (``uhrnet import-weights``) leave in their folder, and how
every command, workflow and pipeline reads it back.

- **File names** (use the constants, never the strings): :data:`LAST_PT` (written atomically after every
  epoch), :data:`BEST_PT` (a copy of last when the epoch is the best so far), :data:`HISTORY_CSV` and
  :data:`HISTORY_PNG` (one row per epoch), :data:`CONFIG_JSON` (the resolved options), :data:`IMAGES_JSON`
  (an adaptation's per-image record); :data:`CHECKPOINTS`: the checkpoint a RUN folder stands for, in order
  of preference (:func:`uhrnet.checkpoint.checkpoint_file`, which also writes them: ``save_epoch``).
- **History**: :func:`write_history` and :func:`read_history`.
- **Resume checks**: :func:`run_epochs` / :func:`run_done` (what a run has finished), :func:`fresh` (a result
  newer than what it was made from).
- **Ownership**: the names a run writes are claimed in the folder's ownership record first
  (:mod:`fppsim.owned`, :func:`claim_run_folder`: a file another tool or a person put there is never replaced,
  ``--overwrite`` or not), a folder holding a run is never replaced without ``--overwrite``
  (:func:`check_run_folder`), and a run never writes into the folder of the checkpoint it starts from, nor
  ``uhrnet predict`` into the folder of the checkpoint it reads (:func:`refuse_own_source`).
- **Inputs of a workflow**: :func:`default_meshes`.

No torch here: pipelines read a run's history without it.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
from pathlib import Path
from typing import Callable

from fppsim.dataio.encoding import json_default
from fppsim.files import atomic_write_text, json_text
from uhrnet.plots import plot_history  # matplotlib itself loads only when a history is drawn (plots.pyplot)
from fppsim.geometry.rig import data_path
from fppsim.owned import ForeignFiles, claim, owners, same_folder
from uhrnet import __version__
from uhrnet.errors import ConfigError

__all__ = ["LAST_PT", "BEST_PT", "HISTORY_CSV", "HISTORY_PNG", "CONFIG_JSON", "IMAGES_JSON", "CHECKPOINTS", "RUN_FILES",
           "TRAINED_FILES", "TRAIN_TOOL", "IMPORT_TOOL", "HISTORY_COLUMNS", "write_history", "read_history", "run_epochs",
           "run_done", "fresh", "default_meshes", "write_run_config", "check_run_folder", "claim_run_folder",
           "refuse_own_source", "package_version"]

LAST_PT = "last.pt"  # the latest epoch's checkpoint (a resume starts from it)
BEST_PT = "best.pt"  # the best epoch's checkpoint (predict / evaluate prefer it)
HISTORY_CSV = "history.csv"
HISTORY_PNG = "history.png"
CONFIG_JSON = "config.json"
IMAGES_JSON = "images.json"  # an adaptation's per-image record
CHECKPOINTS = (BEST_PT, LAST_PT)  # the checkpoint a RUN folder stands for: the first that exists

TRAIN_TOOL = "uhrnet train"
IMPORT_TOOL = "uhrnet import-weights"
RUN_FILES = (BEST_PT, LAST_PT, HISTORY_CSV, HISTORY_PNG, CONFIG_JSON)  # what a training run writes
TRAINED_FILES = (BEST_PT, LAST_PT, HISTORY_CSV)  # a folder holding any of them holds a trained run

HISTORY_COLUMNS = ("epoch", "train_loss", "train_rmse_mm", "train_ssim", "val_rmse_mm", "val_ssim",
                   "val_rmse_mm_real", "val_ssim_real", "val_rmse_mm_synthetic", "val_ssim_synthetic",
                   "val_phase_ratio", "val_phase_rad", "val_phase_heldout_ratio", "val_phase_heldout_rad", "lr",
                   "seconds", "best")


# ---------------------------------------------------------------------------------------------- history
def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def write_history(rows: list[dict], out: Path, columns: tuple[str, ...] = HISTORY_COLUMNS, extra: bool = False,
                  plot: bool = True) -> None:
    """``out/history.csv``, one row per epoch in ``columns`` order (floats as ``%.6g``, missing / NaN empty),
    written atomically; ``extra``: columns the rows hold beyond ``columns`` follow, sorted (an adaptation
    resumed from an older version keeps its old terms); ``plot``: also ``history.png`` (training curves)."""
    names = list(columns) + (sorted({k for r in rows for k in r} - set(columns)) if extra else [])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow({k: _fmt(row.get(k)) for k in names})
    atomic_write_text(out / HISTORY_CSV, buf.getvalue())
    if not plot:
        return
    try:
        plot_history(rows, out / HISTORY_PNG)
    except Exception as exc:  # a plotting problem must not stop training
        print(f"warning: could not draw {HISTORY_PNG} ({exc})", file=sys.stderr)


def _cell(value: str | None):
    """A history cell: a number as float, an empty cell None, anything else as written."""
    if value in ("", None):
        return None
    try:
        return float(value)
    except ValueError:
        return value


def read_history(run: str | Path) -> list[dict]:
    """The rows of the ``history.csv`` in folder ``run`` (numbers as floats, empty cells None); [] without one
    (or when it cannot be read)."""
    try:
        with open(Path(run) / HISTORY_CSV, newline="") as fh:
            return [{k: _cell(v) for k, v in r.items()} for r in csv.DictReader(fh)]
    except OSError:
        return []


# ---------------------------------------------------------------------------------------------- resume checks
def run_epochs(run: str | Path) -> int:
    """Epochs the training run in folder ``run`` has finished (``last.pt`` and its history); 0: none."""
    rows = read_history(run) if (Path(run) / LAST_PT).is_file() else []
    return int(rows[-1]["epoch"]) if rows else 0


def run_done(run: str | Path, epochs: int) -> bool:
    """Whether the training run in folder ``run`` has finished ``epochs`` epochs (``last.pt`` at them)."""
    done = run_epochs(run)
    return done > 0 and done >= epochs


def fresh(result: Path, source: Path) -> bool:
    """Whether the file ``result`` exists and is not older than ``source`` (e.g. an evaluation of a checkpoint)."""
    return result.is_file() and result.stat().st_mtime >= source.stat().st_mtime


def default_meshes(shared: str | Path | None = None) -> list[str]:
    """The meshes a workflow renders when none are given: ``shared/meshes`` when that folder exists (the
    third-party meshes beside a checkout, ``../shared``), then the meshes fppsim ships."""
    found = [Path(shared) / "meshes"] if shared is not None else []
    return [str(p) for p in found if p.is_dir()] + [str(data_path("meshes"))]


# ---------------------------------------------------------------------------------------------- writing a run
def write_run_config(out: Path, config: dict) -> None:
    """``out/config.json``: the resolved options and what they were resolved to."""
    atomic_write_text(out / CONFIG_JSON, json_text(config, indent=2, default=json_default))


def check_run_folder(out: Path, resume, overwrite: bool) -> str:
    """How to treat ``out``: ``"resume"``, ``"fresh"`` (a ``--resume`` of a run killed before its first
    checkpoint: nothing was trained, so it starts afresh) or ``"new"``; a folder that already holds a
    trained run is refused (:class:`ConfigError`) unless ``resume`` or ``overwrite`` (a ``config.json``
    alone, left by a run that failed before its first epoch, is no run)."""
    if resume == "auto" and not any((out / n).exists() for n in TRAINED_FILES):
        return "fresh"
    if resume:
        return "resume"
    if not overwrite:
        existing = [n for n in TRAINED_FILES if (out / n).exists()]
        if existing:
            raise ConfigError(f"{out} already holds a run ({', '.join(existing)}): pass --resume to continue "
                              "it, --overwrite to replace it, or choose another --out")
    return "new"


def claim_run_folder(out: Path, tool: str, names, kind_of: Callable[[Path], str | None],
                     kind: str | None = None) -> None:
    """Claim ``names`` in ``out`` for ``tool`` (:func:`fppsim.owned.claim`); a folder written before the
    ownership record is recognised by its ``last.pt`` / ``best.pt``: a uhrnet checkpoint whose kind
    (``kind_of(path)``, :func:`uhrnet.checkpoint.checkpoint_kind`: ``"adapt"`` an adaptation, ``"import"``
    imported weights, None a training run; raising when the file is no checkpoint) is ``kind``."""

    def legacy():
        for name in (LAST_PT, BEST_PT):
            if (out / name).is_file():
                try:
                    made = kind_of(out / name)
                except Exception:  # not a checkpoint at all: nothing here is provably ours
                    return ()
                return names if made == kind else ()
        return ()

    claim(out, tool, names, legacy=legacy)


def refuse_own_source(out: Path, source, flag: str,
                      why: str = "writing there would replace the weights this run starts from",
                      runs_only: bool = False) -> None:
    """:class:`ConfigError` when the checkpoint ``source`` (a file or a run folder) lies in ``out``: the
    run would replace the weights it starts from (``why``: what else writing there would do). ``runs_only``:
    only when that folder is a run's (``source`` a folder, or a file its ownership record lists), not for a
    loose checkpoint file in a folder of the user's."""
    src = Path(source)
    folder = src if src.is_dir() else src.parent
    if not same_folder(folder, out):
        return
    if runs_only and not src.is_dir():
        try:
            recorded = src.name in (owners(folder) or {})
        except ForeignFiles:  # an unreadable record: a run's folder all the same
            recorded = True
        if not recorded:
            return
    raise ConfigError(f"--out {out} is the folder of {flag} {source}: {why}; choose another --out")


def package_version() -> str:
    return __version__
