"""Fringe measurements on real and synthetic fringe images: period, modulation, tilt.

:func:`estimate_period` (and per image quarter, :func:`quarter_periods`), the fringe amplitude and
background :func:`fringe_modulation`, and the fringe lines' angle :func:`fringe_tilt`, all along image
rows (vertical fringes); numpy only. ``compare-real``, ``fit-rig`` and ``fit-optics`` measure real and
rendered images with them, so estimator bias cancels.

Units: pixels for periods, degrees for the tilt (as reported); images are 2-D grey arrays (any real
dtype; 8-bit scale unless stated).
"""

from __future__ import annotations

import numpy as np

__all__ = ["estimate_period", "quarter_periods", "fringe_modulation", "fringe_tilt"]


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
