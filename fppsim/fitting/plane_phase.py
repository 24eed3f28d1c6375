"""The reference plane's phase: which pixels are the plane, and a rig's projector fitted to their phase.

For two pinholes and a plane the absolute phase of the plane is the ratio of two linear functions of the
camera pixel, ``Phi(u, v) = (a . (u, v, 1)) / (b . (u, v, 1))`` up to a constant: four numbers besides
the offset, the direction and size of the phase gradient (the projector's roll and the fringe periods)
and its perspective change across the image (the projector's yaw and pitch). :func:`fit_plane_phase`
fits those four of a rig to phase maps (:class:`PhaseMap`: the absolute phase of phase-shifting scans,
or one fringe image's single-shot phase unwrapped, :func:`image_phase_map`), one free offset per map.

Which pixels are the plane is found, not assumed: the plane is the surface this model fits to a few
hundredths of a radian (an object is not, even a large and nearly flat one): :func:`find_plane` seeds a
fit in each of the largest smooth regions (:func:`smooth_regions`) and keeps the hypothesis most pixels
agree with (:func:`consensus`). Objects stand on the plane, so the sign of their phase relief tells
which way raised surfaces shift the phase (:func:`relief_sign`), and the projector's shadows, whose far
side is the plane, tell where the projector is (:func:`shadow_side`). :mod:`fppsim.fitting.rig_start`
builds a rig from images with these.

Units: radians, camera pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from dataclasses import replace as dc_replace

import numpy as np

from fppsim.errors import RigError
from fppsim.fitting.fit_periods import adjust_rig, cover_plane
from fppsim.geometry.rig import Rig
from fppsim.phase import wrap
from fppsim.phase.fringe_axis import fringe_axis, oriented_single_shot_phase
from fppsim.phase.plane import plane_level

__all__ = ["PhaseMap", "fringe_axis", "plane_phase_gradient", "relief_sign", "PLANE_PARAMS", "LENS_PARAMS", "TAU",
           "PlanePhaseFit",
           "plane_phase_residual", "smooth_regions", "fit_plane_phase", "consensus", "find_plane", "shadow_side",
           "image_phase_map"]



# ====================================================================== what a phase map says
@dataclass
class PhaseMap:
    """One image's phase for the fit: ``phase`` (H, W) float64 rad, absolute (phase-shifting) or unwrapped
    from one fringe image (then ``absolute`` is False: known only up to 2 pi steps between regions and
    its sign is a convention); ``valid`` (H, W) bool; ``name`` for messages; ``reliable``: the pixels
    whose phase is trusted enough to seed a plane candidate (:func:`find_plane`; default ``valid``);
    ``shadow``: the projector's shadows (default: the pixels that are not ``valid``; one fringe image's
    low-reliability edges are not shadows); ``fringed``: the lit pixels that carry fringes (default :attr:`lit`;
    one fringe image's: a dark background's sensor noise or ambient light is not a dark run, yet has none)."""

    phase: np.ndarray
    valid: np.ndarray
    name: str = ""
    absolute: bool = True
    reliable: np.ndarray | None = None  # (H, W) bool: where plane candidates may grow (default: valid)
    shadow: np.ndarray | None = None  # (H, W) bool: projector shadows (default: not valid)
    fringed: np.ndarray | None = None  # (H, W) bool: lit pixels with fringes (default: lit)

    @property
    def lit(self) -> np.ndarray:
        """Pixels the projector lights (not :attr:`shadow`)."""
        return self.valid if self.shadow is None else ~self.shadow


def _grid(valid, n: int) -> np.ndarray:
    """Up to ``n`` valid pixels (flat indices), evenly strided (deterministic)."""
    idx = np.flatnonzero(valid.ravel())
    if idx.size > n:
        idx = idx[np.linspace(0, idx.size - 1, n).round().astype(int)]
    return idx


def plane_phase_gradient(phase: np.ndarray, valid: np.ndarray, n: int = 40_000) -> tuple[float, float]:
    """The plane's phase gradient ``(g_u, g_v)`` (rad/px) at the image centre: a robust (iteratively
    trimmed) quadratic fit of the phase in (u, v) over the valid pixels (objects are the outliers; the
    quadratic terms take the perspective)."""
    H, W = phase.shape
    ok = valid & np.isfinite(phase)
    idx = _grid(ok, n)
    if idx.size < 50:
        raise RigError("too few pixels with a phase to measure the fringe direction")
    v, u = np.divmod(idx, W)
    x, y = (u - (W - 1) / 2.0) / W, (v - (H - 1) / 2.0) / W  # the quadratic terms take the perspective
    A = np.stack([np.ones(idx.size), x, y, x * x, x * y, y * y], axis=1)
    b = phase.ravel()[idx]
    sel = np.ones(idx.size, bool)
    for _ in range(6):
        coef = np.linalg.lstsq(A[sel], b[sel], rcond=None)[0]
        r = b - A @ coef
        s = 1.4826 * np.median(np.abs(r[sel] - np.median(r[sel])))
        sel = np.abs(r - np.median(r[sel])) <= max(2.5 * s, 0.5)
        if sel.sum() < 50:
            break
    return float(coef[1]) / W, float(coef[2]) / W


def relief_sign(residual: np.ndarray, plane: np.ndarray, valid: np.ndarray, min_rad: float = 1.0) -> tuple[int, float]:
    """Which way raised surfaces shift the phase: ``(sign, share)``, ``sign`` +1 when the phase relief
    off the plane (``residual`` = phase minus the fitted plane phase, rad) is mostly positive, -1 when
    mostly negative, 0 when there is too little relief (fewer than 0.2 % of the valid pixels more than
    ``min_rad`` off the plane); ``share`` is the fraction of those pixels of the winning sign. Objects
    stand ON the plane, so their relief has one sign (shadow edges and stray pixels make the rest)."""
    off = valid & ~plane & np.isfinite(residual) & (np.abs(residual) > min_rad)
    n = int(off.sum())
    if n < max(50, 0.002 * int(valid.sum())):
        return 0, float("nan")
    pos = float(np.sum(np.abs(residual[off]) * (residual[off] > 0)))
    neg = float(np.sum(np.abs(residual[off]) * (residual[off] < 0)))
    sign = 1 if pos >= neg else -1
    return sign, max(pos, neg) / (pos + neg)


# ====================================================================== the plane-phase fit
PLANE_PARAMS = ("yaw", "pitch", "roll", "periods")
LENS_PARAMS = ("k1",)  # the camera's radial distortion (OpenCV k1), fitted on request: lenses bend the plane's phase
_STEP = {"yaw": math.radians(2.0), "pitch": math.radians(2.0), "roll": math.radians(2.0), "k1": 0.01}
# search bounds in the scaled units: yaw and pitch +-60 deg (a camera tilted by 15 deg needs a yaw of 24 deg
# from a start looking straight down, by 30 deg over 30), roll +-20 deg (the start has the fringes'
# direction already), periods x / 2.7
_BOUND = {"yaw": 30.0, "pitch": 30.0, "roll": 10.0, "periods": 20.0, "k1": 100.0}  # k1 +-1
TAU = 0.2  # rad: a pixel agrees with a plane hypothesis within this (the real planes fit to 0.01-0.1 rad)


@dataclass
class PlanePhaseFit:
    """Result of :func:`fit_plane_phase`: the fitted ``rig``, the parameter values (``params``: yaw /
    pitch / roll in rad relative to the start, periods), the constant offset per map (rad: the rig's
    phase = map phase + offset on the plane), the plane pixels' residual (median |r| and RMS, rad, after
    the offset), the plane share of the valid pixels per map, and the start rig's median |r|;
    ``planes`` and ``residuals`` (per map, (H, W)) are the plane pixels and the map's phase minus the
    rig's plane phase less the offset (wrapped for maps that are not absolute)."""

    rig: Rig
    params: dict
    offsets: list
    median_rad: float
    rms_rad: float
    plane_share: list
    start_median_rad: float
    planes: list = field(default_factory=list, repr=False)
    residuals: list = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        return {"params": self.params, "offsets_rad": self.offsets, "plane_median_residual_rad": self.median_rad,
                "plane_rms_residual_rad": self.rms_rad, "plane_share": self.plane_share,
                "start_median_residual_rad": self.start_median_rad}


