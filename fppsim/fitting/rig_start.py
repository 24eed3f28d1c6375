"""A rig from its own images: the start of ``fppsim fit-rig`` when there is no calibration (no ``--base``).

What a set of fringe images (or phase-shifting scans) of an unknown rig can and cannot tell:

* the camera's size (the images'); not its focal length: the intrinsics come from a field of view,
  the default rig's (29.2 deg across the width) unless the user gives ``fov`` or ``focal``;
* the fringe direction and the phase's slope across the image: the plane's absolute phase is, for two
  pinholes and a plane, the ratio of two linear functions of the camera pixel,
  ``Phi(u, v) = (a . (u, v, 1)) / (b . (u, v, 1))`` up to a constant, i.e. four numbers besides the
  offset: the direction and size of the phase gradient (the projector's roll and the fringe periods)
  and its perspective change across the image (the projector's yaw and pitch). A phase map pins all
  four (:func:`fit_plane_phase`); one fringe image pins them only through its wrapped phase,
  unwrapped on the plane (:func:`image_phase_map`), and cannot tell which way the phase grows;
* which side of the camera the projector is on: raised surfaces shift the phase one way, the sign of
  ``grad(Phi) . (C - P)`` (camera and projector centres C, P). Objects stand on the plane, so the
  sign of the objects' phase relief against the fitted plane gives the side
  (:func:`relief_sign`; phase maps only: a single image's wrapped phase cannot);
* NOT the depth scale: the whole scene, camera distance and baseline scaled together, gives the
  same images. The distance (default 500 mm, the default rig's) and the baseline (default 0.66 x the
  distance, the default rig's 330 mm at 500 mm: its triangulation angle) come from the user
  (``distance``, ``baseline``) or from height labels (``fit-rig --params ...,distance`` with a base).

The start rig (:func:`start_rig`): a camera looking straight down at the plane from ``distance``, a
projector of 912 x 1140 pixels (the default rig's DMD) at the camera's height, ``baseline`` mm beside
(vertical fringes) or above / below it (horizontal fringes), rolled about its axis so that its
columns run along the measured phase gradient (0, 90, 180 or -90 deg plus the fringes' lean), lens
shift so the scene centre lands mid-projector, and a focal length that lights the camera's whole view
with a margin. :func:`fit_plane_phase` then fits the projector's yaw, pitch, roll and the periods to
the plane's phase (least squares with a free constant offset, plane pixels chosen robustly), and
:func:`rig_from_images` does all of it for a folder (``fppsim fit-rig`` without ``--base``).

Units: mm, radians (degrees in reports), camera pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fppsim.errors import RigError
from fppsim.geometry.rig import Device, Rig, rotation

__all__ = ["DEFAULT_FOV_DEG", "DEFAULT_DISTANCE", "BASELINE_RATIO", "PROJECTOR_SIZE", "PhaseMap", "camera_for",
           "start_rig", "plane_phase_gradient", "relief_sign", "fit_plane_phase", "PlanePhaseFit",
           "image_phase_map", "phase_maps_of", "StartRigResult", "rig_from_images", "plane_phase_residual",
           "fringe_axis"]

# the default rig's camera: fx = 1230 px across 640 px
DEFAULT_FOV_DEG = math.degrees(2.0 * math.atan(320.0 / 1230.0))  # 29.17 deg across the image width
DEFAULT_DISTANCE = 500.0  # mm, camera above the plane (the default rig's)
BASELINE_RATIO = 330.0 / 500.0  # baseline / distance of the default rig (its triangulation angle, 33.4 deg)
PROJECTOR_SIZE = (912, 1140)  # DMD columns x rows (the default rig's)
_COVER = 1.4  # the projector's image spans this many times the camera's view of the plane


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


def fringe_axis(gradient) -> str:
    """``"vertical"`` fringes (the phase grows along the camera columns) or ``"horizontal"`` (along the
    rows), from the phase gradient ``(g_u, g_v)`` (rad/px)."""
    gu, gv = (float(g) for g in gradient)
    return "vertical" if abs(gu) >= abs(gv) else "horizontal"


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


# ====================================================================== what a phase map says
@dataclass
class PhaseMap:
    """One image's phase for the fit: ``phase`` (H, W) float64 rad, absolute (phase-shifting) or unwrapped
    from one fringe image (then ``absolute`` is False: known only up to 2 pi steps between regions and
    its sign is a convention); ``valid`` (H, W) bool; ``name`` for messages."""

    phase: np.ndarray
    valid: np.ndarray
    name: str = ""
    absolute: bool = True


def _grid(shape, valid, n: int, rng=None) -> np.ndarray:
    """Up to ``n`` valid pixels (flat indices), evenly strided (deterministic)."""
    idx = np.flatnonzero(valid.ravel())
    if idx.size > n:
        idx = idx[np.linspace(0, idx.size - 1, n).round().astype(int)]
    return idx


def plane_phase_gradient(phase: np.ndarray, valid: np.ndarray, n: int = 40_000) -> tuple[float, float]:
    """The plane's phase gradient ``(g_u, g_v)`` (rad/px): a robust (iteratively trimmed) linear fit
    ``Phi ~ c + g_u u + g_v v`` over the valid pixels (objects are the outliers)."""
    H, W = phase.shape
    ok = valid & np.isfinite(phase)
    idx = _grid((H, W), ok, n)
    if idx.size < 50:
        raise RigError("too few pixels with a phase to measure the fringe direction")
    v, u = np.divmod(idx, W)
    A = np.stack([np.ones(idx.size), u - W / 2.0, v - H / 2.0], axis=1)
    b = phase.ravel()[idx]
    sel = np.ones(idx.size, bool)
    for _ in range(6):
        coef = np.linalg.lstsq(A[sel], b[sel], rcond=None)[0]
        r = b - A @ coef
        s = 1.4826 * np.median(np.abs(r[sel] - np.median(r[sel])))
        sel = np.abs(r - np.median(r[sel])) <= max(2.5 * s, 0.5)
        if sel.sum() < 50:
            break
    return float(coef[1]), float(coef[2])


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
_STEP = {"yaw": math.radians(2.0), "pitch": math.radians(2.0), "roll": math.radians(2.0)}
# search bounds in the scaled units: yaw and pitch +-30 deg, roll +-20 deg (the start has the fringes'
# direction already), periods x / 2.7
_BOUND = {"yaw": 15.0, "pitch": 15.0, "roll": 10.0, "periods": 20.0}


@dataclass
class PlanePhaseFit:
    """Result of :func:`fit_plane_phase`: the fitted ``rig``, the parameter changes (``params``: yaw /
    pitch / roll in rad relative to the start, periods), the constant offset per map (rad: the rig's
    phase = map phase + offset on the plane), the plane pixels' residual (median |r| and RMS, rad, after
    the offset), the plane share of the valid pixels per map, and the start rig's median |r|."""

    rig: Rig
    params: dict
    offsets: list
    median_rad: float
    rms_rad: float
    plane_share: list
    start_median_rad: float
    planes: list = field(default_factory=list, repr=False)  # (H, W) bool plane pixels per map
    residuals: list = field(default_factory=list, repr=False)  # (H, W) phase - rig phase - offset, rad

    def to_dict(self) -> dict:
        return {"params": self.params, "offsets_rad": self.offsets, "plane_median_residual_rad": self.median_rad,
                "plane_rms_residual_rad": self.rms_rad, "plane_share": self.plane_share,
                "start_median_residual_rad": self.start_median_rad}


