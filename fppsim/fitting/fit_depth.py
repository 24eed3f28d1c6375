"""How a rig's height sensitivity changes with height, fitted to labelled real images
(``fppsim fit-rig --params ...,distance``).

A raised surface shifts the fringe phase by ``Phi(h)``; for a projector at distance ``D`` above the
plane with baseline ``b`` (parallel axes, image centre) ``Phi(h) ~ s0 D h / (D - h)``: the
sensitivity ``s0`` at the plane grows as ``(D / (D - h))^2`` with height. Two rigs with the same plane
(periods, fringe tilt) and the same slope at one height can therefore disagree by whole fringes at
40 mm. The fit changes ``distance`` (:func:`fppsim.fitting.fit_periods.adjust_rig`: camera and projector move
away from the scene together, focal lengths with them, the plane's image and fringes stay) and the
``baseline`` (the level of the sensitivity), re-fitting the projector's yaw / roll / periods to the
plane's band periods and tilt after each change (:func:`fppsim.fitting.fit_periods.fit_rig_periods`).

Measurement (:func:`depth_check`), per labelled image (:class:`fppsim.dataio.readers.FringeImage` with
``height_mm``), on the rig-vs-labels check :func:`fppsim.fitting.height_sensitivity.label_residual`:

1. The real fringe, less its local mean, is demodulated with ``exp(-i Phi_rig(h))``
   (:func:`fppsim.fitting.height_sensitivity.surface_phase` of the labelled surface) and low-passed: the
   residual phase ``r = wrap(phi_real - Phi_rig)`` (:func:`fppsim.fitting.height_sensitivity.demodulated_residual`;
   no carrier band, no unwrapping: what the rig explains is removed before filtering), on the plane
   (``|h| < 1 mm``) and object (``h > 2 mm``) pixels away from invalid pixels and height steps
   (:func:`fppsim.fitting.height_sensitivity.label_masks`).
2. One constant ``o`` (the circular mean of ``r`` on the plane) is removed: for the right rig the
   wrapped residual is then about 0 on the plane AND on the object.
3. A wrapped residual is blind to whole fringes. Projector shadows fix them: the plane pixel at the
   shadow's far edge and the object pixel at its near edge are lit by the same projector ray (the
   one grazing the object's edge), so their absolute phases agree (:func:`shadow_bridge`; on the
   phase-shifting frame FP1523, whose fringe orders are known, the two sides agree to 0.16 rad
   median, IQR -0.06..0.32). That turns the object's wrapped offset into an absolute one.

Fit (:func:`fit_depth`): for each candidate distance the baseline is solved so that the absolute
object offset (object-pixel weighted over the images) is 0; the distance whose object residual is
then smallest (``mean(1 - cos r)`` on object pixels: the residual no longer changes with height) wins,
refined by a bounded scalar search. Units: mm, radians.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fppsim.errors import RigError
from fppsim.fitting.fit_periods import PARAMETERS, BandPeriods, RigFit, adjust_rig, base_values, fit_rig_periods, unfitted
from fppsim.fitting.height_sensitivity import centre_sensitivity, label_residual, surface_phase
from fppsim.phase import wrap
from fppsim.phase.unwrap import shadow_runs
from fppsim.dataio.readers import FringeImage
from fppsim.geometry.rig import Rig

__all__ = ["shadow_edges", "shadow_bridge", "sensitivity_at", "DepthCheck", "depth_check", "DepthFit", "fit_depth",
           "format_depth_fit"]


# ====================================================================== measuring one image
def shadow_edges(valid: np.ndarray, plane: np.ndarray, obj: np.ndarray, shadow_left: bool = True, k: int = 3,
                 min_width: int = 8) -> np.ndarray:
    """Projector shadows crossed along image rows: (n, 3) int rows ``(row, u_plane, u_object)``, the last
    plane pixel before a run of invalid pixels (at least ``min_width`` long) and the first object pixel
    after it. ``shadow_left``: shadows fall to the left of objects (projector on the camera's +x side,
    as in the figshare rig); else the image is searched mirrored. The ``k + 2`` pixels on each side must
    be plane / object respectively."""
    valid, plane, obj = (np.asarray(a, dtype=bool) for a in (valid, plane, obj))
    if not shadow_left:
        e = shadow_edges(valid[:, ::-1], plane[:, ::-1], obj[:, ::-1], True, k, min_width)
        W = valid.shape[1]
        return np.stack([e[:, 0], W - 1 - e[:, 1], W - 1 - e[:, 2]], axis=1) if len(e) else e
    W = valid.shape[1]
    runs = shadow_runs(~valid)
    r, x, x1 = runs.T
    runs = runs[(x1 - x - 1 >= min_width) & (x - k - 1 >= 0) & (x1 + k + 2 <= W)]
    r, x, x1 = (c[:, None] for c in runs.T)
    keep = plane[r, x + np.arange(-k - 1, 1)].all(axis=1) & obj[r, x1 + np.arange(k + 2)].all(axis=1)
    return runs[keep].reshape(-1, 3)


def _edge_values(phase: np.ndarray, edges: np.ndarray, k: int = 3, shadow_left: bool = True):
    """Phase extrapolated linearly to the shadow's two boundaries from ``k`` px inside each side."""
    r, up, uo = edges.T
    s = 1 if shadow_left else -1  # direction from the plane towards the object
    a = phase[r, up - s * k]
    a_edge = a + (k + 0.5) * (a - phase[r, up - s * (k + 1)])
    b = phase[r, uo + s * k]
    b_edge = b - (k + 0.5) * (phase[r, uo + s * (k + 1)] - b)
    return a_edge, b_edge


