"""Checkpoints on real phase-shifting data without height labels (``uhrnet evaluate-phase`` calls
:func:`evaluate_phase_folder`).

Reads the folder layout of the public phase-retrieval data (``<root>/PSin``, ``PCos``, ``Fringe``,
``iPattern``, one ``<id>.mat`` each; :mod:`fppsim.psp_io`), predicts a height map from every iPattern
image, and fits the real absolute phase with a smooth reference-plane polynomial plus the predicted
height terms (h, h^2) (:mod:`uhrnet.phase_eval`). Writes to ``--out``: ``phase_results.md``,
``phase_results.json`` (per model and image: residual phase RMSE in rad, fraction of the relief phase
explained, fitted coefficients; the same for the flat h = 0 baseline) and ``figures/<id>.png``
(single-shot image, relief phase, each model's predicted height and residual phase map).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fppsim.formats import atomic_write_text
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.data import parse_size
from uhrnet.device import select_device
from uhrnet.errors import ConfigError

__all__ = ["PhaseEvalConfig", "evaluate_phase_folder", "markdown", "plot_phase_residuals"]


@dataclass
class PhaseEvalConfig:
    """What ``uhrnet evaluate-phase`` does; the fields are its flags (see :mod:`uhrnet.cli`)."""

    checkpoints: list
    phase_root: str | Path
    out: str | Path
    degree: int = 3
    robust: bool = False
    convention: str = "benchmark"
    negate_sin: bool = False
    mask_predicted_invalid: bool = False
    names: list | None = None
    ids: list | None = None
    limit: int | None = None
    figures: int = 3
    device: str = "auto"

    def __post_init__(self):
        if self.degree < 0:
            raise ConfigError(f"--degree must be >= 0, got {self.degree}")


def _mean(values) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def markdown(summary: list[dict], n: int, root: str, degree: int, robust: bool) -> str:
    lines = [f"# Calibration-free phase evaluation: {n} image{'s' if n != 1 else ''} of {root}", "",
             f"Real absolute phase fitted by a degree-{degree} polynomial in (x, y) plus a*h + b*h^2 of the "
             f"predicted height h (mm), {'Huber IRLS' if robust else 'least squares'} over valid pixels. "
             "Explained = 1 - SS_residual / SS_relief, relief = phase minus the plane-only fit. "
             "Flat = the same fit with h = 0 on the same pixels (explains 0 by construction). Means over images.", "",
             "| Model | Residual RMSE (rad) | Explained | Flat RMSE (rad) | a (rad/mm) | b (rad/mm^2) "
             "| Residual (mm equiv.) | Pixels used |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in summary:
        lines.append(f"| {r['name']} | {r['rmse_rad']:.4f} | {r['explained']:.4f} | {r['flat_rmse_rad']:.4f} | "
                     f"{r['a_rad_per_mm']:+.4f} | {r['b_rad_per_mm2']:+.2e} | {r['rmse_mm_equiv']:.2f} | "
                     f"{r['pixel_fraction']:.1%} |")
    return "\n".join(lines) + "\n"


def plot_phase_residuals(image: np.ndarray, relief: np.ndarray, heights: dict, residuals: dict, path: Path,
                         title: str = "") -> Path:
    """One row per model: predicted height (mm) and residual phase (rad); the top row: image and relief."""
    from uhrnet.plots import _plt, _save

    plt = _plt()
    rows = 1 + len(heights)
    fig, axes = plt.subplots(rows, 2, figsize=(10, 2.9 * rows), squeeze=False)
    axes[0, 0].imshow(image, cmap="gray", vmin=0, vmax=255)
    axes[0, 0].set_title("single-shot image (iPattern)")
    lim = np.nanpercentile(np.abs(relief), 99) if np.isfinite(relief).any() else 1.0
    im = axes[0, 1].imshow(relief, cmap="coolwarm", vmin=-lim, vmax=lim)
    axes[0, 1].set_title("relief phase (rad): phase - plane fit")
    fig.colorbar(im, ax=axes[0, 1], fraction=0.025)
    rlim = max((np.nanpercentile(np.abs(r), 99) for r in residuals.values() if np.isfinite(r).any()), default=1.0)
    for k, name in enumerate(heights, start=1):
        im = axes[k, 0].imshow(heights[name], cmap="viridis")
        axes[k, 0].set_title(f"{name}: predicted height (mm)")
        fig.colorbar(im, ax=axes[k, 0], fraction=0.025)
        im = axes[k, 1].imshow(residuals[name], cmap="coolwarm", vmin=-rlim, vmax=rlim)
        axes[k, 1].set_title(f"{name}: residual phase (rad)")
        fig.colorbar(im, ax=axes[k, 1], fraction=0.025)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = _save(fig, path)
    plt.close(fig)
    return out


def evaluate_phase_folder(args: PhaseEvalConfig, echo=print) -> dict:
    """Evaluate ``args.checkpoints`` on the folder layout at ``args.phase_root``; writes the report to
    ``args.out`` and returns ``{"summary", "per_image", "markdown", "figures"}``. ``echo`` gets one line
    per image (None: silent)."""
    from fppsim.psp_io import PSPMatError, list_psp_ids, load_psp_folder_sample
    from uhrnet.evaluation import model_names
    from uhrnet.inference import predict_labels
    from uhrnet.phase_eval import evaluate_phase, fit_phase

    echo = echo or (lambda line: None)
    try:
        ids = list_psp_ids(args.phase_root)
    except PSPMatError as exc:
        raise ConfigError(str(exc)) from None
    if args.ids:
        unknown = [i for i in args.ids if i not in ids]
        if unknown:
            raise ConfigError(f"{args.phase_root}: no such id(s): {', '.join(unknown[:10])}")
        ids = list(args.ids)
    if args.limit is not None:
        ids = ids[: max(0, args.limit)]
    if not ids:
        raise ConfigError(f"{args.phase_root}: nothing to evaluate")
    ckpts = [load_checkpoint(p) for p in args.checkpoints]
    names = model_names(ckpts, args.names)
    device = select_device(args.device)
    models = []
    for ck in ckpts:
        model, transform = model_from_checkpoint(ck, device)
        models.append((model, transform, parse_size(ck.get("args", {}).get("resize"))))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fit_kw = dict(degree=args.degree, robust=args.robust)

    per_image, figures = [], []
    for k, sid in enumerate(ids):
        try:
            s = load_psp_folder_sample(args.phase_root, sid, convention=args.convention, negate_sin=args.negate_sin)
        except PSPMatError as exc:
            raise ConfigError(str(exc)) from None
        img = s.image
        x = torch.from_numpy(img.astype(np.float32) / 127.5 - 1.0)[None, None]
        record = {"id": sid, "valid_phase_fraction": float(s.valid.mean()), "models": {}}
        try:
            _, relief = fit_phase(s.phase, np.zeros(img.shape), s.valid, return_residual=True, **fit_kw)
        except ValueError as exc:
            raise ConfigError(f"{s.path}: {exc}") from None
        heights, residuals = {}, {}
        for (model, transform, size), name in zip(models, names):
            label = predict_labels(model, x, size)[0, 0].cpu().numpy().astype(np.float64)
            h = transform.height_mm(label)
            pred_valid = np.asarray(transform.valid(label))
            ok = s.valid & (img > 0)
            if args.mask_predicted_invalid:
                ok &= pred_valid
            try:
                res = evaluate_phase(s.phase, h, ok, **fit_kw)
            except ValueError as exc:
                raise ConfigError(f"{s.path}: {name}: {exc}") from None
            record["models"][name] = {"prediction": res["prediction"], "flat": res["flat"],
                                      "pixel_fraction": float(ok.mean()),
                                      "predicted_invalid_fraction": float((s.valid & ~pred_valid).mean())}
            heights[name] = np.where(ok, h, np.nan)
            residuals[name] = res["residual"]
        per_image.append(record)
        if k < args.figures:
            figures.append(plot_phase_residuals(img, relief, heights, residuals, out / "figures" / f"{sid}.png",
                                                title=f"{sid}: calibration-free phase fit (degree {args.degree})"))
        echo(f"{sid}: " + ", ".join(f"{n} residual {r['prediction']['rmse_rad']:.3f} rad "
                                     f"(flat {r['flat']['rmse_rad']:.3f}), explained {r['prediction']['explained']:.3f}"
                                     for n, r in record["models"].items()))
    summary = []
    for ck, name in zip(ckpts, names):
        rows = [r["models"][name] for r in per_image]
        summary.append({
            "name": name, "checkpoint": ck["path"], "images": len(rows),
            **{key: _mean(r["prediction"][key] for r in rows)
               for key in ("rmse_rad", "explained", "a_rad_per_mm", "b_rad_per_mm2", "rmse_mm_equiv", "relief_rms_rad")},
            "flat_rmse_rad": _mean(r["flat"]["rmse_rad"] for r in rows),
            "flat_explained": _mean(r["flat"]["explained"] for r in rows),
            "pixel_fraction": _mean(r["pixel_fraction"] for r in rows),
            "predicted_invalid_fraction": _mean(r["predicted_invalid_fraction"] for r in rows),
        })
    md = markdown(summary, len(ids), args.phase_root, args.degree, args.robust)
    atomic_write_text(out / "phase_results.md", md)
    atomic_write_text(out / "phase_results.json", json.dumps(
        {"phase_root": str(args.phase_root), "convention": args.convention, "negate_sin": args.negate_sin,
         "degree": args.degree, "robust": args.robust, "models": summary, "per_image": per_image},
        indent=1, allow_nan=True))
    return {"summary": summary, "per_image": per_image, "markdown": md, "figures": figures}