def _adjust(rig: Rig, values: dict) -> Rig:
    from fppsim.fitting.fit_periods import adjust_rig

    return adjust_rig(rig, **values)


def plane_phase_residual(rig: Rig, phase: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, float]:
    """``(residual, offset)``: the map's phase minus the rig's reference-plane phase
    (:meth:`fppsim.geometry.rig.Rig.phase_at_height` at 0 mm) less the constant offset that centres
    the residual on the plane (histogram mode, then the median within 1 rad), NaN where invalid. The
    check of a rig against a phase-shifting frame: the plane pixels' median |residual|."""
    from fppsim.phase.fringe import plane_level

    pp = rig.phase_at_height(0.0)
    d = np.where(valid, phase - pp, np.nan)
    ok = np.isfinite(d)
    if not ok.any():
        return d, float("nan")
    c = plane_level(d, ok, bin_width=0.05, window=1.0)
    return d - c, -c


def fit_plane_phase(start: Rig, maps: list[PhaseMap], params: tuple[str, ...] = PLANE_PARAMS,
                    pixels: int = 6000, plane_rad: float = 0.5, rounds: int = 3) -> PlanePhaseFit:
    """Fit ``params`` (of yaw, pitch, roll, periods; the projector turned about its own axes, the
    camera fixed) of ``start`` so its reference-plane phase matches the maps' phase on the plane, one
    free constant offset per map (the phase origin of a scan is arbitrary).

    Plane pixels are chosen robustly: a first fit with a Cauchy loss over all valid pixels (objects are
    outliers of the four-parameter plane), then ``rounds`` fits on the pixels within ``max(plane_rad,
    3 robust sigmas)`` of it (plain least squares). ``pixels``: evenly strided pixels per map and fit.
    Raises RigError when a map has too few valid pixels or the fitted projector leaves part of the
    camera's view of the plane unlit.
    """
    from scipy.optimize import least_squares

    from fppsim.fitting.fit_periods import plane_coverage

    params = tuple(params)
    bad = [p for p in params if p not in PLANE_PARAMS]
    if bad:
        raise RigError(f"the plane-phase fit adjusts {', '.join(PLANE_PARAMS)}, not {', '.join(bad)}")
    H, W = start.camera.height, start.camera.width
    for m in maps:
        if m.phase.shape != (H, W):
            raise RigError(f"{m.name}: the phase map is {m.phase.shape[1]} x {m.phase.shape[0]} px but the rig's "
                           f"camera is {W} x {H}")
    uv = start.camera.pixel_grid()
    f0 = float(start.periods)

    def values(x):
        out = {}
        for p, xi in zip(params, x):
            out[p] = f0 * math.exp(xi * 0.05) if p == "periods" else xi * _STEP[p]
        return out

    def model(x, idx_list):
        rig = _adjust(start, values(x))
        flat = uv.reshape(-1, 2)
        return [rig.phase_at_height(0.0, flat[idx]) for idx in idx_list]

    def fit(x0, idx_list, loss, scale):
        targets = [m.phase.ravel()[idx] for m, idx in zip(maps, idx_list)]

        def fun(z):
            x, c = z[: len(params)], z[len(params):]
            try:
                preds = model(x, idx_list)
            except RigError:
                return np.full(sum(len(t) for t in targets), 1e3)
            r = np.concatenate([p - t - ci for p, t, ci in zip(preds, targets, c)])
            return np.where(np.isfinite(r), r, 1e3)

        preds = model(x0, idx_list)
        c0 = [float(np.median(p - t)) for p, t in zip(preds, targets)]
        lo = np.concatenate([[-_BOUND[p] for p in params], np.full(len(c0), -np.inf)])
        z0 = np.clip(np.concatenate([x0, c0]), lo + 1e-9, -lo - 1e-9)
        sol = least_squares(fun, z0, loss=loss, f_scale=scale, x_scale=1.0, bounds=(lo, -lo),
                            diff_step=1e-5, max_nfev=200)
        return sol.x[: len(params)], sol.x[len(params):]

    idx_all = []
    for m in maps:
        ok = m.valid & np.isfinite(m.phase)
        if ok.sum() < 200:
            raise RigError(f"{m.name}: fewer than 200 pixels with a phase")
        idx_all.append(_grid((H, W), ok, pixels))
    x = np.zeros(len(params))
    start_med = _median_plane_residual(start, maps, plane_rad)[0]
    x, _ = fit(x, idx_all, "cauchy", 0.5)
    planes = []
    for _ in range(int(rounds)):
        rig = _adjust(start, values(x))
        planes, idx_plane = [], []
        for m in maps:
            r, _ = plane_phase_residual(rig, m.phase, m.valid & np.isfinite(m.phase))
            ok = np.isfinite(r)
            s = 1.4826 * float(np.median(np.abs(r[ok]))) if ok.any() else 0.0
            plane = ok & (np.abs(np.nan_to_num(r, nan=np.inf)) <= max(plane_rad, 3.0 * s))
            if plane.sum() < 200:
                plane = ok & (np.abs(np.nan_to_num(r, nan=np.inf)) <= np.percentile(np.abs(r[ok]), 30))
            planes.append(plane)
            idx_plane.append(_grid((H, W), plane, pixels))
        x, _ = fit(x, idx_plane, "linear", 1.0)
    rig = _adjust(start, values(x))
    rig.name = start.name + " (plane phase fitted: " + ", ".join(params) + ")"
    rig.check()
    coverage = plane_coverage(rig)
    if coverage < 0.999:
        raise RigError(f"the fitted projector lights only {coverage:.1%} of the camera's view of the plane")
    med, rms, offsets, shares, planes, residuals = _median_plane_residual(rig, maps, plane_rad, planes)
    return PlanePhaseFit(rig=rig, params={p: float(v) for p, v in values(x).items()}, offsets=offsets,
                         median_rad=med, rms_rad=rms, plane_share=shares, start_median_rad=start_med,
                         planes=planes, residuals=residuals)


