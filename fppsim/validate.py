"""`fppsim validate-psp`: how far is phase-shifting (PSP) "ground truth" from the exact geometry?

Real FPP datasets label their images with the height a multi-frequency PSP measurement gives. The
simulator knows the exact height, so it can measure the error of that PSP ground truth: for every
sample the PSP height (``height_psp``, decoded from the rendered 8-bit phase-shifted images, see
:func:`fppsim.synth.psp_decode`) is compared with the exact height on the pixels the exact mask calls
valid (seen and lit by the projector).

Pixel classes (all over the exact-valid pixels ``V``; fractions are relative to ``|V|``)
-----------------------------------------------------------------------------------------
* accepted: ``V`` and PSP kept the pixel (``mask_psp`` = 1 and a finite ``height_psp``).
* rejected: ``V`` and PSP did not keep it; split by reason when the PSP images are there
  (re-decoded from ``psp/f{f}_s{n}.png``): low modulation (``B`` below the decoder's
  ``min_modulation``), fringe order flagged unreliable by the unwrapper, other (triangulation).
* order error: ``|phase_psp - phase_true| > pi`` (absolute phase of the highest frequency vs the
  exact projector phase), i.e. a wrong fringe order or an equally gross phase error. Counted on all
  of ``V`` (what the unwrapper got wrong) and on the accepted pixels (what silently ends up in the
  ground truth). The unwrapper flags conservatively, so "rejected" and "wrong" differ: the report
  gives both and their overlap.

Height error statistics (``height_psp - height``, mm) are computed on the accepted pixels, once
including and once excluding the order-error pixels (keys ``*_incl_order_errors`` /
``*_excl_order_errors``), and, excluding order errors, separately for pixels near edges (within
``edge_px`` pixels of an invalid pixel, of a depth discontinuity or of the image border) and for
the interior. A depth discontinuity is a jump between 4-neighbours larger than 4 pixel footprints
(``4 * depth / fx``; surfaces steeper than about 76 degrees to the view count as edges too).

Aggregates pool the pixels of all samples (RMSE = sqrt(sum of squares / count)); the pooled 99th
percentile comes from a log-spaced histogram (0.6 % relative resolution, upper bin edge), per-sample
percentiles are exact. The tool reports numbers only: it has no pass/fail thresholds.

Sweeps
------
``--sweep noise=0,0.5,1,2 gamma=1,2.2`` renders the same scenes (same seed and sample indices; the
scene draws do not depend on the optics) once per combination of the given values -- the full grid,
here 4 x 2 = 8 settings -- with the swept parameters fixed and everything else drawn from the usual
ranges, and tabulates the aggregate error per setting. Names: ``noise`` = ``noise_sigma`` (gray
levels; ``shot_noise`` is then fixed to 0 unless it is swept or given with ``--optics``), ``gamma`` =
``projector_gamma``, ``blur`` = ``projector_blur`` (projector pixels), or any
:class:`fppsim.optics.OpticsRanges` field (``camera_blur``, ``camera_gamma``, ``gain``, ...). Each
setting renders into its own subfolder ``<out>/sweep/<name>/`` so an interrupted sweep resumes.
Within one sweep the other optics draws are identical across settings (a fixed parameter consumes no
random draw in every setting alike), and so is the noise realisation (scaled by the setting).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import DatasetError, ValidateError
from .formats import atomic_path, atomic_write_text, json_default, load_native_sample, read_manifest, read_settings

__all__ = [
    "SWEEP_ALIASES", "DEFAULT_SWEEP", "ValidateError", "resolve_dataset", "evaluate_sample", "validate_dataset",
    "parse_sweep", "sweep_settings", "format_table", "format_sweep_table", "write_error_map",
    "ValidateConfig", "validate_psp",
]

SWEEP_ALIASES = {"noise": "noise_sigma", "gamma": "projector_gamma", "blur": "projector_blur"}
DEFAULT_SWEEP = ("noise=0,0.5,1,2", "gamma=1,2.2")
ORDER_ERROR_RAD = math.pi
_HIST_EDGES = np.concatenate([[0.0], np.logspace(-6, 4, 4001)])  # |error| in mm, 0.58 % per bin


# ====================================================================== input
def resolve_dataset(path) -> Path:
    """The native sample root of a dataset folder (itself, or ``<path>/native`` for figshare output).

    Raises :class:`ValidateError` for a missing folder, an empty one, or one that is not an fppsim dataset.
    """
    p = Path(path)
    if not p.exists():
        raise ValidateError(f"dataset folder not found: {p}")
    if not p.is_dir():
        raise ValidateError(f"not a folder: {p}")
    if not any(p.iterdir()):
        raise ValidateError(f"{p}: empty folder (no samples to validate)")
    if not (p / "manifest.jsonl").is_file() and (p / "native" / "manifest.jsonl").is_file():
        p = p / "native"
    if not (p / "manifest.jsonl").is_file():
        raise ValidateError(f"{p}: not an fppsim dataset folder (no manifest.jsonl)")
    return p


def _records(root: Path) -> list[dict]:
    try:
        records = [r for r in read_manifest(root) if (root / str(r.get("id"))).is_dir()]
    except DatasetError as exc:
        raise ValidateError(str(exc)) from None
    if not records:
        raise ValidateError(f"{root}: no finished samples to validate")
    return records


def _settings(root: Path) -> dict | None:
    try:
        return read_settings(root)
    except DatasetError as exc:
        raise ValidateError(str(exc)) from None


def _load(root: Path, rec: dict) -> tuple[dict, dict | None]:
    """Arrays + meta of one sample and its PSP stacks ``{f: (N, H, W) uint8}`` (None if images are missing)."""
    import cv2

    folder = root / str(rec["id"])
    try:
        s = load_native_sample(folder)
    except (OSError, KeyError, ValueError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValidateError(f"{folder}: unreadable sample ({why})") from None
    psp = s["meta"].get("psp")
    if not psp or "phase_psp" not in s or "height_psp" not in s or "mask_psp" not in s:
        raise ValidateError(f"{root}: no PSP data in sample {rec['id']} (generated with --no-psp?): "
                            "re-generate without --no-psp")
    stacks = {}
    for f in psp["freqs"]:
        imgs = [cv2.imread(str(folder / "psp" / f"f{f}_s{n}.png"), cv2.IMREAD_UNCHANGED) for n in range(psp["steps"])]
        if any(im is None for im in imgs):
            return s, None
        stacks[f] = np.stack(imgs)
    return s, stacks


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


def _stats(e: np.ndarray) -> dict:
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
        :func:`fppsim.synth.psp_decode`.
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
    incl, excl = _stats(err[accepted]), _stats(err[ok])
    for key in ("rmse_mm", "mean_mm", "p99_abs_mm", "max_abs_mm"):
        out[f"{key}_incl_order_errors"] = incl[key]
        out[f"{key}_excl_order_errors"] = excl[key]
    fx = float(np.asarray(rig["camera"]["K"], float)[0, 0]) if "camera" in rig else 1.0
    edge = _edge_region(valid, np.asarray(arrays.get("depth", h), np.float64), fx, edge_px)
    e_edge, e_int = _stats(err[ok & edge]), _stats(err[ok & ~edge])
    out.update({"n_edge": e_edge["n"], "n_interior": e_int["n"],
                "rmse_mm_edge_excl_order_errors": e_edge["rmse_mm"],
                "rmse_mm_interior_excl_order_errors": e_int["rmse_mm"],
                "p99_abs_mm_interior_excl_order_errors": e_int["p99_abs_mm"]})

    if stacks is not None and freqs:
        from . import psp
        from .synth import psp_decode

        if min_modulation is None:
            import inspect

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
        out.update(_breakdown_fractions(out))
    if with_errors:
        out["_maps"] = {"error_mm": err, "valid": valid, "accepted": accepted, "wrong": wrong, "edge": edge}
    return out


_BREAKDOWN = ("low_modulation", "flagged_unreliable", "flagged_unreliable_wrong", "flagged_unreliable_correct",
              "order_inconsistent", "order_inconsistent_wrong", "rejected_other")


def _breakdown_fractions(c: dict) -> dict:
    nv = c["n_valid_with_images"] if "n_valid_with_images" in c else c["n_valid"]
    return {f"{k}_fraction": (c[f"n_{k}"] / nv if nv else None) for k in _BREAKDOWN}


# ====================================================================== aggregation
class _Pool:
    """Pooled statistics over samples (counts, sums of squares, histograms of |error|)."""

    COUNTS = ("n_valid", "n_accepted", "n_rejected", "n_order_errors", "n_order_errors_accepted",
              "n_order_errors_rejected", "n_rejected_correct_order", "n_edge", "n_interior")

    def __init__(self):
        self.counts = dict.fromkeys(self.COUNTS, 0)
        self.breakdown = dict.fromkeys(["n_valid_with_images"] + [f"n_{k}" for k in _BREAKDOWN], 0)
        self.sums = {}   # name -> [n, sum, sum of squares, max |e|]
        self.hist = {}
        self.rmse = []

    def _add(self, name: str, e: np.ndarray, hist: bool = False) -> None:
        s = self.sums.setdefault(name, [0, 0.0, 0.0, 0.0])
        if e.size:
            s[0] += e.size
            s[1] += float(e.sum())
            s[2] += float((e * e).sum())
            s[3] = max(s[3], float(np.abs(e).max()))
        if hist:
            h = np.histogram(np.minimum(np.abs(e), _HIST_EDGES[-1]), _HIST_EDGES)[0]
            self.hist[name] = self.hist.get(name, 0) + h

    def add(self, stats: dict, maps: dict) -> None:
        for k in self.COUNTS:
            self.counts[k] += stats[k]
        if "n_low_modulation" in stats:
            self.breakdown["n_valid_with_images"] += stats["n_valid"]
            for k in _BREAKDOWN:
                self.breakdown[f"n_{k}"] += stats[f"n_{k}"]
        err, acc, wrong, edge = maps["error_mm"], maps["accepted"], maps["wrong"], maps["edge"]
        ok = acc & ~wrong
        self._add("incl", err[acc], hist=True)
        self._add("excl", err[ok], hist=True)
        self._add("edge", err[ok & edge])
        self._add("interior", err[ok & ~edge], hist=True)
        if stats["rmse_mm_incl_order_errors"] is not None:
            self.rmse.append(stats["rmse_mm_incl_order_errors"])

    def _p99(self, name):
        h = self.hist.get(name)
        if h is None or h.sum() == 0:
            return None
        i = int(np.searchsorted(np.cumsum(h), 0.99 * h.sum()))
        return float(_HIST_EDGES[min(i + 1, len(_HIST_EDGES) - 1)])

    def result(self, n_samples: int) -> dict:
        c = self.counts
        nv = c["n_valid"]
        frac = (lambda n: float(n) / nv if nv else None)
        out = {"n_samples": n_samples, **c,
               "rejected_fraction": frac(c["n_rejected"]),
               "order_error_fraction": frac(c["n_order_errors_accepted"]),
               "order_error_fraction_before_rejection": frac(c["n_order_errors"]),
               "rejected_correct_order_fraction": frac(c["n_rejected_correct_order"]),
               "order_errors_caught_fraction": (c["n_order_errors_rejected"] / c["n_order_errors"])
               if c["n_order_errors"] else None}

        def rm(name):
            n, s, ss, mx = self.sums.get(name, [0, 0.0, 0.0, 0.0])
            return (math.sqrt(ss / n), s / n, mx) if n else (None, None, None)

        for tag, name in (("incl_order_errors", "incl"), ("excl_order_errors", "excl")):
            r, m, mx = rm(name)
            out[f"rmse_mm_{tag}"], out[f"mean_mm_{tag}"], out[f"max_abs_mm_{tag}"] = r, m, mx
            out[f"p99_abs_mm_{tag}"] = self._p99(name)
        out["rmse_mm_edge_excl_order_errors"] = rm("edge")[0]
        out["rmse_mm_interior_excl_order_errors"] = rm("interior")[0]
        out["p99_abs_mm_interior_excl_order_errors"] = self._p99("interior")
        if self.breakdown["n_valid_with_images"]:
            out.update(self.breakdown)
            out.update(_breakdown_fractions(self.breakdown))
        r = np.asarray(self.rmse)
        out["per_sample_rmse_mm_incl_order_errors"] = (
            {"mean": float(r.mean()), "median": float(np.median(r)), "min": float(r.min()), "max": float(r.max())}
            if r.size else None)
        return out


# ====================================================================== error map
def write_error_map(path, error_mm: np.ndarray, valid: np.ndarray, accepted: np.ndarray, wrong: np.ndarray,
                    title: str = "", vmax: float | None = None) -> Path:
    """PNG of the PSP height error (mm) with a symmetric colour scale.

    Accepted pixels: colour (``RdBu_r``, +-``vmax``; default the 99th percentile of |error| without order
    errors); order-error pixels magenta, exact-valid pixels PSP rejected grey, pixels outside the exact
    mask (shadow, outside the projector) black.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import colors
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    path = Path(path)
    ok = accepted & ~wrong
    if vmax is None:
        vmax = float(np.percentile(np.abs(error_mm[ok]), 99)) if ok.any() else 1.0
    vmax = max(vmax, 1e-3)
    cmap = matplotlib.colormaps["RdBu_r"]
    norm = colors.Normalize(-vmax, vmax, clip=True)
    rgb = cmap(norm(np.nan_to_num(error_mm)))[..., :3]
    rgb[~valid] = (0.0, 0.0, 0.0)
    rgb[valid & ~accepted] = (0.55, 0.55, 0.55)
    rgb[wrong & accepted] = (1.0, 0.0, 1.0)  # rejected wrong orders stay grey: PSP refused them
    H, W = error_mm.shape
    iw, ih = W / 100.0, H / 100.0  # 1 image pixel = 1 PNG pixel at dpi 100
    fw, fh = iw + 1.3, ih + 0.75
    fig = Figure(figsize=(fw, fh), dpi=100)
    ax = fig.add_axes((0.1 / fw, 0.35 / fh, iw / fw, ih / fh))
    ax.imshow(rgb, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=7)
    cax = fig.add_axes(((iw + 0.25) / fw, 0.35 / fh + 0.1 * ih / fh, 0.12 / fw, 0.8 * ih / fh))
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, extend="both")
    cb.set_label("PSP - exact height (mm)", fontsize=7)
    cb.ax.tick_params(labelsize=6)
    fig.legend(handles=[Patch(color=(1, 0, 1), label="order error"),
                        Patch(color=(0.55, 0.55, 0.55), label="PSP rejected"),
                        Patch(color=(0, 0, 0), label="not valid (exact mask)")],
               loc="lower left", bbox_to_anchor=(0.1 / fw, 0.0), ncol=3, fontsize=7, frameon=False)
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    return path