def shadow_bridge(rig: Rig, residual: np.ndarray, edges: np.ndarray, height_mm: np.ndarray, plane_offset: float,
                  object_offset: float, shadow_left: bool = True, *,
                  rig_phase: np.ndarray | None = None) -> np.ndarray:
    """Per shadow crossing: absolute real phase at the plane side minus at the object side (rad), with the
    object's residual taken on the branch around ``object_offset`` (``plane_offset`` likewise). About 0
    for the branch that is right; ``2 pi n`` off when the object is really ``n`` fringes further.

    The real phase is modelled as ``Phi_rig(h) + residual`` (the residual unwrapped around the offsets),
    extrapolated to the shadow's boundaries (:func:`shadow_edges`); ``rig_phase`` as in
    :func:`fppsim.fitting.height_sensitivity.demodulated_residual`."""
    if not len(edges):
        return np.zeros(0)
    P = surface_phase(rig, np.nan_to_num(height_mm)) if rig_phase is None else rig_phase
    rp = wrap(residual - plane_offset) + plane_offset
    ro = wrap(residual - object_offset) + object_offset
    a, _ = _edge_values(P + rp, edges, shadow_left=shadow_left)
    _, b = _edge_values(P + ro, edges, shadow_left=shadow_left)
    return a - b


def sensitivity_at(rig: Rig, height_mm: float, dh: float = 0.5) -> float:
    """Phase change (rad per mm) at the camera's image centre for a surface at ``height_mm`` (central
    difference over +-``dh``, :meth:`fppsim.geometry.rig.Rig.sensitivity`); :func:`fppsim.fitting.height_sensitivity.centre_sensitivity`
    is the one at 0 mm."""
    return rig.sensitivity(height_mm - dh, height_mm + dh)


@dataclass
class DepthCheck:
    """How well a rig's phase-height relation matches one labelled real image (:func:`depth_check`).

    plane_residual, object_residual : median |wrapped residual| (rad) on plane / object pixels after one
        constant (the plane's circular mean) is removed; about 0 on both for the right rig.
    object_offset : the object's mean residual relative to the plane, absolute (rad; whole fringes fixed by
        the shadows, see :func:`shadow_bridge`); ``wrapped_offset`` the same within (-pi, pi].
    fringes : ``(object_offset - wrapped_offset) / 2 pi``, the whole fringes the shadows added.
    slope : object residual per mm of height (rad/mm; 0 when the sensitivity's growth with height matches).
    coherence : |mean phasor| of the object residual. bridge : median shadow residual on the chosen branch
        (rad; about 0) over the crossings that voted for the chosen fringe count (each crossing votes
        ``round((bridge_i - bridge_ref) / 2 pi)``; the most common count wins). bridge_iqr : its
        interquartile range; vote_share : the share of crossings that voted for it. n_plane, n_object,
        n_edges : pixels and shadow crossings used. ``object_offset`` is NaN (and ``fringes`` 0) without
        shadow crossings. cost : ``mean(1 - cos r)`` over object pixels plus the same over plane pixels plus
        ``|fringes|`` (what :func:`fit_depth` minimises; a wrong fringe count never looks right).
    """

    plane_residual: float
    object_residual: float
    object_offset: float
    wrapped_offset: float
    fringes: int
    slope: float
    coherence: float
    bridge: float
    bridge_iqr: float
    n_plane: int
    n_object: int
    n_edges: int
    cost: float = float("nan")
    vote_share: float = float("nan")

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else int(v)) for k, v in self.__dict__.items()}


