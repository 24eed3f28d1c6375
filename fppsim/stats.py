"""Statistics that compare a synthetic FPP dataset with real figshare-format data.

Used by ``fppsim compare-real REAL_DIR SYN_DIR``: both folders are read with :func:`iter_samples`
(three layouts, see below), every sample is measured with :func:`sample_stats`, the per-sample values
are aggregated by their median (:func:`dataset_stats`) and :func:`format_comparison` prints a
side-by-side table, so a user can tune the rig and optics to their own lab data.

Folder layouts (detected in this order):

(a) figshare: ``f1_80.npy`` (fringe, 8-bit intensity / 127.5 - 1) and ``Z.npy`` (height label), shape
    (N, H, W, 1), (N, H, W) or (H, W); memory-mapped, so large files are cheap to sample;
(b) one real sample: ``fringe_pattern.npy`` + ``height_map.npy`` (2-D, same encoding);
(c) native fppsim: ``manifest.jsonl`` + ``<id>/fringe.png`` (8-bit gray) + ``<id>/arrays.npz``
    (``height`` mm world z, ``mask`` 1 = valid); heights become labels through a
    :class:`fppsim.formats.LabelTransform` (the figshare preset by default).

All three are read by :class:`fppsim.formats.SampleReader`.

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

from typing import Iterator

import numpy as np

from .formats import PRESETS, LabelTransform, SampleReader

__all__ = [
    "open_dataset",
    "iter_samples",
    "estimate_period",
    "quarter_periods",
    "fringe_modulation",
    "fringe_tilt",
    "plane_level",
    "sample_stats",
    "dataset_stats",
    "compare_real",
    "format_comparison",
    "STAT_ROWS",
]

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


# --------------------------------------------------------------------------- readers


def open_dataset(folder, label: LabelTransform = FIGSHARE) -> SampleReader:
    """Detect the layout of ``folder`` and open it (arrays memory-mapped); ValueError if unreadable.

    ``label`` turns native heights (mm) into labels; figshare-format folders already hold labels.
    """
    return SampleReader(folder, label)


def _pick(n: int, max_samples: int | None) -> np.ndarray:
    """Evenly spaced sample indices (all when max_samples is None or >= n)."""
    if max_samples is None or max_samples >= n:
        return np.arange(n)
    if max_samples < 1:
        raise ValueError(f"max_samples must be >= 1, got {max_samples}")
    return np.unique(np.linspace(0, n - 1, max_samples).round().astype(int))


def iter_samples(folder, max_samples: int | None = None,
                 label: LabelTransform = FIGSHARE) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (gray uint8 (H, W), label float32 (H, W)) for up to max_samples evenly spaced samples."""
    ds = folder if isinstance(folder, SampleReader) else open_dataset(folder, label)
    for i in _pick(len(ds), max_samples):
        yield ds.sample(int(i))


# --------------------------------------------------------------------------- fringe measurements


def _rows_for_fft(gray: np.ndarray, valid: np.ndarray | None, min_valid: float = 0.5):
    """Rows (float64) with the invalid pixels replaced by the row's valid mean; and which rows to use."""
    x = np.asarray(gray, np.float64)
    if valid is None:
        valid = np.ones(x.shape, bool)
    nv = valid.sum(axis=1)
    mean = np.where(nv > 0, (x * valid).sum(axis=1) / np.maximum(nv, 1), 0.0)
    x = np.where(valid, x, mean[:, None])
    use = nv >= min_valid * x.shape[1]
    if not use.any():
        use = nv >= max(8, int(nv.max() * 0.5)) if nv.max() > 0 else use
    return x - mean[:, None], use