# ====================================================================== dataset validation
def validate_dataset(dataset, out, maps: bool = True, progress: bool = True, edge_px: int = 3,
                     min_modulation: float | None = None, extra: dict | None = None) -> dict:
    """Validate every sample of a native dataset; write ``<out>/report.json`` (and ``<out>/maps/<id>.png``).

    Returns the report: ``{"dataset", "settings", "analysis", "samples": [...], "aggregate": {...}}``.
    """
    from tqdm import tqdm

    root = resolve_dataset(dataset)
    records = _records(root)
    settings = _settings(root)
    if settings is not None and not (settings.get("config") or {}).get("psp_freqs", [1]):
        raise ValidateError(f"{root}: no PSP data (generated with --no-psp): re-generate without --no-psp")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if maps:
        (out / "maps").mkdir(exist_ok=True)
    pool, samples = _Pool(), []
    used_min_mod = None
    for rec in tqdm(records, desc="validate-psp", unit="sample", disable=not progress, dynamic_ncols=True):
        s, stacks = _load(root, rec)
        meta = s["meta"]
        st = evaluate_sample(s, meta, stacks, edge_px=edge_px, min_modulation=min_modulation, with_errors=True)
        m = st.pop("_maps")
        used_min_mod = st.get("min_modulation", used_min_mod)
        pool.add(st, m)
        sid = str(rec["id"])
        row = {"id": sid, "index": meta.get("index"), "seed": meta.get("seed"), "optics": meta.get("optics"),
               "noise_free": meta.get("noise_free"), **st}
        if maps:
            title = (f"{sid}: RMSE {_fmt(st['rmse_mm_incl_order_errors'])} mm "
                     f"(excl. order errors {_fmt(st['rmse_mm_excl_order_errors'])} mm), "
                     f"{st['n_order_errors_accepted']} order-error px, "
                     f"{_pct(st['rejected_fraction'])} % rejected")
            write_error_map(out / "maps" / f"{sid}.png", m["error_mm"], m["valid"], m["accepted"], m["wrong"], title)
            row["error_map"] = f"maps/{sid}.png"
        samples.append(row)
    report = {
        "tool": "fppsim validate-psp",
        "dataset": str(root.resolve()),
        "settings": settings,
        "analysis": {
            "order_error_rule": "|phase_psp - phase_true| > pi (absolute phase of the highest ladder frequency)",
            "fractions_relative_to": "exact-valid pixels (mask: seen and lit)",
            "height_error": "height_psp - height (mm) on accepted pixels (exact-valid and PSP-valid)",
            "edge_px": edge_px,
            "edge_rule": "within edge_px of an invalid pixel, a depth jump > 4 pixel footprints, or the image border",
            "min_modulation_for_breakdown": used_min_mod,
            "pooled_p99": "from a log-spaced |error| histogram, 0.58 % relative resolution (upper bin edge)",
        },
        **(extra or {}),
        "samples": samples,
        "aggregate": pool.result(len(samples)),
    }
    atomic_write_text(out / "report.json", json.dumps(report, indent=1, default=json_default))
    return report