def _shadow_left(rig: Rig) -> bool:
    return bool(rig.projector.center[0] >= rig.camera.center[0])


def depth_check(rig: Rig, image: FringeImage, smooth: float = 4.0, bridge_ref: float = 0.0,
                min_object: int = 200, min_edges: int = 10) -> DepthCheck | None:
    """Compare the phase-height relation of ``rig`` with one labelled real image (see the module notes).

    ``bridge_ref``: the shadow residual expected for the right branch (rad; 0 in theory, 0.16 measured on
    FP1523). Returns None without labels or with fewer than ``min_object`` object pixels; without
    ``min_edges`` shadow crossings the offset stays wrapped (``object_offset`` NaN).
    """
    res = label_residual(rig, image, smooth, min_object=min_object)
    if res is None:
        return None
    valid = np.asarray(image.valid, dtype=bool)
    h, plane, obj, P, d, r, o = res.height, res.plane, res.obj, res.rig_phase, res.demodulated, res.residual, \
        res.plane_offset
    ro = r[obj]
    coherence, wrapped, slope = res.coherence, res.offset, res.slope
    left = _shadow_left(rig)
    edges = shadow_edges(valid, valid & (np.abs(h) < 1.5), valid & (h > 5.0), left)
    fringes, offset, bridge, iqr, share = 0, float("nan"), float("nan"), float("nan"), float("nan")
    if len(edges) >= min_edges:
        b = shadow_bridge(rig, d, edges, h, o, o + wrapped, left, rig_phase=P)
        # each crossing votes for a whole number of fringes; the most common wins (crossings whose first
        # lit object pixel is not the occluding edge, e.g. a shadow cast by a higher part, vote wrong)
        votes = np.round((b - bridge_ref) / (2 * np.pi)).astype(np.int64)
        values, counts = np.unique(votes, return_counts=True)
        best = counts == counts.max()
        fringes = int(values[best][np.argmin(np.abs(values[best]))])
        share = float(counts.max() / counts.sum())
        offset = wrapped + 2 * np.pi * fringes
        b = b[votes == fringes] - 2 * np.pi * fringes
        bridge = float(np.median(b))
        iqr = float(np.subtract(*np.percentile(b, [75, 25])))
    # the residual the object would have with the absolute offset: 1 - cos is blind to whole fringes,
    # so the cost adds the fringe count (a wrong branch must never look right)
    # (the plane's residual counts too: a rig that explains the object by bending the plane is no better)
    cost = float(np.mean(1.0 - np.cos(ro))) + float(np.mean(1.0 - np.cos(r[plane]))) + float(abs(fringes))
    return DepthCheck(float(np.median(np.abs(r[plane]))), float(np.median(np.abs(ro))), offset, wrapped, fringes,
                      slope, coherence, bridge, iqr, int(plane.sum()), int(obj.sum()), int(len(edges)),
                      cost, share)


_CHECK_HEADER = (f"{'rig':<14}{'plane |r|':>10}{'object |r|':>11}{'offset':>9}{'slope':>9}{'coher.':>8}"
                 f"{'s(0)':>8}{'s(40)':>8}\n"
                 f"{'':<14}{'rad':>10}{'rad':>11}{'rad':>9}{'rad/mm':>9}{'0..1':>8}{'rad/mm':>8}{'rad/mm':>8}")


def _check_line(name: str, checks: list, s0: float, s40: float) -> str:
    if not checks:
        return f"{name:<14}  (no labelled image with enough object pixels)"
    p = {k: _pooled(checks, k) for k in ("plane_residual", "object_residual", "object_offset", "slope", "coherence")}
    return (f"{name:<14}{p['plane_residual']:>10.3f}{p['object_residual']:>11.3f}{p['object_offset']:>+9.2f}"
            f"{p['slope']:>+9.4f}{p['coherence']:>8.3f}{abs(s0):>8.3f}{abs(s40):>8.3f}")


