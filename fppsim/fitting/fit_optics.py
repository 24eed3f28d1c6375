"""Fit the optics ranges (:class:`fppsim.rendering.optics.OpticsRanges`) to real fringe images (``fppsim fit-optics``).

On the reference plane the image model of :mod:`fppsim.rendering.optics` reduces to

    I = A + B cos(phi) + noise,   A = g (ambient + k/2),   B = g (k/2) c(sigma)

with ``g = gain * albedo_plane``, ``k = cos_incidence * falloff`` (known from the rig), and ``c`` the
attenuation of the fringe by projector + camera blur (and the DMD's pixelation), tabulated once by
rendering noise-free planes through :func:`fppsim.rendering.optics.optical_image` and measuring them with the same
estimator as the real images (:func:`fppsim.phase.measure.fringe_modulation`), so estimator bias cancels.
Per image, on plane pixels (:func:`plane_masks`, one choice for every input: height labels, else the rig's
plane phase, from a scan's phase or, for plain fringe images, the image's own single-shot phase, so a scan
folder and the same frames as image files are measured on the same pixels; the darker background only
where neither tells, which assumes objects brighter than the plane):

* ``A``, ``B/A``: medians of the fringe background and modulation;
* noise: fringes are vertical to within a degree or two (the real pair's -1.34 deg lean changes the
  phase by 0.013 rad a row), so the vertical second difference of plane pixels is noise (variance
  ``6 (sigma^2 + shot * E + 1/12)``, the 1/12 from 8-bit rounding); a robust line through
  the variance against intensity gives ``noise_sigma`` (intercept) and ``shot_noise`` (slope);
* blur: ``c = (B/A) (ambient + k/2) / (k/2)`` inverted through the table, split between projector and
  camera blur in the proportion of the default ranges' centres. Ambient light and blur both lower the
  contrast and cannot be told apart from the plane alone: ambient is kept at ``ambient`` (default: the
  default range's centre), unless even zero blur cannot reach the measured contrast, in which case the
  blur is 0 and ambient is solved for;
* gain and albedos: only ``gain * albedo`` is visible. ``albedo_plane`` keeps the default centre and
  ``gain = g / albedo_plane``; object pixels give ``albedo_object``: with height labels from
  ``A = gain albedo (ambient + k/2)`` with ``k`` of each surface point from the rig and the heights
  (:func:`object_shading`); with only real phase from the brightest object pixels,
  ``p95(A + B) / (gain (ambient + (1 + c)/2))`` (a surface facing the projector, rough). Gain rises if
  the albedo would exceed 0.95.

The ranges are [min, max] of the per-image estimates, widened to at least +-10 % around their median
(``albedo_object`` also to the 25th-75th percentile of its per-pixel estimates: real plaster varies).
"""

from __future__ import annotations

import tempfile
import json
import os
from dataclasses import dataclass, field
from dataclasses import fields as dc_fields
from dataclasses import replace as dc_replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fppsim.commands import ReportLines
from fppsim.errors import InputError, RigError, UsageError, check_seed
from fppsim.files import (JSON_SUFFIXES, YAML_SUFFIXES, Output, atomic_write_text, check_outputs, holds_keys, json_text,
                          starts_with)
from fppsim.rendering.optics import Optics, OpticsRanges, optical_image, projector_radiance
from fppsim.dataio.readers import check_read_convention, load_fringe_images
from fppsim.rendering.render import plane_geometry, projector_incidence
from fppsim.geometry.rig import Rig, check_image_size, data_path, load_rig
from fppsim.phase.measure import estimate_period, fringe_modulation
from fppsim.phase.fringe_axis import fringe_axis, rig_phase_gradient
from fppsim.fitting.plane_phase import image_phase_map, plane_phase_residual
from fppsim.phase import wrap
from fppsim.generation import generate_dataset
from fppsim.fitting.compare import STAT_ROWS, dataset_stats, format_value
from fppsim.rendering.synth import SynthConfig

__all__ = ["OpticsFit", "plane_model", "contrast_table", "image_estimates", "object_estimates", "unlit_share",
           "NO_PLANE_SHARE", "NO_PLANE", "fit_optics", "ranges_yaml",
           "format_optics_fit", "compare_before_after", "FitOpticsConfig", "FitOpticsResult", "fit_optics_images"]

FITTED = ("gain", "ambient", "albedo_plane", "albedo_object", "projector_blur", "camera_blur", "noise_sigma",
          "shot_noise")


def _centre(r) -> float:
    return 0.5 * (float(r[0]) + float(r[1]))