def _adjust(rig: Rig, values: dict) -> Rig:
    values = dict(values)
    k1 = values.pop("k1", None)
    out = adjust_rig(rig, **values)
    if k1 is not None:  # the camera's radial distortion; its other coefficients stay the start's
        dist = out.camera.dist.copy()
        dist[0] = k1
        out = dc_replace(out, camera=dc_replace(out.camera, dist=dist))
    return out


def plane_phase_residual(rig: Rig, phase: np.ndarray, valid: np.ndarray, plane: np.ndarray | None = None,
                         absolute: bool = True) -> tuple[np.ndarray, float]:
    """``(residual, offset)``: the map's phase minus the rig's reference-plane phase
    (:meth:`fppsim.geometry.rig.Rig.phase_at_height` at 0 mm), less the constant that centres it on the
    ``plane`` pixels (their median; default: the histogram mode of all valid pixels, refined by the
    median within 1 rad), NaN where not ``valid``; ``offset`` is what the rig's phase exceeds the map's
    by on the plane. ``absolute=False`` (a phase known modulo 2 pi): the residual is wrapped. THE check
    of a rig against a phase-shifting frame: the plane pixels' median |residual|."""
    d = np.where(valid, phase - rig.phase_at_height(0.0), np.nan)
    ok = np.isfinite(d)
    if not ok.any():
        return d, float("nan")
    if not absolute:
        ref = plane if plane is not None and (plane & ok).any() else ok
        z = np.exp(1j * d[ref])
        c = float(np.angle(z.mean()))
        return wrap(d - c), -c
    if plane is not None and (plane & ok).any():
        c = float(np.median(d[plane & ok]))
    else:
        c = plane_level(d, ok, bin_width=0.05, window=1.0)
    return d - c, -c


