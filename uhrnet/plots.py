"""Figures: training curves like the paper's Fig. 6 and comparison panels like Figs. 7-9.

Every uhrnet figure gets matplotlib from :func:`pyplot` and is written by :func:`save_figure` (both
through :mod:`fppsim.plots`, the one place that sets matplotlib up).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from fppsim.phase import circular_mean, wrap
from fppsim.plots import pyplot, save_figure as save

__all__ = ["pyplot", "save_figure", "plot_history", "plot_comparison", "plot_adaptation"]


def save_figure(fig, path, dpi: float = 110) -> Path:
    """Write ``fig`` to ``path`` atomically, trimmed to its content (``bbox_inches="tight"``)."""
    return save(fig, path, dpi=dpi, bbox_inches="tight")


def _column(rows: Sequence[dict], key: str) -> np.ndarray:
    out = []
    for r in rows:
        v = r.get(key, "")
        try:
            out.append(float(v))
        except (TypeError, ValueError):
            out.append(np.nan)
    return np.array(out, dtype=float)


def plot_history(rows: Sequence[dict], path) -> Path:
    """Loss, RMSE (mm) and SSIM per epoch, train vs validation (the paper's Fig. 6); and the real frames'
    phase residual as a fraction of flat when the run has one (``--val-phase``)."""
    plt = pyplot()
    epochs = _column(rows, "epoch")
    panels = [
        ("loss", [("train_loss", "train")], "loss", True),
        ("RMSE (mm)", [("train_rmse_mm", "train"), ("val_rmse_mm", "validation")], "RMSE (mm)", True),
        ("SSIM", [("train_ssim", "train"), ("val_ssim", "validation")], "SSIM", False),
    ]
    if np.isfinite(_column(rows, "val_phase_ratio")).any():  # uhrnet train --val-phase
        panels.append(("real frames (--val-phase)", [("val_phase_ratio", "phase residual / flat: choosing best.pt"),
                                                      ("val_phase_heldout_ratio", "held-out frames")],
                       "residual / flat", False))
    fig, axes = plt.subplots(1, len(panels), figsize=(14 / 3 * len(panels), 3.8))
    for ax, (title, series, ylabel, log) in zip(axes, panels):
        for key, label in series:
            y = _column(rows, key)
            if np.isfinite(y).any():
                ax.plot(epochs, y, marker="o" if len(epochs) < 30 else None, ms=3, label=label)
        if log and all(np.nanmin(_column(rows, k)) > 0 for k, _ in series if np.isfinite(_column(rows, k)).any()):
            ax.set_yscale("log")
        ax.set_title(title)
        ax.set_xlabel("epoch")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if ax.has_data():
            ax.legend()
    fig.tight_layout()
    path = save_figure(fig, path)
    plt.close(fig)
    return path


def plot_comparison(fringe: np.ndarray, truth_mm: np.ndarray, valid: np.ndarray, predictions: dict[str, np.ndarray],
                    path, row: int | None = None, title: str = "") -> Path:
    """One sample: fringe, ground truth, each model's prediction and error map (mm), and a cross-section.

    ``truth_mm`` and the predictions are heights in mm (same reference); ``valid`` masks both. Layout:
    row 1 fringe | ground truth | predictions...; row 2 cross-section | error maps... (Figs. 7-9).
    """
    plt = pyplot()
    h, w = truth_mm.shape
    row = h // 2 if row is None else int(np.clip(row, 0, h - 1))
    n = len(predictions)
    cols = max(2 + n, 2)
    fig, axes = plt.subplots(2, cols, figsize=(3.3 * cols, 5.4), squeeze=False)
    gt = np.where(valid, truth_mm, np.nan)
    finite = gt[np.isfinite(gt)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    errs = {k: np.where(valid, p - truth_mm, np.nan) for k, p in predictions.items()}
    all_err = np.concatenate([e[np.isfinite(e)] for e in errs.values()]) if errs else np.zeros(1)
    emax = float(np.percentile(np.abs(all_err), 99)) if all_err.size else 1.0
    emax = emax if emax > 0 else 1.0

    ax = axes[0, 0]
    ax.imshow(fringe, cmap="gray", vmin=-1, vmax=1)
    ax.axhline(row, color="r", lw=0.8, ls="--")
    ax.set_title("fringe")
    ax = axes[0, 1]
    im = ax.imshow(gt, cmap="viridis", vmin=lo, vmax=hi)
    ax.set_title("ground truth (mm)")
    fig.colorbar(im, ax=ax, fraction=0.046)
    for j, (name, pred) in enumerate(predictions.items()):
        ax = axes[0, 2 + j]
        im = ax.imshow(np.where(valid, pred, np.nan), cmap="viridis", vmin=lo, vmax=hi)
        ax.set_title(name)
        fig.colorbar(im, ax=ax, fraction=0.046)
        ax = axes[1, 2 + j]
        e = errs[name]
        rmse = float(np.sqrt(np.nanmean(e**2))) if np.isfinite(e).any() else float("nan")
        im = ax.imshow(e, cmap="coolwarm", vmin=-emax, vmax=emax)
        ax.set_title(f"error {name}\nRMSE {rmse:.3f} mm")
        fig.colorbar(im, ax=ax, fraction=0.046)
    ax = axes[1, 0]
    x = np.arange(w)
    ax.plot(x, gt[row], "k-", lw=1.5, label="ground truth")
    for name, pred in predictions.items():
        ax.plot(x, np.where(valid[row], pred[row], np.nan), lw=1, label=name)
    ax.set_title(f"cross-section, row {row}")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("height (mm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    axes[1, 1].axis("off")
    for a in list(axes[0]) + list(axes[1, 2:]):
        a.set_xticks([])
        a.set_yticks([])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = save_figure(fig, path)
    plt.close(fig)
    return path


def plot_adaptation(image, before_mm: np.ndarray, after_mm: np.ndarray, layer, path) -> Path:
    """One figure per adapted image (:mod:`uhrnet.training.adapt`): the fringe, the height before and after
    (mm, one colour range), their difference, and the wrapped phase residual ``wrap(phi - Phi(h) - o)``
    (rad) before and after, on the image's reliable pixels. ``image``: :class:`uhrnet.training.adapt.ImagePhase`."""
    import torch

    plt = pyplot()
    valid = image.reliability > 0
    rel = image.reliability >= 0.5

    def residual(h):
        with torch.no_grad():
            phi = layer.phase_from_height(torch.as_tensor(np.nan_to_num(h), dtype=torch.float64)).numpy()
        d = wrap(image.wrapped - phi)
        o = circular_mean(d, mask=rel) if rel.any() else 0.0
        return np.where(rel, wrap(d - o), np.nan)

    show = lambda h: np.where(valid, h, np.nan)  # noqa: E731
    both = np.concatenate([before_mm[valid], after_mm[valid]])
    lo, hi = (np.nanpercentile(both, [1, 99]) if both.size else (0.0, 1.0))
    diff = show(after_mm - before_mm)
    dmax = float(np.nanpercentile(np.abs(diff), 99)) if np.isfinite(diff).any() else 1.0
    fig, axes = plt.subplots(2, 3, figsize=(15, 6.2))
    panels = [(image.fringe, "fringe (input)", "gray", None, None),
              (show(before_mm), "height before (mm)", "viridis", lo, hi),
              (show(after_mm), "height after (mm)", "viridis", lo, hi),
              (diff, "after - before (mm)", "RdBu_r", -dmax, dmax),
              (residual(before_mm), "phase residual before (rad)", "twilight", -np.pi, np.pi),
              (residual(after_mm), "phase residual after (rad)", "twilight", -np.pi, np.pi)]
    for ax, (img, title, cmap, vmin, vmax) in zip(axes.ravel(), panels):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_title(title)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.03)
    fig.suptitle(f"{image.name}: label-free adaptation")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
    plt.close(fig)
    return Path(path)


