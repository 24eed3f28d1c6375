"""What ``uhrnet evaluate-phase`` writes and prints of its scores (:mod:`uhrnet.scoring.phase_residual`): the
``phase_results.md`` table (:func:`markdown`), one line per frame (:func:`frame_line`) and the residual maps
(:func:`plot_phase_residuals`). A frame with no reference plane in view has no plane-pixel score: its columns
read ``-`` and a line says why (null in ``phase_results.json``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uhrnet.plots import pyplot, save_figure

__all__ = ["markdown", "frame_line", "plot_phase_residuals"]


def _cell(value, fmt: str) -> str:
    """A table cell; ``-`` where there is no number (no plane in view)."""
    return "-" if value is None or not np.isfinite(value) else format(value, fmt)


def markdown(summary: list[dict], n: int, root: str, degree: int, robust: bool, no_plane: dict | None = None) -> str:
    """The report's table. ``no_plane``: frame id -> why it shows no reference plane, a line under the table."""
    lines = [f"# Calibration-free phase evaluation: {n} image{'s' if n != 1 else ''} of {root}", "",
             f"Real absolute phase fitted by a degree-{degree} polynomial in (x, y) plus a*h + b*h^2 of the "
             f"predicted height h (mm), {'Huber IRLS' if robust else 'least squares'} over valid pixels. "
             "Explained = 1 - SS_residual / SS_relief, relief = phase minus the plane-only fit. "
             "Flat = the same fit with h = 0 on the same pixels (explains 0 by construction); ratio = residual / flat "
             "(the default score). Plane-pixel columns: the same with the plane polynomial fitted on the reference "
             "plane's own pixels only (found in the phase, fppsim.phase.plane.phase_plane_masks), so an object "
             "covering much of the view cannot bend it; over the frames with a plane in view. Means over images; "
             "Residual (mm equiv.) = mean residual / mean |a|.", "",
             "| Model | Residual RMSE (rad) | Flat RMSE (rad) | Ratio | Explained | Plane-pixel plane: residual "
             "| flat | ratio | a (rad/mm) | b (rad/mm^2) | Residual (mm equiv.) | Pixels used |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in summary:
        lines.append(f"| {r['name']} | {r['rmse_rad']:.4f} | {r['flat_rmse_rad']:.4f} | {r['ratio']:.3f} | "
                     f"{r['explained']:.4f} | {_cell(r['plane_rmse_rad'], '.4f')} | "
                     f"{_cell(r['plane_flat_rmse_rad'], '.4f')} | {_cell(r['plane_ratio'], '.3f')} | "
                     f"{r['a_rad_per_mm']:+.4f} | {r['b_rad_per_mm2']:+.2e} | {r['rmse_mm_equiv']:.2f} | "
                     f"{r['pixel_fraction']:.1%} |")
    if no_plane:
        by_why = {}
        for sid, why in no_plane.items():
            by_why.setdefault(why, []).append(sid)
        lines += ["", ("No plane in view: no plane-pixel score (" if len(no_plane) == n else
                       f"No plane in view on {len(no_plane)} of the {n} frames, left out of the plane-pixel columns (")
                  + "; ".join(f"{', '.join(ids)}: {why}" for why, ids in by_why.items()) + ")."]
    return "\n".join(lines) + "\n"


def frame_line(sid: str, models: dict, no_plane: str | None = None) -> str:
    """One frame's scores, as evaluate-phase prints them: each model's residual beside the flat one, then the
    plane-pixel scores, or why there are none."""
    line = f"{sid}: " + ", ".join(
        f"{n} residual {r['prediction']['rmse_rad']:.3f} rad (flat {r['flat']['rmse_rad']:.3f}), explained "
        f"{r['prediction']['explained']:.3f}" + (f"; plane-pixel plane {r['plane']['prediction']['rmse_rad']:.3f} "
                                                  f"(flat {r['plane']['flat']['rmse_rad']:.3f})" if r["plane"] else "")
        for n, r in models.items())
    return line + (f"; plane-pixel score: no plane in view ({no_plane})" if no_plane else "")


def plot_phase_residuals(image: np.ndarray, relief: np.ndarray, heights: dict, residuals: dict, path: Path,
                         title: str = "") -> Path:
    """One row per model: predicted height (mm) and residual phase (rad); the top row: image and relief."""
    plt = pyplot()
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
    out = save_figure(fig, path)
    plt.close(fig)
    return out
