"""The scaling study's statistics: per-arm mean and sample standard deviation over the training seeds, an
arm against the reference arm (the project's rule: a difference inside the seed spread is no difference;
Welch's t beside it) and the samples series' slope per doubling of the synthetic samples."""

from __future__ import annotations

import math

import numpy as np

from uhrnet.workflows.scaling.results import PAIR_KEYS

__all__ = ["REFERENCE_ARM", "mean_std", "summarise", "compare", "series_slope"]

REFERENCE_ARM = "n400"  # the judged recipe: every arm is compared with it on the same device and size


def mean_std(values: list) -> dict:
    """``{"mean", "std" (ddof 1; None with fewer than 2), "n"}`` of the finite values (None ones skipped)."""
    v = np.array([x for x in values if x is not None and np.isfinite(x)], float)
    return {"mean": float(v.mean()) if v.size else None, "std": float(v.std(ddof=1)) if v.size > 1 else None,
            "n": int(v.size)}


def summarise(seeds: list[dict]) -> dict:
    """Per-arm mean and sample standard deviation (ddof 1; None with fewer than 2 seeds) of every result."""
    out = {k: mean_std([s.get(k) for s in seeds]) for k in (*PAIR_KEYS, "synthetic_val_rmse_mm", "minutes")}
    frames = sorted({f for s in seeds for f in s.get("phase_residual_rad", {})})
    out["phase_residual_rad"] = {f: mean_std([s["phase_residual_rad"].get(f) for s in seeds]) for f in frames}
    out["n_seeds"] = len(seeds)
    return out


def compare(arm: dict, ref: dict, key: str, frame: str | None = None) -> dict | None:
    """``arm`` against ``ref`` on one result (``key``, or a phase ``frame``), both with at least 2 seeds:
    ``diff`` (difference of the means), ``spread`` (the larger of the two seed standard deviations),
    ``beyond`` (|diff| > spread: the project's rule, a difference inside the seed spread is no difference) and
    Welch's ``t`` (diff / sqrt(s1²/n1 + s2²/n2))."""
    def stat(a):
        return a["summary"]["phase_residual_rad"].get(frame, {}) if frame else a["summary"].get(key, {})
    x, r = stat(arm), stat(ref)
    if not x or not r or x.get("std") is None or r.get("std") is None:
        return None
    diff, spread = x["mean"] - r["mean"], max(x["std"], r["std"])
    se = math.sqrt(x["std"] ** 2 / x["n"] + r["std"] ** 2 / r["n"])
    t = diff / se if se > 0 else (math.copysign(math.inf, diff) if diff else math.nan)
    return {"diff": diff, "spread": spread, "beyond": abs(diff) > spread, "t": t}


def series_slope(arms: list[dict], key: str, frame: str | None = None, means: bool = False) -> dict | None:
    """Least-squares slope of the results against log2(samples) over ``arms`` (one device and size): ``slope``
    per doubling, its standard error and 95 % interval (Student t), ``n`` points. Every seed is a point, or
    with ``means`` every arm's mean: an arm's seeds share its synthetic data, so the per-seed interval counts
    them as independent (optimistic); the arm means' interval has only n - 2 degrees of freedom
    (conservative). None with fewer than 3 points or 2 sample counts."""
    from scipy import stats  # SciPy: an optional heavy dependency, only the table's slopes need it

    x, y = [], []
    for a in arms:
        vals = [s_.get("phase_residual_rad", {}).get(frame) if frame else s_.get(key) for s_ in a["seeds"]]
        vals = [v for v in vals if v is not None and np.isfinite(v)]
        if means and vals:
            vals = [float(np.mean(vals))]
        x += [np.log2(a["count"])] * len(vals)
        y += vals
    if len(x) < 3 or len(set(x)) < 2:
        return None
    fit = stats.linregress(x, y)
    half = stats.t.ppf(0.975, len(x) - 2) * fit.stderr
    return {"slope": fit.slope, "stderr": fit.stderr, "low": fit.slope - half, "high": fit.slope + half, "n": len(x)}
