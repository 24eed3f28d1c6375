"""Per-sample PSP evaluation: the PSP height of one sample against its exact height.

:func:`evaluate_sample` classifies the exact-valid pixels (accepted, rejected by reason, order errors)
and measures the height error (``height_psp - height``, mm) on the accepted ones, overall and split
into edge and interior pixels. See :mod:`fppsim.validate` for the definitions.
"""

from __future__ import annotations

import inspect
import math

import numpy as np
from fppsim.phase import psp
from fppsim.rendering.synth import psp_decode

__all__ = ["ORDER_ERROR_RAD", "evaluate_sample", "BREAKDOWN", "breakdown_fractions", "error_stats"]

ORDER_ERROR_RAD = math.pi


# ====================================================================== per-sample evaluation
def _edge_region(valid: np.ndarray, depth: np.ndarray, fx: float, edge_px: int) -> np.ndarray:
    """Pixels within ``edge_px`` of an invalid pixel, a depth discontinuity or the image border."""
    from scipy.ndimage import binary_dilation

    if edge_px <= 0:
        return np.zeros(valid.shape, dtype=bool)
    d = np.where(valid, depth, np.nan).astype(np.float64)
    seed = ~valid
    with np.errstate(invalid="ignore"):
        tol = 4.0 * np.abs(d) / fx
        jx = np.abs(np.diff(d, axis=1)) > np.fmin(tol[:, 1:], tol[:, :-1])
        jy = np.abs(np.diff(d, axis=0)) > np.fmin(tol[1:], tol[:-1])
    seed = seed.copy()
    seed[:, 1:] |= jx
    seed[:, :-1] |= jx
    seed[1:] |= jy
    seed[:-1] |= jy
    seed[:edge_px] = seed[-edge_px:] = True
    seed[:, :edge_px] = seed[:, -edge_px:] = True
    return binary_dilation(seed, structure=np.ones((3, 3), bool), iterations=edge_px) & valid


def error_stats(e: np.ndarray) -> dict:
    n = int(e.size)
    if n == 0:
        return {"n": 0, "rmse_mm": None, "mean_mm": None, "p99_abs_mm": None, "max_abs_mm": None}
    a = np.abs(e)
    return {"n": n, "rmse_mm": float(np.sqrt(np.mean(e * e))), "mean_mm": float(np.mean(e)),
            "p99_abs_mm": float(np.percentile(a, 99)), "max_abs_mm": float(a.max())}


