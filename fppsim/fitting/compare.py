"""Compare a synthetic FPP dataset with real figshare-format data: statistics side by side.

Used by ``fppsim compare-real REAL_DIR SYN_DIR``: both folders are read by their readers
(:func:`fppsim.dataio.readers.open_labelled`, :func:`fppsim.dataio.readers.iter_samples`: any labelled layout,
see below), every sample is measured with
:func:`sample_stats` (the fringe measurements of :mod:`fppsim.phase.measure`), the per-sample values
are aggregated by their median (:func:`dataset_stats`) and :func:`format_comparison` prints a
side-by-side table, so a user can tune the rig and optics to their own lab data.

Folder layouts (recognised by :func:`fppsim.dataio.readers.open_source`; a layout registered there is read too):

(a) figshare: ``f1_80.npy`` (fringe, 8-bit intensity / 127.5 - 1) and ``Z.npy`` (height label), shape
    (N, H, W, 1), (N, H, W) or (H, W); memory-mapped, so large files are cheap to sample;
(b) one real sample: ``fringe_pattern.npy`` + ``height_map.npy`` (2-D, same encoding);
(c) native fppsim: ``manifest.jsonl`` + ``<id>/fringe.png`` (8-bit gray) + ``<id>/arrays.npz``
    (``height`` mm world z, ``mask`` 1 = valid); heights become labels through a
    :class:`fppsim.dataio.formats.LabelTransform` (the figshare preset by default).

All are read through their :class:`fppsim.dataio.readers.Source`.

Statistics per sample (fringe in 8-bit gray levels, labels in label units):

- ``period_px``: fringe period from the dominant horizontal frequency (Hann-windowed, zero-padded row
  FFTs with the power summed over rows, parabolic peak interpolation); ``period_q_min_px`` /
  ``period_q_max_px``: the same in each image quarter, min and max over the four;
  ``period_left_px`` / ``period_right_px``: the left and right halves (a converging rig shows a trend);
- ``intensity_p1/p50/p99``: gray-level percentiles over all pixels; ``intensity_valid_p50``: median over
  valid pixels;
- ``modulation_gray``: median fringe amplitude B (I = A + B cos phi) over valid pixels, from a band-pass
  around the fringe frequency along rows (analytic signal, i.e. the Hilbert envelope); ``contrast``: median
  B / A with A the low-passed background; ``plane_modulation_lr``: the median B on the reference plane
  (valid pixels within ``object_mm`` of the plane level) in the right quarter of the image over the left
  quarter: how the projector's light falls across the plane (the real figshare pair: about 1.14);
  ``fringe_tilt_deg``: the fringe lines' angle from vertical on the plane (:func:`fringe_tilt`; the
  real pair: about -1.35);
- ``invalid_fraction``: label == invalid marker; ``below_threshold_fraction``: label <= -100 (the reference
  evaluation's invalid rule);
- ``height_p1/p50/p99``: label percentiles over pixels that are not the invalid marker;
- ``plane_level``: label of the reference plane (histogram mode, refined by a local median);
  ``object_fraction``: pixels with label > plane + object_mm * units_per_mm; ``relief_p99_mm``: 99th percentile
  of the object pixels' height above the plane, in mm.
"""

from __future__ import annotations

import json
import os

import numpy as np

from fppsim.dataio.encoding import json_default
from fppsim.files import JSON_SUFFIXES, Output, atomic_write_text, check_outputs, holds_keys, json_text
from fppsim.dataio.formats import PRESETS, LabelTransform
from fppsim.phase.measure import estimate_period, fringe_modulation, fringe_tilt, quarter_periods
from fppsim.phase.fringe_axis import fringe_orientation
from fppsim.phase.plane import plane_level
from fppsim.dataio.readers import iter_samples, open_labelled
from fppsim.errors import InputError

__all__ = ["sample_stats", "dataset_stats", "compare_real", "format_comparison", "format_value", "STAT_ROWS"]

FIGSHARE = PRESETS["figshare"]