def estimate_period(gray: np.ndarray, valid: np.ndarray | None = None, min_period: float = 2.5,
                    max_period: float = 64.0, pad: int = 16) -> float:
    """Dominant horizontal fringe period in pixels (vertical fringes), NaN if it cannot be measured.

    Each row (invalid pixels set to the row's valid mean) is mean-removed, Hann-windowed and
    zero-padded to ``pad`` x its length; the power spectra of the rows with at least half of their
    pixels valid are summed, the peak between ``max_period`` and ``min_period`` is located and refined
    by a parabola through the log-power of its neighbours.
    """
    x, use = _rows_for_fft(gray, valid)
    if not use.any():
        return float("nan")
    x = x[use]
    w = x.shape[1]
    if w < 16:
        return float("nan")
    nfft = int(2 ** np.ceil(np.log2(w * pad)))
    power = (np.abs(np.fft.rfft(x * np.hanning(w), n=nfft, axis=1)) ** 2).sum(axis=0)
    k_lo = max(int(np.floor(nfft / min(max_period, w / 2.0))), 1)
    k_hi = min(int(np.ceil(nfft / min_period)), len(power) - 2)
    if k_hi <= k_lo + 1:
        return float("nan")
    k = k_lo + int(np.argmax(power[k_lo:k_hi + 1]))
    if k <= k_lo or k >= k_hi or power[k] <= 0:
        return float("nan")  # peak at the edge of the search band: no fringe there
    a, b, c = np.log(power[k - 1:k + 2] + 1e-300)
    den = a - 2 * b + c
    delta = 0.5 * (a - c) / den if den < 0 else 0.0
    return float(nfft / (k + delta))


