"""Is a fringe image the way round its rig sees the scene? A check from the image's own phase and the rig, no
label and no network (:func:`check_orientation`).

One image cannot tell which way its phase grows, so the single-shot phase is read growing the way the rig's plane
phase grows (:func:`uhrnet.inference.prediction.fringe_phase`). An image rotated by 180 degrees, or mirrored across
its fringes, then reads as the image of a scene whose relief is NEGATED through the rig: objects come out below
the reference plane they stand on. Two things in the image can tell, both measured against the rig alone:

* **shadows** (the physics of :func:`fppsim.phase.unwrap.shadow_bridges` and of fit-rig's projector side): the
  projector ray that grazes an object's edge lands on the plane at the far side of its shadow, so one ray carries
  one phase at both ends, and the object end is raised by ``(Phi0(plane end) - Phi0(object end)) / s`` through the
  rig (``Phi0`` its plane phase, ``s`` its phase per mm). That is positive only when the plane end lies on one side
  of the shadow, the rig's; in a flipped image it lies on the other. Along the baseline (rows for vertical fringes)
  every shadow between a stretch of plane and a stretch of object votes;
* **the plane's fringes** (perspective): the reference plane's phase is the rig's ``Phi0`` up to a constant; a
  flipped image's plane follows ``Phi0`` flipped (and negated) instead. The share of the reliable pixels within
  :data:`PLANE_TOL_RAD` of each says which; through a rig whose plane phase is nearly linear (projector and camera
  axes near parallel) all three fit alike and this says nothing.

The plane pixels the shadows need are those of the best fitting of the three plane phases.

A false warning costs more than a missed one, so each evidence is read only where it held on images as given (the
constants below say where it did not): the shadows in an image mostly lit (a dark area that is not a shadow votes
like one) on a plane found on half of the reliable pixels, the plane's fringes for a flip only where a turned plane
phase fits most of them and the image is not mostly dark (objects on black: their flat tops fit anything).

Measured (docs/USAGE.md, predict: every number): the labelled pair and FP1523/1201 through the default rig,
FP672/541 and FP147/109 through rigs fitted to their own frames, and 40 rendered scenes (the default rig twice, the
FP147 and FP672 rigs, the parallel rig), each as given, rotated 180 degrees and mirrored across its fringes. With at
least :data:`MIN_RUNS` runs the shadows agreed with the rig in 0.62-1.00 of them as given and 0.00-0.32 turned; no
given frame reads flipped, every real frame turned does, and 8 of the 80 turned scene images do not (no plane in
view; no shadow through a rig whose plane phase is nearly linear; shadows agreeing on 0.32): silence does not prove
the orientation. Of 1498 images as given made to mislead it (crops, intensity, noise, blur, a plane blackened in
part or whole, objects on black, rigs of the right kind but not the image's; review h69r3), none reads flipped; a
dark stretch on the projector's side of every object, through a nearly linear rig, still does (said in the
evidence: :data:`SHADOWS_ALONE`).

numpy in, numpy out.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from fppsim.geometry.rig import Rig
from fppsim.phase import circular_median, wrap
from fppsim.phase.fringe_axis import fringe_axis, rig_phase_gradient
from fppsim.phase.unwrap import shadow_runs

__all__ = ["OrientationCheck", "check_orientation", "flipped_warning", "lean_warning", "plane_lean", "plane_phases",
           "shadow_sides"]

#: a reliable pixel is on a plane phase within this (rad) of it, once the image's phase origin is taken off
PLANE_TOL_RAD = 0.5
#: the plane phase that fits a reliable share at least this large, and this many times the other's, says the image
#: is as given (PLANE_MIN_SHARE) or flipped (PLANE_FLIP_SHARE: more, as a rig that is not the image's, projector on
#: the same side but of another baseline or yaw, fitted its turned plane phases to 0.39-0.50 of real frames, its own
#: to 0.17-0.27), the latter only in an image at most PLANE_MAX_DARK of which has no fringes: with no plane in view
#: the fit is the objects' flat tops', which may follow any of the three (boxes on black through FP147's rig:
#: mirrored 0.86, as given 0.48)
PLANE_MIN_SHARE = 0.5
PLANE_FLIP_SHARE = 0.6
PLANE_RATIO = 1.8
PLANE_MAX_DARK = 0.7
#: the shadows decide with at least this many runs, on a plane found on at least this share of the reliable pixels
#: (chance alone puts 0.16 of any phase within the tolerance; on a plane found on 0.35-0.40 of them, a wrong rig's or
#: the objects' flat tops, the runs voted flipped on images as given), in an image at most MAX_DARK_SHARE of which has
#: no fringes: a dark area that is not a shadow (a plane black or out of view but for a part of it) votes like a
#: shadow wherever the plane lies beyond it (0.28-0.84 dark gave unanimous flipped votes on images as given; the
#: scenes and real frames here are 0.02-0.24 dark)
MIN_RUNS = 15
SHADOW_PLANE_SHARE = 0.5
MAX_DARK_SHARE = 0.25
#: the share of the runs agreeing with the rig at or below which the image is flipped (0.32-0.38 agreed on images as
#: given with dark areas beside the objects), at or above which it is not
SHADOWS_FLIPPED = 0.25
SHADOWS_AS_GIVEN = 0.6
#: said of a flip the shadows call alone (the plane's fringes silent, as through a rig whose plane phase is nearly
#: linear): a dark stretch beside each object on the projector's side, a dark mat or base, votes as a shadow of a
#: turned image does (ray-traced boxes through the parallel rig, such stretches 25-50 px wide: called flipped)
SHADOWS_ALONE = (" (shadows alone: dark areas that are not shadows, beside the objects on the projector's side, read "
                 "so too)")
MIN_RELIABILITY = 0.5
#: the plane the orders path reads leans against the network's by more than this many fringe periods of height (at
#: the image centre) across the image (:func:`plane_lean`), and the rig's plane phase as given explains less than
#: LEAN_PLANE_FIT of the reliable pixels (:func:`check_orientation`), both: then it is said. Images as given: 0.03-0.09
#: period on the real pair, FP1523/1201 and FP672/541 (5 networks), at most 0.03 on 32 rendered scenes (3 networks),
#: plane fits 0.53-0.98; FP147/109 through a network of another rig 1.26 periods (the network sees the face flat, the
#: path lifts it), its fit 0.53 (a nearly linear plane phase: every orientation fits about alike). The pair and FP1523
#: upside down (mirrored ALONG their fringes, which the checks above cannot see): 1.56 and 1.37 periods, fits 0.24-0.25
LEAN_PERIODS = 0.5
LEAN_PLANE_FIT = 0.4
#: the lean is read only where the network's estimate puts at least this share of the image on the plane and the
#: path moved it
LEAN_MIN_SHARE = 0.1


@dataclass
class OrientationCheck:
    """What :func:`check_orientation` found. ``plane_fit``: the share of the reliable pixels on the rig's plane phase
    as given, rotated by 180 degrees and mirrored across the fringes (:func:`plane_phases`); ``shadow_runs``: the
    shadows that voted; ``shadows_agree``: the share of them whose plane end lies where the rig puts it (None: none);
    ``verdict``: ``"flipped"`` (the relief reads below the plane), ``"as given"`` or ``"undecided"``; ``evidence``:
    what decided, in words; ``dark_share``: the share of the image without fringes (shadows are not read above
    :data:`MAX_DARK_SHARE`)."""

    plane_fit: dict
    shadow_runs: int
    shadows_agree: float | None
    verdict: str
    evidence: str
    dark_share: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def plane_phases(rig: Rig) -> dict:
    """The rig's reference-plane phase (H, W) as an image shows it: ``as given``, ``rotated 180 deg`` and ``mirrored
    across its fringes`` (the last two negated, as the phase read growing the rig's way is)."""
    phi0 = rig.phase_at_height(0.0)
    across = 1 if fringe_axis(rig_phase_gradient(rig)) == "vertical" else 0
    return {"as given": phi0, "rotated 180 deg": -phi0[::-1, ::-1],
            "mirrored across its fringes": -np.flip(phi0, across)}


def shadow_sides(plane: np.ndarray, lit: np.ndarray, vertical: bool, side: int, skip: int = 2,
                 reach: int = 8) -> tuple[float, int]:
    """``(share, runs)``: of the shadow runs (``~lit``, at least 3 px) along the baseline (rows for ``vertical``
    fringes, else columns) with all lit pixels ``skip`` to ``reach`` px beyond both ends, one end mostly plane (>= 70 %
    of them) and the other mostly not, the share whose plane end lies ``side`` (+1: towards growing index) of the
    other; NaN when none votes."""
    pl, sh = (plane, ~lit) if vertical else (plane.T, ~lit.T)
    n = sh.shape[1]
    agree = runs = 0
    for r, x0, x1 in shadow_runs(sh):  # x0: last lit before the run, x1: first lit after it
        if x1 - x0 - 1 < 3 or x0 - reach + 1 < 0 or x1 + reach > n:
            continue
        before, after = slice(x0 - reach + 1, x0 - skip + 1), slice(x1 + skip, x1 + reach)
        if sh[r, before].any() or sh[r, after].any():
            continue
        pb, pa = float(pl[r, before].mean()), float(pl[r, after].mean())
        if pb >= 0.7 and pa <= 0.3:
            found = -1
        elif pa >= 0.7 and pb <= 0.3:
            found = 1
        else:
            continue
        runs += 1
        agree += found == side
    return (agree / runs if runs else float("nan")), runs


def check_orientation(wrapped: np.ndarray, reliability: np.ndarray, lit: np.ndarray, rig: Rig) -> OrientationCheck:
    """Whether the image whose single-shot phase is ``wrapped`` (read growing the rig's way; ``reliability``, ``lit``:
    its reliability and its pixels with fringes, (H, W)) is flipped through ``rig`` (module docstring). A rig with no
    plane in view: undecided."""
    if not rig.plane_in_view:
        return OrientationCheck({}, 0, None, "undecided", "the rig has no reference plane in view")
    w = np.asarray(wrapped, np.float64)
    lit = np.asarray(lit, bool)
    usable = lit & np.isfinite(w) & (np.nan_to_num(np.asarray(reliability, np.float64)) >= MIN_RELIABILITY)
    if not usable.any():
        return OrientationCheck({}, 0, None, "undecided", "no reliable fringe phase")
    on = {}
    for name, phi in plane_phases(rig).items():
        d = wrap(w - phi)
        on[name] = usable & (np.abs(wrap(d - circular_median(d[usable]))) < PLANE_TOL_RAD)
    fit = {k: float(v.sum() / usable.sum()) for k, v in on.items()}
    best = max(fit, key=fit.get)  # ties: as given (first)
    gu, gv = rig_phase_gradient(rig)
    vertical = fringe_axis((gu, gv)) == "vertical"
    per_mm = _centre_per_mm(rig)
    # raised by (Phi0(plane end) - Phi0(object end)) / per_mm > 0: the plane end lies sign(g / per_mm) of the object's
    side = int(np.sign((gu if vertical else gv) * per_mm))
    agree, runs = shadow_sides(on[best], lit, vertical, side)
    dark = float(1.0 - lit.mean())
    return OrientationCheck({k: round(v, 4) for k, v in fit.items()}, runs, None if runs == 0 else round(agree, 4),
                            *_verdict(fit, agree, runs, dark), dark_share=round(dark, 4))


def flipped_warning(orientation: dict | None, rig_name: str) -> str | None:
    """The sentence said of an image that reads flipped (``orientation``: :meth:`OrientationCheck.to_dict`, as the
    refine statistics carry it) through the rig named ``rig_name``, else None: one owner for predict's and
    evaluate-phase's warning, which never changes a height."""
    o = orientation or {}
    if o.get("verdict") != "flipped":
        return None
    return (f"relief below the reference plane through {rig_name}: rotated or mirrored image, or a rig with the "
            f"projector on the other side? ({o['evidence']})")


def plane_lean(height_mm: np.ndarray, moved: np.ndarray, estimate_mm: np.ndarray, rig: Rig,
               flat_mm: float = 1.0) -> dict:
    """How far the plane the orders path reads leans against the network's: a plane ``a + b row + c col`` fitted to
    ``height_mm - estimate_mm`` (mm, (H, W)) over the ``moved`` pixels the estimate puts within ``flat_mm`` of the
    reference plane, on those within half a fringe period of their median and then again on those within half a
    period of the last fit, until these no longer change (at most 10 fits): a region the path put at another order is
    left out (a large one only where the plane leans well under half a period across the rest). Returns
    ``{"mm": its rise across the image (corner to corner), "periods": the same in fringe periods of height at the
    image centre through ``rig``, "pixels": those moved flat pixels, before any is left out}``; ``mm`` and
    ``periods`` are None where they are fewer than :data:`LEAN_MIN_SHARE` of the image (no plane the network sees),
    ``periods`` also where the rig's phase does not change with height at the image centre."""
    h, e = np.asarray(height_mm, np.float64), np.asarray(estimate_mm, np.float64)
    on = np.asarray(moved, bool) & np.isfinite(h) & np.isfinite(e) & (np.abs(e) < flat_mm)
    out = {"mm": None, "periods": None, "pixels": int(on.sum())}
    if on.sum() < max(3, LEAN_MIN_SHARE * on.size):
        return out
    per_mm = abs(_centre_per_mm(rig))
    period = 2.0 * np.pi / per_mm if per_mm > 0 else np.inf
    rows, cols = np.nonzero(on)
    A = np.stack([np.ones(rows.size), rows, cols], axis=1).astype(np.float64)
    d = (h - e)[on]
    # started from the median level, not from a plane fitted to every pixel: a region one order off that holds a
    # large share of them (a third of FP1523 cropped to its bottom half) tilts such a plane enough to keep it, and
    # the step then read as a lean of 1.3 periods
    keep = np.abs(d - np.median(d)) < 0.5 * period
    for _ in range(10):
        coef = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
        again = np.abs(d - A @ coef) < 0.5 * period
        if again.sum() < 3 or (again == keep).all():
            break
        keep = again
    rise = abs(coef[1]) * (on.shape[0] - 1) + abs(coef[2]) * (on.shape[1] - 1)
    periods = round(float(rise / period), 3) if np.isfinite(period) else None
    return {**out, "mm": round(float(rise), 3), "periods": periods}


def lean_warning(stats: dict | None, rig_name: str) -> str | None:
    """The sentence said of an image whose plane leans more than :data:`LEAN_PERIODS` through the rig named
    ``rig_name`` while the rig's plane phase as given fits under :data:`LEAN_PLANE_FIT` of it (``stats``: the refine
    statistics, ``plane_lean`` from :func:`plane_lean` and ``orientation`` from :func:`check_orientation`), else None;
    None too for an image that reads flipped: :func:`flipped_warning` names that (the pair mirrored across its fringes
    leans 1.9 periods, and "mirrored along its fringes" would send the reader the wrong way). One owner for predict's
    and evaluate-phase's warning, which never changes a height."""
    lean = (stats or {}).get("plane_lean") or {}
    orientation = (stats or {}).get("orientation") or {}
    fit = orientation.get("plane_fit", {}).get("as given")
    if (lean.get("periods") is None or lean["periods"] <= LEAN_PERIODS or fit is None or fit >= LEAN_PLANE_FIT
            or orientation.get("verdict") == "flipped"):
        return None
    return (f"the plane the phase reads through {rig_name} leans {lean['periods']:.1f} fringe periods "
            f"({lean['mm']:.1f} mm) across the image where the network sees it flat, and the rig's plane fringes "
            f"follow the image's on {fit:.2f} of it: an image mirrored along its fringes, or not of this rig? "
            "(the path's heights are kept)")


def _centre_per_mm(rig: Rig) -> float:
    """The rig's phase per mm of height (rad / mm; :meth:`fppsim.geometry.rig.Rig.sensitivity`) at the pixel
    centre of the image."""
    cam = rig.camera
    return float(rig.sensitivity(0.0, 1.0, np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0]))[()])


