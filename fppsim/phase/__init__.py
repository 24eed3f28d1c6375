"""Phase helpers of both packages (numpy): wrapping, the circular mean and median, masked demodulation.

One convention: a wrapped phase lies in ``(-pi, pi]`` (what ``atan2`` and ``np.angle`` return; the
phase-shifting decode :mod:`fppsim.phase.psp` wraps with :func:`wrap`). :mod:`uhrnet.physics.rig_layer` holds the
torch twins (``wrap``, ``circular_mean``), tested equal. Units: radians.
"""

from __future__ import annotations

import numpy as np

__all__ = ["TWO_PI", "wrap", "mean_phasor", "circular_mean", "circular_median", "lowpass", "demodulate"]

TWO_PI = 2.0 * np.pi


def wrap(phase) -> np.ndarray:
    """Wrap phases (rad) into ``(-pi, pi]`` (float64, NaN stays NaN); values already there are unchanged
    (bit for bit)."""
    p = np.asarray(phase, dtype=np.float64)
    if p.ndim and p.size and p.min() > -np.pi + 1e-9 and p.max() <= np.pi:
        # Already wrapped (and finite): (p - pi) / 2pi then lies in (-1, 0], ceil gives -0.0 or 0.0 and
        # the formula below returns p + 0.0 (the same bits; -0.0 becomes +0.0 there as here).
        return p + 0.0
    w = p - TWO_PI * np.ceil((p - np.pi) / TWO_PI)
    return np.where(w <= -np.pi, w + TWO_PI, np.where(w > np.pi, w - TWO_PI, w))


def mean_phasor(phase, weights=None, mask=None) -> complex:
    """Mean unit phasor ``mean(w e^{i phase})`` over ``mask`` (all pixels when None), weighted by
    ``weights`` (``sum w e^{i phase} / sum w``). Its angle is :func:`circular_mean`, its modulus the
    coherence (1 = all phases equal, about 0 = spread evenly). NaN when nothing is selected."""
    p = np.asarray(phase)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        p = p[m]
        if weights is not None:
            weights = np.asarray(weights)[m]
    if p.size == 0:
        return complex("nan+nanj")
    if weights is None:
        return complex(np.mean(np.exp(1j * p)))
    w = np.asarray(weights, dtype=np.float64)
    return complex(np.sum(w * np.exp(1j * p)) / np.sum(w))


def circular_mean(phase, weights=None, mask=None) -> float:
    """Circular mean (rad, in ``(-pi, pi]``) of ``phase`` over ``mask``, optionally weighted: the angle of
    :func:`mean_phasor`. NaN when nothing is selected."""
    return float(np.angle(mean_phasor(phase, weights, mask)))


def circular_median(angles, candidates: int = 256, max_samples: int = 20000) -> float:
    """Circular median (rad, in ``(-pi, pi]``) of ``angles`` (any shape, NaN ignored): the direction
    minimising the summed arc distance, robust to outliers (unlike :func:`circular_mean`). NaN when no
    angle is finite.

    A coarse search over ``candidates`` directions on at most ``max_samples`` evenly strided angles,
    then the exact median of all angles re-centred on the best candidate (the arc distance is then
    the ordinary absolute difference).
    """
    a = np.asarray(angles, dtype=np.float64).ravel()
    a = a[np.isfinite(a)]
    if a.size == 0:
        return float("nan")
    sample = a[:: max(1, a.size // int(max_samples))]
    cands = np.linspace(-np.pi, np.pi, int(candidates), endpoint=False)
    cost = [np.abs(wrap(sample - c)).sum() for c in cands]
    c0 = cands[int(np.argmin(cost))]
    return float(wrap(c0 + np.median(wrap(a - c0))))


def lowpass(z: np.ndarray, sigma: float, weights=None, mode: str = "reflect") -> np.ndarray:
    """Gaussian low-pass (sigma in px) of a complex field, ``G[w z]`` (real and imaginary parts
    filtered separately; ``weights`` (H, W), e.g. a validity mask, multiply before filtering, not
    normalised). ``mode``: scipy.ndimage's border mode."""
    from scipy import ndimage as ndi  # optional heavy dependency (SciPy)

    re, im = (z.real, z.imag) if weights is None else (z.real * weights, z.imag * weights)
    return ndi.gaussian_filter(re, sigma, mode=mode) + 1j * ndi.gaussian_filter(im, sigma, mode=mode)


def demodulate(signal: np.ndarray, phase: np.ndarray, sigma: float, weights=None, mode: str = "reflect") -> np.ndarray:
    """Masked demodulation: :func:`lowpass` of ``signal e^{-i phase}`` (complex (H, W)); its angle is the
    phase of ``signal`` relative to ``phase`` (positive where the signal is ahead), low-passed over
    ``sigma`` px and the pixels ``weights`` select."""
    return lowpass(np.asarray(signal) * np.exp(-1j * np.asarray(phase)), sigma, weights, mode)
