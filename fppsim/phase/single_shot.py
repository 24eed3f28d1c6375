"""Single-shot phase: the wrapped phase of ONE fringe image and its per-pixel reliability
(:func:`single_shot_phase`, result :class:`SingleShotPhase`); numpy and SciPy.

Fourier-transform profilometry (or per-row analytic signals) followed by local demodulation passes, with
an error model fitted to exact phase; the method's steps are in :func:`single_shot_phase`, its conventions and
measured accuracy below. Units: radians, pixels.

Convention: fppsim renders the single-shot ``fringe.png`` with the pattern ``0.5 + 0.5 cos(2 pi f
u_p / W_p + 0)`` (phase shift 0), so ``wrapped ~ fppsim.phase.wrap(phase_true)``: measured offset
``median wrap(wrapped - phase_true)`` 0.000 rad (sample-to-sample SD 0.001). On the real figshare-rig
frame FP1523/1201 (public layout, absolute phase ``atan2(-PSin, -PCos) + pi + 2 pi Order``):
``wrapped ~ wrap(absolute)`` with an offset of -0.011 rad and the same sign, i.e. the single-shot
image is the public convention's ``A + B cos(Phi)``, and ``wrapped = atan2(PSin, PCos)`` up to noise.

Accuracy (rad, ``|wrap(wrapped - truth - offset)|``, median / 90th / 99th percentile; default settings;
measured 2026-11-24, scenes from ``fppsim generate --meshes ../shared/meshes --count 8 --seed 7``):

================================  ==========================  =======================
data                              pixels                      median / p90 / p99
================================  ==========================  =======================
rendered plain plane (4 images)   all                         0.010 / 0.028 / 0.17
                                  >= 6 px from the border     0.010 / 0.026 / 0.044
rendered scenes (8 images)        reference plane             0.010 / 0.032 / 0.33
                                  object interiors            0.046 / 0.30 / 1.46
                                  edges (< 3 px from a mask   0.40 / 1.88 / 3.0
                                  boundary or a 2 mm step)
                                  all valid (mask)            0.013 / 0.14 / 1.58
                                  reliability > 0.5 (83 %)    0.010 / 0.031 / 0.24
real frame FP1523/1201 vs PSP     all valid                   0.028 / 0.18 / 1.14
                                  < 3 px from invalid         0.55 / 1.71 / 2.8
                                  reliability > 0.5 (82 %)    0.023 / 0.075 / 0.31
================================  ==========================  =======================

Without ``refine`` (plain FTP): object interiors 0.12 / 0.57 / 2.1, real frame 0.033 / 0.23 / 1.25.
``method="rows"``: plane 0.020 (1-D, noisier), objects 0.045, real frame 0.030. A windowed Fourier
ridge (Kemao) tried during development was slower and no better after ``refine`` (objects 0.061).
Shadows are meaningless by construction (reliability 0); edges and phase steps are the limit of any
local method (the window straddles the step) and get low reliability.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fppsim.phase import lowpass
from fppsim.errors import InputError

__all__ = ["SingleShotPhase", "SINGLE_SHOT_METHODS", "single_shot_phase"]

SINGLE_SHOT_METHODS = ("ftp", "rows")

# Phase-error model of single_shot_phase (rad): sqrt(floor^2 + sum (coef * feature)^2), fitted (robust
# least squares on log error) to the method's error against exact phase_true on 8 rendered samples
# (`fppsim generate --seed 7`), checked on the real frame FP1523/1201 against its PSP phase.
_ERR_FLOOR = 0.006
_ERR_COEF = {"noise": 0.069, "curvature": 1.15, "detune": 0.083, "edge": 0.015}


@dataclass
class SingleShotPhase:
    """Result of :func:`single_shot_phase`; all maps are (H, W) like the input image.

    wrapped : float32, rad in ``(-pi, pi]``: the fringe phase ``phi`` of ``I = A + B cos(phi)``, increasing
        along +columns for ``direction=+1``. Defined everywhere (extrapolated into invalid pixels), meaningful
        only where ``valid``.
    reliability : float32 in [0, 1]: ``1 / (1 + (error / error_scale)^2)``, 0 where not ``valid``; 0.5 means
        a predicted error of ``error_scale`` rad.
    error : float32, rad: predicted typical |phase error| (model below); ``pi`` where not ``valid``.
    modulation : float32, fringe amplitude ``B`` in image units (0 where not ``valid``).
    background : float32, fringe background ``A`` in image units (filled smoothly into invalid pixels).
    valid : bool, pixels that carry fringes: inside ``mask``, finite, and not in a run of dark pixels at
        least one period long along the row (projector shadows, the figshare ``-1`` / PSP ``0`` marker).
    period : float, px: carrier period (``1 / |carrier|``, across the fringes).
    tilt : float, degrees: carrier fringe lines' angle from the image vertical, positive when a line leans
        right going down (the convention of :func:`fppsim.phase.measure.fringe_tilt`).
    carrier : (fx, fy) cycles/px of the carrier phase gradient along columns and rows (fx > 0 before
        ``direction`` is applied).
    method : the method used.
    """

    wrapped: np.ndarray
    reliability: np.ndarray
    error: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    valid: np.ndarray
    period: float
    tilt: float
    carrier: tuple[float, float]
    method: str


def single_shot_phase(image: np.ndarray, period: float | None = None, mask: np.ndarray | None = None,
                      method: str = "ftp", *, direction: int = 1, band: tuple[float, float] = (0.7, 1.0),
                      refine: tuple[float, ...] = (0.35, 0.25, 0.25), dark: float = 0.05,
                      error_scale: float = 0.05) -> SingleShotPhase:
    """Wrapped phase and its per-pixel reliability from ONE fringe image (single-shot FPP).

    Parameters
    ----------
    image : (H, W) or (H, W, 1) real array, grey intensity of ``I = A + B cos(phi)``: 8-bit levels, float,
        or the figshare encoding ``8bit / 127.5 - 1`` in [-1, 1] (every step is invariant to an affine
        change of intensity with positive gain, so the three give the same phase). NaN/inf are invalid.
        H, W >= 16.
    period : carrier period in px if known (the search is then limited to +-20 % of it); default: found
        as the peak of the 2-D power spectrum of the background-removed, amplitude-normalised image.
    mask : (H, W) bool, True = usable pixel; default all. Dark runs are removed in any case (``valid``).
    method : ``"ftp"`` (default): Fourier-transform profilometry, 2-D FFT with a smooth elliptical sideband
        window around the carrier (half-widths ``band`` x carrier frequency along and across the carrier);
        ``"rows"``: the analytic signal of each row (1-D band ``band[0]`` x carrier around the carrier).
        Either is followed by the ``refine`` passes.
    direction : +1 (default): the phase increases along +columns (fppsim's rigs and the figshare rig);
        -1: it decreases (the result is conjugated). One image cannot tell the two apart (cos is even).
    band : (along, across) half-widths of the FTP sideband window, in units of the carrier frequency.
    refine : Gaussian sigmas (in carrier periods) of the local demodulation passes, one pass each:
        ``a <- e^{i phi} G_s[(I - A - conj(a)) e^{-i phi}] / G_s[valid]`` (normalised convolution over valid
        pixels). Each pass follows the local fringe frequency wherever the previous phase is close, so
        sloped surfaces whose fringes leave the global band are still demodulated, and invalid pixels
        never enter; removing the conjugate sideband first lets the window shrink to a quarter period.
        ``()`` = the plain FTP / row result.
    dark : a pixel is invalid when it and the whole one-period run left or right of it along its row lie
        below ``min + dark * (p99.5 - min)`` of the image.
    error_scale : rad; the predicted error at which ``reliability`` is 0.5.

    Returns
    -------
    :class:`SingleShotPhase`. Raises ValueError for a non-2-D or too small image, a bad ``method``,
    ``direction`` or ``mask`` shape, or when no carrier is found (no valid pixels, no spectral peak
    between 2.5 and 64 px).

    Notes
    -----
    Steps: (1) pixels with fringes (``valid``); (2) background ``A``: mean over a one-period box along rows
    (which nulls the carrier) and a Gaussian down columns, normalised over valid pixels, filled smoothly
    into invalid ones; ``g = I - A`` is zero outside ``valid`` so holes and borders add no step (no
    ringing); (3) carrier from the spectrum peak (parabolic refinement); (4) sideband / row analytic
    signal ``a ~ (B/2) e^{i phi}`` of ``g`` zero-padded by two periods; (5) ``refine`` passes; (6) the
    error model ``error = sqrt(0.006^2 + (0.069 n)^2 + (1.15 c)^2 + (0.083 d)^2 + (0.015 e)^2)`` rad with
    n = local RMS of the model residual ``I - A - 2 Re(a)`` / B (over half a period), c = |gradient of the
    local fringe frequency| / carrier frequency (px^-1, smoothed over 1 px: phase steps and sharp
    curvature), d = |local frequency vector - carrier| / carrier frequency, e = exp(-distance to an
    invalid pixel or the border / period). The coefficients were fitted to the log error of the default
    method against exact ``phase_true`` on 8 rendered samples; on the real frame the error ranks the
    pixels (Spearman 0.56) but underestimates by about 1.5x (its PSP reference is noisy too).

    Conventions and measured accuracy: the module notes. About 0.4 s for 352 x 640 on one core.
    """
    x, valid = _checked_image(image, mask, method, direction)
    guess = _period_guess(x, valid, period)
    valid &= ~_dark_runs(x, guess, dark)
    if valid.sum() < 64:
        raise InputError("single_shot_phase: fewer than 64 pixels carry fringes")
    bg = _local_background(x, valid, guess)
    g = np.where(valid, x - bg, 0.0)
    fx0, fy0 = _normalised_carrier(g, valid, guess, period)
    f0 = float(np.hypot(fx0, fy0))
    per = 1.0 / f0
    a = _analytic(g, fx0, fy0, per, method, band)
    for s in refine:
        a = _demodulate(g, a, valid, s * per)
    err = _phase_error(g, a, valid, fx0, fy0, per)
    rel = np.where(valid, 1.0 / (1.0 + (err / error_scale) ** 2), 0.0)
    wrapped = np.angle(a)
    if direction < 0:
        wrapped = -wrapped
    return SingleShotPhase(
        wrapped=wrapped.astype(np.float32), reliability=rel.astype(np.float32),
        error=np.where(valid, err, np.pi).astype(np.float32),
        modulation=np.where(valid, 2.0 * np.abs(a), 0.0).astype(np.float32), background=bg.astype(np.float32),
        valid=valid, period=per, tilt=float(np.degrees(np.arctan(-fy0 / fx0))),
        carrier=(direction * fx0, direction * fy0), method=method)


def _checked_image(image: np.ndarray, mask: np.ndarray | None, method: str,
                   direction: int) -> tuple[np.ndarray, np.ndarray]:
    """The image as float64 (NaN/inf set to its finite minimum) and its usable pixels (finite, in ``mask``):
    every argument is checked before any filtering, so a bad call fails fast and says why."""
    x = np.asarray(image)
    if x.ndim == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.ndim != 2 or x.dtype.kind not in "biuf":
        raise InputError(f"single_shot_phase: image must be a 2-D real array, got shape {x.shape} dtype {x.dtype}")
    h, w = x.shape
    if min(h, w) < 16:
        raise InputError(f"single_shot_phase: image {h} x {w} is too small (need at least 16 x 16)")
    if method not in SINGLE_SHOT_METHODS:
        raise InputError(f"single_shot_phase: method must be one of {SINGLE_SHOT_METHODS}, got {method!r}")
    if direction not in (1, -1):
        raise InputError(f"single_shot_phase: direction must be +1 or -1, got {direction!r}")
    x = x.astype(np.float64)
    valid = np.isfinite(x)
    if not valid.any():
        raise InputError("single_shot_phase: no finite pixel")
    x = np.where(valid, x, np.min(x[valid]))  # NaN-free; these pixels stay invalid
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (h, w):
            raise InputError(f"single_shot_phase: mask shape {mask.shape} differs from the image's {(h, w)}")
        valid &= mask
    if not valid.any():
        raise InputError("single_shot_phase: no valid pixel")
    return x, valid


def _period_guess(x: np.ndarray, valid: np.ndarray, period: float | None) -> float:
    """The period that sizes the dark-run and background windows: ``period`` when given, else the spectrum
    peak of the mean-removed image (good enough for windows; the carrier itself is found after them)."""
    if period is None:
        fx0, fy0 = _carrier_peak(np.where(valid, x - x[valid].mean(), 0.0), None)
        return 1.0 / np.hypot(fx0, fy0)
    return float(period)


def _normalised_carrier(g: np.ndarray, valid: np.ndarray, guess: float,
                        period: float | None) -> tuple[float, float]:
    """Carrier (fx, fy) of the background-removed image ``g`` normalised by its local amplitude, so that
    every pixel counts alike in the spectrum, not the bright ones."""
    from scipy import ndimage as ndi
    env = np.sqrt(2.0 * ndi.gaussian_filter(g * g, guess) / np.maximum(ndi.gaussian_filter(valid * 1.0, guess), 1e-6))
    return _carrier_peak(np.where(valid, g / np.maximum(env, 1e-9 * env.max() + 1e-300), 0.0), period)


def _dark_runs(x: np.ndarray, period: float, dark: float) -> np.ndarray:
    """Dark pixels whose one-period run to the left or to the right along the row is all dark, and the dark
    pixels within a quarter period of those (a fringe trough is dark for less than a period along a row)."""
    from scipy import ndimage as ndi
    lo = float(x.min())
    d = (x <= lo + dark * max(float(np.percentile(x, 99.5)) - lo, 1e-12)).astype(np.float64)
    n = max(int(np.ceil(period)), 2)
    k = np.ones(n) / n
    left = ndi.correlate1d(d, k, axis=1, mode="nearest", origin=(n - 1) // 2)  # run ending at the pixel
    right = ndi.correlate1d(d, k, axis=1, mode="nearest", origin=-(n // 2))  # run starting at the pixel
    seeds = (d > 0) & ((left > 1 - 1e-9) | (right > 1 - 1e-9))
    # and the dark pixels within a quarter period of those (the shorter chords at a shadow's top and bottom)
    return seeds | ((d > 0) & ndi.binary_dilation(seeds, iterations=max(1, int(np.ceil(period / 4)))))


def _local_background(x: np.ndarray, valid: np.ndarray, period: float) -> np.ndarray:
    """Fringe background: a one-period box along rows (a zero of its response at the carrier) and a
    Gaussian (period/4) down columns, normalised over valid pixels; filled into the rest at growing scales."""
    from scipy import ndimage as ndi
    half = period / 2.0
    n = int(np.ceil(half + 0.5))
    t = np.arange(-n, n + 1, dtype=np.float64)
    k = np.clip(np.minimum(t + 0.5, half) - np.maximum(t - 0.5, -half), 0.0, None)  # box of width `period`
    k /= k.sum()
    v = valid.astype(np.float64)
    sy = max(period / 4.0, 1.0)
    num = ndi.gaussian_filter1d(ndi.correlate1d(x * v, k, axis=1, mode="constant"), sy, axis=0, mode="constant")
    den = ndi.gaussian_filter1d(ndi.correlate1d(v, k, axis=1, mode="constant"), sy, axis=0, mode="constant")
    have = valid & (den > 0.3)
    out = np.where(have, num / np.maximum(den, 1e-12), 0.0)
    s = period
    while not have.all():
        if s > 4 * max(x.shape):
            out[~have] = out[have].mean() if have.any() else float(x[valid].mean())
            break
        num = ndi.gaussian_filter(out * have, s, mode="constant")
        den = ndi.gaussian_filter(have * 1.0, s, mode="constant")
        new = ~have & (den > 1e-3)
        out[new] = num[new] / den[new]
        have |= new
        s *= 2.0
    return out


def _carrier_peak(g: np.ndarray, period: float | None, min_period: float = 2.5,
                  max_period: float = 64.0) -> tuple[float, float]:
    """(fx, fy) cycles/px of the strongest spectral peak with fx > 0 (Hann window, 4x zero padding,
    parabolic refinement on the log power); within +-20 % of 1/period when given."""
    from scipy import fft as sfft
    h, w = g.shape
    ny, nx = sfft.next_fast_len(4 * h), sfft.next_fast_len(4 * w, real=True)
    p = np.abs(sfft.rfft2(g * np.outer(np.hanning(h), np.hanning(w)), s=(ny, nx))) ** 2
    fy = sfft.fftfreq(ny)[:, None]
    fx = sfft.rfftfreq(nx)[None, :]
    fr = np.hypot(fx, fy)
    sel = (fx > 0) & (fr >= 1.0 / max_period) & (fr <= 1.0 / min_period)
    if period is not None:
        sel &= np.abs(fr * period - 1.0) <= 0.2
    if not sel.any() or not np.any(p[sel] > 0):
        raise InputError("single_shot_phase: no fringe carrier found (no spectral peak between "
                         f"{min_period:g} and {max_period:g} px)")
    iy, ix = np.unravel_index(np.argmax(np.where(sel, p, -1.0)), p.shape)

    def vertex(a, b, c):
        a, b, c = np.log(np.array([a, b, c]) + 1e-300)
        den = a - 2.0 * b + c
        return 0.5 * (a - c) / den if den < 0 else 0.0

    dx = vertex(p[iy, ix - 1], p[iy, ix], p[iy, ix + 1]) if 0 < ix < p.shape[1] - 1 else 0.0
    dy = vertex(p[iy - 1, ix], p[iy, ix], p[(iy + 1) % ny, ix])
    return float((ix + dx) / nx), float(sfft.fftfreq(ny)[iy] + dy / ny)


def _analytic(g: np.ndarray, fx0: float, fy0: float, period: float, method: str,
              band: tuple[float, float]) -> np.ndarray:
    """(B/2) e^{i phi} of the zero-mean fringe g by a sideband filter (ftp) or per row (rows)."""
    from scipy import fft as sfft
    h, w = g.shape
    pad = int(np.ceil(2 * period))
    ny, nx = sfft.next_fast_len(h + 2 * pad), sfft.next_fast_len(w + 2 * pad)
    gp = np.zeros((ny, nx))
    gp[pad:pad + h, pad:pad + w] = g
    f0 = np.hypot(fx0, fy0)
    fx = sfft.fftfreq(nx)[None, :]
    if method == "ftp":
        fy = sfft.fftfreq(ny)[:, None]
        ux, uy = fx0 / f0, fy0 / f0  # unit vector along the carrier
        along = ((fx - fx0) * ux + (fy - fy0) * uy) / (band[0] * f0)
        across = (-(fx - fx0) * uy + (fy - fy0) * ux) / (band[1] * f0)
        r = np.hypot(along, across)
        win = np.where(r <= 0.7, 1.0, np.cos(0.5 * np.pi * np.clip((r - 0.7) / 0.3, 0.0, 1.0)) ** 2)
        a = sfft.ifft2(sfft.fft2(gp) * win)
    else:
        win = np.sqrt(np.clip(1.0 - np.abs(fx / fx0 - 1.0) / band[0], 0.0, 1.0))
        a = sfft.ifft(sfft.fft(gp, axis=1) * win, axis=1)
    return a[pad:pad + h, pad:pad + w]


def _demodulate(g: np.ndarray, a: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """One local demodulation pass (see ``refine`` of :func:`single_shot_phase`)."""
    from scipy import ndimage as ndi
    rot = np.exp(-1j * np.angle(a))
    z = np.where(valid, g - np.conj(a), 0.0) * rot
    wsum = ndi.gaussian_filter(valid * 1.0, sigma, mode="constant")
    return np.conj(rot) * lowpass(z, sigma, mode="constant") / np.maximum(wsum, 1e-6)


def _phase_error(g: np.ndarray, a: np.ndarray, valid: np.ndarray, fx0: float, fy0: float,
                 period: float) -> np.ndarray:
    """The error model of :func:`single_shot_phase` (rad)."""
    from scipy import ndimage as ndi
    f0 = np.hypot(fx0, fy0)
    v = valid * 1.0
    s = max(period / 2.0, 1.0)
    resid = np.where(valid, g - 2.0 * a.real, 0.0)
    rms = np.sqrt(ndi.gaussian_filter(resid ** 2, s, mode="constant") / np.maximum(ndi.gaussian_filter(v, s, mode="constant"), 1e-6))
    noise = rms / np.maximum(2.0 * np.abs(a), 1e-12)
    # local frequency (cycles/px) from neighbour products: no unwrapping
    fxl = np.empty(g.shape)
    fyl = np.empty(g.shape)
    dx = np.angle(a[:, 1:] * np.conj(a[:, :-1])) / (2 * np.pi)
    dy = np.angle(a[1:, :] * np.conj(a[:-1, :])) / (2 * np.pi)
    fxl[:, :-1], fxl[:, -1] = dx, dx[:, -1]
    fyl[:-1, :], fyl[-1, :] = dy, dy[-1, :]
    curv = ndi.gaussian_filter(np.hypot(*np.gradient(fxl)) + np.hypot(*np.gradient(fyl)), 1.0) / f0
    detune = np.hypot(fxl - fx0, fyl - fy0) / f0
    dist = ndi.distance_transform_edt(np.pad(valid, 1))[1:-1, 1:-1]
    edge = np.exp(-dist / period)
    c = _ERR_COEF
    return np.sqrt(_ERR_FLOOR ** 2 + (c["noise"] * noise) ** 2 + (c["curvature"] * curv) ** 2
                   + (c["detune"] * detune) ** 2 + (c["edge"] * edge) ** 2)