# ====================================================================== tables
def _fmt(v, spec=".4f"):
    return "-" if v is None else format(v, spec)


def _pct(v):
    return "-" if v is None else f"{100 * v:.3f}"


_COLS = [("RMSE mm", "rmse_mm_incl_order_errors", _fmt), ("RMSE_ok mm", "rmse_mm_excl_order_errors", _fmt),
         ("p99_ok mm", "p99_abs_mm_excl_order_errors", _fmt), ("max_ok mm", "max_abs_mm_excl_order_errors", _fmt),
         ("max mm", "max_abs_mm_incl_order_errors", lambda v: _fmt(v, ".3f")),
         ("order err %", "order_error_fraction", _pct), ("rejected %", "rejected_fraction", _pct)]
_LEGEND = ("RMSE/max: all accepted pixels; *_ok: excluding order errors (|phase_psp - phase_true| > pi); "
           "order err %: accepted pixels with a wrong order; rejected %: exact-valid pixels PSP rejected "
           "(both % of exact-valid pixels)")


def _table(header0: str, rows: list[tuple[str, dict]]) -> str:
    head = [header0, "valid px"] + [c[0] for c in _COLS]
    body = [[name, str(r.get("n_valid", "-"))] + [f(r.get(k)) for _, k, f in _COLS] for name, r in rows]
    widths = [max(len(x[i]) for x in [head] + body) for i in range(len(head))]
    line = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(head), "  ".join("-" * w for w in widths)] + [line(b) for b in body])


