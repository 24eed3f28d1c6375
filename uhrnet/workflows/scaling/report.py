"""The scaling study's table (``scaling_table.md``: one line per arm, mean ± std over its finished seeds; each
arm against the reference arm; the samples series' slope) and figures (``scaling_samples.png``,
``scaling_steps.png``: the real pair's object RMSE with its level / relief parts and the phase residuals
against the arms' sample counts or optimizer steps)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fppsim.plots import pyplot, save_figure
from uhrnet.workflows.scaling.arms import SERIES, arm_label
from uhrnet.workflows.scaling.stats import REFERENCE_ARM, compare, series_slope

__all__ = ["TABLE_MARK", "GOALS", "markdown", "plot_series"]

TABLE_MARK = "<!-- written by pipelines/scaling.py from scaling.json; do not edit -->"
GOALS = {"pair_object_rmse_mm": 4.5, "phase_residual_rad": 1.32}  # issue 35's targets (dashed in the figures)


def _cell(stat: dict, fmt: str = ".2f") -> str:
    if not stat or stat.get("mean") is None:
        return ""
    return format(stat["mean"], fmt) + (f" ± {format(stat['std'], fmt)}" if stat.get("std") is not None else "")


def markdown(doc: dict) -> str:
    """``scaling_table.md``: one line per arm, mean ± std over its finished seeds."""
    frames = sorted({f for a in doc["arms"] for f in a["summary"]["phase_residual_rad"]})
    lines = ["# Scaling study of the sim-to-real recipe", "",
             "Mean ± sample standard deviation over the finished training seeds (n). Pair: the labelled real "
             "pair(s); level / relief: the object RMSE split over connected object regions (median split); phase: "
             "calibration-free residual on held-out real frames (rad). Commands: scaling.json.", "",
             "| arm | samples | steps | n | pair object RMSE (mm) | level (mm) | relief (mm) |"
             + "".join(f" {f} (rad) |" for f in frames) + " minutes / seed |",
             "|---|---|---|---|---|---|---|" + "---|" * len(frames) + "---|"]
    for a in doc["arms"]:
        s = a["summary"]
        lines.append(f"| {arm_label(a)} | {a.get('count', '')} | {a.get('steps', '')} | {s['n_seeds']} | "
                     f"{_cell(s['pair_object_rmse_mm'])} | "
                     f"{_cell(s['pair_level_rmse_mm'])} | {_cell(s['pair_relief_rmse_mm'])} |"
                     + "".join(f" {_cell(s['phase_residual_rad'].get(f, {}), '.3f')} |" for f in frames)
                     + f" {_cell(s['minutes'], '.1f')} |")
    descriptions = {a["name"]: a.get("description") for a in doc["arms"]}
    lines += ["", "Arms marked @HxW trained at that size (uhrnet train --resize), [cuda] on a GPU; the rest at full "
              "size on the CPU.", "", *[f"- {n}: {d}" for n, d in descriptions.items() if d]]
    lines += _what_moves(doc, frames)
    return "\n".join(lines) + "\n"


def _what_moves(doc: dict, frames: list[str]) -> list[str]:
    """The table's second part: each arm against n400 on the same device (beyond the seed spread or not) and
    the samples series' slope per doubling."""
    def cell(f):
        return "" if f is None else f"{f['slope']:+.3f} ± {f['stderr']:.3f} [{f['low']:+.3f}, {f['high']:+.3f}]"

    lines = []
    groups: dict = {}
    for a in doc["arms"]:
        groups.setdefault((a.get("device", "cpu"), a.get("resize")), []).append(a)
    for (device, resize), arms in groups.items():
        where = device + (f" @{resize}" if resize else "")
        ref = next((a for a in arms if a["name"] == REFERENCE_ARM), None)
        rows = []
        for a in arms:
            if ref is None or a is ref:
                continue
            cells = [compare(a, ref, "pair_object_rmse_mm"), *(compare(a, ref, "", f) for f in frames)]
            if not any(cells):
                continue
            rows.append(f"| {arm_label(a)} | " + " | ".join(
                "" if c is None else f"{c['diff']:+.2f} ({'beyond' if c['beyond'] else 'within'} ±{c['spread']:.2f}; "
                                     f"t {c['t']:+.1f})" for c in cells) + " |")
        if rows:
            lines += ["", f"## Against {REFERENCE_ARM} ({where})", "",
                      "Difference of the means (arm - n400); 'beyond' when it exceeds the larger seed standard "
                      "deviation of the two arms (a difference inside the seed spread is no difference); t: Welch's.",
                      "", "| arm | pair object RMSE (mm) |" + "".join(f" {f} (rad) |" for f in frames),
                      "|---|---|" + "---|" * len(frames), *rows]
        samples = [a for a in arms if "samples" in a.get("series", []) and a.get("count")]
        fits = [(label, series_slope(samples, key, frame), series_slope(samples, key, frame, means=True))
                for label, key, frame in [("pair object RMSE (mm)", "pair_object_rmse_mm", None),
                                          *((f"{f} (rad)", "", f) for f in frames)]]
        fits = [(label, f, m) for label, f, m in fits if f]
        if fits and len({a["count"] for a in samples}) > 2:
            lines += ["", f"## Samples series slope ({where}: {', '.join(arm_label(a) for a in samples)})", "",
                      "Least-squares slope against log2(samples), per doubling of the synthetic samples at the same "
                      "steps, ± its standard error [95 % interval]: every seed a point (an arm's seeds share its "
                      "data, so this interval is optimistic) and every arm's mean a point (conservative).", "",
                      "| result | every seed | seeds | arm means | arms |", "|---|---|---|---|---|",
                      *[f"| {label} | {cell(f)} | {f['n']} | {cell(m)} | {m['n'] if m else ''} |"
                        for label, f, m in fits]]
    return lines


