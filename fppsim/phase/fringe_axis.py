"""Fringes in either direction: which way an image's fringes run, and the single-shot phase of either.

:func:`fppsim.phase.single_shot.single_shot_phase` works along image rows (its shadow detector follows rows,
its carrier has a positive column frequency): right for vertical fringes (a projector beside the
camera). A projector above or below the camera gives horizontal fringes; :func:`oriented_single_shot_phase`
then runs it on the transposed image and transposes the result back, so the phase grows down the rows
(``direction=+1``) instead of along them. :func:`fringe_orientation` tells the two apart from the
image's spectrum, :func:`rig_phase_gradient` from a rig's forward model.

Units: pixels, radians, cycles per pixel.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fppsim.phase.single_shot import SingleShotPhase, single_shot_phase
from fppsim.errors import InputError

__all__ = ["fringe_orientation", "fringe_carrier", "fringe_axis", "rig_phase_gradient", "oriented_single_shot_phase",
           "local_carrier"]


def fringe_orientation(image: np.ndarray, valid: np.ndarray | None = None) -> str:
    """``"vertical"`` when the fringes of ``image`` (2-D) run down the image (their phase changes along
    the rows), ``"horizontal"`` when they run across it: the strongest peak of the mean-removed,
    Hann-windowed 2-D spectrum between periods of 2.5 and 64 px. ValueError without any fringe."""
    x = np.asarray(image, np.float64)
    if x.ndim == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    ok = np.isfinite(x) if valid is None else (np.asarray(valid, bool) & np.isfinite(x))
    if ok.sum() < 64:
        raise InputError("too few valid pixels to tell the fringe direction")
    g = np.where(ok, x - x[ok].mean(), 0.0)
    h, w = g.shape
    p = np.abs(np.fft.rfft2(g * np.outer(np.hanning(h), np.hanning(w)))) ** 2
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    fr = np.hypot(fx, fy)
    sel = (fr >= 1.0 / 64.0) & (fr <= 1.0 / 2.5)
    if not np.any(p[sel] > 0):
        raise InputError("no fringes found (no spectral peak between 2.5 and 64 px)")
    iy, ix = np.unravel_index(np.argmax(np.where(sel, p, -1.0)), p.shape)
    return "vertical" if abs(fx[0, ix]) >= abs(fy[iy, 0]) else "horizontal"


def fringe_carrier(image: np.ndarray, valid: np.ndarray | None = None, near: float = 0.25) -> tuple[float, float]:
    """The fringes' carrier ``(fx, fy)`` (cycles/px, sign-free: fx >= 0) of ``image`` (2-D) where ``valid``, read so
    that the objects' outline and shading cannot pass for it: the peak of the Hann-windowed spectrum of the
    image less its local mean over the valid pixels, weighted by the frequency squared (the spectrum of the
    image's slope: an outline's and a shading's power falls with frequency), between periods of 2.5 and 64 px;
    then the power-weighted median frequency (and mean direction) within ``near`` of it and 30 deg of its
    direction, which unweighted power decides. The plain spectrum's peak (:func:`fringe_orientation`) is the
    outline's on objects on black: FP672/541's figurine read 34-56 px, the plane's fringes are 10.5 px; this reads
    0.83-1.01 of the plane's period on the three rigs here, with and without their plane (docs/own_rig.md). On a
    few periods it reads short (0.66 / 0.78 / 0.89 / 0.98 of the period across 2 / 2.7 / 4 / 5.5 of them, 32-64 px
    images). InputError (one line) without any fringe: no valid pixel varies (a blank or saturated image, whose
    round-off read as a 63 px or 2.8 px carrier), fewer than 64 valid pixels, or an image not 2-D or under 16 px a
    side."""
    from scipy import ndimage as ndi  # SciPy: only here

    x = np.asarray(image, np.float64)
    if x.ndim == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.ndim != 2 or min(x.shape) < 16 or (valid is not None and np.shape(valid) != x.shape):
        raise InputError(f"the fringe carrier is read on a 2-D image of 16 px a side or more (and a valid mask of its "
                         f"shape), got {'x'.join(map(str, np.shape(image)))}"
                         + ("" if valid is None else f" (mask {'x'.join(map(str, np.shape(valid)))})"))
    ok = np.isfinite(x) if valid is None else (np.asarray(valid, bool) & np.isfinite(x))
    if ok.sum() < 64:
        raise InputError("too few valid pixels to read the fringe carrier")
    m = ok.astype(np.float64)
    x = np.where(ok, x, 0.0)
    mean = ndi.gaussian_filter(x * m, 8.0) / np.maximum(ndi.gaussian_filter(m, 8.0), 1e-6)  # a lit-only mean
    h, w = x.shape
    g = np.where(ok, x - mean, 0.0)
    if not np.abs(g).max() > 1e-9 * max(1.0, float(np.abs(x).max())):  # only the local mean's round-off left
        raise InputError("no fringes found (the valid pixels are all one level: blank or saturated)")
    g = g * np.outer(np.hanning(h), np.hanning(w))
    p = ndi.gaussian_filter(np.abs(np.fft.rfft2(g, s=(2 * h, 2 * w))) ** 2, 2.0, mode="wrap")  # 2x padded
    fy, fx = np.fft.fftfreq(2 * h)[:, None], np.fft.rfftfreq(2 * w)[None, :]
    fr = np.hypot(fx, fy)
    band = (fr >= 1.0 / 64.0) & (fr <= 1.0 / 2.5)
    if not np.any(p[band] > 0):
        raise InputError("no fringes found (no spectral peak between 2.5 and 64 px)")
    iy, ix = np.unravel_index(np.argmax(np.where(band, p * fr ** 2, -1.0)), p.shape)
    f0, a0 = fr[iy, ix], np.arctan2(fy[iy, 0], fx[0, ix])
    turn = np.abs(np.angle(np.exp(2j * (np.arctan2(fy, fx) - a0)))) / 2.0  # sign-free: 0-90 deg
    sel = band & (np.abs(fr / f0 - 1.0) <= near) & (turn <= np.radians(30.0))
    f, wts = np.broadcast_to(fr, p.shape)[sel], p[sel]
    order = np.argsort(f)
    cum = np.cumsum(wts[order])
    fm = float(f[order][np.searchsorted(cum, 0.5 * cum[-1])])
    z = np.sum(wts * np.exp(2j * np.broadcast_to(np.arctan2(fy, fx), p.shape)[sel]))
    a = float(np.angle(z) / 2.0)  # in (-90, 90] deg: fx >= 0
    return fm * float(np.cos(a)), fm * float(np.sin(a))


def fringe_axis(gradient) -> str:
    """``"vertical"`` fringes (the phase grows along the camera columns) or ``"horizontal"`` (along the
    rows), from the phase gradient ``(g_u, g_v)`` (rad/px), e.g. :func:`rig_phase_gradient`'s."""
    gu, gv = (float(g) for g in gradient)
    return "vertical" if abs(gu) >= abs(gv) else "horizontal"


def rig_phase_gradient(rig) -> tuple[float, float]:
    """``(g_u, g_v)``: the rig's reference-plane phase gradient at the image centre (rad per camera px,
    along columns and rows), from its forward model (:meth:`fppsim.geometry.rig.Rig.phase_at_height`)."""
    cam = rig.camera
    c = np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0])
    uv = np.stack([c + [-1, 0], c + [1, 0], c + [0, -1], c + [0, 1]])
    ph = rig.phase_at_height(0.0, uv)
    return float((ph[1] - ph[0]) / 2.0), float((ph[3] - ph[2]) / 2.0)


