"""The reference plane in height, label and phase maps: its level, the one polynomial plane basis of both
packages, and the plane / object pixels of a real phase map.

:func:`plane_level` (the level of the reference plane in a height or label map), :func:`poly_basis` /
:func:`poly_terms` (the polynomial in pixel coordinates every plane fit uses) and
:func:`phase_plane_masks` (plane and object pixels of a real absolute phase map without labels) and
:func:`plane_sides` / :func:`sides_reached` (whether plane pixels reach beyond the view, as a reference plane does:
the one rule of ``fppsim fit-rig`` and ``uhrnet evaluate-phase``); numpy only.

Units: those of the map (mm, label units, radians); pixels for coordinates.
"""

from __future__ import annotations

import numpy as np
from fppsim.errors import InputError

__all__ = ["plane_level", "poly_basis", "poly_terms", "phase_plane_masks", "PLANE_SIDE_SHARE", "PLANE_SIDES",
           "PLANE_SIDE_BAND", "plane_sides", "sides_reached"]


def plane_level(label: np.ndarray, valid: np.ndarray, bin_width: float = 0.5, window: float = 6.0) -> float:
    """Level of the reference plane in a height or label map: the mode of the valid values (histogram
    of ``bin_width`` bins, lightly smoothed), refined by the median of the values within ``window``.

    ``label`` (H, W) float (label units or mm; ``bin_width`` and ``window`` in the same unit), ``valid``
    (H, W) bool. NaN when no pixel is valid.
    """
    v = np.asarray(label, np.float64)[np.asarray(valid, bool)]
    if v.size == 0:
        return float("nan")
    lo, hi = np.floor(v.min()), np.ceil(v.max()) + bin_width
    hist, edges = np.histogram(v, bins=max(1, int(np.ceil((hi - lo) / bin_width))), range=(lo, hi))
    # smooth the histogram a little so a tilted plane still has one clear mode
    hist = np.convolve(hist, np.ones(5) / 5.0, mode="same")
    mode = 0.5 * (edges[np.argmax(hist)] + edges[np.argmax(hist) + 1])
    near = v[np.abs(v - mode) <= window]
    return float(np.median(near)) if near.size else float(mode)


def poly_basis(h: int, w: int, degree: int) -> np.ndarray:
    """The polynomial plane basis: (h*w, n) float64 monomials ``x^i y^j`` (``i + j <= degree``) of the
    pixel coordinates scaled to [-1, 1] (x along columns, y down rows), ordered by total degree, then by
    the power of y (names: :func:`poly_terms`); column 0 is the constant. ValueError for a degree that is
    not an integer >= 0."""
    if int(degree) != degree or degree < 0:
        raise InputError(f"plane degree must be an integer >= 0, got {degree!r}")
    yy, xx = np.mgrid[0:h, 0:w]
    x, y = xx.ravel() / max(w - 1, 1) * 2 - 1, yy.ravel() / max(h - 1, 1) * 2 - 1
    return np.stack([x ** i * y ** j for t in range(int(degree) + 1) for j in range(t + 1) for i in [t - j]], axis=1)

def poly_terms(degree: int) -> list[str]:
    """Names of the :func:`poly_basis` columns: ``["1", "x", "y", "x^2", "xy", "y^2", ...]``."""
    out = []
    for total in range(int(degree) + 1):
        for j in range(total + 1):
            i = total - j
            out.append("1" if total == 0 else "".join(p for p in (f"x^{i}" if i else "", f"y^{j}" if j else "") if p)
                       .replace("^1", ""))
    return out


