"""The period fit of a rig to real fringe images: the core of ``fppsim fit-rig`` (:mod:`fppsim.fitting.fit_rig`).

The fringe period a camera sees on the reference plane follows from the rig alone: a camera pixel
``(u, v)`` sees the plane point ``X(u, v)``, which the projector sees at column ``u_p(X)``; the pattern
``cos(2 pi f u_p / W_p)`` therefore has the horizontal period (camera pixels)

    T(u, v) = W_p / (f |d u_p / d u|)

(:func:`period_map`; no rendering). :func:`measure_bands` measures the period per column band and per
row band of real images, :func:`fit_rig_periods` adjusts a few projector parameters until the band periods of
:func:`period_map` match, and the fringe lines' angle on the plane (:func:`plane_tilt`). The baseline
fit (:mod:`fppsim.fitting.fit_rig`) and the depth fit (:mod:`fppsim.fitting.fit_depth`) both build on this module, and
the ``fit-rig`` workflow (:func:`fppsim.fitting.fit_rig.fit_rig_images`) on all three.

Units: mm, radians, camera pixels for periods.
"""

from __future__ import annotations

import warnings
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from fppsim.phase.measure import estimate_period, fringe_tilt
from fppsim.dataio.readers import FringeImage
from fppsim.geometry.rig import Device, Rig, RigError, rotation
from fppsim.errors import InputError

__all__ = ["PARAMETERS", "BandPeriods", "RigFit", "period_map", "band_model", "adjust_rig", "measure_bands", "fit_rig_periods",
           "plane_tilt", "format_fit", "unfitted", "plane_coverage", "cover_plane"]

PARAMETERS = {
    "yaw": "rotation of the projector about its own y axis (rad); tilts the pattern's depth left to right",
    "pitch": "rotation of the projector about its own x axis (rad); period trend top to bottom",
    "roll": "rotation of the projector about its optical axis (rad); tilts the fringes",
    "baseline": "distance between camera and projector centres along world x (mm)",
    "periods": "fringe periods across the projector width",
    "focal": "projector focal length fx = fy (px)",
    "distance": "camera height above the reference plane (mm); camera and projector move away from the scene "
                "together (positions scaled about the world origin, both focal lengths with them: the plane's "
                "image and fringes stay); sets how fast the height sensitivity grows with height",
}
"""Parameters :func:`fit_rig_periods` can adjust (name -> meaning)."""

# typical scales: keep the optimiser's steps comparable and the weak prior meaningful
_SCALE = {"yaw": np.radians(2.0), "pitch": np.radians(2.0), "roll": np.radians(2.0), "baseline": 20.0,
          "periods": 2.0, "focal": 30.0, "distance": 50.0}


# ====================================================================== the analytic period map
def _plane_points(cam: Device, uv: np.ndarray) -> np.ndarray:
    return cam.backproject(uv, cam.plane_depth(uv))


def _lit(rig: Rig, uv: np.ndarray) -> np.ndarray:
    """(...) bool: the reference-plane points camera pixels ``uv`` (..., 2) see fall inside the projector image."""
    proj = rig.projector
    with np.errstate(invalid="ignore", divide="ignore"):
        uvp, z = proj.project(_plane_points(rig.camera, uv))
    return (z > 0) & (uvp[..., 0] >= -0.5) & (uvp[..., 0] <= proj.width - 0.5) \
        & (uvp[..., 1] >= -0.5) & (uvp[..., 1] <= proj.height - 0.5)