def format_table(report: dict, max_rows: int = 20) -> str:
    """Per-sample rows (the first ``max_rows``) and the pooled row of a :func:`validate_dataset` report."""
    samples = report["samples"]
    rows = [(s["id"], s) for s in samples[:max_rows]]
    rows.append((f"all ({len(samples)}, pooled)", report["aggregate"]))
    text = _table("sample", rows)
    if len(samples) > max_rows:
        text += f"\n({len(samples) - max_rows} more samples in report.json)"
    return text + "\n" + _LEGEND


def format_sweep_table(rows: list[dict]) -> str:
    """One pooled row per sweep setting (``rows`` = [{"name", "aggregate"}, ...])."""
    return _table("setting", [(r["name"], r["aggregate"]) for r in rows]) + "\n" + _LEGEND


# ====================================================================== sweep
def _optics_fields() -> dict:
    from .optics import OpticsRanges

    return {f.name: getattr(OpticsRanges(), f.name) for f in fields(OpticsRanges)}


def parse_sweep(items) -> list[tuple[str, list]]:
    """``["noise=0,0.5", "gamma=1,2.2"]`` -> ``[("noise_sigma", [0.0, 0.5]), ("projector_gamma", [1.0, 2.2])]``.

    An empty list means :data:`DEFAULT_SWEEP`. Raises :class:`ValidateError` on unknown names, bad
    values or a name given twice.
    """
    items = list(items) or list(DEFAULT_SWEEP)
    known = _optics_fields()
    out, seen = [], set()
    for item in items:
        key, sep, vals = str(item).partition("=")
        key = key.strip()
        name = SWEEP_ALIASES.get(key, key)
        if not sep or not vals.strip():
            raise ValidateError(f"--sweep expects NAME=V1,V2,..., got '{item}'")
        if name not in known:
            raise ValidateError(f"--sweep: unknown optics parameter '{key}' (use noise, gamma, blur or one of: "
                                f"{', '.join(known)})")
        if name in seen:
            raise ValidateError(f"--sweep: '{key}' given twice")
        seen.add(name)
        values = []
        for v in vals.split(","):
            try:
                x = float(v)
            except ValueError:
                raise ValidateError(f"--sweep {key}: '{v}' is not a number") from None
            if not math.isfinite(x) or x < 0 or (name.endswith("gamma") and x <= 0):
                raise ValidateError(f"--sweep {key}: {v} is out of range (>= 0; gammas > 0)")
            default = known[name]
            if isinstance(default, bool):
                x = bool(x)
            elif isinstance(default, int):
                x = int(round(x))
            if x not in values:
                values.append(x)
        out.append((name, values))
    return out