def plane_model(rig: Rig) -> dict:
    """Per camera pixel on the reference plane, as :func:`fppsim.rendering.render.plane_geometry` computes it:
    projector column ``u_p``, ``k = cos_incidence * falloff`` and ``lit`` (inside the projector),
    (H, W) float64 / bool, and the ``geometry`` itself (what :func:`fppsim.rendering.optics.form_images` forms
    the plane's images on)."""
    g = plane_geometry(rig)
    return {"u_p": g.u_p, "k": g.cos_incidence * g.falloff, "lit": g.lit, "geometry": g}


def object_shading(rig: Rig, height_mm: np.ndarray) -> np.ndarray:
    """``k = cos_incidence * falloff`` of surfaces of known height (mm, (H, W), NaN = unknown): each camera
    ray cut at its height, normals from the neighbours, the light as :func:`fppsim.rendering.render.projector_incidence`
    gives it to rendered surfaces."""
    cam, proj = rig.camera, rig.projector
    h = np.where(np.isfinite(height_mm), height_mm, 0.0)
    _, P = cam.ray_cut(cam.pixel_grid(), h)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= np.sign(n[..., 2:3]) + (n[..., 2:3] == 0)  # towards +z (the camera side)
    cos_inc, falloff = projector_incidence(proj, P, n)
    k = cos_inc * falloff
    return np.where(np.isfinite(height_mm), np.maximum(k, 0.0), np.nan)


def _split(sigma_eff: float, ratio: tuple[float, float]) -> tuple[float, float]:
    """Effective blur (camera px) -> (projector blur in projector px, camera blur in camera px)."""
    rp, rc = ratio
    n = np.hypot(rp, rc)
    return sigma_eff * rp / n, sigma_eff * rc / n


def _default_ratio(rig: Rig, period_cam: float) -> tuple[float, float]:
    d = OpticsRanges()
    px = period_cam / (rig.projector.width / rig.periods)  # camera px per projector px
    return _centre(d.projector_blur) * px, _centre(d.camera_blur)