def period_map(rig: Rig, step: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal fringe period (camera px) of the rig's pattern on its reference plane.

    Parameters
    ----------
    rig : the rig (distortion of both devices included).
    step : evaluate every ``step``-th camera pixel in u and v.

    Returns
    -------
    ``(u, v, period)``: column and row coordinates (1-D, camera px) and the (len(v), len(u)) float64
    period ``W_p / (f |du_p/du|)``; NaN where the plane point is outside the projector or behind it.
    """
    cam, proj = rig.camera, rig.projector
    u = np.arange(0, cam.width, step, dtype=np.float64)
    v = np.arange(0, cam.height, step, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    h = 0.5
    up = []
    for du in (-h, h):
        X = _plane_points(cam, np.stack([uu + du, vv], axis=-1))
        uvp, z = proj.project(X)
        up.append(np.where(z > 0, uvp[..., 0], np.nan))
    with np.errstate(divide="ignore", invalid="ignore"):
        deriv = np.abs(up[1] - up[0]) / (2 * h)
        period = proj.width / (rig.periods * deriv)
    return u, v, np.where(_lit(rig, np.stack([uu, vv], axis=-1)), period, np.nan)


def plane_tilt(rig: Rig, step: int = 8) -> float:
    """Angle of the pattern's lines on the reference plane from the camera's vertical, degrees, positive
    when a line leans right going down (as :func:`fppsim.phase.measure.fringe_tilt` measures images): the
    median of ``atan(-(du_p/dv) / (du_p/du))`` over the lit plane. A rolled projector tilts the lines;
    the real figshare rig: about -1.35 deg."""
    cam, proj = rig.camera, rig.projector
    u = np.arange(0, cam.width, step, dtype=np.float64)
    v = np.arange(0, cam.height, step, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    h = 0.5

    def up(du, dv):
        uvp, z = proj.project(_plane_points(cam, np.stack([uu + du, vv + dv], axis=-1)))
        return np.where(z > 0, uvp[..., 0], np.nan)

    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = -(up(0, h) - up(0, -h)) / (up(h, 0) - up(-h, 0))
    ratio = ratio[np.isfinite(ratio)]
    return float(np.degrees(np.arctan(np.median(ratio)))) if ratio.size else float("nan")


def _band_edges(n: int, bands: int) -> np.ndarray:
    return np.linspace(0, n, bands + 1).round().astype(int)


def band_model(rig: Rig, col_bands: int = 4, row_bands: int = 3, step: int = 4) -> dict:
    """Periods of :func:`period_map` per column band and per row band (the mean frequency of a band,
    what an FFT of the band measures), plus the left and right halves. Keys: ``columns`` (col_bands,),
    ``rows`` (row_bands,), ``halves`` (2,), all camera px; ``tilt_deg`` (1,), :func:`plane_tilt`."""
    u, v, T = period_map(rig, step)
    freq = 1.0 / T

    def mean_period(mask2d):
        f = freq[mask2d]
        f = f[np.isfinite(f)]
        return float(1.0 / f.mean()) if f.size else float("nan")

    W, H = rig.camera.width, rig.camera.height
    ce, re = _band_edges(W, col_bands), _band_edges(H, row_bands)
    uu, vv = np.meshgrid(u, v)
    cols = [mean_period((uu >= a) & (uu < b)) for a, b in zip(ce[:-1], ce[1:])]
    rows = [mean_period((vv >= a) & (vv < b)) for a, b in zip(re[:-1], re[1:])]
    halves = [mean_period(uu < W // 2), mean_period(uu >= W // 2)]
    return {"columns": np.array(cols), "rows": np.array(rows), "halves": np.array(halves),
            "tilt_deg": np.array([plane_tilt(rig, 2 * step)])}


# ====================================================================== changing the rig
def _recentre(rig: Rig, proj: Device) -> Device:
    """Shift the projector's principal point so the plane point seen at the camera's image centre lands
    at the projector's centre (lens shift keeps the camera view lit)."""
    cam = rig.camera
    centre = np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0])
    X = _plane_points(cam, centre)
    uv, _ = proj.project(X)
    K = proj.K.copy()
    K[0, 2] += (proj.width - 1) / 2.0 - uv[0]
    K[1, 2] += (proj.height - 1) / 2.0 - uv[1]
    return Device(K=K, R=proj.R, t=proj.t, width=proj.width, height=proj.height, dist=proj.dist)


def base_values(rig: Rig) -> dict:
    """Current values of :data:`PARAMETERS` (angles relative to the rig itself, hence 0)."""
    return {"yaw": 0.0, "pitch": 0.0, "roll": 0.0,
            "baseline": float(rig.projector.center[0] - rig.camera.center[0]),
            "periods": float(rig.periods), "focal": float(rig.projector.K[0, 0]),
            "distance": float(rig.camera.center[2])}


