"""A rig from its own images: the start of ``fppsim fit-rig`` when there is no calibration (no ``--base``).

What a set of fringe images (or phase-shifting scans) of an unknown rig can and cannot tell:

* the camera's size (the images'); not its focal length: the intrinsics come from a field of view,
  the default rig's (29.2 deg across the width) unless the user gives ``fov`` or ``focal``;
* the fringe direction and the phase's slope across the image: the plane's absolute phase is, for two
  pinholes and a plane, the ratio of two linear functions of the camera pixel,
  ``Phi(u, v) = (a . (u, v, 1)) / (b . (u, v, 1))`` up to a constant, i.e. four numbers besides the
  offset: the direction and size of the phase gradient (the projector's roll and the fringe periods)
  and its perspective change across the image (the projector's yaw and pitch). A phase map pins all
  four (:func:`fppsim.fitting.plane_phase.fit_plane_phase`, which also finds the plane's pixels); one
  fringe image pins them only through its wrapped phase, unwrapped on the plane
  (:func:`fppsim.fitting.plane_phase.image_phase_map`), and cannot tell which way the phase grows;
* which side of the camera the projector is on: raised surfaces shift the phase one way, the sign of
  ``grad(Phi) . (C - P)`` (camera and projector centres C, P). Objects stand on the plane, so the
  sign of the objects' phase relief against the fitted plane gives the side (phase maps only); the
  projector's shadows, whose far side is the plane, give it too (plain images as well);
* NOT the depth scale: the whole scene, camera distance and baseline scaled together, gives the
  same images, and so does a steeper angle with lower objects. The distance (default 500 mm, the default
  rig's) and the baseline (default 0.66 x the distance, the default rig's 330 mm at 500 mm: its
  triangulation angle) come from the user (``distance``, ``baseline``) or from height labels
  (``fit-rig --params ...,distance`` with a base). Whatever the scale, the synthetic scenes follow the
  frames: the largest object's extent (px) and the objects' phase relief (rad) measured here become the
  rig file's ``scenes`` (:mod:`fppsim.fitting.frame_scenes`), which ``fppsim generate`` renders.

The start rig (:func:`start_rig`): a camera looking straight down at the plane from ``distance``, a
projector of 912 x 1140 pixels (the default rig's DMD) at the camera's height, ``baseline`` mm beside
(vertical fringes) or above / below it (horizontal fringes), rolled about its axis so that its
columns run along the measured phase gradient (0, 90, 180 or -90 deg plus the fringes' lean), lens
shift so the scene centre lands mid-projector, and a focal length that lights the camera's whole view
with a margin. The plane-phase fit then adjusts the projector's yaw, pitch, roll and the periods to
the plane's phase (least squares with a free constant offset, plane pixels chosen robustly), and
:func:`rig_from_images` does all of it for a folder (``fppsim fit-rig`` without ``--base``).

Units: mm, radians (degrees in reports), camera pixels.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from fppsim.commands import ReportLines
from fppsim.dataio.readers import load_fringe_images, open_source
from fppsim.dataio.readers.samples import pick_evenly
from fppsim.errors import RigError, UsageError, InputError
from fppsim.files import JSON_SUFFIXES, RIG_SUFFIXES, Output, atomic_write_text, check_outputs, holds_keys, json_text
from fppsim.geometry.rig_files import save_rig
from fppsim.fitting.fit_depth import fit_depth, format_depth_fit
from fppsim.fitting.fit_periods import format_fit, measure_bands
from fppsim.fitting.frame_scenes import frame_scenes, scenes_line
from fppsim.fitting.fit_rig import check_fit_options, fit_baseline, format_baseline_fit, unused_label_options
from fppsim.fitting.start_result import (StartRigResult, first_lines, plane_fits_poorly, poor_plane_words,
                                         saturation_words, start_lines)
from fppsim.fitting.plane_phase import (LENS_PARAMS, PLANE_PARAMS, PhaseMap, find_plane,
                                        fit_plane_phase, fringe_axis, image_phase_map, plane_phase_gradient,
                                        relief_sign, shadow_side)
from fppsim.geometry.rig import Device, Rig, rotation
from fppsim.phase import wrap
from fppsim.phase.fringe_axis import fringe_carrier, fringe_orientation, oriented_single_shot_phase

__all__ = ["DEFAULT_FOV_DEG", "DEFAULT_DISTANCE", "BASELINE_RATIO", "PROJECTOR_SIZE", "SIDES", "camera_for",
           "start_rig", "phase_maps_of", "StartRigResult", "rig_from_images", "plane_fits_poorly", "StartRigConfig",
           "StartFitResult", "fit_rig_from_images", "plain_image_gradient"]

# the default rig's camera: fx = 1230 px across 640 px
DEFAULT_FOV_DEG = math.degrees(2.0 * math.atan(320.0 / 1230.0))  # 29.17 deg across the image width
DEFAULT_DISTANCE = 500.0  # mm, camera above the plane (the default rig's)
BASELINE_RATIO = 330.0 / 500.0  # baseline / distance of the default rig (its triangulation angle, 33.4 deg)
PROJECTOR_SIZE = (912, 1140)  # DMD columns x rows (the default rig's)
_COVER = 1.4  # the projector's image spans this many times the camera's view of the plane
# the camera's radial distortion is fitted (phase-shifting scans) when the pinhole's plane residual exceeds this
# (rad; the real frames here fit to 0.03-0.12 without it, and k1 gains them under 10 %) and kept when it takes at
# least LENS_GAIN of it away
LENS_FROM_RAD = 0.1
LENS_GAIN = 0.3


# ====================================================================== the start rig
def camera_for(width: int, height: int, distance: float = DEFAULT_DISTANCE, fov: float | None = None,
               focal: float | None = None) -> Device:
    """A camera ``width`` x ``height`` px looking straight down at the plane from ``distance`` mm, square
    pixels, principal point at the image centre; focal length ``focal`` px, else from the horizontal
    field of view ``fov`` (degrees across the width; default :data:`DEFAULT_FOV_DEG`)."""
    if focal is None:
        fov = DEFAULT_FOV_DEG if fov is None else float(fov)
        if not 1.0 <= fov <= 170.0:
            raise RigError(f"the field of view must be 1..170 degrees across the image width, got {fov:g}")
        focal = (width / 2.0) / math.tan(math.radians(fov) / 2.0)
    focal = float(focal)
    if not (np.isfinite(focal) and focal > 0):
        raise RigError(f"the camera focal length must be > 0 px, got {focal:g}")
    if not (np.isfinite(distance) and distance > 0):
        raise RigError(f"the camera distance must be > 0 mm, got {distance:g}")
    return Device.looking_down([0.0, 0.0, float(distance)], focal, focal, (width - 1) / 2.0, (height - 1) / 2.0,
                               int(width), int(height))


def start_rig(width: int, height: int, gradient, side: int = 1, distance: float = DEFAULT_DISTANCE,
              baseline: float | None = None, fov: float | None = None, focal: float | None = None,
              projector: tuple[int, int] = PROJECTOR_SIZE, name: str = "") -> Rig:
    """The start rig for images ``width`` x ``height`` px whose plane phase grows along ``gradient``
    ``(g_u, g_v)`` (rad per camera px, at the image centre).

    The camera is :func:`camera_for`. The projector hangs at the camera's height, ``baseline`` mm
    (default :data:`BASELINE_RATIO` x ``distance``) from it along the world axis of the fringe
    direction (x for vertical fringes, y for horizontal ones), on the side ``side`` (+1: raised
    surfaces LOWER the phase, as on the default rig; -1: they raise it): a raised surface moves the
    plane point a pixel sees by ``h (C - P) / D``, so the phase changes by ``grad(Phi) . (C - P) h / D``.
    It looks straight down, rolled about its axis so its columns grow along the gradient (the
    fringes' lean included), with lens shift so the scene centre lands mid-projector, its focal length
    such that its image spans 1.4 x the camera's view of the plane; ``periods`` across it give the
    measured period at the image centre. Raises RigError for a zero gradient.
    """
    gu, gv = float(gradient[0]), float(gradient[1])
    g = math.hypot(gu, gv)
    if not (np.isfinite(g) and g > 0):
        raise RigError("the images show no fringe phase gradient")
    cam = camera_for(width, height, distance, fov, focal)
    D = float(distance)
    B = BASELINE_RATIO * D if baseline is None else float(baseline)
    if not (np.isfinite(B) and B > 0):
        raise RigError(f"the baseline must be > 0 mm, got {B:g}")
    if not 0.01 <= B / D <= 10.0:  # (a camera 1 mm up and a projector 1 km away gave NaN and the wrong reason)
        raise RigError(f"a baseline of {B:g} mm at a distance of {D:g} mm ({B / D:.3g} x the distance): a fringe "
                       "projection rig's is 0.01-10 x (the default rig's 0.66 x); check --baseline and --distance")
    # world direction of the phase gradient (camera looking down: world x = +u, world y = -v)
    gw = np.array([gu, -gv]) / g
    axis = np.array([1.0, 0.0]) * np.sign(gw[0]) if abs(gw[0]) >= abs(gw[1]) else np.array([0.0, 1.0]) * np.sign(gw[1])
    # grad . (C - P) has the sign of -side  =>  P - C = side * axis (along the gradient's axis)
    offset = int(side if side else 1) * B * axis
    centre = np.array([offset[0], offset[1], D])
    roll = math.atan2(gw[1], gw[0])  # projector columns along the world gradient direction
    R = rotation("z", roll) @ np.diag([1.0, -1.0, -1.0])
    Wp, Hp = int(projector[0]), int(projector[1])
    # camera's view of the plane (half-extents, mm) seen along the projector's own x and y axes
    xh, yh = (width / 2.0) / cam.K[0, 0] * D, (height / 2.0) / cam.K[1, 1] * D
    c, s = abs(math.cos(roll)), abs(math.sin(roll))
    ex, ey = c * xh + s * yh, s * xh + c * yh
    fp = min((Wp / 2.0) / (_COVER * ex), (Hp / 2.0) / (_COVER * ey)) * D
    t = -R @ centre
    cx = (Wp - 1) / 2.0 - fp * t[0] / t[2]
    cy = (Hp - 1) / 2.0 - fp * t[1] / t[2]
    proj = Device(K=[[fp, 0, cx], [0, fp, cy], [0, 0, 1]], R=R, t=t, width=Wp, height=Hp)
    # periods: the projector column changes by fp / fc per camera px along the gradient (parallel axes)
    period_px = 2.0 * math.pi / g
    periods = Wp * cam.K[0, 0] / (period_px * fp)
    side_word = {1: "lowers", -1: "raises"}.get(int(side), "lowers")
    where = {(1, 0): "right of", (-1, 0): "left of", (0, 1): "above", (0, -1): "below"}[
        (int(np.sign(round(offset[0], 9))), int(np.sign(round(offset[1], 9))))]
    rig = Rig(camera=cam, projector=proj, periods=float(periods),
              name=name or f"from images ({width} x {height} px, projector {B:.0f} mm {where} the camera, "
                           f"a raised surface {side_word} the phase)")
    rig.check()
    return rig


def phase_maps_of(path, max_maps: int = 4, convention: str = "benchmark", negate_sin: bool = False
                  ) -> tuple[list[PhaseMap], str, list]:
    """The phase maps of a folder for :func:`fppsim.fitting.plane_phase.fit_plane_phase` (at most ``max_maps``,
    evenly spaced): ``(maps, kind, images)``. Frames with a measured absolute phase (phase-shifting scans
    in the public ``PSin/PCos/Fringe`` layout, ``atan2(-PSin, -PCos) + pi + 2 pi Order``; fppsim's native
    samples with their decoded ``phase_psp``: :meth:`fppsim.dataio.readers.Source.measured_phase`) give
    absolute maps (``kind`` ``"phase"``); any other layout :func:`fppsim.dataio.readers.load_fringe_images`
    reads gives one single-shot map per image (``"fringe images"``). ``images`` are the fringe images
    read (:class:`fppsim.dataio.readers.FringeImage`, for the label-based fits). ``convention`` /
    ``negate_sin``: scans in the public layout written another way
    (:func:`fppsim.dataio.readers.load_psp_folder_sample`)."""
    src = open_source(path)
    images, _ = load_fringe_images(path, max_maps, convention=convention, negate_sin=negate_sin)
    ids = src.measured_phase_ids()
    if ids:
        maps = []
        for i in pick_evenly(len(ids), max_maps):
            measured = src.measured_phase(ids[int(i)], convention=convention, negate_sin=negate_sin)
            if measured is not None:
                maps.append(PhaseMap(measured[0], measured[1], ids[int(i)]))
        if maps:
            return maps, "phase", images
    maps = []
    for im in images[:max_maps]:
        try:
            maps.append(image_phase_map(im.gray, im.valid, im.name))
        except (InputError, RigError) as exc:  # a blank or fringe-less image: name it and its folder
            named = str(exc) if str(exc).startswith(f"{im.name}: ") else f"{im.name}: {exc}"
            raise type(exc)(f"{path}: {named}") from None
    return maps, "fringe images", images


# ====================================================================== the whole start: a folder -> a rig
SIDES = {"right": (1.0, 0.0), "left": (-1.0, 0.0), "above": (0.0, 1.0), "below": (0.0, -1.0)}
"""``--projector-side`` words -> the projector's direction from the camera in world x, y (image right, up)."""


def _world_axis(gradient) -> np.ndarray:
    gw = np.array([gradient[0], -gradient[1]], float)
    return np.array([np.sign(gw[0]), 0.0]) if abs(gw[0]) >= abs(gw[1]) else np.array([0.0, np.sign(gw[1])])


def _where(rig: Rig) -> str:
    d = rig.projector.center[:2] - rig.camera.center[:2]
    if abs(d[0]) >= abs(d[1]):
        return f"{abs(d[0]):.0f} mm {'right of' if d[0] > 0 else 'left of'} the camera"
    return f"{abs(d[1]):.0f} mm {'above' if d[1] > 0 else 'below'} the camera"


def _object_extent(planes, maps, min_share: float = 0.005, lit: bool = True) -> tuple[float, bool]:
    """The largest object's extent (px, the longer side of its bounding box, median over the maps): the
    biggest connected region off the plane of ``lit`` pixels with fringes (:attr:`PhaseMap.fringed`; else those
    with a phase), at least ``min_share`` of the image; 0 when there is none. Also whether it reaches the image
    border in any map (then it is at least that big). Lit, not only those with a phase: a plain image's reliable
    single-shot phase breaks an object into pieces (FP672/541 as a PNG: 61 px where its scans measure 262). With
    fringes: a dark background's noise is lit, not object. Without the phase-less pixels within 4 px of the plane:
    a shadow's rim joined the object (333 px; without it 265). Scans: fringed = lit = valid. Frames without a plane
    (``lit`` False) keep the pixels with a phase: the lit ones (and a 'plane' that is part of an object) give bigger
    objects whose relief caps, with no relief measured, grow with them; FP147's face on black at 640 px instead of
    351 (caps 84-133 mm for a face of about 42 mm) trained to 0.84-0.92 of flat at epochs 13-14 against 0.69-0.72
    (one seed, stop 68)."""
    from scipy import ndimage as ndi  # SciPy: only here

    sizes, border = [], False
    for plane, m in zip(planes, maps):
        keep = m.valid
        if lit:  # less a shadow's phase-less rim on the plane
            keep = (m.lit if m.fringed is None else m.fringed) & ~(ndi.binary_dilation(plane, iterations=4) & ~m.valid)
        lab, n = ndi.label(ndi.binary_opening(keep & ~plane, iterations=2))
        if n == 0:
            continue
        counts = np.bincount(lab.ravel())[1:]
        k = int(np.argmax(counts)) + 1
        if counts[k - 1] < min_share * plane.size:
            continue
        rows, cols = np.nonzero(lab == k)
        sizes.append(max(rows.max() - rows.min(), cols.max() - cols.min()) + 1)
        H, W = plane.shape
        edge = 2  # the opening pulls a region this far off the border
        border |= bool(rows.min() <= edge or cols.min() <= edge or rows.max() >= H - 1 - edge
                       or cols.max() >= W - 1 - edge)
    return (float(np.median(sizes)), border) if sizes else (0.0, False)


def _object_relief(fit, maps) -> float:
    """The objects' phase relief (rad, the 99th percentile of |phase - plane| off the plane where it
    exceeds 1 rad); 0 when fewer than 50 such pixels."""
    off = np.concatenate([np.abs(r[m.valid & ~p & np.isfinite(r)]) for r, p, m in zip(fit.residuals, fit.planes, maps)])
    off = off[off > 1.0]
    return float(np.percentile(off, 99)) if off.size > 50 else 0.0


def _local_gradient(images, axis: str) -> tuple[float, float]:
    """The fringes' phase gradient (rad/px, growing along +columns / +rows as a single image's phase does by
    convention): the median wrapped step between reliable 4-neighbours of each image's single-shot phase, the median
    over the images. On objects on black it is the objects' own (FP1523 on black: 11.45-11.58 px, the plane's 11.73),
    where the plane fit of their phase, unwrapped object by object, gave 45.9 px. The phase is demodulated at the
    carrier :func:`fppsim.phase.fringe_axis.fringe_carrier` reads (within 20 %): the plain spectrum's peak is the
    outline's on a figurine on black (FP672/541: 34-56 px, then 3-5 x the plane's 10.54 px; now 8.9 px)."""
    steps = []
    for im in images:
        gray = np.asarray(im.gray, np.float64)
        try:
            period = 1.0 / math.hypot(*fringe_carrier(gray, im.valid))
        except InputError as exc:
            raise InputError(f"{im.name}: {exc}") from None
        ssp = oriented_single_shot_phase(gray, axis, mask=im.valid, period=period)
        ok = ssp.valid & (ssp.reliability >= 0.3)
        w = ssp.wrapped.astype(np.float64)
        du, dv = wrap(np.diff(w, axis=1)), wrap(np.diff(w, axis=0))
        pu, pv = ok[:, 1:] & ok[:, :-1], ok[1:] & ok[:-1]
        if pu.sum() < 200 or pv.sum() < 200:
            raise RigError(f"{im.name}: too few pixels with a reliable fringe phase")
        steps.append((float(np.median(du[pu])), float(np.median(dv[pv]))))
    gu, gv = np.median(np.asarray(steps), axis=0)
    return float(gu), float(gv)


def _objects_gradient(images, axis: str, gradient, scans: bool, fringe_period: float | None) -> tuple[float, float]:
    """The fringes' gradient with no plane in view: the images' own local steps (:func:`_local_gradient`), for scans
    the way their phase grows (``gradient``'s sign along ``axis``); ``fringe_period`` (px, the plane's) sets the
    period instead, along the axis with no lean, refused in one line when more than 3 x off the measured one. Not the
    scans' plane gradient: their phase, fitted over a figurine, gave 18.4 px on FP672/541 on black (the plane's
    10.54), where a period 4 x the plane's passed the check; the local steps read 8.9 px."""
    local = _local_gradient(images, axis)
    if scans and (local[0] if axis == "vertical" else local[1]) * (gradient[0] if axis == "vertical"
                                                                  else gradient[1]) < 0:
        local = (-local[0], -local[1])  # a single image's phase grows one way by convention, the scans' is measured
    if fringe_period is None:
        return local
    measured = 2.0 * np.pi / math.hypot(*local)
    if not 1 / 3 <= float(fringe_period) / measured <= 3:  # objects widen or narrow it, not threefold
        raise RigError(f"--fringe-period {fringe_period:g} px is {float(fringe_period) / measured:.3g} x the "
                       f"period the frames show ({measured:.1f} px): give the plane's period in camera pixels")
    g = 2.0 * np.pi / float(fringe_period)
    return (math.copysign(g, local[0]), 0.0) if axis == "vertical" else (0.0, math.copysign(g, local[1]))


def plain_image_gradient(images, gradient) -> tuple[tuple[float, float], str]:
    """Plain fringe images: ``(gradient, axis)``, the fringes' direction from their spectrum (as their phase maps
    were read). Where the maps' plane gradient points the other way (objects on black, their phase unwrapped piece
    by piece: FP672's figurine on black read as horizontal fringes) the gradient is :func:`_local_gradient`'s."""
    votes = [fringe_orientation(np.asarray(im.gray, np.float64), im.valid) for im in images]
    axis = "vertical" if votes.count("vertical") >= votes.count("horizontal") else "horizontal"
    return (gradient, axis) if fringe_axis(gradient) == axis else (_local_gradient(images, axis), axis)


def _maps_and_size(path, max_maps, convention, negate_sin):
    maps, kind, images = phase_maps_of(path, max_maps, convention, negate_sin)
    if not maps:
        raise InputError(f"{path}: no fringe images")
    H, W = maps[0].phase.shape
    for m in maps[1:]:
        if m.phase.shape != (H, W):
            raise InputError(f"{path}: {m.name}: image is {m.phase.shape[1]} x {m.phase.shape[0]} px, the first "
                             f"({maps[0].name}) is {W} x {H}: one rig, one image size")
    return maps, kind, images, W, H


def _maps_gradient(path, maps) -> tuple[float, float]:
    """The median plane phase gradient of ``maps``, naming a map with too few phase pixels (an all-black iPattern)."""
    try:
        return tuple(float(v) for v in np.median([plane_phase_gradient(m.phase, m.valid) for m in maps], axis=0))
    except RigError as exc:
        bad = next(m.name for m in maps if (m.valid & np.isfinite(m.phase)).sum() < 50)
        raise RigError(f"{path}: {bad}: {exc} (a pixel has one where its phase-shifting sums are not both 0 "
                       "and its image is not black)") from None


def _first_plane_fit(maps, W, H, gradient, D, baseline, fov, focal):
    """Plane pixels per map from a provisional start (the side does not change the plane's phase), then the
    plane fit on the side most maps prefer: ``(fit, side, maps)`` (single-shot maps unwrapped on the plane).
    At steep angles a start on the wrong side cannot follow the plane's perspective (its fitted projector no
    longer lights the whole view: FP672 at a 580 mm baseline), so both sides are tried."""
    starts = {sd: start_rig(W, H, gradient, sd, D, baseline, fov, focal) for sd in (1, -1)}
    maps, seeds, wins = list(maps), [], 0
    for k, m in enumerate(maps):
        found = {sd: find_plane(st, m, gradient) for sd, st in starts.items()}
        agree = {sd: max((c for _, c, _ in f[1]), default=-1.0) for sd, f in found.items()}
        sd = -1 if agree[-1] > agree[1] + 0.05 else 1
        wins += sd
        plane, _, one = found[sd]
        seeds.append(plane)
        if not m.absolute and one is not None:  # its plane pixels unwrapped onto one period of the plane fit
            maps[k] = PhaseMap(np.where(m.valid, one.rig.phase_at_height(0.0) - one.offsets[0] + one.residuals[0],
                                        np.nan), m.valid, m.name, absolute=False, reliable=m.reliable,
                               shadow=m.shadow, fringed=m.fringed)
    first = 1 if wins >= 0 else -1
    return fit_plane_phase(starts[first], maps, seeds=seeds), first, maps


def _projector_side(fit, maps, kind, gradient, axis, projector_side, assumed) -> tuple[int, str]:
    """Which side of the camera the projector is on (+1: raised surfaces lower the phase) and where that
    came from: the option when given (the measurement said beside it when it disagrees), else the objects'
    phase relief (scans), else the shadows, else assumed (``assumed["projector_side"]``)."""
    waxis = _world_axis(gradient)
    relief, share = 0, float("nan")
    if kind == "phase":
        res = np.concatenate([r[m.valid].ravel() for r, m in zip(fit.residuals, maps)])
        pl = np.concatenate([p[m.valid].ravel() for p, m in zip(fit.planes, maps)])
        relief, share = relief_sign(res, pl, np.ones(res.shape, bool))
    votes = [shadow_side(p, m.lit, axis) for p, m in zip(fit.planes, maps)]
    shadow_dir = int(np.sign(sum(d * n for d, n in votes)))
    n_votes = sum(n for _, n in votes)
    shadow_pdir = np.array([shadow_dir, 0.0]) if axis == "vertical" else np.array([0.0, -shadow_dir])
    shadow = int(np.sign(shadow_pdir @ waxis))
    if projector_side is not None:
        pdir = np.array(SIDES[projector_side])
        if abs(pdir @ waxis) < 0.5:
            raise RigError(f"projector side '{projector_side}': the fringes are {axis}, so the projector is "
                           + ("left or right of" if axis == "vertical" else "above or below") + " the camera")
        side, source = int(np.sign(pdir @ waxis)), "given (--projector-side)"
        measured = -relief if relief else shadow
        if measured and measured != side:
            source += ("; the scans measure the other side (" + (f"{share:.0%} of the relief off the plane" if relief
                       else f"{n_votes} shadow runs") + "): check the option")
        return side, source
    if relief:
        source = (f"measured: raised surfaces {'raise' if relief > 0 else 'lower'} the phase "
                  f"({share:.0%} of the relief off the plane)")
        if shadow and shadow != -relief:
            source += f"; the shadows say the other side ({n_votes} runs): check the scans"
        elif shadow:
            source += f", and the shadows agree ({n_votes} runs)"
        return -relief, source
    if shadow:
        return shadow, f"measured from the projector's shadows ({n_votes} shadow runs)"
    assumed["projector_side"] = "assumed"
    return 1, ("NOT identifiable from these images (no phase relief, no clear shadows): assumed; "
               "give --projector-side")


def _lens(fit, maps, W, H, gradient, side, D, baseline, fov, focal):
    """``(params, fit, lens)``: a lens bends the plane's phase: its radial distortion is fitted when the
    pinhole plane fits worse than LENS_FROM_RAD and kept when it takes LENS_GAIN of the residual away;
    ``lens``: (pinhole rad, with k1 rad, k1) when tried, else None."""
    if fit.median_rad <= LENS_FROM_RAD:
        return PLANE_PARAMS, fit, None
    bent = fit_plane_phase(start_rig(W, H, gradient, side, D, baseline, fov, focal), maps,
                           params=PLANE_PARAMS + LENS_PARAMS, seeds=fit.planes)
    lens = (fit.median_rad, bent.median_rad, bent.params["k1"])
    if bent.median_rad < (1.0 - LENS_GAIN) * fit.median_rad:
        return PLANE_PARAMS + LENS_PARAMS, bent, lens
    return PLANE_PARAMS, fit, lens


def scenes_of(start: StartRigResult, rig: Rig) -> dict | None:
    """The synthetic scenes for the frames ``start`` measured, through ``rig``
    (:func:`fppsim.fitting.frame_scenes.frame_scenes`)."""
    return frame_scenes(start.extent_px, start.relief_rad, rig, start.at_border)


def rig_from_images(path, *, fov: float | None = None, focal: float | None = None, distance: float | None = None,
                    baseline: float | None = None, projector_side: str | None = None, max_maps: int = 4,
                    convention: str = "auto", negate_sin: bool = False, fringe_period: float | None = None,
                    say=None) -> StartRigResult:
    """A rig from a folder of fringe images or phase-shifting scans alone (``fppsim fit-rig`` without
    ``--base``; module docstring): camera from the image size and ``fov`` / ``focal``; the fringe
    direction, the phase slope and its perspective from the plane's phase (:func:`phase_maps_of`,
    plane pixels found by :func:`find_plane`); the projector side from the objects' phase relief
    (phase-shifting scans), else from the shadows (:func:`shadow_side`), else ``projector_side``
    (``left`` / ``right`` / ``above`` / ``below``; when given it wins), else assumed; ``distance``
    (default 500 mm) and ``baseline`` (default 0.66 x distance) as given or assumed; the synthetic scenes
    that follow the frames at that scale (``result.scenes``, :func:`scenes_of`); ``convention`` / ``negate_sin`` as
    :func:`phase_maps_of`. ``say`` receives each report line (:func:`fppsim.fitting.start_result.start_lines`).

    Scans whose plane model fits poorly (:func:`plane_fits_poorly`: too few pixels, too large a residual, or pixels
    that reach fewer than 2 of the image's sides: no reference plane in view, e.g. busts on a black background, or a
    phase read the wrong way) cannot pin the projector's pose: a RigError names what
    is needed, unless ``distance``, ``baseline`` and ``projector_side`` are all given; then the rig is the
    start rig at that geometry (projector aimed at the view's centre, the measured fringe period), its pose
    assumed and said so (``StartRigResult.no_plane``). Without a plane the fringes' period and lean are measured
    on the objects' images (:func:`_objects_gradient`), whose surfaces turned towards or away from the projector
    widen or narrow them (FP672 with its plane blacked out: 8.9 px on the figurine, 10.54 px on the plane):
    ``fringe_period`` (px at the image centre, the plane's, e.g. from any frame that shows it) then sets the period,
    along the measured axis with no lean;
    with a plane in view it is not used (the plane's is measured) and said. RigError / ValueError (one line) for
    unusable inputs."""
    if projector_side is not None and projector_side not in SIDES:
        raise RigError(f"projector side must be one of {', '.join(SIDES)}, got {projector_side!r}")
    if fov is not None and focal is not None:
        raise RigError("give the camera's field of view or its focal length, not both")
    say = say or (lambda line: None)
    maps, kind, images, W, H = _maps_and_size(path, max_maps, convention, negate_sin)
    D = DEFAULT_DISTANCE if distance is None else float(distance)
    assumed = {k: v for k, v, given in (("distance_mm", D, distance), ("baseline_mm", BASELINE_RATIO * D, baseline),
                                       ("fov_deg", DEFAULT_FOV_DEG, fov if focal is None else focal)) if given is None}
    gradient = _maps_gradient(path, maps)
    axis = fringe_axis(gradient)
    if kind != "phase":
        gradient, axis = plain_image_gradient(images[:max_maps], gradient)
    lines = first_lines(path, maps, kind, images)
    for line in lines:
        say(line)
    fit, first, maps = _first_plane_fit(maps, W, H, gradient, D, baseline, fov, focal)
    side, source = _projector_side(fit, maps, kind, gradient, axis, projector_side, assumed)
    if side != first:
        fit = fit_plane_phase(start_rig(W, H, gradient, side, D, baseline, fov, focal), maps, seeds=fit.planes)
    params, lens = PLANE_PARAMS, None
    if kind == "phase":  # before the plane is judged: a lens bends it
        params, fit, lens = _lens(fit, maps, W, H, gradient, side, D, baseline, fov, focal)
    no_plane = plane_fits_poorly(fit)  # single images too: FP147's face on black (62 % of the view) was a 'plane'
    if no_plane:
        missing = [f"--{k.replace('_', '-')}" for k, v in (("distance", distance), ("baseline", baseline),
                                                         ("projector_side", projector_side)) if v is None]
        what = "scans" if kind == "phase" else "images"
        if missing:  # plain images have no --convention to read them by
            read = " (or the phase is written another way: --convention, --negate-sin)" if kind == "phase" else ""
            raise RigError(f"{path}: the plane model fits the {what} poorly ({poor_plane_words(fit)}): no reference "
                           f"plane in view{read}, so the projector's pose cannot be fitted; give {what} that show the "
                           f"plane, or {', '.join(missing)} for a rig whose projector pose is assumed (and --fringe-period "
                           f"PX if you know the plane's fringe period: the objects' own is used otherwise){saturation_words(images)}")
        # the side is the given one; the relief and shadows it was checked against were read off a "plane" fitted
        # to the objects, so they measure nothing here
        source = f"given (--projector-side; without the plane the {what} cannot measure it)"
        gradient = _objects_gradient(images[:max_maps], axis, gradient, kind == "phase", fringe_period)
        if fringe_period is None:
            assumed["fringe_period"] = "measured on the objects"
        rig = start_rig(W, H, gradient, side, D, baseline, fov, focal)
    else:
        if fringe_period is not None:
            say(f"--fringe-period {fringe_period:g} px not used: the plane is in view, and its period is measured")
        rig = fit.rig
    where = _where(rig)
    relief = _object_relief(fit, maps) if kind == "phase" and not no_plane else 0.0
    extent, at_border = _object_extent(fit.planes, maps, lit=not no_plane)  # no plane: see _object_extent
    depth = "given" if "distance_mm" not in assumed and "baseline_mm" not in assumed else "assumed"
    rig.plane_in_view = not no_plane
    rig.name = (f"from its own images ({W} x {H} px, {axis} fringes, projector {where}; "
                + ("projector pose assumed: no plane in view" if no_plane else "plane phase fitted")
                + f", depth scale {depth})")
    result = StartRigResult(rig=rig, fit=fit, kind=kind, n_maps=len(maps), gradient=gradient, axis=axis, side=side,
                            side_source=source, where=where, sensitivity=float(rig.sensitivity()), assumed=assumed,
                            lines=lines, images=images, params=params, lens=lens, relief_rad=relief,
                            extent_px=extent, at_border=at_border, no_plane=no_plane, absolute=kind == "phase")
    result.scenes = scenes_of(result, rig)
    for line in start_lines(result):
        lines.append(line)
        say(line)
    rig.check_usable()
    return result


# ====================================================================== fppsim fit-rig without --base
@dataclass
class StartRigConfig:
    """What ``fppsim fit-rig`` does without ``--base`` (the fields are its flags; the rest as
    :class:`fppsim.fitting.fit_rig.FitRigConfig`).

    real : the images: phase-shifting scans (public layout, fppsim's native PSP output) or any layout
        :func:`fppsim.dataio.readers.load_fringe_images` reads. out : the rig file (refused if it exists
        unless ``force``). fov / focal : the camera's field of view (deg across the width) or focal length
        (px); None: the default rig's field of view. distance / baseline : mm; None: 500 and 0.66 x the
        distance (images cannot tell them; the rig file's ``scenes`` follow the frames at that scale). projector_side :
        ``left`` / ``right`` / ``above`` / ``below``; None: measured (relief, shadows) or assumed. fringe_period :
        px, the reference plane's fringe period for scans with no plane in view (:func:`rig_from_images`).
        convention / negate_sin : how the public layout's PSin / PCos / Order make the phase
        (:func:`fppsim.dataio.readers.load_psp_folder_sample`). params,
        sensitivity, col_bands, row_bands : the label-based fits that follow with height labels and
        vertical fringes (``label_options``: those given, refused where it cannot run). max_images : images
        read (at most 4 phase maps are fitted). json : also write the report as JSON.
    """

    real: object
    out: object
    fov: float | None = None
    focal: float | None = None
    distance: float | None = None
    baseline: float | None = None
    projector_side: str | None = None
    fringe_period: float | None = None
    convention: str = "auto"
    negate_sin: bool = False
    params: tuple = ("yaw", "roll", "periods")
    col_bands: int = 4
    row_bands: int = 3
    max_images: int = 20
    sensitivity: str = "auto"
    json: object = None
    force: bool = False
    label_options: tuple = ()  # flags of params / col_bands / row_bands / sensitivity given: fit_rig.unused_label_options

    def __post_init__(self):

        if self.fov is not None and self.focal is not None:
            raise UsageError("give --fov or --focal, not both")
        for key, lo, hi in (("fov", 1.0, 170.0), ("focal", 1.0, 1e6), ("distance", 1.0, 1e6), ("baseline", 1.0, 1e6),
                            ("fringe_period", 2.0, 1e4)):
            v = getattr(self, key)
            if v is not None and not (np.isfinite(v) and lo <= v <= hi):
                raise UsageError(f"--{key.replace('_', '-')} must be a number in {lo:g}..{hi:g}, got {v}")
        if self.projector_side is not None and self.projector_side not in SIDES:
            raise UsageError(f"--projector-side must be one of {', '.join(SIDES)}, got {self.projector_side!r}")
        check_fit_options(self)


@dataclass
class StartFitResult:
    """What :func:`fit_rig_from_images` did: the ``start`` (:class:`StartRigResult`), the label-based
    period ``fit`` / ``baseline`` / ``depth`` fits when height labels refined it (else None), the rig
    written (``rig``, to ``out``) and the report ``lines``."""

    start: StartRigResult
    rig: Rig
    out: object
    lines: list
    fit: object = None
    baseline: object = None
    depth: object = None
    scenes: dict | None = None  # the rig file's scenes (fppsim.fitting.frame_scenes), through the rig written

    def to_dict(self) -> dict:
        """The JSON document of ``--json``: ``start`` (the rig from the images), the label fits and ``scenes``."""
        doc = {"start": self.start.to_dict(), "scenes": self.scenes}
        if self.fit is not None:
            doc.update(self.fit.to_dict())
        if self.baseline is not None:
            doc["sensitivity"] = self.baseline.to_dict()
        if self.depth is not None:
            doc["depth"] = self.depth.to_dict()
        return doc


def fit_rig_from_images(config: StartRigConfig, echo=None) -> StartFitResult:
    """``fppsim fit-rig`` without ``--base``: the rig from the images alone (:func:`rig_from_images`, with
    ``config``'s ``fov``, ``focal``, ``distance``, ``baseline``, ``projector_side``); with height labels
    and vertical fringes (``sensitivity="auto"``) the label-based fits follow from it as from a base rig:
    the baseline whose fringe shift per mm matches the labels (:func:`fppsim.fitting.fit_rig.fit_baseline`),
    or with ``distance`` in ``params`` the camera distance and baseline (:func:`fppsim.fitting.fit_depth.fit_depth`).
    Writes ``config.out`` (and ``config.json``). ``echo`` receives every report line."""
    lines = ReportLines(echo)
    say = lines.say
    out, *_ = check_outputs([Output("--out", config.out, RIG_SUFFIXES, "a rig file", holds_keys("camera", "projector")),
                             Output("--json", config.json, JSON_SUFFIXES, "the JSON report", holds_keys("start"))],
                            inputs=[config.real], force=config.force)  # before any work
    if "distance" in config.params and config.sensitivity != "auto":
        raise RigError("fitting 'distance' needs the height labels: drop it from the parameters or use "
                       "sensitivity 'auto'")
    unused_label_options(config, open_source(config.real).labelled)  # refused, not ignored, before any work
    start = rig_from_images(config.real, fov=config.fov, focal=config.focal, distance=config.distance,
                            baseline=config.baseline, projector_side=config.projector_side,
                            max_maps=min(int(config.max_images), 4), convention=config.convention,
                            negate_sin=config.negate_sin, fringe_period=config.fringe_period, say=say)
    rig, fit, bfit, dfit = start.rig, None, None, None
    labelled = any(im.height_mm is not None for im in start.images)
    if "distance" in config.params and not labelled:
        raise RigError("fitting 'distance' needs images with height labels, objects and projector shadows "
                       "(figshare folder or the real-sample pair)")
    unused_label_options(config, True, start.axis)  # before anything is written
    if labelled and config.sensitivity == "auto":
        if start.axis != "vertical":
            say("height labels: the label-based depth fits read vertical fringes only; the depth scale stays "
                "as above")
        else:
            images, _ = load_fringe_images(config.real, config.max_images, convention=config.convention,
                                           negate_sin=config.negate_sin)
            measured = measure_bands(images, config.col_bands, config.row_bands)
            params = tuple(config.params)
            say("")
            if "distance" in params:
                dfit = fit_depth(images, measured, rig, params)
                if dfit is None:
                    raise RigError("fitting 'distance' needs images with height labels, objects and projector "
                                   "shadows (figshare folder or the real-sample pair)")
                say(format_depth_fit(dfit))
                fit = dfit.fit
            else:
                bfit = fit_baseline(images, measured, rig, params)
                if bfit is not None:
                    say(format_baseline_fit(bfit))
                    fit = bfit.fit
                else:
                    say("height sensitivity: no labelled images with enough object pixels; baseline kept")
            if fit is not None:
                say("")
                say(format_fit(fit))
                rig = fit.rig
    scenes = scenes_of(start, rig)
    if rig is not start.rig and scenes != start.scenes:
        say(f"scenes     after the label fits: {scenes_line(scenes)}")
    doc = rig.to_dict()
    if scenes is not None:  # what fppsim generate --scenes auto renders through this rig
        doc["scenes"] = scenes
    save_rig(doc, out)
    say(f"rig: {out}")
    result = StartFitResult(start, rig, out, list(lines), fit, bfit, dfit, scenes)
    if config.json:
        atomic_write_text(config.json, json_text(result.to_dict(), indent=1))
    return result