# ====================================================================== the fit
@dataclass
class DepthFit:
    """Result of :func:`fit_depth`: the chosen ``distance`` and ``baseline`` (mm), the period fit there
    (``fit.rig`` is the fitted rig), the scan (one dict per distance tried: distance, baseline, cost,
    object residual, slope, sensitivities at 0 and 40 mm), the per-image checks of the base and the
    fitted rig."""

    distance: float
    baseline: float
    fit: RigFit
    scan: list
    checks: list
    base_checks: list
    sensitivity: float
    sensitivity_40: float
    base_distance: float = float("nan")
    base_baseline: float = float("nan")
    base_sensitivity: float = float("nan")
    base_sensitivity_40: float = float("nan")
    notes: list = field(default_factory=list)
    kept: bool = False  # nothing improved on the base rig: ``fit.rig`` is the base rig itself

    def to_dict(self) -> dict:
        return {"distance_mm": self.distance, "baseline_mm": self.baseline, "kept_base": self.kept,
                "base_distance_mm": self.base_distance, "base_baseline_mm": self.base_baseline,
                "base_centre_sensitivity_rad_per_mm": self.base_sensitivity,
                "base_sensitivity_40mm_rad_per_mm": self.base_sensitivity_40,
                "centre_sensitivity_rad_per_mm": self.sensitivity,
                "sensitivity_40mm_rad_per_mm": self.sensitivity_40, "scan": self.scan,
                "checks": [c.to_dict() for c in self.checks], "base_checks": [c.to_dict() for c in self.base_checks],
                "notes": list(self.notes)}


def _pooled(checks: list[DepthCheck], key: str) -> float:
    ok = [c for c in checks if np.isfinite(getattr(c, key))]
    if not ok:
        return float("nan")
    w = np.array([c.n_object for c in ok], dtype=np.float64)
    return float(np.sum(w * [getattr(c, key) for c in ok]) / w.sum())


def fit_depth(images: list[FringeImage], measured: BandPeriods, base: Rig,
              params: tuple[str, ...] = ("yaw", "roll", "focal"), distances=None, smooth: float = 4.0,
              bridge_ref: float = 0.0, tol_mm: float = 2.0) -> DepthFit | None:
    """Fit the rig's ``distance`` and ``baseline`` to labelled real images (see the module notes).

    ``params``: the projector parameters re-fitted to the plane's band periods and tilt after every
    change (``distance`` and ``baseline`` are dropped from them: they are what this fits). The default
    keeps the fringe count across the projector (80 in the figshare data) and refits the projector's
    focal length; with ``periods`` instead the plane matches as well but the count drifts (75.8 on the
    real pair).
    ``distances``: candidate camera heights (mm; default 0.4 .. 4 x the base rig's, 12 steps evenly in
    ``1 / distance``, never below 3 x the highest label); the best is refined to ``tol_mm``.
    ``bridge_ref``: see :func:`depth_check`. Returns None when no image has height labels, enough object
    pixels and projector shadows. Raises RigError when no candidate distance gives a usable rig.
    """
    labelled = [im for im in images if im.height_mm is not None]
    if not labelled:
        return None
    period_params = tuple(p for p in params if p not in ("distance", "baseline"))  # none: the plane stays as is
    unknown = [p for p in period_params if p not in PARAMETERS]
    if unknown:
        raise RigError(f"unknown parameter(s) {', '.join(unknown)} (known: {', '.join(PARAMETERS)})")
    b0 = base_values(base)
    distances = _candidate_distances(labelled, b0, distances)

    def checks_of(rig: Rig) -> list[DepthCheck]:
        return [c for c in (depth_check(rig, im, smooth, bridge_ref) for im in labelled) if c is not None]

    base_checks = checks_of(base)
    if not base_checks or not np.isfinite(_pooled(base_checks, "object_offset")):
        return None
    cache: dict = {}

    def solve(distance: float):
        """The zero-offset baseline at this distance, solved once per distance (rounded to 1 um)."""
        key = round(float(distance), 3)
        if key not in cache:
            cache[key] = _zero_offset_baseline(distance, base, b0, measured, period_params, checks_of)
        return cache[key]

    done = _scan_distances(distances, solve, cache, tol_mm)
    best_key = min(done, key=lambda kv: kv[1][0]["cost"])[0]
    row, fit, checks = cache[best_key]
    scan = [v[0] for _, v in done]
    base_cost = _pooled(base_checks, "cost")
    if not row["cost"] < base_cost:  # never a rig worse than the start on this objective: keep the base
        return _base_kept(base, b0, measured, period_params, row["cost"], base_cost, scan, base_checks)
    fit.rig.name = (f"fit-rig depth fit: camera {row['distance_mm']:.1f} mm above the plane, baseline "
                    f"{row['baseline_mm']:.1f} mm, {abs(row['sensitivity_0']):.3f} rad/mm at the plane "
                    f"({', '.join(period_params)} refitted to the plane; started from: {base.name})")
    notes = []
    if best_key in (done[0][0], done[-1][0]):
        notes.append("the best distance is at the end of the scanned range: widen --distances / distances")
    return DepthFit(distance=row["distance_mm"], baseline=row["baseline_mm"], fit=fit,
                    scan=scan, checks=checks, base_checks=base_checks,
                    sensitivity=row["sensitivity_0"], sensitivity_40=row["sensitivity_40"],
                    base_distance=b0["distance"], base_baseline=b0["baseline"],
                    base_sensitivity=centre_sensitivity(base), base_sensitivity_40=sensitivity_at(base, 40.0),
                    notes=notes)