def sweep_settings(grid: list[tuple[str, list]], base: dict | None = None) -> list[tuple[str, dict]]:
    """All combinations (the grid) as ``(folder_name, {field: value})``.

    ``base`` holds the user's explicit optics overrides; with ``noise_sigma`` swept, ``shot_noise`` is
    fixed to 0 unless swept or overridden.
    """
    base = base or {}
    names = [n for n, _ in grid]
    out = []
    for combo in itertools.product(*(v for _, v in grid)):
        fixed = dict(zip(names, combo))
        if "noise_sigma" in fixed and "shot_noise" not in fixed and "shot_noise" not in base:
            fixed["shot_noise"] = 0.0
        label = "__".join(f"{n}={_num(v)}" for n, v in zip(names, combo))
        out.append((label, fixed))
    return out


def _num(v) -> str:
    return str(v) if isinstance(v, bool) else f"{v:g}"


def _ranges_with(ranges, fixed: dict):
    from .optics import OpticsRanges

    d = ranges.to_dict()
    d.update(fixed)
    return OpticsRanges.from_dict(d)


# ====================================================================== sources
def _config_from_settings(settings: dict):
    """SynthConfig, meshes, seed, noise_free of a dataset's ``dataset.json`` (to re-render its scenes)."""
    from .synth import SynthConfig

    try:
        config = SynthConfig.from_settings(settings)
        return config, list(settings["meshes"]), int(settings["seed"]), bool(settings.get("noise_free", False))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValidateError(f"dataset.json cannot be turned back into generation settings ({exc})") from None