def quarter_periods(gray: np.ndarray, valid: np.ndarray | None = None, **kw) -> np.ndarray:
    """Periods of the four image quarters (top-left, top-right, bottom-left, bottom-right)."""
    h, w = gray.shape
    out = []
    for rs in (slice(0, h // 2), slice(h // 2, h)):
        for cs in (slice(0, w // 2), slice(w // 2, w)):
            out.append(estimate_period(gray[rs, cs], None if valid is None else valid[rs, cs], **kw))
    return np.array(out)


def fringe_modulation(gray: np.ndarray, period: float, valid: np.ndarray | None = None,
                      band: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel fringe amplitude B and background A (gray levels) of I = A + B cos(phi).

    Along each row: B = 2 |analytic signal| of the band [(1-band) f0, (1+band) f0] around the fringe
    frequency f0 = 1/period (positive frequencies only, i.e. the Hilbert envelope of the band-passed
    row); A = the row low-passed below (1-band) f0.  Invalid pixels are filled with the row mean first.
    """
    analytic, background = _analytic_rows(gray, period, valid, band)
    return 2.0 * np.abs(analytic), background


def fringe_tilt(gray: np.ndarray, period: float, mask: np.ndarray | None = None, band: float = 0.5) -> float:
    """Angle of the fringe lines from the image's vertical, degrees: positive when a line leans to the
    right going down the image (``atan(du/dv)`` along a line of constant phase).

    From the rows' analytic signals (as :func:`fringe_modulation`): the phase gradients along rows
    (``g_u``) and down columns (``g_v``), each from the angle of neighbouring samples' product (no
    unwrapping), give ``du/dv = -g_v / g_u``; the median over ``mask`` (e.g. the reference plane, where
    the fringes are the rig's own) is returned, NaN with fewer than 100 usable pixels. The real
    figshare pair: about -1.35 deg; a rig whose projector is not rolled: 0.
    """
    x = np.asarray(gray, np.float64)
    m = np.ones(x.shape, bool) if mask is None else np.asarray(mask, bool)
    a, _ = _analytic_rows(x, period, m, band)
    gu = np.angle(a[:-1, 1:] * np.conj(a[:-1, :-1]))
    gv = np.angle(a[1:, :-1] * np.conj(a[:-1, :-1]))
    ok = m[:-1, :-1] & m[1:, :-1] & m[:-1, 1:] & (np.abs(gu) > 0.25 * 2 * np.pi / period)
    if ok.sum() < 100:
        return float("nan")
    return float(np.degrees(np.arctan(np.median(-gv[ok] / gu[ok]))))


def _analytic_rows(gray, period, valid, band):
    x0 = np.asarray(gray, np.float64)
    h, w = x0.shape
    if valid is None:
        valid = np.ones(x0.shape, bool)
    nv = valid.sum(axis=1)
    mean = np.where(nv > 0, (x0 * valid).sum(axis=1) / np.maximum(nv, 1), 0.0)
    x = np.where(valid, x0, mean[:, None])
    # reflect-pad to reduce edge effects of the circular FFT
    padw = min(w - 1, int(np.ceil(3 * period)))
    xp = np.pad(x, ((0, 0), (padw, padw)), mode="reflect")
    n = xp.shape[1]
    spec = np.fft.fft(xp, axis=1)
    f = np.fft.fftfreq(n)
    f0 = 1.0 / period
    sel = (f >= (1 - band) * f0) & (f <= (1 + band) * f0)
    low = np.abs(f) < (1 - band) * f0
    analytic = np.fft.ifft(spec * sel, axis=1)[:, padw:padw + w]
    background = np.fft.ifft(spec * low, axis=1).real[:, padw:padw + w]
    return analytic, background


def plane_level(label: np.ndarray, valid: np.ndarray, bin_width: float = 0.5, window: float = 6.0) -> float:
    """Label of the reference plane: the mode of the valid labels, refined by the median within +-window."""
    v = np.asarray(label, np.float64)[valid]
    if v.size == 0:
        return float("nan")
    lo, hi = np.floor(v.min()), np.ceil(v.max()) + bin_width
    hist, edges = np.histogram(v, bins=max(1, int(np.ceil((hi - lo) / bin_width))), range=(lo, hi))
    # smooth the histogram a little so a tilted plane still has one clear mode
    hist = np.convolve(hist, np.ones(5) / 5.0, mode="same")
    mode = 0.5 * (edges[np.argmax(hist)] + edges[np.argmax(hist) + 1])
    near = v[np.abs(v - mode) <= window]
    return float(np.median(near)) if near.size else float(mode)


def sample_stats(gray: np.ndarray, label: np.ndarray, transform: LabelTransform = FIGSHARE,
                 object_mm: float = 2.0) -> dict:
    """All statistics of one sample (gray uint8 (H, W), label float (H, W)); see the module docstring."""
    gray = np.asarray(gray)
    label = np.asarray(label, np.float32)
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
    ds = open_dataset(folder, label)
    per, shape = [], None
    for gray, lab in iter_samples(ds, max_samples):
        shape = list(gray.shape)
        per.append(sample_stats(gray, lab, label, object_mm=object_mm))
    if not per:
        raise ValueError(f"{folder}: the dataset is empty")
    keys = list(per[0])
    stats, spread = {}, {}
    for k in keys:
        vals = np.array([p[k] for p in per], np.float64)
        fin = vals[np.isfinite(vals)]
        stats[k] = float(np.median(fin)) if fin.size else float("nan")
        spread[k] = [float(fin.min()), float(fin.max())] if fin.size else [float("nan")] * 2
    return {"path": str(folder), "layout": ds.layout, "n_total": len(ds), "n_samples": len(per),
            "shape": shape, "stats": stats, "spread": spread, "per_sample": per}


def compare_real(real_dir, syn_dir, max_samples: int | None = 50, label: LabelTransform = FIGSHARE,
                 object_mm: float = 2.0) -> dict:
    """Statistics of a real and a synthetic dataset, side by side.

    ``label`` converts native fppsim heights (mm) to labels; figshare-format
    folders already hold labels.  Returns {'real': dataset_stats(...), 'synthetic': dataset_stats(...),
    'difference': {key: synthetic - real}}.
    """
    kw = dict(max_samples=max_samples, label=label, object_mm=object_mm)
    real = dataset_stats(real_dir, **kw)
    syn = dataset_stats(syn_dir, **kw)
    diff = {k: syn["stats"][k] - real["stats"][k] for k in real["stats"]}
    return {"real": real, "synthetic": syn, "difference": diff,
            "preset": {**label.to_dict(), "object_mm": object_mm}}


def _fmt(fmt: str, v) -> str:
    try:
        return "nan" if v is None or not np.isfinite(v) else fmt.format(v)
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
        rows.append([name, _fmt(fmt, r), _fmt(fmt, s), _fmt(dfmt, d)])
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    line = lambda cells: "  ".join(  # noqa: E731
        c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(cells))
    body = [line(cols), "  ".join("-" * w for w in widths)] + [line(r) for r in rows]
    return "\n".join(head + body)