def _median_plane_residual(rig: Rig, maps: list[PhaseMap], plane_rad: float, planes=None):
    """Median |residual| and RMS over the plane pixels of all maps (the plane re-chosen as the pixels
    within ``max(plane_rad, 3 robust sigmas)`` unless ``planes`` are given), offsets, shares."""
    allr, offsets, shares, out_planes, residuals = [], [], [], [], []
    for k, m in enumerate(maps):
        ok0 = m.valid & np.isfinite(m.phase)
        r, off = plane_phase_residual(rig, m.phase, ok0)
        ok = np.isfinite(r)
        if planes is None:
            s = 1.4826 * float(np.median(np.abs(r[ok]))) if ok.any() else 0.0
            plane = ok & (np.abs(np.nan_to_num(r, nan=np.inf)) <= max(plane_rad, 3.0 * s))
        else:
            plane = planes[k] & ok
        if plane.any():  # the offset that centres the plane pixels themselves
            c = float(np.median(r[plane]))
            r, off = r - c, off - c
        allr.append(r[plane])
        offsets.append(float(off))
        shares.append(float(plane.sum() / max(int(ok0.sum()), 1)))
        out_planes.append(plane)
        residuals.append(r)
    a = np.concatenate(allr) if allr else np.array([np.nan])
    a = a if a.size else np.array([np.nan])
    return (float(np.median(np.abs(a))), float(np.sqrt(np.mean(a ** 2))), offsets, shares, out_planes, residuals)
