"""The reference plane of a height or phase scan: the phase the rig predicts for it, the constant phase
offset that puts a scan's plane at 0 mm, and its level, flatness and tilt.

A wrong rig or phase origin shows on the reference plane first: through the right rig and origin the
plane's pixels triangulate to a flat plane at 0 mm (world z = 0). :mod:`fppsim.fitting.label_real` labels real
scans with these; they serve any height map in millimetres.

Units: millimetres for heights, radians for phases, pixels for images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fppsim.phase.plane import plane_level, poly_basis
from fppsim.geometry.rig import Rig
from fppsim.phase.triangulation import height_from_phase

__all__ = ["PlaneFit", "reference_plane_phase", "plane_flatness", "fit_phase_offset"]


def reference_plane_phase(rig: Rig, periods: float | None = None, z: float = 0.0) -> np.ndarray:
    """Absolute projector phase (rad) the plane at height ``z`` (mm) shows at each camera pixel.

    Parameters
    ----------
    rig : the calibrated rig.
    periods : fringe periods across the projector (default ``rig.periods``).
    z : world height of the plane (mm); 0 = the reference plane.

    Returns
    -------
    float64 (H, W) of the camera: ``2 pi f u_p / W_p`` of the projector column ``u_p`` (projector
    distortion applied) where the camera ray of the pixel meets the plane; NaN where it does not
    (:meth:`fppsim.geometry.rig.Rig.phase_at_height`).
    """
    return rig.phase_at_height(float(z), periods=periods)


@dataclass
class PlaneFit:
    """The reference plane of one height map (see :func:`plane_flatness`).

    level_mm : median height of the plane pixels (mm); 0 when phase origin and rig are right.
    rms_mm : RMS of the plane pixels' heights about 0 mm (level and flatness in one number).
    rms_fit_mm : RMS of the plane pixels about the fitted plane ``a + b x + c y`` (flatness alone).
    tilt_x_mm, tilt_y_mm : rise of the fitted plane across the image width / height (mm).
    share : plane pixels / valid pixels.
    pixels : bool (H, W) plane pixels.
    residual : float64 (H, W) height minus the fitted plane on plane pixels, NaN elsewhere (mm).
    """

    level_mm: float
    rms_mm: float
    rms_fit_mm: float
    tilt_x_mm: float
    tilt_y_mm: float
    share: float
    pixels: np.ndarray = field(repr=False)
    residual: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("level_mm", "rms_mm", "rms_fit_mm", "tilt_x_mm", "tilt_y_mm", "share")}


def plane_flatness(height: np.ndarray, valid: np.ndarray, window_mm: float = 3.0, iterations: int = 3) -> PlaneFit:
    """Find the reference plane of a height map and measure its level, flatness and tilt.

    Parameters
    ----------
    height : float (H, W) heights above the reference plane (mm).
    valid : bool (H, W) pixels with a height.
    window_mm : plane pixels lie within this of the plane (mm).
    iterations : refits of the plane ``a + b x + c y`` on the pixels within ``window_mm`` of the last fit.

    Returns
    -------
    :class:`PlaneFit`. The plane is the dominant flat mode: the histogram mode of the heights
    (:func:`fppsim.phase.plane.plane_level`), then pixels within ``window_mm`` of a least-squares plane,
    refitted ``iterations`` times (a tilted plane is followed; objects above it are left out). All
    numbers are NaN when no plane pixel is found.
    """
    h = np.asarray(height, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(h)
    H, W = h.shape
    nan = float("nan")
    empty = PlaneFit(nan, nan, nan, nan, nan, 0.0, np.zeros((H, W), bool), np.full((H, W), np.nan))
    if not valid.any():
        return empty
    level0 = plane_level(h, valid, bin_width=0.1, window=window_mm)
    basis = poly_basis(H, W, 1).reshape(H, W, 3)  # 1, x, y: pixel coordinates in [-1, 1] (the one plane basis)
    x, y = basis[..., 1], basis[..., 2]
    fit = np.full((H, W), level0)
    coef = np.array([level0, 0.0, 0.0])
    sel = valid & (np.abs(h - fit) < window_mm)
    for _ in range(int(iterations)):
        if sel.sum() < 3:
            break
        coef = np.linalg.lstsq(basis[sel], h[sel], rcond=None)[0]
        fit = coef[0] + coef[1] * x + coef[2] * y
        sel = valid & (np.abs(h - fit) < window_mm)
    if not sel.any():
        return empty
    res = np.where(sel, h - fit, np.nan)
    hp = h[sel]
    return PlaneFit(level_mm=float(np.median(hp)), rms_mm=float(np.sqrt(np.mean(hp ** 2))),
                    rms_fit_mm=float(np.sqrt(np.nanmean(res[sel] ** 2))), tilt_x_mm=float(2 * coef[1]),
                    tilt_y_mm=float(2 * coef[2]), share=float(sel.sum() / valid.sum()), pixels=sel, residual=res)


def fit_phase_offset(phase: np.ndarray, valid: np.ndarray, rig: Rig, periods: float | None = None,
                     window_mm: float = 3.0, iterations: int = 4, plane_phase: np.ndarray | None = None) -> float:
    """Constant phase offset (rad) that puts the scan's reference plane at 0 mm through ``rig``.

    Parameters
    ----------
    phase : float (H, W) absolute phase of the scan (rad); NaN where invalid.
    valid : bool (H, W) pixels with a phase.
    rig, periods : the rig and the phase's fringe periods across the projector (default ``rig.periods``).
    window_mm : plane pixels lie within this height of 0 mm once the offset is applied.
    iterations : refinements (see Notes).
    plane_phase : :func:`reference_plane_phase` of ``rig`` (computed when None).

    Returns
    -------
    offset ``c`` (rad, float) such that ``phase + c`` is the phase the rig predicts for the plane on the
    plane pixels; NaN when no valid pixel exists.

    Notes
    -----
    With ``d = plane_phase - phase`` a plane pixel has ``d = c`` exactly (for a correct rig) and object
    pixels differ from it. Start from the histogram mode of ``d`` (the plane is the dominant flat
    mode), then repeat: triangulate ``phase + c``, take the pixels within ``window_mm`` of 0 mm, set
    ``c`` to the median of their ``d``. A rig that does not fit leaves ``d`` varying over the plane;
    the median then centres it and :func:`plane_flatness` shows the misfit.
    """
    phi = np.asarray(phase, dtype=np.float64)
    f = rig.periods if periods is None else float(periods)
    pp = reference_plane_phase(rig, f) if plane_phase is None else plane_phase
    d = pp - phi
    ok = np.asarray(valid, dtype=bool) & np.isfinite(d)
    if not ok.any():
        return float("nan")
    # the window in radians at the image centre: the phase change of 1 mm of height there
    sens = abs(rig.sensitivity(0.0, 1.0, periods=f))
    sens = sens if math.isfinite(sens) and sens > 0 else 1.0
    c = plane_level(d, ok, bin_width=max(0.02, 0.05 * sens), window=window_mm * sens)
    for _ in range(int(iterations)):
        h = height_from_phase(rig, phi + c, periods=f, mask=ok)
        near = ok & (np.abs(h) < window_mm)
        if not near.any():
            break
        new = float(np.median(d[near]))
        if abs(new - c) < 1e-9:
            c = new
            break
        c = new
    return float(c)