# ====================================================================== the whole command as a function
@dataclass
class ValidateConfig:
    """What ``fppsim validate-psp`` does, checked on construction (:class:`ValidateError`).

    Either ``dataset`` (a generated native folder, or a figshare output with ``native/``) or ``meshes``
    + ``count`` to render a fresh set into ``out/samples`` (the scene fields then apply as in
    :class:`fppsim.generation.GenerateConfig`). ``sweep``: None (no sweep), [] (:data:`DEFAULT_SWEEP`)
    or ``["noise=0,1", ...]``: the full grid of the given optics values, rendered into
    ``out/sweep/<setting>/``. ``edge_px``: width of the edge region for the edge/interior split (0: off).
    """

    out: str | os.PathLike
    dataset: str | os.PathLike | None = None
    meshes: Sequence[str] | None = None
    count: int | None = None
    seed: int = 0
    rig: object = None
    objects: tuple[int, int] = (1, 3)
    optics: dict = field(default_factory=dict)
    noise_free: bool = False
    supersample: int = 1
    psp_steps: int = 4
    psp_freqs: tuple[int, ...] = (1, 8, 80)
    workers: int = 1
    tmp_samples: bool = False
    sweep: Sequence[str] | None = None
    edge_px: int = 3
    maps: bool = True
    progress: bool = True

    def __post_init__(self):
        if self.dataset and self.meshes:
            raise ValidateError("give either a DATASET folder or --meshes, not both")
        if not self.dataset and not self.meshes:
            raise ValidateError("nothing to validate: give a DATASET folder or --meshes PATH... --count N")
        if self.meshes and not self.count:
            raise ValidateError("--meshes needs --count N")
        if self.dataset and (self.count or self.optics or self.noise_free):
            raise ValidateError("--count/--optics/--noise-free only apply with --meshes")
        if self.psp_steps < 3:
            raise ValidateError(f"--psp-steps must be >= 3, got {self.psp_steps}")

    def grid(self) -> list[tuple[str, list]] | None:
        return parse_sweep(self.sweep) if self.sweep is not None else None