def plot_series(doc: dict, series: str, path: Path) -> Path | None:
    """Pair object RMSE with its level and relief parts (left) and each phase frame's residual (right), mean
    ± std over seeds (single seeds as dots), against the arms' x of ``series``: one row per device (full-size
    arms only; a CPU and a GPU seed are different computations); the goals of :data:`GOALS` dashed. None when
    no arm has a result."""
    key, xlabel = SERIES[series]
    arms = [a for a in doc["arms"] if series in a.get("series", []) and a["seeds"] and not a.get("resize")]
    devices = sorted({a.get("device", "cpu") for a in arms}, key=lambda d: (d != "cpu", d))
    if not arms:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(len(devices), 2, figsize=(12, 4.2 * len(devices)), squeeze=False)
    parts = (("pair_object_rmse_mm", "object RMSE", "k", "o"),
             ("pair_level_rmse_mm", "level (region medians)", "C3", "s"),
             ("pair_relief_rmse_mm", "relief (rest)", "C0", "^"))
    for ax, device in zip(axes, devices):
        row = sorted((a for a in arms if a.get("device", "cpu") == device), key=lambda a: a[key])
        x = np.array([a[key] for a in row], float)
        for k, label, color, marker in parts:
            mean = np.array([a["summary"][k]["mean"] if a["summary"][k]["mean"] is not None else np.nan for a in row])
            std = np.array([a["summary"][k]["std"] or 0.0 for a in row])
            ax[0].errorbar(x, mean, yerr=std, color=color, marker=marker, capsize=4, label=label)
            for xi, a in zip(x, row):
                ys = [s_[k] for s_ in a["seeds"] if s_.get(k) is not None]
                ax[0].plot([xi] * len(ys), ys, ".", color=color, alpha=0.35)
        ax[0].axhline(GOALS["pair_object_rmse_mm"], color="k", ls="--", lw=1,
                      label=f"goal {GOALS['pair_object_rmse_mm']} mm")
        ax[0].set_ylabel("labelled real pair (mm)")
        ax[0].set_ylim(bottom=0)
        ax[0].set_title(f"{device}: real pair object RMSE, its level and relief parts", fontsize=10)
        frames = sorted({f for a in row for f in a["summary"]["phase_residual_rad"]})
        for j, f in enumerate(frames):
            mean = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("mean") or np.nan for a in row])
            std = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("std") or 0.0 for a in row])
            ax[1].errorbar(x, mean, yerr=std, color=f"C{j}", marker="o", capsize=4, label=f)
            for xi, a in zip(x, row):
                ys = [s_["phase_residual_rad"][f] for s_ in a["seeds"] if f in s_.get("phase_residual_rad", {})]
                ax[1].plot([xi] * len(ys), ys, ".", color=f"C{j}", alpha=0.35)
        if frames:
            ax[1].axhline(GOALS["phase_residual_rad"], color="k", ls="--", lw=1,
                          label=f"goal {GOALS['phase_residual_rad']} rad")
        ax[1].set_ylabel("phase residual (rad)")
        ax[1].set_ylim(bottom=0)
        ax[1].set_title(f"{device}: held-out real phase frames" if frames else "held-out real phase frames: none given",
                        fontsize=10)
        n = sorted({a["summary"]["n_seeds"] for a in row})
        ax[0].text(0.01, 0.02, f"{'/'.join(map(str, n))} seed(s): " + ", ".join(arm_label(a) for a in row),
                   transform=ax[0].transAxes, fontsize=7)
        for a_ in ax:
            a_.set_xscale("log", base=2)
            a_.set_xticks(x, [f"{int(v)}" for v in x])
            a_.set_xlabel(xlabel)
            a_.grid(alpha=0.3)
            if a_.get_legend_handles_labels()[0]:
                a_.legend(fontsize=7)
    fig.suptitle(f"sim-to-real scaling ({series}): mean ± std over training seeds (dots: each seed), full size",
                 fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)