def plot_orders(fringe: np.ndarray, network_mm: np.ndarray, choice, path, error_mm: np.ndarray | None = None,
                title: str = "") -> Path:
    """One figure of a fringe-order choice (:class:`uhrnet.physics.orders.OrderChoice`): the fringe, the network's
    height and the chosen one (mm, one colour range), every phase region coloured by its confidence with its
    chosen order written at its centre (undecided regions hatched grey; orders relative to the largest region),
    where each height came from, and, when ``error_mm`` (chosen - truth) is given, the error (mm)."""
    from scipy import ndimage as ndi

    plt = pyplot()
    lab = choice.labels
    both = np.concatenate([network_mm[np.isfinite(network_mm)], choice.height[np.isfinite(choice.height)]])
    lo, hi = (np.percentile(both, [1, 99]) if both.size else (0.0, 1.0))
    panels = [(fringe, "fringe (input)", "gray", None, None),
              (network_mm, "network height (mm)", "viridis", lo, hi),
              (choice.height, "orders chosen: height (mm)", "viridis", lo, hi),
              (choice.confidence_map(), "regions: confidence (colour), order (text)", "RdYlGn", 0.0, 1.0)]
    source = np.where(choice.moved, 2.0, np.where(np.isfinite(network_mm) & (choice.height != network_mm), 1.0, 0.0))
    if choice.rim is not None:
        source = np.where(choice.rim, 3.0, source)
    panels.append((np.where(np.isfinite(choice.height), source, np.nan),
                   "height from: 3 rim split, 2 the phase, 1 network + correction, 0 network", "cividis", 0.0, 3.0))
    if error_mm is not None:
        panels.append((error_mm, "error (mm)", "RdBu_r", -8.0, 8.0))
    fig, axes = plt.subplots(2, 3, figsize=(15, 6.4))
    axes = axes.ravel()
    for ax in axes[len(panels):]:
        ax.axis("off")
    for ax, (img, name, cmap, vmin, vmax) in zip(axes, panels):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.03)
    ax = axes[3]
    undecided = np.isin(lab, [r.label for r in choice.regions if not r.decided])
    if undecided.any():
        ax.contourf(undecided, levels=[0.5, 1.5], colors="none", hatches=["////"])
    if choice.regions:
        centres = ndi.center_of_mass(np.ones(lab.shape), lab, [r.label for r in choice.regions])
        base = choice.regions[0].order
        for r, (cy, cx) in zip(choice.regions, centres):
            if r.pixels >= 300:
                ax.text(cx, cy, f"{r.order - base:+d}", ha="center", va="center", fontsize=7,
                        color="black" if r.decided else "grey")
    fig.suptitle(title or "fringe orders", fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=75)  # six panels: a smaller file for the write-ups
    plt.close(fig)
    return Path(path)