def adjust_rig(rig: Rig, recentre: bool = True, **values) -> Rig:
    """A copy of ``rig`` with the projector changed by ``values`` (names of :data:`PARAMETERS`).

    Angles rotate the projector about its own centre (device-frame axes), ``baseline`` moves it along
    world x relative to the camera, ``periods`` and ``focal`` replace the rig's values. The camera is
    unchanged, except by ``distance`` (applied first): the camera's and the projector's centres are
    scaled about the world origin by ``k = distance / camera height`` and both devices' focal lengths
    by ``k`` (the camera's view of the plane stays exactly the same for a camera looking straight
    down; the baseline scales with ``k`` unless ``baseline`` is given, which keeps the triangulation
    angle and, to first order, the plane's sensitivity; ``baseline`` and ``focal``, when given, are
    the values after the scaling). With ``recentre`` the projector's principal point follows (see
    :func:`_recentre`).
    """
    unknown = set(values) - set(PARAMETERS)
    if unknown:
        raise RigError(f"unknown rig parameter(s) {', '.join(sorted(unknown))} (known: {', '.join(PARAMETERS)})")
    cam, p = rig.camera, rig.projector
    K = p.K.copy()
    c = p.center.copy()
    if "distance" in values:
        d = float(values["distance"])
        if not (np.isfinite(d) and d > 0 and cam.center[2] > 0):
            raise RigError(f"distance must be > 0 mm with the camera above the plane, got {d}")
        k = d / float(cam.center[2])
        Kc = cam.K.copy()
        Kc[:2, :2] *= k
        cam = Device(K=Kc, R=cam.R, t=-cam.R @ (k * cam.center), width=cam.width, height=cam.height, dist=cam.dist)
        K[:2, :2] *= k
        c = k * c
    R = p.R.copy()
    for name, axis in (("roll", "z"), ("pitch", "x"), ("yaw", "y")):
        if values.get(name):
            R = rotation(axis, float(values[name])) @ R
    if "baseline" in values:
        c[0] = cam.center[0] + float(values["baseline"])
    if "focal" in values:
        K[0, 0] = K[1, 1] = float(values["focal"])
    proj = Device(K=K, R=R, t=-R @ c, width=p.width, height=p.height, dist=p.dist)
    out = dataclasses.replace(rig, camera=cam, projector=proj, periods=float(values.get("periods", rig.periods)))
    if recentre:
        out.projector = _recentre(out, proj)
    return out


def plane_coverage(rig: Rig, step: int = 8) -> float:
    """Fraction of the camera's view of the reference plane that falls inside the projector image (every
    ``step``-th camera pixel in u and v)."""
    cam = rig.camera
    uu, vv = np.meshgrid(np.arange(0, cam.width, step, dtype=np.float64),
                         np.arange(0, cam.height, step, dtype=np.float64))
    return float(_lit(rig, np.stack([uu, vv], axis=-1)).mean())


def cover_plane(rig: Rig, margin: int = 8) -> Rig:
    """``rig`` itself when its projector lights the camera's whole view of the reference plane, else a copy
    whose projector image is grown (same pose, focal length and pixel pitch; the principal point moved
    with the added pixels, ``periods`` scaled to the new width) to hold that view plus ``margin`` projector
    px: every plane point keeps its phase up to one constant. For rigs whose projector size is a modelling
    choice (:mod:`fppsim.fitting.rig_start`: a start has no real DMD size), not for a calibrated one."""
    cam, proj = rig.camera, rig.projector
    W, H = cam.width, cam.height
    u, v = np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)
    border = np.concatenate([np.stack([u, np.zeros(W)], -1), np.stack([u, np.full(W, H - 1.0)], -1),
                             np.stack([np.zeros(H), v], -1), np.stack([np.full(H, W - 1.0), v], -1)])
    uvp, z = proj.project(_plane_points(cam, border))
    if not (np.all(z > 0) and np.all(np.isfinite(uvp))):
        raise RigError("the fitted projector does not face the camera's whole view of the plane")
    over = [-0.5 - uvp[:, 0].min(), uvp[:, 0].max() - (proj.width - 0.5),
            -0.5 - uvp[:, 1].min(), uvp[:, 1].max() - (proj.height - 0.5)]  # px beyond each edge
    if max(over) <= 0:
        return rig
    left, right, top, bottom = (int(np.ceil(o)) + margin if o > 0 else 0 for o in over)
    K = np.array(proj.K, dtype=np.float64)
    K[0, 2] += left
    K[1, 2] += top
    width = proj.width + left + right
    grown = Device(K=K, R=proj.R, t=proj.t, width=width, height=proj.height + top + bottom, dist=proj.dist)
    out = dataclasses.replace(rig, projector=grown, periods=rig.periods * width / proj.width)
    out.check()
    return out