def phase_plane_masks(phase: np.ndarray, valid: np.ndarray, degree: int = 3, plane_rad: float = 0.3,
                      object_rad: float = 1.0, seed_rad: float = 0.3, grow_rad: float = 0.6, tries: int = 200,
                      window: int = 24, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Reference-plane and object pixels of a real absolute phase map (rad) without labels.

    The plane's phase is one smooth surface across the view; an object's is another, often as smooth
    locally. A polynomial fitted to ALL pixels and trimmed bends towards an object that covers much of the
    view (on FP1523/1201 it called 4 % of the valid pixels plane), so the plane is found by consensus
    first: ``tries`` planes (degree 1) fitted to random ``window``-px squares (``seed``: the draw), the one
    that most pixels follow within ``seed_rad`` taken; its followers are refitted with degrees 1, 2, 3 (up
    to ``degree``), each time keeping the pixels within ``max(3 robust sigmas, grow_rad)``. Plane = final
    residual within ``plane_rad``, object = beyond ``object_rad`` (about 2 mm at the figshare rig's 0.5
    rad/mm). ``phase``, ``valid``: (H, W); returns two (H, W) bool masks (both empty when fewer than
    100 valid pixels).
    """
    h, w = phase.shape
    b = np.asarray(phase, np.float64).ravel()
    use = np.asarray(valid, bool).ravel() & np.isfinite(b)
    if use.sum() < max(100, 4 * len(poly_terms(degree))):
        return np.zeros((h, w), bool), np.zeros((h, w), bool)
    A1 = poly_basis(h, w, 1)
    sub = np.flatnonzero(use)[:: max(1, int(use.sum()) // 20_000)]
    ys, xs = np.divmod(np.flatnonzero(use), w)
    rng = np.random.default_rng(seed)

    def square(k):
        y0, x0 = max(0, ys[k] - window), max(0, xs[k] - window)
        yy, xx = np.mgrid[y0:min(h, ys[k] + window), x0:min(w, xs[k] + window)]
        idx = (yy * w + xx).ravel()
        return idx[use[idx]]

    best, best_fit = -1, None
    # a quadric through several squares was tried: on FP147/109 it takes the face (a larger smooth surface
    # than the plane in view) for the plane, where one plane through one square finds the plane
    for k in rng.integers(len(ys), size=tries):
        idx = square(k)
        if idx.size < 100:
            continue
        coef = np.linalg.lstsq(A1[idx], b[idx], rcond=None)[0]
        n = int(np.sum(np.abs(b[sub] - A1[sub] @ coef) < seed_rad))
        if n > best:
            best, best_fit = n, (A1, coef)
    if best_fit is None:
        return np.zeros((h, w), bool), np.zeros((h, w), bool)
    r = b - best_fit[0] @ best_fit[1]
    sel = use & (np.abs(r) < seed_rad)
    for deg in [d for d in (1, 2, 2, 3, 3, 3) if d <= max(int(degree), 1)]:
        if sel.sum() < 4 * len(poly_terms(deg)):
            break
        A = poly_basis(h, w, deg)
        idx = np.flatnonzero(sel)[:: max(1, int(sel.sum()) // 50_000)]
        r = b - A @ np.linalg.lstsq(A[idx], b[idx], rcond=None)[0]
        rs = r[sel]
        s = 1.4826 * np.median(np.abs(rs - np.median(rs)))
        sel = use & (np.abs(r) <= max(3 * s, grow_rad))
    r = np.where(use, r, np.inf).reshape(h, w)
    return valid & (np.abs(r) <= plane_rad), valid & (np.abs(r) > object_rad)


PLANE_SIDE_SHARE, PLANE_SIDES, PLANE_SIDE_BAND = 0.1, 2, 0.01
"""A reference plane reaches beyond the view: its pixels reach PLANE_SIDE_SHARE or more of PLANE_SIDES or more of the
image's sides, each within PLANE_SIDE_BAND of the shorter side (at least 2 px: FP1523 and FP672 with a 1-px invalid
border reach none at the edge itself). Measured (docs/own_rig.md): frames with their plane 2-4 sides; on black none
(the 'plane' found is a smooth part of an object); one side is not enough (a face cut off at its top)."""


def plane_sides(plane: np.ndarray, band: int | None = None) -> list[float]:
    """The share of each image side (top, bottom, left, right) along which the (H, W) bool ``plane`` has a pixel
    within ``band`` px of it (default :data:`PLANE_SIDE_BAND` of the shorter side, at least 2 px)."""
    p = np.asarray(plane, bool)
    k = band or max(2, round(PLANE_SIDE_BAND * min(p.shape)))
    return [float(e.any(axis=a).mean()) for e, a in ((p[:k], 0), (p[-k:], 0), (p[:, :k], 1), (p[:, -k:], 1))]


def sides_reached(sides) -> int:
    """How many of the :func:`plane_sides` shares reach :data:`PLANE_SIDE_SHARE`: a reference plane in view reaches
    :data:`PLANE_SIDES` or more."""
    return sum(float(x) >= PLANE_SIDE_SHARE for x in sides)
