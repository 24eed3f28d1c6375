"""What a training run leaves in its folder: ``history.csv``/``history.png``, ``last.pt``/``best.pt``
(written atomically; best is a copy of last), ``config.json``; and the run-folder protocol of every
uhrnet command that writes a run (``train``, ``adapt``): the names it writes are claimed in the folder's
ownership record first (:mod:`fppsim.owned`: a file another tool or a person put there is never
replaced, ``--overwrite`` or not), a folder holding a run is never replaced without ``--overwrite``, and
the run never writes into the folder of the checkpoint it starts from (:func:`refuse_own_source`).
"""

from __future__ import annotations

import csv
import io
import json
import math
import shutil
import sys
from pathlib import Path

from fppsim.dataio.encoding import json_default
from fppsim.files import atomic_path, atomic_write_text
from uhrnet.checkpoint import atomic_save
from uhrnet.errors import ConfigError

__all__ = ["RUN_FILES", "TRAINED_FILES", "TRAIN_TOOL", "IMPORT_TOOL", "HISTORY_COLUMNS", "write_history", "save_epoch",
           "write_run_config", "check_run_folder", "claim_run_folder", "refuse_own_source", "package_version"]

TRAIN_TOOL = "uhrnet train"
IMPORT_TOOL = "uhrnet import-weights"
RUN_FILES = ("best.pt", "last.pt", "history.csv", "history.png", "config.json")  # what a training run writes
TRAINED_FILES = ("best.pt", "last.pt", "history.csv")  # a folder holding any of them holds a trained run

HISTORY_COLUMNS = ("epoch", "train_loss", "train_rmse_mm", "train_ssim", "val_rmse_mm", "val_ssim",
                   "val_rmse_mm_real", "val_ssim_real", "val_rmse_mm_synthetic", "val_ssim_synthetic",
                   "lr", "seconds", "best")



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
    atomic_write_text(out / "history.csv", buf.getvalue())
    if not plot:
        return
    try:
        from uhrnet.plots import plot_history

        plot_history(rows, out / "history.png")
    except Exception as exc:  # a plotting problem must not stop training
        print(f"warning: could not draw history.png ({exc})", file=sys.stderr)


def save_epoch(out: Path, payload: dict, is_best: bool) -> None:
    """``out/last.pt`` (atomically); a copy as ``out/best.pt`` when this epoch is the best so far."""
    atomic_save(payload, out / "last.pt")
    if is_best:
        _atomic_copy(out / "last.pt", out / "best.pt")


def write_run_config(out: Path, config: dict) -> None:
    """``out/config.json``: the resolved options and what they were resolved to."""
    atomic_write_text(out / "config.json", json.dumps(config, indent=2, default=json_default))


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


def claim_run_folder(out: Path, tool: str, names, kind: str | None = None) -> None:
    """Claim ``names`` in ``out`` for ``tool`` (:func:`fppsim.owned.claim`); a folder written before the
    ownership record is recognised by its ``last.pt`` / ``best.pt``: a uhrnet checkpoint whose ``kind``
    (``"adapt"``: an adaptation, ``"import"``: imported weights, None: a training run) is ``tool``'s."""
    from fppsim.owned import claim

    def legacy():
        for name in ("last.pt", "best.pt"):
            if (out / name).is_file():
                from uhrnet.checkpoint import load_checkpoint

                try:
                    ck = load_checkpoint(out / name)
                except Exception:  # not a checkpoint at all: nothing here is provably ours
                    return ()
                made = "adapt" if "adapt" in ck else "import" if "imported" in ck else None
                return names if made == kind else ()
        return ()

    claim(out, tool, names, legacy=legacy)


def refuse_own_source(out: Path, source, flag: str) -> None:
    """:class:`ConfigError` when the checkpoint ``source`` (a file or a run folder) lies in ``out``: the
    run would replace the weights it starts from."""
    from fppsim.owned import same_folder

    src = Path(source)
    folder = src if src.is_dir() else src.parent
    if same_folder(folder, out):
        raise ConfigError(f"--out {out} is the folder of {flag} {source}: writing there would replace the weights "
                          "this run starts from; choose another --out")


def _atomic_copy(src: Path, dst: Path) -> None:
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def package_version() -> str:
    from uhrnet import __version__

    return __version__