def _render(meshes, folder: Path, count: int, seed: int, config, noise_free: bool, workers: int, progress: bool,
            echo) -> None:
    from .generation import generate_dataset

    summary = generate_dataset(meshes, folder, count, seed=seed, config=config, workers=workers,
                               noise_free=noise_free, progress=progress)
    for line in summary.lines():
        echo(line)


def validate_psp(config: ValidateConfig, echo=None) -> dict:
    """Run ``fppsim validate-psp``: validate a dataset, render and validate a fresh set, or a sweep.

    Writes ``out/report.json`` (and maps, samples, sweep folders) and returns the report: the
    :func:`validate_dataset` report, or for a sweep ``{"grid", "rows": [{"name", "setting", "folder",
    "aggregate"}], ...}``. ``echo`` receives progress lines of the rendering runs (None: silent).
    """
    echo = echo or (lambda line: None)
    grid = config.grid()
    out = Path(config.out)
    kw = dict(maps=config.maps, progress=config.progress, edge_px=config.edge_px)
    if config.dataset:
        root = resolve_dataset(config.dataset)
        _records(root)  # fail early on an empty dataset
        settings = _settings(root)
        if grid is None:
            return validate_dataset(root, out, **kw)
        if settings is None:
            raise ValidateError(f"{root}: no dataset.json, so its scenes cannot be re-rendered for --sweep")
        synth, meshes, seed, noise_free = _config_from_settings(settings)
        if not synth.psp_freqs:
            raise ValidateError(f"{root}: no PSP data (generated with --no-psp): re-generate without --no-psp")
        missing = [m for m in meshes if not Path(m).exists()]
        if missing:
            raise ValidateError(f"cannot re-render the dataset's scenes for --sweep: mesh not found: {missing[0]}")
        count = max(int(r["index"]) for r in _records(root)) + 1
        base = {}
    else:
        from .errors import ConfigError
        from .generation import GenerateConfig

        try:
            synth = GenerateConfig(meshes=list(config.meshes), out=out, count=config.count, seed=config.seed,
                                   rig=config.rig, objects=tuple(config.objects), optics=dict(config.optics),
                                   supersample=config.supersample, psp_steps=config.psp_steps,
                                   psp_freqs=tuple(config.psp_freqs)).synth_config()
        except ConfigError as exc:
            raise ValidateError(str(exc)) from None
        base = dict(config.optics)
        meshes, seed, noise_free, count = list(config.meshes), config.seed, config.noise_free, config.count

    if grid is not None and noise_free and any(n in ("noise_sigma", "shot_noise") for n, _ in grid):
        raise ValidateError("a noise sweep needs noise: the dataset/run is noise-free (--noise-free), so every "
                            "setting would render the same images")
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="fppsim-validate-")) if config.tmp_samples else None
    render = dict(workers=config.workers, progress=config.progress, echo=echo)
    try:
        if grid is None:
            samples = (tmp or out) / "samples"
            _render(meshes, samples, count, seed, synth, noise_free, **render)
            return validate_dataset(samples, out, extra={"samples_folder": None if tmp else str(samples)}, **kw)
        rows = []
        settings = sweep_settings(grid, base)
        for i, (name, fixed) in enumerate(settings, 1):
            if config.progress:
                echo(f"sweep {i}/{len(settings)}: {name}")
            cfg = replace(synth, optics=_ranges_with(synth.optics, fixed))
            sub = out / "sweep" / name
            samples = ((tmp / name) if tmp else sub) / "samples"
            _render(meshes, samples, count, seed, cfg, noise_free, **render)
            rep = validate_dataset(samples, sub, extra={"sweep_setting": fixed}, **kw)
            rows.append({"name": name, "setting": fixed, "folder": f"sweep/{name}", "aggregate": rep["aggregate"]})
        sweep_report = {
            "tool": "fppsim validate-psp --sweep",
            "grid": {n: v for n, v in grid},
            "combination": "full grid (every combination of the given values)",
            "seed": seed, "count": count, "meshes": [str(Path(m).resolve()) for m in meshes],
            "noise_free": noise_free, "base_optics_ranges": synth.optics.to_dict(),
            "config": synth.to_dict(), "rig": synth.rig.to_dict(),
            "rows": rows,
        }
        atomic_write_text(out / "report.json", json.dumps(sweep_report, indent=1, default=json_default))
        return sweep_report
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
