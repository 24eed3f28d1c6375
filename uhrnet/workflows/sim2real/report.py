"""The sim-to-real report: the ablation table (``report.md``) and a figure per real image."""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np

from fppsim.plots import pyplot, save_figure
from uhrnet.workflows.sim2real.real_metrics import object_mask

__all__ = ["markdown_report", "plot_real"]


def _level_cell(level: dict | None) -> str:
    slope = _fmt((level or {}).get("slope"), "+.2f")  # None: null in a result file read back (was NaN)
    prior = _fmt((level or {}).get("prior_level_mm"), ".1f")
    return slope + (f" / {prior}" if slope and prior else "")


def markdown_report(report: dict) -> str:
    """The ablation table (one row per variant) as Markdown."""
    c = report["config"]
    lines = [f"# Sim-to-real ({c['scale']} scale): synthetic-only training, evaluated on real data", "",
             f"{c['count']} synthetic samples (seed {c['seed']}), {c['model']}"
             + (f" base {c['base_channels']}" if c.get("base_channels") else "")
             + f", {c['epochs']} epochs, batch {c['batch_size']}, lr {c['lr']:g}, loss {c['loss']}. "
             f"Object pixels: valid and more than {c['object_mm']:g} mm above the plane.", "",
             "| variant | generate | train | object RMSE (mm) | valid RMSE (mm) | flat plane, object (mm) | "
             "true / pred. object mean (mm) | relief effect (mm) | synthetic val RMSE (mm) | "
             "level slope / prior (mm) | minutes |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for v in report["variants"]:
        r = v["real"]
        mins = sum(x for x in v["timing"].values() if isinstance(x, (int, float))) / 60.0
        sv = v.get("synthetic_val_rmse_mm")
        lines.append(f"| {v['name']} | {shlex.join(v['generate']) or '(defaults)'} | "
                     f"{shlex.join(v['train']) or '(defaults)'} | {_fmt(r.get('object_rmse_mm'), '.2f')} | "
                     f"{_fmt(r.get('valid_rmse_mm'), '.2f')} | {_fmt(r.get('flat_object_rmse_mm'), '.2f')} | "
                     f"{_fmt(r.get('true_object_mean_mm'), '.1f')} / {_fmt(r.get('pred_object_mean_mm'), '.1f')} | "
                     f"{_fmt(r.get('relief_effect_mm'), '.1f')} | "
                     f"{_fmt(sv, '.2f')} | {_level_cell(v.get('synthetic_level'))} | {mins:.1f} |")
    return "\n".join(lines + _rows_table(report)) + "\n"


def _frame_name(frame: dict) -> str:
    return f"{Path(frame['folder']).name}/{frame['id']}"


def _rows_table(report: dict) -> list[str]:
    """Every evaluation row (network, refined, adapted, adapted and refined) of every variant: the real pairs'
    object metrics, the phase residual of each real phase-shifting frame, and where adaptation read images."""
    rows = [r for v in report["variants"] for r in v.get("rows") or []]
    if not rows:
        return []
    frames = []
    for r in rows:
        for f in r.get("real_phase") or []:
            if _frame_name(f) not in frames:
                frames.append(_frame_name(f))
    lines = ["", "## Every row on real data", "",
             "Real pairs: object RMSE, median |error| and share of object pixels within 1 mm (errors in mm over "
             "the object pixels), coverage = share of object pixels the prediction marks valid. Level / relief: "
             "the object RMSE split over the object's connected regions into each region's median error (level) "
             "and the rest (relief); the median split does not add up exactly, the mean split (each region's "
             "mean error) does: level^2 + relief^2 = RMSE^2 (`uhrnet.workflows.sim2real.real_metrics.error_split`). Phase frames: "
             "calibration-free phase residual (rad) of the prediction, as `uhrnet evaluate-phase` reports it "
             "(lower is better; the flat plane h = 0 is in the last line).", "",
             "| row | object RMSE (mm) | level (mm) | relief (mm) | level / relief, mean split (mm) | "
             "median abs. error (mm) | within 1 mm | coverage |"
             + "".join(f" {f} residual (rad) |" for f in frames),
             "|---|---|---|---|---|---|---|---|" + "---|" * len(frames)]

    def cell(x, fmt):
        return "" if x is None or not np.isfinite(x) else format(x, fmt)

    for r in rows:
        m = r["real"]
        by = {_frame_name(f): f for f in r.get("real_phase") or []}
        lines.append(f"| {r['row']} | {cell(m.get('object_rmse_mm'), '.2f')}"
                     f" | {cell(m.get('object_level_rmse_mm'), '.2f')}"
                     f" | {cell(m.get('object_relief_rmse_mm'), '.2f')} | {_split_cell(m)}"
                     f" | {cell(m.get('object_median_abs_mm'), '.2f')}"
                     f" | {cell(m.get('object_within_1mm'), '.1%')} | {cell(m.get('object_coverage'), '.1%')} |"
                     + "".join(f" {cell(by[f]['rmse_rad'], '.3f') if f in by else ''} |" for f in frames))
    if frames:
        flat = {}
        for r in rows:
            for f in r.get("real_phase") or []:
                flat.setdefault(_frame_name(f), f["flat_rmse_rad"])
        m = report["variants"][0]["real"]
        lines.append(f"| flat plane (h = 0) | {cell(m.get('flat_object_rmse_mm'), '.2f')} | | | | | | |"
                     + "".join(f" {cell(flat.get(f), '.3f')} |" for f in frames))
    notes = [f"- {v['name']} +adapt: adapted on: {', '.join(v['adapt']['images'])} (no labels; "
             f"{v['adapt']['epochs']} epochs{', ' + shlex.join(v['adapt']['flags']) if v['adapt'].get('flags') else ''})"
             ": its rows on these images are not held out" for v in report["variants"] if v.get("adapt")]
    reused = [f"- {v['name']}: reused the finished run {v['run']} (trained on {v['data']})"
              for v in report["variants"] if v.get("reused")]
    return lines + _split_table(rows) + ([""] + notes if notes else []) + ([""] + reused if reused else [])


def _fmt(x, fmt: str) -> str:
    """``x`` formatted, blank when it was not measured (None, as a result file read back holds it, or NaN)."""
    return "" if x is None or not np.isfinite(x) else format(x, fmt)


def _split_cell(m: dict) -> str:
    """``level / relief`` of the mean split, blank where not measured."""
    a, b = _fmt(m.get("object_level_rmse_mean_mm"), ".2f"), _fmt(m.get("object_relief_rmse_mean_mm"), ".2f")
    return f"{a} / {b}" if a and b else ""


def _split_table(rows: list[dict]) -> list[str]:
    """Every row on every labelled real image: object RMSE, its level / relief split and the largest regions'
    median errors (``real_per_image`` of the report's rows; nothing for rows measured before the split)."""
    items = [(r["row"], i) for r in rows for i in r.get("real_per_image") or []
             if i.get("object_level_rmse_mm") is not None]
    if not items:
        return []
    lines = ["", "## Object error per labelled real image: level and relief", "",
             "Level: RMS of each connected object region's median error; relief: RMS of the error minus it; the "
             "mean split adds up (level^2 + relief^2 = RMSE^2). Regions: connected object regions of at least "
             "50 px (8-connectivity); the largest three with their area and median error (prediction - truth).", "",
             "| row | image | object RMSE (mm) | level (mm) | relief (mm) | level / relief, mean split (mm) | "
             "regions | largest regions: px, median error (mm) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, i in items:
        regions = "; ".join(f"{g['area_px']} px {g['median_mm']:+.1f}"
                            for g in (i.get("object_region_errors") or [])[:3])
        lines.append(f"| {name} | {Path(i['folder']).name}/{i['index']} | {_fmt(i.get('object_rmse_mm'), '.2f')} | "
                     f"{_fmt(i.get('object_level_rmse_mm'), '.2f')} | {_fmt(i.get('object_relief_rmse_mm'), '.2f')} | "
                     f"{_split_cell(i)} | {i.get('object_regions', '')} | {regions} |")
    return lines


def plot_real(fringe: np.ndarray, label: np.ndarray, valid: np.ndarray, pred: np.ndarray, units_per_mm: float,
              metrics: dict, path, object_mm: float = 1.0, title: str = "") -> Path:
    """Real fringe | truth | prediction | error (mm above the plane) and a cross-section row.

    ``fringe`` (H, W) in [-1, 1]; ``label``, ``valid``, ``pred``: real and predicted labels (H, W);
    ``metrics``: the image's :func:`~uhrnet.workflows.sim2real.real_metrics.real_metrics` (plane label, RMSEs).
    """
    plt = pyplot()
    plane = metrics["plane_label"]
    t = np.where(valid, (label - plane) / units_per_mm, np.nan)
    p = np.where(valid, (pred - plane) / units_per_mm, np.nan)
    e = p - t
    obj, _ = object_mask(label, valid, units_per_mm, object_mm, plane)
    # the cross-section goes through the row with most object pixels
    row = int(np.argmax(obj.sum(axis=1))) if obj.any() else t.shape[0] // 2
    fig, ax = plt.subplots(1, 5, figsize=(22, 3.6))
    ax[0].imshow(fringe, cmap="gray", vmin=-1, vmax=1)
    ax[0].axhline(row, color="r", lw=0.8, ls="--")
    ax[0].set_title("real fringe")
    hi = float(np.nanpercentile(t, 99.5)) if np.isfinite(t).any() else 1.0
    for a, img, name in ((ax[1], t, "truth (mm above plane)"), (ax[2], p, "prediction (mm)")):
        im = a.imshow(img, cmap="viridis", vmin=-5, vmax=max(hi, 1.0))
        a.set_title(name)
        fig.colorbar(im, ax=a, fraction=0.03)
    emax = float(np.nanpercentile(np.abs(e), 99)) if np.isfinite(e).any() else 1.0
    im = ax[3].imshow(e, cmap="coolwarm", vmin=-emax, vmax=emax)
    ax[3].set_title(f"error: object RMSE {metrics['object_rmse_mm']:.1f} mm, valid {metrics['valid_rmse_mm']:.1f}")
    fig.colorbar(im, ax=ax[3], fraction=0.03)
    for a in ax[:4]:
        a.set_xticks([])
        a.set_yticks([])
    ax[4].plot(t[row], "k-", lw=1.5, label="truth")
    ax[4].plot(p[row], "C1-", lw=1, label="prediction")
    ax[4].set_title(f"row {row}")
    ax[4].set_xlabel("column (px)")
    ax[4].set_ylabel("mm above plane")
    ax[4].legend(fontsize=7)
    ax[4].grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path, dpi=70)
    plt.close(fig)
    return Path(path)
