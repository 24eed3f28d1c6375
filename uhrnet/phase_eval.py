"""Calibration-free evaluation of predicted heights against real absolute phase (no height labels).

On a fringe projection rig the absolute phase of a camera pixel is, to a very good approximation,
a smooth function of the pixel position (the reference plane's phase) plus a smooth function of the
height above the plane. Without a calibration the two are unknown, so they are fitted:

    Phi(x, y) ~ sum_{i + j <= d} c_ij x^i y^j  +  a h(x, y)  +  b h(x, y)^2

by least squares over the valid pixels, ``x, y`` being the pixel column / row scaled to [-1, 1] and
``h`` the predicted height in mm. A good height prediction leaves a small residual; a flat prediction
(``h = 0``) leaves the whole relief. Reported (per image):

* ``rmse_rad``: RMSE of the residual phase (rad) over the fitted pixels;
* ``relief_rms_rad``: RMS of the relief phase, the residual of the plane-only fit (``a = b = 0``);
* ``explained``: fraction of the relief phase explained, ``1 - SS_res / SS_relief`` (1 = perfect, 0 = no
  better than a flat predictor, negative impossible for least squares);
* ``a_rad_per_mm, b_rad_per_mm2`` and the plane coefficients; ``rmse_mm_equiv = rmse_rad / |a|``, the
  residual expressed in mm at the fitted phase-per-mm scale (rough: ignores the h^2 term).

``robust=True`` replaces least squares by a few iteratively reweighted (Huber) iterations, which keeps
shadow edges, wrong fringe orders and prediction outliers from dominating; the reported sums are then
over the same pixels, unweighted. Plain numpy; nothing here reads files or imports torch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["PhaseFit", "plane_terms", "fit_phase", "evaluate_phase"]


@dataclass
class PhaseFit:
    """Result of :func:`fit_phase` for one image (see the module docstring for the meaning)."""

    rmse_rad: float
    relief_rms_rad: float
    explained: float
    a_rad_per_mm: float
    b_rad_per_mm2: float
    rmse_mm_equiv: float
    plane_coefficients: list
    plane_terms: list
    pixels: int
    degree: int
    robust: bool

    def to_dict(self) -> dict:
        return asdict(self)


def plane_terms(shape: tuple[int, int], degree: int) -> tuple[np.ndarray, list[str]]:
    """Monomials ``x^i y^j`` (``i + j <= degree``) on an (H, W) grid, x, y scaled to [-1, 1].

    Returns ``(terms (n_terms, H, W) float64, names)``; the first term is the constant.
    """
    if int(degree) != degree or degree < 0:
        raise ValueError(f"plane degree must be an integer >= 0, got {degree!r}")
    h, w = shape
    x = np.linspace(-1.0, 1.0, w) if w > 1 else np.zeros(1)
    y = np.linspace(-1.0, 1.0, h) if h > 1 else np.zeros(1)
    xx, yy = np.meshgrid(x, y)
    terms, names = [], []
    for total in range(int(degree) + 1):
        for j in range(total + 1):
            i = total - j
            terms.append(xx ** i * yy ** j)
            names.append("1" if total == 0 else "".join(p for p in (f"x^{i}" if i else "", f"y^{j}" if j else "") if p)
                         .replace("^1", ""))
    return np.stack(terms), names


def _solve(A: np.ndarray, b: np.ndarray, robust: bool, iterations: int, huber: float) -> np.ndarray:
    """Least squares (or Huber IRLS) coefficients; all-zero columns get coefficient 0."""
    live = np.any(A != 0, axis=0)
    coef = np.zeros(A.shape[1])
    if not live.any():
        return coef
    Al = A[:, live]
    # column scaling keeps lstsq well conditioned when h^2 reaches thousands of mm^2
    scale = np.sqrt((Al * Al).mean(axis=0))
    scale[scale == 0] = 1.0
    As = Al / scale
    sol = np.linalg.lstsq(As, b, rcond=None)[0]
    if robust:
        for _ in range(iterations):
            r = b - As @ sol
            s = 1.4826 * np.median(np.abs(r - np.median(r)))
            if not s > 0:
                break
            k = huber * s
            wgt = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-300))
            sw = np.sqrt(wgt)
            sol = np.linalg.lstsq(As * sw[:, None], b * sw, rcond=None)[0]
    coef[live] = sol / scale
    return coef


def fit_phase(phase: np.ndarray, height_mm: np.ndarray, valid: np.ndarray | None = None, degree: int = 3,
              robust: bool = False, iterations: int = 5, huber: float = 1.345, max_pixels: int | None = 200_000,
              return_residual: bool = False):
    """Fit ``phase ~ plane(x, y) + a h + b h^2`` over valid pixels (see the module docstring).

    Parameters
    ----------
    phase : (H, W) absolute phase, rad (NaN where invalid).
    height_mm : (H, W) predicted height above the reference plane, mm (NaN where the prediction is
        invalid); all zeros is the flat baseline.
    valid : (H, W) bool, pixels to use (also restricted to finite phase and height).
    degree : total degree of the plane polynomial (default 3).
    robust : Huber IRLS (``iterations`` steps, threshold ``huber`` x the MAD scale) instead of plain
        least squares.
    max_pixels : fit on an evenly strided subset of at most this many pixels (None: all); the reported
        statistics use every valid pixel.
    return_residual : also return the (H, W) residual phase map (NaN outside the fitted pixels).

    Returns
    -------
    :class:`PhaseFit` (and the residual map when asked). ValueError when fewer valid pixels than
    unknowns remain.
    """
    phi = np.asarray(phase, dtype=np.float64)
    h = np.asarray(height_mm, dtype=np.float64)
    if phi.ndim != 2 or phi.shape != h.shape:
        raise ValueError(f"phase {phi.shape} and height {h.shape} must be the same 2-D shape")
    ok = np.isfinite(phi) & np.isfinite(h)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    P, names = plane_terms(phi.shape, degree)
    n_unknown = len(names) + 2
    n = int(ok.sum())
    if n < 2 * n_unknown:
        raise ValueError(f"only {n} valid pixels for {n_unknown} unknowns (degree {degree})")
    idx = np.flatnonzero(ok)
    fit_idx = idx if max_pixels is None or n <= max_pixels else idx[:: int(np.ceil(n / max_pixels))]
    Pf = P.reshape(len(names), -1)
    hv = h.ravel()
    b = phi.ravel()

    def design(sel):
        return np.concatenate([Pf[:, sel].T, hv[sel, None], hv[sel, None] ** 2], axis=1)

    A = design(fit_idx)
    coef_plane = _solve(A[:, :-2], b[fit_idx], robust, iterations, huber)
    coef = _solve(A, b[fit_idx], robust, iterations, huber)
    Aall = design(idx)
    relief = b[idx] - Aall[:, :-2] @ coef_plane
    resid = b[idx] - Aall @ coef
    ss_relief = float(np.sum(relief ** 2))
    ss_res = float(np.sum(resid ** 2))
    a = float(coef[-2])
    out = PhaseFit(
        rmse_rad=float(np.sqrt(ss_res / n)), relief_rms_rad=float(np.sqrt(ss_relief / n)),
        explained=float(1.0 - ss_res / ss_relief) if ss_relief > 0 else float("nan"),
        a_rad_per_mm=a, b_rad_per_mm2=float(coef[-1]),
        rmse_mm_equiv=float(np.sqrt(ss_res / n) / abs(a)) if a != 0 else float("nan"),
        plane_coefficients=[float(c) for c in coef[:-2]], plane_terms=names, pixels=n, degree=int(degree),
        robust=bool(robust))
    if not return_residual:
        return out
    res_map = np.full(phi.size, np.nan)
    res_map[idx] = resid
    return out, res_map.reshape(phi.shape)


def evaluate_phase(phase: np.ndarray, height_mm: np.ndarray, valid: np.ndarray | None = None, **kw) -> dict:
    """:func:`fit_phase` for the prediction and for the flat (h = 0) baseline on the same pixels.

    Returns ``{"prediction": PhaseFit dict, "flat": PhaseFit dict, "residual": (H, W) map}``.
    """
    h = np.asarray(height_mm, dtype=np.float64)
    ok = np.isfinite(h) if valid is None else (np.asarray(valid, bool) & np.isfinite(h))
    pred, res = fit_phase(phase, h, ok, return_residual=True, **kw)
    flat = fit_phase(phase, np.zeros_like(h), ok, **kw)
    return {"prediction": pred.to_dict(), "flat": flat.to_dict(), "residual": res}