# (key, label in the table, number format)
STAT_ROWS: list[tuple[str, str, str]] = [
    ("period_px", "fringe period (px)", "{:.2f}"),
    ("period_q_min_px", "  period, min over quarters", "{:.2f}"),
    ("period_q_max_px", "  period, max over quarters", "{:.2f}"),
    ("period_left_px", "  period, left half", "{:.2f}"),
    ("period_right_px", "  period, right half", "{:.2f}"),
    ("intensity_p1", "intensity p1 (8-bit)", "{:.1f}"),
    ("intensity_p50", "intensity p50 (8-bit)", "{:.1f}"),
    ("intensity_p99", "intensity p99 (8-bit)", "{:.1f}"),
    ("intensity_valid_p50", "intensity p50, valid px", "{:.1f}"),
    ("modulation_gray", "fringe modulation B (gray)", "{:.1f}"),
    ("contrast", "fringe contrast B/A", "{:.3f}"),
    ("plane_modulation_lr", "  plane modulation, right/left", "{:.2f}"),
    ("fringe_tilt_deg", "fringe tilt on the plane (deg)", "{:.2f}"),
    ("invalid_fraction", "invalid fraction (marker)", "{:.2%}"),
    ("below_threshold_fraction", "fraction label <= -100", "{:.2%}"),
    ("height_p1", "height p1 (label)", "{:.1f}"),
    ("height_p50", "height p50 (label)", "{:.1f}"),
    ("height_p99", "height p99 (label)", "{:.1f}"),
    ("plane_level", "plane level (label)", "{:.1f}"),
    ("object_fraction", "object coverage", "{:.2%}"),
    ("relief_p99_mm", "relief p99 above plane (mm)", "{:.1f}"),
]