def contrast_table(rig: Rig, period: float, sigmas=np.linspace(0.0, 4.0, 17), model: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fringe contrast ``c(sigma)`` (ambient 0) for effective blurs ``sigma`` (camera px), measured on
    noise-free rendered planes with :func:`fppsim.phase.measure.fringe_modulation`. Returns (sigmas, c)."""

    m = plane_model(rig) if model is None else model
    ratio = _default_ratio(rig, period)
    cs = []
    for s in sigmas:
        pb, cb = _split(float(s), ratio)
        # the image before the sensor, in float64: 8-bit rounding would only add noise to the table
        o = Optics(gain=200.0, ambient=0.0, albedo_plane=1.0, projector_blur=pb, camera_blur=cb, noise_sigma=0.0,
                   shot_noise=0.0)
        pattern = projector_radiance(m["u_p"], rig.projector.width, rig.periods, 0.0, o)
        E = optical_image((0.0, 200.0 * m["k"]), pattern, o)
        b, a = fringe_modulation(E, period, m["lit"])
        ok = m["lit"] & (a > 1)
        cs.append(float(np.median(b[ok] / a[ok])))
    return np.asarray(sigmas, float), np.asarray(cs)


def _noise_fit(gray: np.ndarray, mask: np.ndarray, shot_default: float) -> tuple[float, float]:
    """(noise_sigma, shot_noise) from vertical second differences (see the module docstring).

    ``d = I(v-1) - 2 I(v) + I(v+1)`` removes the (vertical) fringes and any linear vertical trend, leaving
    noise of variance ``6 (sigma^2 + shot * E + 1/12)``; a robust (MAD) variance per intensity decile and
    a weighted line through them give both terms. When the intensities span less than 40 gray levels the
    slope is not measurable and ``shot_noise`` stays at ``shot_default``.
    """
    g = gray.astype(np.float64)
    ok = mask & (gray < 255) & (gray > 0)
    trip = ok[:-2] & ok[1:-1] & ok[2:]
    d = (g[:-2] - 2 * g[1:-1] + g[2:])[trip]
    e = g[1:-1][trip]
    if d.size < 200:
        return float("nan"), float("nan")
    edges = np.unique(np.percentile(e, np.linspace(0, 100, 11)))
    xs, vs, ws = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (e >= lo) & (e <= hi)
        if sel.sum() < 50:
            continue
        dd = d[sel]
        s = 1.4826 * np.median(np.abs(dd - np.median(dd)))  # robust: texture, edges, curved fringes
        xs.append(e[sel].mean())
        vs.append(s * s / 6.0 - 1.0 / 12.0)
        ws.append(sel.sum())
    xs, vs, ws = map(np.asarray, (xs, vs, ws))
    shot = float(shot_default)
    if len(xs) >= 3 and np.ptp(xs) >= 40:
        A = np.stack([np.ones_like(xs), xs], axis=1) * np.sqrt(ws)[:, None]
        c0, c1 = np.linalg.lstsq(A, vs * np.sqrt(ws), rcond=None)[0]
        if c1 >= 0 and c0 >= 0:
            return float(np.sqrt(c0)), float(c1)
        shot = max(float(c1), 0.0) if c0 >= 0 else float(np.sum(ws * vs * xs) / np.sum(ws * xs * xs))
    c0 = float(np.average(vs - shot * xs, weights=ws))
    return float(np.sqrt(max(c0, 0.0))), max(shot, 0.0)


def _masks(im, model: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """Plane and object pixels: ``im.plane`` (:func:`plane_masks`), or where nothing told them apart the
    darker mode of the background (objects assumed brighter than the plane; a dark object is then taken for
    the plane: :func:`fit_optics_images` says so)."""
    if im.plane is not None and im.plane.sum() > 1000:
        return im.plane & model["lit"], im.obj
    g = im.gray.astype(np.float64)
    v = im.valid & model["lit"]
    med = np.median(g[v]) if v.any() else 0.0
    # objects (bright plaster) lift the local background: keep pixels within the bulk of the plane
    from scipy.ndimage import uniform_filter

    local = uniform_filter(np.where(v, g, med), size=31)
    lo, hi = np.percentile(local[v], [5, 60]) if v.any() else (0, 0)
    return v & (local >= lo) & (local <= hi), None  # objects not identifiable: albedo_object not measured


def _blur(contrast: float, k: float, ambient: float, table, rig: Rig, period: float) -> tuple[float, float, float, float]:
    """``(projector_blur, camera_blur, ambient, c)`` from a surface's fringe contrast ``B/A`` under shading ``k``
    (module docstring): the attenuation ``c`` inverted through the contrast ``table``; sharper than its
    sharpest entry, no blur and the ambient solved for instead."""
    sig, cs = table
    c0 = float(cs[0])
    amb = float(ambient)
    c = contrast * (amb + 0.5 * k) / (0.5 * k)
    if c >= c0:  # sharper than the sharpest table entry: no blur, the ambient explains the rest
        sigma = 0.0
        amb = max(0.5 * k * (c0 / contrast - 1.0), 0.0)
        c = c0
    else:
        order = np.argsort(cs)  # c falls with sigma
        sigma = float(np.interp(c, cs[order], sig[order]))
    pb, cb = _split(sigma, _default_ratio(rig, period))
    return pb, cb, amb, c


NO_PLANE_SHARE = 0.4
"""An image this much without fringes has no plane in view (objects on a black background): real frames with a
plane have 3-11 % (shadows, dark patches), busts rendered on a black plane 65-82 %."""
NO_PLANE = "none: no plane in view"


def unlit_share(gray: np.ndarray, period: float) -> float:
    """The share of the image without fringes: modulation under 3 gray levels or 15 % of the image's median
    (:func:`fppsim.phase.measure.fringe_modulation` along the rows: give the transposed image for horizontal
    fringes)."""
    b, _ = fringe_modulation(gray.astype(np.float64), period, np.ones(gray.shape, bool))
    lit = b >= 3.0
    if not lit.any():
        return 1.0
    return float(np.mean(b < max(3.0, 0.15 * float(np.median(b[lit])))))


def object_estimates(im, rig: Rig, table: tuple[np.ndarray, np.ndarray], period: float, ambient: float,
                     albedo_object: float) -> dict:
    """Optics parameters of an image with no plane in view (:data:`NO_PLANE_SHARE`): ``albedo_plane`` 0 (what
    ``generate`` renders as a black background) and the rest from the objects' fringes. Their brightest fifth
    faces the projector (shading ``k`` about 1): its contrast gives the blur as on the plane, its background
    ``A = gain albedo_object (ambient + 1/2)`` the product ``gain x albedo_object``, of which only the
    product is visible (``albedo_object`` kept, ``gain`` from it). NaN where fewer than 500 pixels carry
    fringes."""
    g = im.gray.astype(np.float64)
    b, a = fringe_modulation(g, period, im.valid)
    lit = im.valid & (b >= 3.0) & (a > 1) & (im.gray < 255)
    if lit.sum() < 500:
        return {k: float("nan") for k in FITTED} | {"plane_pixels": 0}
    bright = lit & (a >= np.percentile(a[lit], 80))
    contrast = float(np.median(b[bright] / a[bright]))
    pb, cb, amb, _ = _blur(contrast, 1.0, ambient, table, rig, period)
    gain = float(np.median(a[bright])) / (amb + 0.5) / albedo_object
    noise, shot = _noise_fit(im.gray, lit, _centre(OpticsRanges().shot_noise))
    return {"gain": gain, "ambient": amb, "albedo_plane": 0.0, "albedo_object": albedo_object,
            "albedo_object_p25": albedo_object, "albedo_object_p75": albedo_object, "projector_blur": pb,
            "camera_blur": cb, "noise_sigma": noise, "shot_noise": shot, "contrast": contrast,
            "background": float(np.median(a[bright])), "plane_pixels": 0, "period_px": period}


def image_estimates(im, rig: Rig, table: tuple[np.ndarray, np.ndarray], period: float, model: dict,
                    ambient: float, albedo_plane: float, transposed: bool = False) -> dict:
    """Optics parameters of one image (see the module docstring); NaN where not measurable. ``transposed``:
    ``im`` and ``model`` are the transposes of the camera's image (a rig with horizontal fringes)."""
    plane, obj = _masks(im, model)
    g = im.gray.astype(np.float64)
    b, a = fringe_modulation(g, period, im.valid)
    ok = plane & (a > 1) & (im.gray < 255)
    if ok.sum() < 500:
        return {k: float("nan") for k in FITTED} | {"plane_pixels": int(ok.sum())}
    contrast = float(np.median(b[ok] / a[ok]))
    A = float(np.median(a[ok]))
    k = float(np.median(model["k"][ok]))
    pb, cb, amb, c = _blur(contrast, k, float(ambient), table, rig, period)
    gp = A / (amb + 0.5 * k)
    gain = gp / albedo_plane
    ap = albedo_plane
    ao, go_spread = float("nan"), None
    if obj is not None:
        okobj = obj & (a > 1) & im.valid & (im.gray < 255)
        go = float("nan")
        if getattr(im, "height_mm", None) is not None and okobj.sum() > 500:
            # heights known: the shading k of every object pixel follows from the rig, A = g_o (amb + k/2)
            ko = object_shading(rig, im.height_mm.T).T if transposed else object_shading(rig, im.height_mm)
            from scipy.ndimage import binary_erosion

            inner = okobj & binary_erosion(okobj, iterations=3) & (ko > 0.3)
            if inner.sum() > 300:
                ratio = a[inner] / (amb + 0.5 * ko[inner])
                go = float(np.median(ratio))
                go_spread = np.percentile(ratio, [25, 75])
        elif okobj.sum() > 500:  # heights unknown: the brightest object pixels face the projector (k ~ 1)
            go = float(np.percentile((a + b)[okobj], 95)) / (amb + 0.5 * (1.0 + c))
        if np.isfinite(go):
            ao = go / gain
            if ao > 0.95:  # albedo cannot exceed 1: the light is brighter, the plane darker
                gain = go / 0.95
                ap = gp / gain
                ao = 0.95
    ao_spread = [float(v) / gain for v in go_spread] if go_spread is not None and np.isfinite(ao) else [ao, ao]
    noise, shot = _noise_fit(im.gray, im.valid & model["lit"], _centre(OpticsRanges().shot_noise))
    return {"gain": gain, "ambient": amb, "albedo_plane": ap, "albedo_object": ao,
            "albedo_object_p25": ao_spread[0], "albedo_object_p75": ao_spread[1], "projector_blur": pb,
            "camera_blur": cb, "noise_sigma": noise, "shot_noise": shot, "contrast": contrast, "background": A,
            "plane_pixels": int(ok.sum()), "period_px": period}


@dataclass
class OpticsFit:
    """Per-image estimates, the fitted centre values (medians) and ranges; ``fixed`` names the values
    that were not measured (kept at the given / default centre)."""

    per_image: list
    centre: dict
    ranges: OpticsRanges
    fixed: dict = field(default_factory=dict)
    n_images: int = 0

    def to_dict(self) -> dict:
        return {"centre": self.centre, "ranges": self.ranges.to_dict(), "fixed": self.fixed,
                "per_image": self.per_image, "n_images": self.n_images}


PLANE_RAD, OBJECT_RAD = 0.3, 1.0  # |phase - the rig's plane phase|: the plane within, objects beyond (rad)
FLAT_SLOPE = 0.03  # rad/px: the plane's residual from a single image's phase slopes less (_flat)

PLANE_SOURCES = ("height labels", "scan phase", "image phase", "phase surface", "brightness", NO_PLANE)
"""Where :func:`plane_masks` takes an image's plane pixels from, best first (``per_image[i]["plane_from"]``)."""


def rig_masks(im, rig: Rig, min_share: float = 0.02) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Plane and object pixels of an image by ``rig``'s own plane phase
    (:func:`fppsim.fitting.plane_phase.plane_phase_residual`): the plane within :data:`PLANE_RAD` of it after
    the constant offset, objects beyond :data:`OBJECT_RAD`. The phase is the scan's absolute phase
    (``im.phase``, source ``"scan phase"``) or, for a plain fringe image, the image's own single-shot phase
    unwrapped (:func:`fppsim.fitting.plane_phase.image_phase_map`, source ``"image phase"``): its sign is a
    convention (the one more pixels fit is taken), regions cut off by shadows may sit whole periods away
    (they are neither plane nor object: objects are told by the phase modulo 2 pi) and low-reliability
    edges are neither. Unlike a smooth surface fitted to the phase itself, or the brightness, this holds
    when an object covers most of the view or is darker than the plane (a rig fitted to these frames:
    ``fit-rig``). Returns ``(plane, obj, source)``, or None when fewer than ``min_share`` of the valid
    pixels are the plane (another rig) or the image has no usable fringe phase."""
    if getattr(im, "phase", None) is not None:
        res, _ = plane_phase_residual(rig, im.phase, im.valid & np.isfinite(im.phase))
        plane = im.valid & (np.abs(np.nan_to_num(res, nan=np.inf)) <= PLANE_RAD)
        obj, source = im.valid & (np.abs(np.nan_to_num(res, nan=0.0)) > OBJECT_RAD), "scan phase"
    else:
        try:
            m = image_phase_map(im.gray, im.valid, im.name)
        except (RigError, ValueError):  # no fringes to read a phase from
            return None
        best = None
        for sign in (1.0, -1.0):
            res, _ = plane_phase_residual(rig, sign * m.phase, m.valid)
            plane = m.valid & (np.abs(np.nan_to_num(res, nan=np.inf)) <= PLANE_RAD)
            if best is None or plane.sum() > best[0].sum():
                best = plane, res
        plane, res = best
        plane &= _flat(res, m.valid)
        obj, source = m.valid & (np.abs(wrap(np.nan_to_num(res, nan=0.0))) > OBJECT_RAD), "image phase"
    if plane.sum() < max(1000, min_share * im.valid.sum()):
        return None
    return plane, obj, source


def _flat(residual: np.ndarray, valid: np.ndarray, max_slope: float = FLAT_SLOPE, size: int = 7) -> np.ndarray:
    """Pixels whose phase residual is flat: its gradient (rad/px), averaged over ``size`` x ``size`` valid
    pixels, below ``max_slope``. An object whose relief passes through a whole number of periods (its
    unwrapped single-shot phase cut at a wall or a shadow) meets the plane's phase in a band there, where
    the residual still slopes; the plane's residual does not."""
    from scipy.ndimage import uniform_filter

    r = np.where(valid, residual, 0.0)
    gy, gx = np.gradient(r)
    w = valid.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = uniform_filter(np.hypot(gx, gy) * w, size) / uniform_filter(w, size)
    return valid & (slope < max_slope)


def plane_masks(im, rig: Rig) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """THE choice of an image's plane and object pixels for the optics fit: ``(plane, obj, source)``
    (:data:`PLANE_SOURCES`). Height labels first (the reader's masks); else the rig's plane phase
    (:func:`rig_masks`), from the scan's phase or from the image itself, so a scan folder and its
    single-shot images written as plain image files give the same pixels; else a smooth surface fitted to a
    scan's phase (the reader's masks); else ``(None, None, "brightness")``: :func:`image_estimates` takes
    the darker mode of the background for the plane (objects assumed brighter than the plane)."""
    if getattr(im, "height_mm", None) is not None and im.plane is not None:
        return im.plane, im.obj, "height labels"
    masks = rig_masks(im, rig)
    if masks is not None:
        return masks
    if im.plane is not None:
        return im.plane, im.obj, "phase surface"
    return None, None, "brightness"


def _transposed(im):
    """The image with every array transposed (the row-wise measurements then run across its fringes)."""
    t = {f.name: (getattr(im, f.name).T if isinstance(getattr(im, f.name), np.ndarray) else getattr(im, f.name))
         for f in dc_fields(im)}
    return type(im)(**t)


def fit_optics(images, rig: Rig, ambient: float | None = None, albedo_plane: float | None = None,
               min_width: float = 0.10) -> OpticsFit:
    """Fit optics ranges to real fringe images (:class:`fppsim.dataio.readers.FringeImage`) of ``rig``.

    ``ambient`` and ``albedo_plane`` are the values that cannot be separated from the others (default:
    the centres of the default ranges). ``min_width``: each range spans at least +-this fraction of its
    centre. Images with real phase have their plane and object pixels told apart by the rig
    (:func:`rig_masks`). A rig with horizontal fringes is measured on the transposed images, so that the
    row-wise fringe measurements run across the fringes. Raises ValueError if no image has enough plane
    pixels with fringes.
    """
    d = OpticsRanges()
    amb = _centre(d.ambient) if ambient is None else float(ambient)
    ap = _centre(d.albedo_plane) if albedo_plane is None else float(albedo_plane)
    ao = _centre(d.albedo_object)  # images with no plane in view keep it: only gain x albedo_object is seen
    model = plane_model(rig)
    across = fringe_axis(rig_phase_gradient(rig)) == "horizontal"
    if across:
        model = {k: (v.T if isinstance(v, np.ndarray) else v) for k, v in model.items()}
    per, tables = [], {}
    # objects on black: the gray image's spectral peak is their outline's (FP672/541's figurine: 31 px, its fringes
    # 8.9-10.5 px), which measured the contrast at that period and clamped the blur to 0: the rig's period instead
    rig_period = float(2 * np.pi / np.hypot(*rig_phase_gradient(rig)))
    for im in images:
        check_image_size(rig, im.gray.shape, im.name, error=InputError, sep=" x ",
                         template="{what}: image is {got} px but {who} {camera}{hint}",
                         hint=": give the frames' own rig (--rig, e.g. from fppsim fit-rig)")
        plane, obj, source = plane_masks(im, rig)
        if plane is not None:
            im = dc_replace(im, plane=plane, obj=obj)
        if across:
            im = _transposed(im)
        no_plane = not rig.plane_in_view
        period = rig_period if no_plane else estimate_period(im.gray.astype(np.float64), im.plane_or_valid)
        if not np.isfinite(period):
            per.append({"name": im.name, "plane_from": source} | {k: float("nan") for k in FITTED})
            continue
        unlit = unlit_share(im.gray, period)
        # before the phase's plane: its constant offset finds one on any flat top; a rig fitted without a plane in
        # view says so itself (a bust filling 62 % of the view leaves less than NO_PLANE_SHARE without fringes)
        if unlit >= NO_PLANE_SHARE and not no_plane:
            no_plane, period = True, rig_period
        key = round(period, 1)  # one contrast table per period (to 0.1 px)
        if key not in tables:
            tables[key] = contrast_table(rig, key, model=model)
        if no_plane:
            per.append({"name": im.name, "plane_from": NO_PLANE, "unlit_share": unlit}
                       | object_estimates(im, rig, tables[key], period, amb, ao))
            continue
        per.append({"name": im.name, "plane_from": source, "unlit_share": unlit}
                   | image_estimates(im, rig, tables[key], period, model, amb, ap, across))
    centre, ranges = {}, {}
    for k in FITTED:
        v = np.array([p[k] for p in per], float)
        v = v[np.isfinite(v)]
        if not v.size:
            continue
        c = float(np.median(v))
        lo, hi = float(v.min()), float(v.max())
        if k == "albedo_object":  # the spread over an object's pixels is albedo variation to sample from
            q = np.array([[p.get(k + "_p25", np.nan), p.get(k + "_p75", np.nan)] for p in per], float)
            if np.isfinite(q).any():
                lo, hi = min(lo, float(np.nanmin(q))), max(hi, float(np.nanmax(q)))
        half = max(min_width * abs(c), 0.5 * (hi - lo))
        lo, hi = min(lo, c - half), max(hi, c + half)
        if k in ("ambient", "noise_sigma", "shot_noise", "projector_blur", "camera_blur"):
            lo = max(lo, 0.0)
        if k.startswith("albedo"):
            hi = min(hi, 1.0)
        centre[k], ranges[k] = c, (lo, hi)
    if "gain" not in centre:
        raise InputError("no image has enough reference-plane pixels with fringes to fit the optics")
    fixed = {"albedo_plane": ap} if "albedo_object" not in centre or centre["albedo_plane"] == ap else {}
    if all(p["plane_from"] == NO_PLANE for p in per if np.isfinite(p["gain"])):
        fixed = {"albedo_object": ao}
    if ambient is None and all(abs(p.get("ambient", amb) - amb) < 1e-12 for p in per if np.isfinite(p.get("ambient", np.nan))):
        fixed["ambient"] = amb
    return OpticsFit(per_image=per, centre=centre, ranges=OpticsRanges.from_dict({k: list(v) for k, v in ranges.items()}),
                     fixed=fixed, n_images=int(sum(np.isfinite(p["gain"]) for p in per)))


OPTICS_HEADER = "# optics ranges fitted by `fppsim fit-optics`"


def ranges_yaml(fit: OpticsFit, source: str = "") -> str:
    """The fitted ranges as YAML for ``fppsim generate --optics-file`` (only the fitted names)."""
    import yaml

    doc = {k: [round(float(v[0]), 5), round(float(v[1]), 5)]
           for k, v in fit.ranges.to_dict().items() if k in fit.centre}
    head = [OPTICS_HEADER + (f" to {source}" if source else ""),
            f"# from {fit.n_images} image(s); centres: " + ", ".join(f"{k} {v:.4g}" for k, v in fit.centre.items())]
    if fit.fixed:
        head.append("# not measurable from the images, kept at: " + ", ".join(f"{k} {v:g}" for k, v in fit.fixed.items()))
    return "\n".join(head) + "\n" + yaml.safe_dump(doc, sort_keys=False)


def format_optics_fit(fit: OpticsFit) -> str:
    """Plain-text table: parameter | default range | fitted centre | fitted range."""
    d = OpticsRanges().to_dict()
    r = fit.ranges.to_dict()
    lines = [f"{'parameter':<16}{'default range':>20}{'fitted centre':>15}{'fitted range':>22}"]
    for k in FITTED:
        if k not in fit.centre:
            lines.append(f"{k:<16}{_fmt_range(d[k]):>20}{'n/a':>15}{'(not measured)':>22}")
            continue
        note = "  (fixed)" if k in fit.fixed else ""
        lines.append(f"{k:<16}{_fmt_range(d[k]):>20} {_num(fit.centre[k]):>14} {_fmt_range(r[k]):>21}{note}")
    return "\n".join(lines)


def _num(x: float) -> str:
    """4 significant digits; a fit's rounding noise (below 1e-12, e.g. a shot noise of 1e-17) reads 0."""
    return "0" if abs(x) < 1e-12 else f"{x:.4g}"


def _fmt_range(v) -> str:
    return f"[{_num(v[0])}, {_num(v[1])}]"


def compare_before_after(real_dir, fit: OpticsFit, rig: Rig, count: int = 4, meshes=None, seed: int = 0,
                         workdir=None) -> str:
    """Render ``count`` samples with the default and with the fitted ranges (temporary folders, PSP off)
    and return compare-real's statistics side by side: statistic | real | default | fitted."""

    if meshes is None:
        meshes = [str(data_path("meshes"))]
    with tempfile.TemporaryDirectory(prefix="fit-optics-", dir=workdir) as tmp:
        results = {"real": dataset_stats(real_dir, max_samples=50)}
        for name, ranges in (("default", OpticsRanges()), ("fitted", fit.ranges)):
            out = Path(tmp) / name
            cfg = SynthConfig(rig=rig, optics=ranges, psp_freqs=())
            generate_dataset(meshes, out, count, seed=seed, config=cfg, workers=1, progress=False)
            results[name] = dataset_stats(out, max_samples=count)
    rows = [("statistic", "real", "default", "fitted")]
    skip = {"height_p1", "height_p50", "height_p99", "plane_level", "object_fraction", "relief_p99_mm",
            "below_threshold_fraction"}
    for key, label, fmt in STAT_ROWS:
        if key in skip:
            continue
        rows.append((label.strip(), *(format_value(fmt, results[n]["stats"].get(key)) for n in ("real", "default", "fitted"))))
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    text = [f"compare-real: real vs {count} rendered samples with the default and with the fitted optics (medians)"]
    for j, r in enumerate(rows):
        text.append("  ".join(c.ljust(w[i]) if i == 0 else c.rjust(w[i]) for i, c in enumerate(r)))
        if j == 0:
            text.append("  ".join("-" * x for x in w))
    return "\n".join(text)


# ============================================================================================ the command
@dataclass
class FitOpticsConfig:
    """What ``fppsim fit-optics`` does (the fields are its flags).

    real : real fringe images (any layout :func:`fppsim.dataio.readers.load_fringe_images` reads); with height
        labels the plane and object pixels are told apart.
    out : the fitted optics ranges as YAML for ``fppsim generate --optics-file``; refused if it exists
        unless ``force``.
    rig : the images' rig (:class:`fppsim.geometry.rig.Rig` or a rig file, e.g. from ``fppsim fit-rig``); None:
        the packaged default rig.
    max_images : evenly spaced images read (>= 1).
    compare : render this many samples with the default and with the fitted ranges and compare them
        with the real images (:func:`compare_before_after`); 0 skips it.
    meshes : meshes of the ``compare`` renders (None: the packaged meshes). seed : their seed.
    json : also write the per-image estimates there (:meth:`OpticsFit.to_dict`).
    convention / negate_sin : how the public layout's PSin / PCos / Order make the phase that tells the plane
        from the objects (:func:`fppsim.dataio.readers.load_psp_folder_sample`).
    """
    real: str | os.PathLike
    out: str | os.PathLike
    rig: Rig | str | os.PathLike | None = None
    max_images: int = 20
    compare: int = 4
    meshes: Sequence[str | os.PathLike] | None = None
    seed: int = 0
    json: str | os.PathLike | None = None
    force: bool = False
    convention: str = "auto"
    negate_sin: bool = False

    def __post_init__(self):
        if self.max_images < 1 or self.compare < 0:
            raise UsageError(f"--max-images must be >= 1 and --compare >= 0, got {self.max_images} and {self.compare}")
        check_seed(self.seed, error=UsageError)  # else a bad seed failed only after the fit, in the compare renders
        check_read_convention(self.convention)


@dataclass
class FitOpticsResult:
    """What :func:`fit_optics_images` did: the images' ``layout`` and count, the ``fit`` (its ranges are
    written to ``out``), the before/after ``comparison`` table (None when skipped) and the report
    ``lines`` (what ``fppsim fit-optics`` prints)."""

    layout: str
    n_images: int
    fit: OpticsFit
    out: Path
    comparison: str | None
    lines: list[str]


def fit_optics_images(config: FitOpticsConfig, echo: Callable[[str], None] | None = None) -> FitOpticsResult:
    """Read real fringe images, fit the optics ranges to them (:func:`fit_optics`), write the ranges to
    ``config.out`` (:func:`ranges_yaml`) and the estimates to ``config.json``, then compare renders with
    the default and the fitted ranges (:func:`compare_before_after`) unless ``config.compare`` is 0.
    ``echo`` receives every report line as soon as it is known (the command line passes ``print``); the
    lines are also in the result. Raises ValueError when no image has enough plane pixels with fringes.
    """
    lines = ReportLines(echo)
    say = lines.say
    out, *_ = check_outputs([Output("--out", config.out, YAML_SUFFIXES, "optics ranges (YAML)",
                                    starts_with(OPTICS_HEADER)),
                             Output("--json", config.json, JSON_SUFFIXES, "the JSON report",
                                    holds_keys("centre", "per_image"))],
                            inputs=[config.real, None if isinstance(config.rig, Rig) else config.rig], force=config.force)  # before any work
    rig = config.rig if isinstance(config.rig, Rig) else load_rig(config.rig)
    images, layout = load_fringe_images(config.real, config.max_images, convention=config.convention,
                                        negate_sin=config.negate_sin)
    try:
        fit = fit_optics(images, rig)
    except InputError as exc:
        raise InputError(f"{config.real}: {exc}") from None
    say(f"{config.real}: {len(images)} image(s), layout {layout}")
    note = next((im.read_as for im in images if im.read_as), None)  # the first scan read another way stands for the folder
    if note:
        say(note)
    say(format_optics_fit(fit))
    bare = [p for p in fit.per_image if p.get("plane_from") == NO_PLANE]
    if bare:
        why = ("the rig was fitted without one" if not rig.plane_in_view else
               f"{min(p['unlit_share'] for p in bare):.0%} or more of the image without fringes")
        say(f"no plane in view in {len(bare)} of {len(fit.per_image)} image(s) ({why}): albedo_plane 0, so generate renders the objects on a black "
            f"background; the gain from the objects' brightest fifth with albedo_object kept at {_centre(OpticsRanges().albedo_object):g}"
            " (only their product is visible)")
    guessed = [p["name"] for p in fit.per_image if p.get("plane_from") == "brightness"]
    if guessed:
        say(f"plane pixels of {len(guessed)} of {len(fit.per_image)} image(s) taken by brightness (the darker "
            "background; objects assumed brighter than the plane): the rig's plane phase fits no part of them; "
            "give --rig fitted to these images (fppsim fit-rig)")
    atomic_write_text(out, ranges_yaml(fit))
    say(f"optics ranges: {out}")
    if config.json:
        atomic_write_text(config.json, json_text(fit.to_dict(), indent=1))
    comparison = None
    if config.compare and not any(im.height_mm is not None for im in images):
        say(f"--compare skipped: the images carry no height labels ({layout}), which compare-real's statistics need")
    elif config.compare:
        say("")
        comparison = compare_before_after(config.real, fit, rig, config.compare, meshes=config.meshes,
                                          seed=config.seed)
        say(comparison)
    return FitOpticsResult(layout, len(images), fit, out, comparison, list(lines))