def smooth_regions(phase: np.ndarray, valid: np.ndarray, gradient, step_rad: float = 1.0,
                   absolute: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Connected regions of smooth phase (8-bit-free: a pixel is cut off from its right / lower
    neighbour when the phase step differs from the plane ``gradient`` by more than ``step_rad``):
    ``(labels, sizes)``, sizes in pixels, largest first (labels renumbered 1..n in that order)."""
    from scipy import ndimage as ndi

    ph = np.where(valid, phase, np.nan)
    dx = np.diff(ph, axis=1, append=np.nan) - gradient[0]
    dy = np.diff(ph, axis=0, append=np.nan) - gradient[1]
    if not absolute:
        dx, dy = wrap(dx), wrap(dy)
    with np.errstate(invalid="ignore"):
        step = ~(np.abs(dx) <= step_rad) | ~(np.abs(dy) <= step_rad)
    cut = step.copy()
    cut[:, 1:] |= step[:, :-1]
    cut[1:, :] |= step[:-1, :]
    smooth = valid & ~cut
    lab, n = ndi.label(smooth)
    if n == 0:
        return lab, np.zeros(0, int)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    order = np.argsort(sizes)[::-1]
    remap = np.zeros(n + 1, int)
    remap[order + 1] = np.arange(1, n + 1)
    return remap[lab], sizes[order]


def fit_plane_phase(start: Rig, maps: list[PhaseMap], params: tuple[str, ...] = PLANE_PARAMS,
                    seeds: list | None = None, pixels: int = 6000, tau: float = TAU,
                    rounds: int = 3) -> PlanePhaseFit:
    """Fit ``params`` (of yaw, pitch, roll, periods: the projector turned about its own axes; and of
    :data:`LENS_PARAMS`: the camera's radial distortion ``k1``, the camera's pose fixed) of ``start`` so its reference-plane phase matches the maps' phase on the plane, one
    free constant offset per map (the phase origin of a scan is arbitrary).

    ``seeds`` (per map, (H, W) bool; default the valid pixels) are where the plane is looked for first
    (for a map that is not absolute: pixels unwrapped consistently, e.g. one smooth region):
    a fit with a Cauchy loss there (objects are outliers of the four-parameter plane), then ``rounds``
    least-squares fits on the pixels within ``max(tau, 3 robust sigmas)`` of the plane found so far
    (which may grow beyond the seeds: the plane is one surface). ``pixels``: evenly strided pixels per
    map and fit. Maps that are not absolute (one fringe image's unwrapped phase) are compared modulo
    2 pi. The fitted projector's image is grown where it leaves part of the camera's view of the plane
    unlit (:func:`fppsim.fitting.fit_periods.cover_plane`: the start's projector size is a modelling
    choice). Raises RigError when a map has too few valid pixels.
    """
    from scipy.optimize import least_squares

    params = tuple(params)
    bad = [p for p in params if p not in PLANE_PARAMS + LENS_PARAMS]
    if bad:
        raise RigError(f"the plane-phase fit adjusts {', '.join(PLANE_PARAMS + LENS_PARAMS)}, not {', '.join(bad)}")
    H, W = start.camera.height, start.camera.width
    for m in maps:
        if m.phase.shape != (H, W):
            raise RigError(f"{m.name}: the phase map is {m.phase.shape[1]} x {m.phase.shape[0]} px but the rig's "
                           f"camera is {W} x {H}")
    flat = start.camera.pixel_grid().reshape(-1, 2)
    f0 = float(start.periods)
    oks = [m.valid & np.isfinite(m.phase) for m in maps]
    for m, ok in zip(maps, oks):
        if ok.sum() < 200:
            raise RigError(f"{m.name}: fewer than 200 pixels with a phase")
    seeds = oks if seeds is None else [np.asarray(sd, bool) & ok for sd, ok in zip(seeds, oks)]

    def values(x):
        return {p: (f0 * math.exp(xi * 0.05) if p == "periods" else xi * _STEP[p]) for p, xi in zip(params, x)}

    def model(x, idx_list):
        rig = _adjust(start, values(x))
        return [rig.phase_at_height(0.0, flat[idx]) for idx in idx_list]

    def fit(x0, idx_list, loss, scale, snap):
        targets = [m.phase.ravel()[idx] for m, idx in zip(maps, idx_list)]
        preds = model(x0, idx_list)
        c0 = []
        for k, (m, p, t) in enumerate(zip(maps, preds, targets)):
            if snap and not m.absolute:  # each pixel to the current model's nearest period
                d = p - t
                cc = float(np.angle(np.mean(np.exp(1j * d))))
                targets[k] = t + 2 * np.pi * np.round((d - cc) / (2 * np.pi))
            c0.append(float(np.median(p - targets[k])))

        def fun(z):
            x, c = z[: len(params)], z[len(params):]
            try:
                pr = model(x, idx_list)
            except RigError:
                return np.full(sum(len(t) for t in targets), 1e3)
            r = np.concatenate([p - t - ci for p, t, ci in zip(pr, targets, c)])
            return np.where(np.isfinite(r), r, 1e3)

        lo = np.concatenate([[-_BOUND[p] for p in params], np.full(len(c0), -np.inf)])
        z0 = np.clip(np.concatenate([x0, c0]), lo + 1e-9, -lo - 1e-9)
        sol = least_squares(fun, z0, loss=loss, f_scale=scale, x_scale=1.0, bounds=(lo, -lo),
                            diff_step=1e-5, max_nfev=200)
        return sol.x[: len(params)]

    x = np.zeros(len(params))
    start_med = _plane_stats(start, maps, oks, seeds)[0]
    # the seeds are taken as they are (a map that is not absolute: unwrapped consistently there)
    x = fit(x, [_grid(sd, pixels) for sd in seeds], "cauchy", 0.5, False)
    planes = seeds
    for _ in range(int(rounds)):
        planes = _grow_planes(_adjust(start, values(x)), maps, oks, planes, tau)
        x = fit(x, [_grid(pl, pixels) for pl in planes], "linear", 1.0, True)
    rig = _adjust(start, values(x))
    planes = _grow_planes(rig, maps, oks, planes, tau)
    rig.name = start.name + " (plane phase fitted: " + ", ".join(params) + ")"
    rig.check()
    # a start's projector size is a modelling choice: grown to light the whole view (a projector that
    # leaves a strip of the real view dark is still identified by the lit part)
    rig = cover_plane(rig)
    med, rms, offsets, shares, residuals = _plane_stats(rig, maps, oks, planes)
    return PlanePhaseFit(rig=rig, params={p: float(v) for p, v in values(x).items()}, offsets=offsets,
                         median_rad=med, rms_rad=rms, plane_share=shares, start_median_rad=start_med,
                         planes=planes, residuals=residuals)


def _grow_planes(rig: Rig, maps, oks, planes, tau: float) -> list:
    """The pixels of each map within ``max(tau, 3 robust sigmas of the current plane)`` of ``rig``'s
    plane phase, the offset taken on the current plane pixels; the current plane when fewer than 200."""
    out = []
    for m, ok, pl in zip(maps, oks, planes):
        r, _ = plane_phase_residual(rig, m.phase, ok, pl, m.absolute)
        a = np.abs(np.nan_to_num(r, nan=np.inf))
        s = 1.4826 * float(np.median(a[pl & ok])) if (pl & ok).any() else 0.0
        new = ok & (a <= max(tau, min(3.0 * s, 1.0)))
        out.append(new if new.sum() >= 200 else pl)
    return out


def _plane_stats(rig: Rig, maps, oks, planes):
    """Median |residual| and RMS over the plane pixels of all maps, offsets, plane shares, residual maps."""
    allr, offsets, shares, residuals = [], [], [], []
    for m, ok, pl in zip(maps, oks, planes):
        r, off = plane_phase_residual(rig, m.phase, ok, pl, m.absolute)
        allr.append(r[pl & np.isfinite(r)])
        offsets.append(float(off))
        shares.append(float((pl & ok).sum() / max(int(ok.sum()), 1)))
        residuals.append(r)
    a = np.concatenate(allr) if allr else np.array([])
    if not a.size:
        return float("nan"), float("nan"), offsets, shares, residuals
    return float(np.median(np.abs(a))), float(np.sqrt(np.mean(a ** 2))), offsets, shares, residuals


def consensus(residual: np.ndarray, tau: float = TAU) -> float:
    """MSAC score of a plane hypothesis: sum over pixels of ``max(0, 1 - (r / tau)^2)``."""
    r = residual[np.isfinite(residual)]
    return float(np.sum(np.clip(1.0 - (r / tau) ** 2, 0.0, None)))


def find_plane(start: Rig, m: PhaseMap, gradient, candidates: int = 5, min_share: float = 0.02,
               pixels: int = 4000, tau: float = TAU) -> tuple[np.ndarray, list]:
    """The reference plane's pixels in one map, whatever share of the image it covers.

    The plane is the surface whose phase the four-parameter plane model fits to a few hundredths of a
    radian; an object is not, even a large and nearly flat one. Each of the ``candidates`` largest
    smooth regions (:func:`smooth_regions`, at least ``min_share`` of the valid pixels) seeds a fit
    (:func:`fit_plane_phase`, one round); the hypothesis that agrees with most pixels within ``tau``
    (:func:`consensus`) wins, unless it touches no image border while another hypothesis that fits its own
    region as well runs along the borders (a flat top inside the view is not the plane the objects stand
    on, which reaches beyond it). Returns ``(plane, scores, fit)``: its pixels, ``(region share, consensus
    share, median |r| on the region)`` per candidate tried, and the winner's :class:`PlanePhaseFit`
    (None, with every valid pixel as the plane, when no region could seed a fit)."""
    ok = m.valid & np.isfinite(m.phase)
    lab, sizes = smooth_regions(m.phase, ok if m.reliable is None else ok & m.reliable, gradient,
                                absolute=m.absolute)
    n_ok = max(int(ok.sum()), 1)
    edge = np.zeros(ok.shape, bool)
    edge[:2], edge[-2:], edge[:, :2], edge[:, -2:] = True, True, True, True
    edge &= ok
    tried, scores = [], []
    for k in range(min(int(candidates), len(sizes))):
        if sizes[k] < max(min_share * n_ok, 200):
            break
        seed = lab == k + 1
        try:
            fit = fit_plane_phase(start, [m], seeds=[seed], pixels=pixels, tau=tau, rounds=1)
        except RigError:
            continue
        score = consensus(fit.residuals[0], tau)
        med = float(np.nanmedian(np.abs(fit.residuals[0][seed])))
        scores.append((float(sizes[k] / n_ok), score / n_ok, med))
        border = float((fit.planes[0] & edge).sum() / max(int(edge.sum()), 1))
        tried.append((score, fit, border, med))
    if not tried:
        return ok, scores, None
    best = max(tried, key=lambda c: c[0])
    if best[2] < 0.05:
        # the winner touches no image border: a flat top inside the view (a box, a plinth) rather than the
        # plane the objects stand on, which reaches beyond the view; another surface the plane model fits
        # as well, along the borders, is the plane (taking the top would mirror the projector's side)
        outer = [c for c in tried if c[2] >= 0.25 and c[3] < tau and c[0] >= 0.05 * n_ok]
        if outer:
            best = max(outer, key=lambda c: c[0])
    return best[1].planes[0], scores, best[1]


def shadow_side(plane: np.ndarray, valid: np.ndarray, axis: str, min_run: int = 3, skip: int = 2,
                reach: int = 8) -> tuple[int, int]:
    """Which way the projector lies, from its shadows: along the baseline (image rows for vertical
    fringes, columns for horizontal ones) every run of invalid pixels (a shadow, at least ``min_run``
    px) between two valid stretches is cast by the surface at one end onto the plane at the other; the
    plane end is the far one. Each end is looked at from ``skip`` to ``reach`` px beyond the run (the
    pixels next to a shadow carry the worst phase): a run votes when one end is mostly plane (>= 70 %)
    and the other mostly not (<= 30 %). Returns ``(direction, votes)``: +1 when the projector lies
    towards growing column (vertical fringes) / row (horizontal) index, -1 the other way, 0 when the
    votes do not say (fewer than 10, or less than a 2:1 majority); ``votes`` is their count."""
    pl = plane if axis == "vertical" else plane.T
    ok = valid if axis == "vertical" else valid.T
    score, votes = 0, 0
    n = ok.shape[1]
    for r in range(ok.shape[0]):
        bad = ~ok[r]
        if not bad.any():
            continue
        d = np.diff(np.concatenate([[0], bad.astype(np.int8), [0]]))
        starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)  # invalid starts .. ends - 1
        for a, b in zip(starts, ends):
            if b - a < min_run or a - reach < 0 or b + reach > n:
                continue
            lo, hi = slice(a - reach, a - skip), slice(b + skip, b + reach)
            if not (ok[r, lo].all() and ok[r, hi].all()):
                continue
            before, after = float(pl[r, lo].mean()), float(pl[r, hi].mean())
            if before >= 0.7 and after <= 0.3:
                score, votes = score + 1, votes + 1  # plane before the shadow: the projector lies after it
            elif after >= 0.7 and before <= 0.3:
                score, votes = score - 1, votes + 1
    if votes < 10 or abs(score) < votes / 3.0:
        return 0, votes
    return (1 if score > 0 else -1), votes


def image_phase_map(gray: np.ndarray, valid: np.ndarray | None = None, name: str = "",
                    min_reliability: float = 0.3) -> PhaseMap:
    """One fringe image's phase for the fit: the single-shot phase in the fringes' own direction
    (:func:`fppsim.phase.fringe_axis.oriented_single_shot_phase`; by convention growing along +columns
    for vertical fringes, +rows for horizontal ones: one image cannot tell), unwrapped spatially over its
    reliable pixels (scikit-image). ``absolute=False``: regions may be whole periods apart, which the
    fit ignores (it compares modulo 2 pi). Shadows (dark runs) and pixels below ``min_reliability``
    are invalid."""
    from skimage.restoration import unwrap_phase

    g = np.asarray(gray, np.float64)
    ssp = oriented_single_shot_phase(g, None, mask=valid)
    ok = ssp.valid & (ssp.reliability >= min_reliability)
    if ok.sum() < 200:
        raise RigError(f"{name}: too few pixels with a reliable fringe phase")
    un = np.asarray(unwrap_phase(np.ma.array(ssp.wrapped.astype(np.float64), mask=~ok)).filled(np.nan))
    # edges (objects, shadows) have a low reliability: cut there, plane candidates do not leak onto objects
    # fringes: a modulation of at least 15 % of the reliable pixels' median (a noisy black is lit, but fringe-less)
    fringed = ssp.valid & (ssp.modulation >= 0.15 * float(np.median(ssp.modulation[ok])))
    return PhaseMap(np.where(ok, un, np.nan), ok, name, absolute=False, reliable=ssp.reliability >= 0.5,
                    shadow=~ssp.valid, fringed=fringed)