def _verdict(fit: dict, agree: float, runs: int, dark: float = 0.0) -> tuple[str, str]:
    """``(verdict, evidence)`` of the plane fits, the shadows' votes and the image's dark share (the thresholds
    above); flipped or as given only where no evidence says the other."""
    flip_name = max(list(fit)[1:], key=fit.get)
    given, flip = fit["as given"], fit[flip_name]
    said = {"flipped": [], "as given": []}
    if flip >= PLANE_FLIP_SHARE and flip >= PLANE_RATIO * given and dark <= PLANE_MAX_DARK:
        said["flipped"].append(f"its plane's fringes follow the rig's plane {flip_name} on {flip:.2f} of the "
                               f"reliable pixels, as given on {given:.2f}")
    elif given >= PLANE_MIN_SHARE and given >= PLANE_RATIO * flip:
        said["as given"].append(f"its plane's fringes follow the rig's plane as given on {given:.2f} of the reliable "
                                f"pixels, {flip_name} on {flip:.2f}")
    shadows = runs >= MIN_RUNS and max(fit.values()) >= SHADOW_PLANE_SHARE and dark <= MAX_DARK_SHARE
    if shadows and agree <= SHADOWS_FLIPPED:
        said["flipped"].append(f"{runs - round(agree * runs)} of {runs} shadows lie on the projector's side"
                               + ("" if said["flipped"] else SHADOWS_ALONE))
    elif shadows and agree >= SHADOWS_AS_GIVEN:
        said["as given"].append(f"{round(agree * runs)} of {runs} shadows lie away from the projector")
    for verdict, other in (("flipped", "as given"), ("as given", "flipped")):
        if said[verdict] and not said[other]:
            return verdict, "; ".join(said[verdict])
    return "undecided", "; ".join(said["flipped"] + said["as given"]) or (
        f"plane phase as given {given:.2f}, {flip_name} {flip:.2f}; {runs} shadow runs"
        + (f", {agree:.2f} away from the projector" if runs else "")
        + (f" (not read: {dark:.2f} of the image dark)" if runs and dark > MAX_DARK_SHARE else ""))