def _candidate_distances(labelled: list[FringeImage], b0: dict, distances) -> np.ndarray:
    """The camera heights to try (default 0.4 .. 4 x the base rig's, evenly in ``1 / distance``), above 3 x
    the highest label: nearer, the ``D / (D - h)`` growth the fit measures is no longer a small correction."""
    top = max(float(np.nanmax(np.where(im.valid, np.nan_to_num(im.height_mm), 0.0))) for im in labelled)
    d_min = max(3.0 * top, 0.05 * b0["distance"])
    if distances is None:
        inv = np.linspace(1.0 / (0.4 * b0["distance"]), 1.0 / (4.0 * b0["distance"]), 12)
        distances = 1.0 / inv
    distances = np.array([d for d in np.asarray(distances, dtype=np.float64) if d > d_min])
    if not distances.size:
        raise RigError(f"no candidate distance above {d_min:.0f} mm (3 x the highest label)")
    return distances


def _zero_offset_baseline(distance: float, base: Rig, b0: dict, measured: BandPeriods, period_params: tuple,
                          checks_of: Callable[[Rig], list]):
    """The baseline whose pooled absolute object offset is 0 at this distance (secant steps), as (scan row,
    period fit, checks); None when the rig there loses the shadow crossings or the baseline diverges."""
    k = distance / b0["distance"]
    xs, ys, last = [], [], None
    b = b0["baseline"] * k
    try:
        for it in range(8):
            rig = adjust_rig(base, distance=distance, baseline=b)
            fit = fit_rig_periods(measured, rig, period_params) if period_params else \
                unfitted(measured, rig, "only distance and baseline fitted")
            checks = checks_of(fit.rig)
            y = _pooled(checks, "object_offset")
            if not np.isfinite(y):
                raise RigError("no shadow crossings")
            xs.append(b)
            ys.append(y)
            last = (fit, checks)
            if abs(y) < 0.01:
                break
            if len(xs) < 2:
                # phase shift ~ proportional to the baseline: scale it by the offset's share
                # (signed: a residual ahead of the rig wants less shift when the phase falls with height)
                total = sensitivity_at(fit.rig, 20.0) * 40.0
                b = b * (1.0 + y / total) if abs(total) > 1.0 else 1.1 * b
            else:
                slope = (ys[-1] - ys[-2]) / (xs[-1] - xs[-2]) if xs[-1] != xs[-2] else 0.0
                if slope == 0.0:
                    break
                b = xs[-1] - ys[-1] / slope
            if not (0.05 * b0["baseline"] * k < abs(b) < 20.0 * abs(b0["baseline"]) * k + 1.0):
                raise RigError("baseline diverged")
    except RigError:
        return None
    fit, checks = last
    row = {"distance_mm": float(distance), "baseline_mm": float(xs[-1]), "cost": _pooled(checks, "cost"),
           "object_offset": _pooled(checks, "object_offset"),
           "object_residual": _pooled(checks, "object_residual"), "slope": _pooled(checks, "slope"),
           "plane_residual": _pooled(checks, "plane_residual"),
           "sensitivity_0": centre_sensitivity(fit.rig), "sensitivity_40": sensitivity_at(fit.rig, 40.0),
           "rms_px": fit.rms_fitted}
    return row, fit, checks