def sample_stats(gray: np.ndarray, label: np.ndarray, transform: LabelTransform = FIGSHARE,
                 object_mm: float = 2.0) -> dict:
    """All statistics of one sample (gray uint8 (H, W), label float (H, W)); see the module docstring.
    Horizontal fringes are measured on the transposed image (the fringe measurements run along rows), so
    "left" / "right" are then the top and the bottom."""
    gray = np.asarray(gray)
    label = np.asarray(label, np.float32)
    try:
        if fringe_orientation(gray) == "horizontal":
            gray, label = gray.T, label.T
    except ValueError:  # no fringe at all: the statistics say so (NaN periods)
        pass
    scale, invalid, threshold = transform.units_per_mm, transform.invalid_value, transform.invalid_threshold
    marker = np.isclose(label, invalid, atol=1e-4, rtol=0) | ~np.isfinite(label)
    valid = ~marker
    g = gray.astype(np.float64)
    period = estimate_period(g, valid)
    qs = quarter_periods(g, valid)
    out = {
        "period_px": period,
        "period_q_min_px": float(np.nanmin(qs)) if np.isfinite(qs).any() else float("nan"),
        "period_q_max_px": float(np.nanmax(qs)) if np.isfinite(qs).any() else float("nan"),
        "period_left_px": estimate_period(g[:, : g.shape[1] // 2], valid[:, : g.shape[1] // 2]),
        "period_right_px": estimate_period(g[:, g.shape[1] // 2:], valid[:, g.shape[1] // 2:]),
    }
    p1, p50, p99 = np.percentile(g, [1, 50, 99])
    out.update(intensity_p1=float(p1), intensity_p50=float(p50), intensity_p99=float(p99))
    out["intensity_valid_p50"] = float(np.median(g[valid])) if valid.any() else float("nan")
    if np.isfinite(period) and valid.any():
        b, a = fringe_modulation(g, period, valid)
        out["modulation_gray"] = float(np.median(b[valid]))
        ok = valid & (a > 1.0)
        out["contrast"] = float(np.median(b[ok] / a[ok])) if ok.any() else float("nan")
    else:
        b = None
        out["modulation_gray"] = out["contrast"] = float("nan")
    out["plane_modulation_lr"] = out["fringe_tilt_deg"] = float("nan")
    out["invalid_fraction"] = float(marker.mean())
    out["below_threshold_fraction"] = float((label <= threshold).mean())
    if valid.any():
        h1, h50, h99 = np.percentile(label[valid].astype(np.float64), [1, 50, 99])
        plane = plane_level(label, valid)
        obj = valid & (label > plane + object_mm * scale)
        above = (label[obj].astype(np.float64) - plane) / scale
        if b is not None:
            on_plane = valid & (np.abs(label - plane) <= object_mm * scale)
            q = g.shape[1] // 4
            left, right = b[:, :q][on_plane[:, :q]], b[:, -q:][on_plane[:, -q:]]
            if left.size >= 100 and right.size >= 100:
                out["plane_modulation_lr"] = float(np.median(right) / max(np.median(left), 1e-9))
            out["fringe_tilt_deg"] = fringe_tilt(g, period, on_plane)
        out.update(height_p1=float(h1), height_p50=float(h50), height_p99=float(h99), plane_level=plane,
                   object_fraction=float(obj.mean()),
                   relief_p99_mm=float(np.percentile(above, 99)) if above.size else 0.0)
    else:
        out.update({k: float("nan") for k in ("height_p1", "height_p50", "height_p99", "plane_level",
                                               "relief_p99_mm")})
        out["object_fraction"] = 0.0
    return out


# --------------------------------------------------------------------------- datasets


def dataset_stats(folder, max_samples: int | None = 50, label: LabelTransform = FIGSHARE,
                  object_mm: float = 2.0) -> dict:
    """Per-sample statistics of up to max_samples evenly spaced samples, aggregated by the median.

    Returns {'path', 'layout', 'n_total', 'n_samples', 'shape', 'stats': {key: median},
    'spread': {key: [min, max] over samples}, 'per_sample': [dict, ...]}.
    """
    ds = open_labelled(folder, label)
    per, shape = [], None
    for gray, lab in iter_samples(ds, max_samples, label):
        shape = list(gray.shape)
        per.append(sample_stats(gray, lab, label, object_mm=object_mm))
    if not per:
        raise InputError(f"{folder}: the dataset is empty")
    keys = list(per[0])
    stats, spread = {}, {}
    for k in keys:
        vals = np.array([p[k] for p in per], np.float64)
        fin = vals[np.isfinite(vals)]
        stats[k] = float(np.median(fin)) if fin.size else float("nan")
        spread[k] = [float(fin.min()), float(fin.max())] if fin.size else [float("nan")] * 2
    return {"path": str(folder), "layout": ds.layout, "n_total": len(ds.ids()), "n_samples": len(per),
            "shape": shape, "stats": stats, "spread": spread, "per_sample": per}


def compare_real(real_dir, syn_dir, max_samples: int | None = 50, label: LabelTransform = FIGSHARE,
                 object_mm: float = 2.0, json_path: str | os.PathLike | None = None, force: bool = False) -> dict:
    """Statistics of a real and a synthetic dataset, side by side (``fppsim compare-real``).

    ``label`` converts native fppsim heights (mm) to labels; figshare-format
    folders already hold labels.  Returns {'real': dataset_stats(...), 'synthetic': dataset_stats(...),
    'difference': {key: synthetic - real}}, also written to ``json_path`` (atomically) when given; an
    existing ``json_path`` is replaced only with ``force`` (checked before anything is read).
    """
    check_outputs([Output("--json", json_path, JSON_SUFFIXES, "the JSON statistics",
                          holds_keys("real", "synthetic"))], inputs=[real_dir, syn_dir],
                  force=force)
    kw = dict(max_samples=max_samples, label=label, object_mm=object_mm)
    real = dataset_stats(real_dir, **kw)
    syn = dataset_stats(syn_dir, **kw)
    diff = {k: syn["stats"][k] - real["stats"][k] for k in real["stats"]}
    result = {"real": real, "synthetic": syn, "difference": diff,
              "preset": {**label.to_dict(), "object_mm": object_mm}}
    if json_path is not None:
        atomic_write_text(json_path, json_text(result, indent=1, default=json_default))
    return result


def format_value(fmt: str, v, missing: str = "nan") -> str:
    """``fmt.format(v)``, or ``missing`` for a missing or non-finite number (table cells)."""
    try:
        return missing if v is None or not np.isfinite(v) else fmt.format(v)
    except (TypeError, ValueError):
        return str(v)


def format_comparison(result: dict) -> str:
    """A plain-text table: statistic | real | synthetic | synthetic - real (medians over samples)."""
    real, syn = result["real"], result["synthetic"]
    head = [
        f"real:      {real['path']} ({real['layout']}, {real['n_samples']} of {real['n_total']} samples, "
        f"{'x'.join(map(str, real['shape'] or []))})",
        f"synthetic: {syn['path']} ({syn['layout']}, {syn['n_samples']} of {syn['n_total']} samples, "
        f"{'x'.join(map(str, syn['shape'] or []))})",
        "values are medians over samples",
        "",
    ]
    cols = ["statistic", "real", "synthetic", "syn - real"]
    rows = []
    for key, name, fmt in STAT_ROWS:
        if key not in real["stats"]:
            continue
        r, s = real["stats"][key], syn["stats"][key]
        d = result.get("difference", {}).get(key, s - r)
        dfmt = fmt.replace("{:", "{:+") if "%" not in fmt else "{:+.2%}"
        rows.append([name, format_value(fmt, r), format_value(fmt, s), format_value(dfmt, d)])
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    line = lambda cells: "  ".join(  # noqa: E731
        c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(cells))
    body = [line(cols), "  ".join("-" * w for w in widths)] + [line(r) for r in rows]
    return "\n".join(head + body)
