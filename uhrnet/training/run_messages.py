"""What a training run prints: its opening summary, one line per epoch and the closing line.

Apart from the loop (:mod:`uhrnet.training.trainer`) so the loop reads as the training it does; these
lines are the run's console log, read by people (and by tests), not parsed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uhrnet.run_folder import BEST_PT, HISTORY_CSV, LAST_PT
from uhrnet.training.train_config import RunConfig

__all__ = ["opening_lines", "epoch_line", "closing_line"]


def opening_lines(cfg: RunConfig, *, n_params: int, n_trainable: int, sources, image_shape, device, world: int,
                  distributed: bool, out: Path, start_epoch: int, val_phase_notes) -> list[str]:
    """The summary a run starts with: the model, the data, where it writes, and how its weights begin."""
    frozen = f", {n_trainable:,} trainable (--freeze {cfg.freeze})" if cfg.freeze != "none" else ""
    lines = [f"uhrnet train: {cfg.model} ({n_params:,} parameters{frozen}), loss {cfg.loss}, "
             f"{sources.train.n_real} real + {sources.train.n_synthetic} synthetic training / {len(sources.val)} "
             f"validation images at {image_shape[0]}x{image_shape[1]}, device {device}"
             + (f" x {world} processes" if distributed else "") + f", run folder {out}"]
    if start_epoch:
        lines.append(f"resuming after epoch {start_epoch}")
    elif cfg.init_from_checkpoint:
        rec = cfg.init_from_checkpoint
        kind = "moving-average (--ema)" if rec["weights"] == "ema" else "trained"
        other = rec.get("other_options") or {}
        other = f"; this run keeps its own {', '.join(other)} (no weight depends on it)" if other else ""
        lines.append(f"init-from {rec['path']}: the {kind} weights of its epoch {rec['epoch']} "
                     f"(sha256 {rec['sha256'][:12]}){other}; fresh optimizer and schedule")
    if cfg.synthetic_ratio is not None and not (sources.train.n_real and sources.train.n_synthetic):
        lines.append("note: --synthetic-ratio has no effect with only one kind of training data")
    lines += [f"--val-phase: {note}" for note in val_phase_notes]
    return lines


def epoch_line(row: dict, epochs: int, is_best: bool) -> str:
    """One epoch's numbers (``row``: its history row)."""
    val = (f"  val RMSE {row['val_rmse_mm']:.3f} mm  val SSIM {row['val_ssim']:.4f}"
           if "val_rmse_mm" in row else "")
    if "val_phase_ratio" in row:
        val += f"  real phase residual {row['val_phase_ratio']:.3f} of flat"
        if np.isfinite(row.get("val_phase_heldout_ratio", float("nan"))):
            val += f" (held-out frames {row['val_phase_heldout_ratio']:.3f})"
    return (f"epoch {row['epoch']}/{epochs}  loss {row['train_loss']:.4g}  train RMSE "
            f"{row['train_rmse_mm']:.3f} mm{val}  {row['seconds']:.1f}s" + ("  *best" if is_best else ""))


def closing_line(out: Path, best: dict) -> str:
    """Where the run's best model and history are (``best``: the trainer's best-epoch record)."""
    if (out / BEST_PT).is_file() and best["epoch"]:
        return (f"done: {out / BEST_PT} (epoch {best['epoch']}, {best['metric']} "
                f"{best['value']:.4f}), history {out / HISTORY_CSV}")
    # every epoch's metric was NaN (e.g. no valid pixel): no best model to point to
    return (f"done: no {BEST_PT} written (no epoch had a finite {best['metric']}); last epoch in "
            f"{out / LAST_PT}, history {out / HISTORY_CSV}")