def _scan_distances(distances: np.ndarray, solve: Callable, cache: dict, tol_mm: float) -> list:
    """Solve every candidate distance, then refine between the best one's neighbours by a bounded scalar
    search (``solve`` fills ``cache``); the solved distances as sorted (key, (row, fit, checks)) pairs."""
    from scipy.optimize import minimize_scalar

    for D in distances:
        solve(float(D))
    done = sorted((k, v) for k, v in cache.items() if v is not None)
    if not done:
        raise RigError("no candidate distance gave a rig that lights the plane and matches the labels")
    costs = np.array([v[0]["cost"] for _, v in done])
    i = int(np.nanargmin(costs))
    lo = done[max(i - 1, 0)][0]
    hi = done[min(i + 1, len(done) - 1)][0]
    if hi > lo:
        def f(D):
            v = solve(float(D))
            return np.inf if v is None else v[0]["cost"]
        minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": tol_mm})
    return sorted((k, v) for k, v in cache.items() if v is not None)


def _base_kept(base: Rig, b0: dict, measured: BandPeriods, period_params: tuple, best_cost: float,
               base_cost: float, scan: list, base_checks: list) -> DepthFit:
    """The result when no distance and baseline beat the base rig on the fit's own objective: the base rig
    itself (labels made through it can only confirm it), with a note saying so."""
    refit = f" (with {', '.join(period_params)} refitted to the plane)" if period_params else ""
    note = (f"no distance and baseline{refit} explains the labels better than the base rig (cost "
            f"{best_cost:.4f} at best vs {base_cost:.4f}): the base rig is kept (labels made through it can only confirm it)")
    s0, s40 = centre_sensitivity(base), sensitivity_at(base, 40.0)
    return DepthFit(distance=b0["distance"], baseline=b0["baseline"],
                    fit=unfitted(measured, base, "the base rig kept (see the note above)"),
                    scan=scan, checks=base_checks, base_checks=base_checks,
                    sensitivity=s0, sensitivity_40=s40, base_distance=b0["distance"],
                    base_baseline=b0["baseline"], base_sensitivity=s0, base_sensitivity_40=s40, notes=[note],
                    kept=True)

def format_depth_fit(fit: DepthFit) -> str:
    """Plain-text summary of :func:`fit_depth`: the distance scan and the base vs fitted rig."""
    lines = ["phase-height relation from the labels (object residual after the baseline that zeroes its offset)",
             f"{'distance':>12}{'baseline':>12}{'cost':>8}{'obj |r|':>9}{'slope':>9}{'s(0)':>8}{'s(40)':>8}",
             f"{'mm':>12}{'mm':>12}{'':>8}{'rad':>9}{'rad/mm':>9}{'rad/mm':>8}{'rad/mm':>8}"]
    for r in fit.scan:
        lines.append(f"{r['distance_mm']:>12.1f}{r['baseline_mm']:>12.1f}{r['cost']:>8.4f}{r['object_residual']:>9.3f}"
                     f"{r['slope']:>+9.4f}{abs(r['sensitivity_0']):>8.3f}{abs(r['sensitivity_40']):>8.3f}")
    lines.append("")
    lines.append(_CHECK_HEADER)
    lines.append(_check_line("base", fit.base_checks, fit.base_sensitivity, fit.base_sensitivity_40))
    lines.append(_check_line("fitted", fit.checks, fit.sensitivity, fit.sensitivity_40))
    if fit.kept:
        lines.append(f"kept: distance {fit.distance:.1f} mm, baseline {fit.baseline:.1f} mm (the base rig); "
                     f"{abs(fit.sensitivity):.3f} rad/mm at the plane, {abs(fit.sensitivity_40):.3f} at 40 mm "
                     "(image centre)")
    else:
        lines.append(f"chosen: distance {fit.base_distance:.1f} -> {fit.distance:.1f} mm, baseline "
                     f"{fit.base_baseline:.1f} -> {fit.baseline:.1f} mm; {abs(fit.sensitivity):.3f} rad/mm at the "
                     f"plane, {abs(fit.sensitivity_40):.3f} at 40 mm (image centre)")
    lines += [f"note: {n}" for n in fit.notes]
    if not fit.kept:
        lines.append("(the period fit below starts from the rig moved to this distance and baseline: its 'base rig' "
                     "column is that rig, not --base)")
    return "\n".join(lines)