# ====================================================================== measuring real images
@dataclass
class BandPeriods:
    """Measured periods (camera px): per column band, per row band and per half; medians over images.
    ``tilt_deg`` (1,): the fringe lines' angle from vertical on the plane (:func:`fppsim.phase.measure.fringe_tilt`),
    median over images. ``spread`` holds [min, max] over images for each entry; ``n_images`` how many
    gave a value."""

    columns: np.ndarray
    rows: np.ndarray
    halves: np.ndarray
    spread: dict = field(default_factory=dict)
    n_images: int = 0
    shape: tuple = ()
    tilt_deg: np.ndarray = field(default_factory=lambda: np.array([np.nan]))

    def to_dict(self) -> dict:
        return {"columns": self.columns.tolist(), "rows": self.rows.tolist(), "halves": self.halves.tolist(),
                "tilt_deg": np.asarray(self.tilt_deg).tolist(),
                "spread": {k: np.asarray(v).tolist() for k, v in self.spread.items()}, "n_images": self.n_images,
                "shape": list(self.shape)}


def measure_bands(images: list[FringeImage], col_bands: int = 4, row_bands: int = 3) -> BandPeriods:
    """Fringe period of every column band, row band and half of each image (plane pixels), median over images."""
    if not images:
        raise InputError("no images to measure")
    shape = images[0].gray.shape
    per = {"columns": [], "rows": [], "halves": [], "tilt_deg": []}
    for im in images:
        if im.gray.shape != shape:
            raise InputError(f"{im.name}: image shape {im.gray.shape} differs from the first image's {shape}")
        g = im.gray.astype(np.float64)
        H, W = shape
        ce, re = _band_edges(W, col_bands), _band_edges(H, row_bands)
        m = im.plane_or_valid
        per["columns"].append([estimate_period(g[:, a:b], m[:, a:b]) for a, b in zip(ce[:-1], ce[1:])])
        per["rows"].append([estimate_period(g[a:b], m[a:b]) for a, b in zip(re[:-1], re[1:])])
        per["halves"].append([estimate_period(g[:, : W // 2], m[:, : W // 2]),
                              estimate_period(g[:, W // 2:], m[:, W // 2:])])
        period = estimate_period(g, m)
        per["tilt_deg"].append([fringe_tilt(g, period, m) if np.isfinite(period) else np.nan])
    med, spread = {}, {}
    for k, rows in per.items():
        a = np.array(rows, dtype=np.float64)
        with warnings.catch_warnings():  # an all-NaN band (no plane there) stays NaN and is ignored
            warnings.simplefilter("ignore", RuntimeWarning)
            med[k] = np.nanmedian(a, axis=0)
            spread[k] = np.stack([np.nanmin(a, axis=0), np.nanmax(a, axis=0)], axis=1)
    n = int(np.isfinite(np.array(per["halves"])).all(axis=1).sum())
    if not np.isfinite(med["columns"]).any():
        raise InputError("no fringe period could be measured in any image (no vertical fringes on the plane?)")
    return BandPeriods(med["columns"], med["rows"], med["halves"], spread, n, tuple(shape), med["tilt_deg"])


# ====================================================================== fitting
@dataclass
class RigFit:
    """Result of :func:`fit_rig_periods`: the fitted rig, parameter values, band periods (measured, base and
    fitted rig) and the RMS residual over the bands (camera px)."""

    rig: Rig
    params: dict
    base_params: dict
    measured: BandPeriods
    base_model: dict
    fitted_model: dict
    rms_base: float
    rms_fitted: float
    coverage: float
    success: bool
    message: str

    def to_dict(self) -> dict:
        return {"params": self.params, "base_params": self.base_params, "measured": self.measured.to_dict(),
                "base_model": {k: v.tolist() for k, v in self.base_model.items()},
                "fitted_model": {k: v.tolist() for k, v in self.fitted_model.items()},
                "rms_base_px": self.rms_base, "rms_fitted_px": self.rms_fitted, "plane_coverage": self.coverage,
                "success": self.success, "message": self.message}


TILT_WEIGHT = 0.5  # camera px of band-period residual per degree of fringe tilt


def _residual(model: dict, measured: BandPeriods) -> np.ndarray:
    tilt = TILT_WEIGHT * (model["tilt_deg"] - np.asarray(measured.tilt_deg, dtype=np.float64))
    r = np.concatenate([model["columns"] - measured.columns, model["rows"] - measured.rows, tilt])
    return np.where(np.isfinite(r), r, 0.0)


def fit_rig_periods(measured: BandPeriods, base: Rig, params: tuple[str, ...] = ("yaw", "roll", "periods"),
            prior: float = 0.02, step: int = 4) -> RigFit:
    """Adjust ``params`` of ``base`` so its band periods and fringe tilt (:func:`band_model`) match
    ``measured`` (the tilt, in degrees, weighs ``TILT_WEIGHT`` px per degree; ``roll`` is what sets it).
    On a yawed, lens-shifted projector ``pitch`` tilts the lines too (0.01 rad of pitch: -0.34 deg, of
    roll: +0.60 deg on the default rig) while hardly moving the row bands, so fitting both splits the
    tilt between them by the prior; the default fits roll and leaves pitch at the base rig's.

    ``prior``: weight (camera px per typical parameter step) of a pull towards the base values, which
    keeps directions the period map cannot see (e.g. baseline vs periods) at the base rig. The camera
    image size of ``measured`` must match the rig's camera. Raises RigError if the fitted projector
    no longer lights the camera's whole view of the plane.
    """
    from scipy.optimize import least_squares

    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise RigError(f"unknown or no parameter(s) to fit: {', '.join(unknown) or 'none'} "
                       f"(known: {', '.join(PARAMETERS)})")
    if measured.shape and tuple(measured.shape) != (base.camera.height, base.camera.width):
        raise RigError(f"the images are {measured.shape[1]} x {measured.shape[0]} px but the rig's camera is "
                       f"{base.camera.width} x {base.camera.height}")
    col_bands, row_bands = len(measured.columns), len(measured.rows)
    b0 = base_values(base)
    x0 = np.array([b0[p] for p in params])
    scale = np.array([_SCALE[p] for p in params])

    def make(x):
        return adjust_rig(base, **dict(zip(params, x * scale + x0)))

    def fun(x):
        try:
            model = band_model(make(x), col_bands, row_bands, step)
        except RigError:
            return np.full(col_bands + row_bands + 1 + len(params), 1e3)
        return np.concatenate([_residual(model, measured), prior * x])

    sol = least_squares(fun, np.zeros(len(params)), method="trf", x_scale=1.0, diff_step=1e-4, xtol=1e-10,
                        ftol=1e-12, gtol=1e-12, max_nfev=200)
    message = str(sol.message)
    if not 0.5 * float(np.sum(fun(sol.x) ** 2)) < 0.5 * float(np.sum(fun(np.zeros(len(params))) ** 2)):
        sol.x = np.zeros(len(params))  # never a rig worse than the start on this objective
        message = "no change of " + ", ".join(params) + " improves on the base rig: kept it"
    rig = make(sol.x)
    rig.name = f"{base.name} (fit-rig: {', '.join(params)})"
    rig.check()
    coverage = plane_coverage(rig)
    if coverage < 0.999:
        raise RigError(f"the fitted projector lights only {coverage:.1%} of the camera's view of the plane; "
                       "fit fewer parameters or start from a closer --base rig")
    base_model = band_model(base, col_bands, row_bands, step)
    fitted_model = band_model(rig, col_bands, row_bands, step)
    rms = lambda m: float(np.sqrt(np.mean(_residual(m, measured)[:-1] ** 2)))  # noqa: E731  (bands only, px)
    values = {p: float(v) for p, v in zip(params, sol.x * scale + x0)}
    return RigFit(rig=rig, params=values, base_params={p: b0[p] for p in params}, measured=measured,
                  base_model=base_model, fitted_model=fitted_model, rms_base=rms(base_model),
                  rms_fitted=rms(fitted_model), coverage=coverage, success=bool(sol.success), message=message)


def unfitted(measured: BandPeriods, rig: Rig, message: str, step: int = 4) -> RigFit:
    """The :class:`RigFit` of ``rig`` as it is (no parameter fitted): its band periods against ``measured``."""
    model = band_model(rig, len(measured.columns), len(measured.rows), step)
    rms = float(np.sqrt(np.mean(_residual(model, measured)[:-1] ** 2)))
    return RigFit(rig=rig, params={}, base_params={}, measured=measured, base_model=model, fitted_model=model,
                  rms_base=rms, rms_fitted=rms, coverage=plane_coverage(rig), success=True, message=message)


def format_fit(fit: RigFit) -> str:
    """Plain-text table: band | measured | base rig | fitted rig (periods in camera px) and the parameters."""
    m = fit.measured
    H, W = m.shape if m.shape else (fit.rig.camera.height, fit.rig.camera.width)
    lines = [f"fringe period on the reference plane (camera px), median of {m.n_images} image(s)",
             f"{'band (camera px)':<22}{'measured':>10}{'base rig':>10}{'fitted':>10}",
             f"{'':<22}{'px':>10}{'px':>10}{'px':>10}"]

    def rows(kind, edges, label):
        for i, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
            lines.append(f"{label} {a:>4}-{b:<4}      "[:22].ljust(22)
                         + f"{m.__dict__[kind][i]:>10.3f}{fit.base_model[kind][i]:>10.3f}{fit.fitted_model[kind][i]:>10.3f}")

    rows("columns", _band_edges(W, len(m.columns)), "columns")
    rows("rows", _band_edges(H, len(m.rows)), "rows")
    for i, name in enumerate(("left half", "right half")):
        lines.append(f"{name:<22}{m.halves[i]:>10.3f}{fit.base_model['halves'][i]:>10.3f}{fit.fitted_model['halves'][i]:>10.3f}")
    lines.append(f"{'fringe tilt (deg)':<22}{float(np.asarray(m.tilt_deg)[0]):>10.3f}"
                 f"{float(fit.base_model['tilt_deg'][0]):>10.3f}{float(fit.fitted_model['tilt_deg'][0]):>10.3f}")
    lines.append(f"{'RMS residual (px)':<22}{'':>10}{fit.rms_base:>10.3f}{fit.rms_fitted:>10.3f}")
    lines.append("")
    for p, v in fit.params.items():
        b = fit.base_params[p]
        unit = {"baseline": " mm", "distance": " mm", "focal": " px"}.get(p, "")
        shown = (lambda x: f"{np.degrees(x):+.3f} deg") if p in ("yaw", "pitch", "roll") \
            else (lambda x: f"{x:.3f}{unit}")
        what = PARAMETERS[p].split(';')[0].replace(" (rad)", "")  # shown in degrees here
        lines.append(f"{p:<10} {shown(b):>14} -> {shown(v):>14}   ({what})")
    lines.append(f"plane coverage by the projector: {fit.coverage:.1%}; optimiser: {fit.message}")
    return "\n".join(lines)


# ====================================================================== the baseline from labelled images