def evaluate_sample(arrays: dict, meta: dict, stacks: dict | None = None, edge_px: int = 3,
                    min_modulation: float | None = None, with_errors: bool = False) -> dict:
    """PSP height vs exact height of one sample.

    Parameters
    ----------
    arrays : ``height``, ``depth``, ``phase_true``, ``mask`` and ``phase_psp``, ``height_psp``, ``mask_psp``
        as in ``arrays.npz``.
    meta : the sample's ``meta.json`` (``psp`` ladder, ``rig`` for the camera focal length and periods).
    stacks : optional ``{f: (N, H, W)}`` PSP images; when given, rejections are split by reason.
    edge_px : width (pixels) of the edge region (0: no edge / interior split).
    min_modulation : modulation threshold for the rejection breakdown; default that of
        :func:`fppsim.rendering.synth.psp_decode`.
    with_errors : also return the per-pixel arrays (``error_mm``, masks) under ``"_maps"``.

    Returns
    -------
    dict of counts, fractions (relative to the exact-valid pixel count) and error statistics (mm);
    see the module docstring for the definitions. Undefined values (no pixels) are None.
    """
    h = np.asarray(arrays["height"], np.float64)
    valid = np.asarray(arrays["mask"]) > 0
    psp_meta = meta.get("psp") or {}
    freqs = list(psp_meta.get("freqs") or [])
    rig = meta.get("rig") or {}
    periods = float(rig.get("periods", freqs[-1] if freqs else 80.0))
    f_top = float(freqs[-1]) if freqs else periods
    phase_true = np.asarray(arrays["phase_true"], np.float64) * (f_top / periods)
    phase_psp = np.asarray(arrays["phase_psp"], np.float64)
    h_psp = np.asarray(arrays["height_psp"], np.float64)
    accepted = valid & (np.asarray(arrays["mask_psp"]) > 0) & np.isfinite(h_psp)
    rejected = valid & ~accepted
    dphi = phase_psp - phase_true
    with np.errstate(invalid="ignore"):
        wrong = valid & ~(np.abs(dphi) <= ORDER_ERROR_RAD)  # NaN phase counts as wrong
    err = np.where(accepted, h_psp - h, np.nan)
    ok = accepted & ~wrong

    n_valid = int(valid.sum())
    frac = (lambda n: float(n) / n_valid if n_valid else None)
    out = {
        "n_valid": n_valid,
        "n_accepted": int(accepted.sum()),
        "n_rejected": int(rejected.sum()),
        "n_order_errors": int(wrong.sum()),
        "n_order_errors_accepted": int((wrong & accepted).sum()),
        "n_order_errors_rejected": int((wrong & rejected).sum()),
        "n_rejected_correct_order": int((rejected & ~wrong).sum()),
        "rejected_fraction": frac(rejected.sum()),
        "order_error_fraction": frac((wrong & accepted).sum()),
        "order_error_fraction_before_rejection": frac(wrong.sum()),
        "rejected_correct_order_fraction": frac((rejected & ~wrong).sum()),
        "order_errors_caught_fraction": (float((wrong & rejected).sum()) / wrong.sum()) if wrong.any() else None,
    }
    incl, excl = error_stats(err[accepted]), error_stats(err[ok])
    for key in ("rmse_mm", "mean_mm", "p99_abs_mm", "max_abs_mm"):
        out[f"{key}_incl_order_errors"] = incl[key]
        out[f"{key}_excl_order_errors"] = excl[key]
    fx = float(np.asarray(rig["camera"]["K"], float)[0, 0]) if "camera" in rig else 1.0
    edge = _edge_region(valid, np.asarray(arrays.get("depth", h), np.float64), fx, edge_px)
    e_edge, e_int = error_stats(err[ok & edge]), error_stats(err[ok & ~edge])
    out.update({"n_edge": e_edge["n"], "n_interior": e_int["n"],
                "rmse_mm_edge_excl_order_errors": e_edge["rmse_mm"],
                "rmse_mm_interior_excl_order_errors": e_int["rmse_mm"],
                "p99_abs_mm_interior_excl_order_errors": e_int["p99_abs_mm"]})

    if stacks is not None and freqs:
        if min_modulation is None:
            min_modulation = inspect.signature(psp_decode).parameters["min_modulation"].default
        dec = psp.decode_stacks(stacks, None, tuple(freqs), min_modulation=min_modulation)
        low_mod = valid & ~dec.quality
        flagged = valid & ~dec.reliable
        inconsistent = valid & dec.quality & dec.reliable & ~dec.consistent
        other = rejected & ~low_mod & ~flagged & ~inconsistent
        out.update({
            "min_modulation": float(min_modulation),
            "n_low_modulation": int(low_mod.sum()),
            "n_flagged_unreliable": int(flagged.sum()),
            "n_flagged_unreliable_wrong": int((flagged & wrong).sum()),
            "n_flagged_unreliable_correct": int((flagged & ~wrong).sum()),
            "n_order_inconsistent": int(inconsistent.sum()),
            "n_order_inconsistent_wrong": int((inconsistent & wrong).sum()),
            "n_rejected_other": int(other.sum()),
        })
        out.update(breakdown_fractions(out))
    if with_errors:
        out["_maps"] = {"error_mm": err, "valid": valid, "accepted": accepted, "wrong": wrong, "edge": edge}
    return out


BREAKDOWN = ("low_modulation", "flagged_unreliable", "flagged_unreliable_wrong", "flagged_unreliable_correct",
              "order_inconsistent", "order_inconsistent_wrong", "rejected_other")


def breakdown_fractions(c: dict) -> dict:
    nv = c["n_valid_with_images"] if "n_valid_with_images" in c else c["n_valid"]
    return {f"{k}_fraction": (c[f"n_{k}"] / nv if nv else None) for k in BREAKDOWN}