def oriented_single_shot_phase(image: np.ndarray, orientation: str | None = None, direction: int = 1,
                               **kw) -> SingleShotPhase:
    """:func:`fppsim.phase.single_shot.single_shot_phase` for fringes in either direction.

    ``orientation``: ``"vertical"`` (the phase grows along +columns for ``direction=+1``) or
    ``"horizontal"`` (along +rows: computed on the transposed image, every map transposed back,
    ``carrier`` given as (fx, fy) of the original image and ``tilt`` the lines' angle from the image's
    horizontal); None: :func:`fringe_orientation`. ``kw`` go to ``single_shot_phase``."""
    x = np.asarray(image)
    if x.ndim == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    if orientation is None:
        orientation = fringe_orientation(x)
    if orientation not in ("vertical", "horizontal"):
        raise InputError(f"orientation must be 'vertical' or 'horizontal', got {orientation!r}")
    if orientation == "vertical":
        return single_shot_phase(x, direction=direction, **kw)
    mask = kw.pop("mask", None)
    r = single_shot_phase(x.T, direction=direction, mask=None if mask is None else np.asarray(mask).T, **kw)
    t = lambda a: np.ascontiguousarray(a.T)  # noqa: E731
    return replace(r, wrapped=t(r.wrapped), reliability=t(r.reliability), error=t(r.error),
                   modulation=t(r.modulation), background=t(r.background), valid=t(r.valid),
                   carrier=(r.carrier[1], r.carrier[0]))


def local_carrier(wrapped: np.ndarray, reliability: np.ndarray, min_reliability: float = 0.5
                  ) -> tuple[float, float, int]:
    """The fringes' period and direction from a wrapped phase's own steps.

    Parameters
    ----------
    wrapped : (H, W) float, a single-shot wrapped phase (rad; NaN = none).
    reliability : (H, W) float in [0, 1]; a pixel counts where it and its right and lower neighbours reach
        ``min_reliability``.

    Returns
    -------
    ``(period_px, angle_rad, count)``: 2 pi over the median magnitude of the phase gradient (one-pixel forward
    steps, wrapped: right for periods over 2 px), the gradient's axis (``atan2(g_v, g_u)`` in (-pi/2, pi/2],
    sign-free: the gradient-weighted mean of the doubled angle, halved), and how many pixels voted (none, or no
    step: NaN, NaN and the count). The phase is only as good as its demodulation: where the spectrum's peak is
    not the fringes' (objects on black), the period read here is the peak's too (FP672 on black: 35-37 px against
    its rig's 10.5), while the axis stays within 12 deg; on the other frames here, with and without their plane,
    the period is 0.91-1.02 of the rig's and the axis within 3 deg (docs/experiments/orders.md, stop 66)."""
    w = np.asarray(wrapped, np.float64)
    ok = np.nan_to_num(np.asarray(reliability, np.float64), nan=0.0) >= min_reliability
    if min(w.shape) < 2:
        return float("nan"), float("nan"), 0
    gu = np.angle(np.exp(1j * (w[:-1, 1:] - w[:-1, :-1])))
    gv = np.angle(np.exp(1j * (w[1:, :-1] - w[:-1, :-1])))
    ok = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & np.isfinite(gu) & np.isfinite(gv)
    gu, gv = gu[ok], gv[ok]
    m = np.hypot(gu, gv)
    if not m.size or not np.median(m) > 0:
        return float("nan"), float("nan"), int(m.size)
    z = np.sum(m * np.exp(2j * np.arctan2(gv, gu)))
    return float(2 * np.pi / np.median(m)), float(np.angle(z) / 2), int(m.size)
