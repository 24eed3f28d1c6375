"""What a sim-to-real checkpoint does on real data: metrics, fringe twins, level response.

Metrics on each real image (heights in mm):

- ``object_rmse_mm``: RMSE over the *object pixels* = valid pixels whose true height is more than
  ``object_mm`` (1 mm) above the reference plane; the plane level is the mode of the valid labels
  (histogram, refined by the median within +-6 label units), as ``fppsim compare-real`` measures it;
- ``valid_rmse_mm``: RMSE over all valid pixels (the paper's metric);
- ``flat_object_rmse_mm``: the same object RMSE of a predictor that outputs the plane everywhere
  (a network that finds nothing scores this);
- ``true_object_mean_mm`` / ``pred_object_mean_mm``: mean height above the plane on the object pixels;
- ``object_fraction``: object pixels / all pixels;
- ``object_median_abs_mm``: median |error| over the object pixels; ``object_within_1mm``: share of the
  object pixels whose |error| is at most 1 mm; ``object_coverage``: share of the object pixels the
  prediction marks valid (finite and above the label transform's invalid threshold, when given).

Where the object error comes from (:func:`error_split`): the object pixels fall into connected regions
(8-connectivity), e.g. a bust and the separate plinth in front of it. Each region's *level* error is the
median of its error (prediction - label, mm); the rest is *relief* error (shape within the region):

- ``object_level_rmse_mm``: RMS over the object pixels of their region's median error (a network that has
  every region's shape right but puts it at the wrong height scores only here);
- ``object_relief_rmse_mm``: RMS over the object pixels of the error minus their region's median error;
- ``object_level_rmse_mean_mm`` / ``object_relief_rmse_mean_mm``: the same split with each region's MEAN
  error; only this one adds up exactly: level^2 + relief^2 = object_rmse^2. The median split does not (the
  median is not the least-squares offset, so its relief part is at least the mean split's); it is shown
  because one bad edge does not move a median;
- ``object_regions``: regions of at least ``min_region_px`` (50) pixels; smaller specks (lone pixels at
  shadow edges) are regions of their own all the same (their few pixels' error counts as their level), and
  ``object_small_regions`` / ``object_small_region_fraction`` say how many and what share of the object
  pixels they hold.

Does the network read the fringes at all? Each real image is also predicted as two twins that keep
its envelope (local background and fringe modulation, i.e. shading, albedo and shadows) but not its
relief (:func:`fringe_twins`): ``flat`` carries the fringes of the bare plane (the carrier fitted on
the plane pixels, extended under the object) and ``envelope`` no fringes at all.

- ``relief_effect_mm``: RMS over the object pixels of prediction(real) - prediction(flat twin), the
  part of the prediction that comes from the fringes' deformation. Near 0: the network reads height
  from shading and shadows, not from the fringes, and will not transfer to other lighting;
- ``flat_twin_object_rmse_mm`` / ``envelope_twin_object_rmse_mm``: the object RMSE of the twins.

Does the network read the object's *level* (its height above the plane behind steep walls, which only
the projector shadow tells)? :func:`level_response` on the synthetic validation split regresses each
object's mean error on its true mean height: slope 0, the level is read; slope -1, the network
predicts one level, the training prior (``prior_level_mm``), whatever the object.

Label maps are (H, W) arrays in label units (figshare: 6 per mm). Running a checkpoint over a folder
and writing the results is :mod:`uhrnet.workflows.sim2real.run`'s job.
"""

from __future__ import annotations

import numpy as np

from fppsim.phase.plane import plane_level, poly_basis  # plane_level re-exported: the one plane level of both packages
from fppsim.phase import lowpass
from uhrnet.errors import Sim2RealError, InputError
from uhrnet.inference.prediction import predict_labels

__all__ = ["plane_level", "object_mask", "real_metrics", "fringe_twins", "twin_metrics", "level_response",
           "object_regions", "error_split"]


def object_mask(label: np.ndarray, valid: np.ndarray, units_per_mm: float = 6.0, object_mm: float = 1.0,
                plane: float | None = None) -> tuple[np.ndarray, float]:
    """(object pixels (bool, H x W), plane label): valid pixels more than ``object_mm`` above the plane."""
    valid = np.asarray(valid, bool)
    plane = plane_level(label, valid) if plane is None else float(plane)
    return valid & (np.asarray(label, np.float64) > plane + object_mm * units_per_mm), plane


def object_regions(obj: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected regions of the object pixels: ``(labels (H, W) int32, 0 off the object, 1..n on it; n)``.

    8-connectivity (pixels touching at a corner are one region), as :func:`scipy.ndimage.label` counts it.
    """
    from scipy import ndimage as ndi

    labels, n = ndi.label(np.asarray(obj, bool), structure=np.ones((3, 3), bool))
    return labels.astype(np.int32), int(n)


def error_split(err_mm: np.ndarray, obj: np.ndarray, min_region_px: int = 50) -> dict:
    """Split the object RMSE into a level part (each connected region's offset) and a relief part (the rest).

    err_mm : (H, W) error of the prediction, prediction - truth, in mm (only the ``obj`` pixels are read).
    obj : (H, W) bool, the object pixels (:func:`object_mask`); regions: :func:`object_regions`.
    min_region_px : regions smaller than this are counted apart (``small_regions``), but every region,
        however small, is its own level (module docstring).

    Returns (mm; NaN without object pixels or with a non-finite error on one):
    ``{"rmse_mm", "level_rmse_mm", "relief_rmse_mm"`` (median split), ``"level_rmse_mean_mm",
    "relief_rmse_mean_mm"`` (mean split: level^2 + relief^2 = rmse^2 exactly), ``"regions"`` (regions of
    at least ``min_region_px``), ``"small_regions", "small_region_fraction"`` (share of the object pixels
    in the smaller ones), ``"per_region": [{"area_px", "median_mm", "mean_mm"}, ...]`` (the regions of at
    least ``min_region_px``, largest first)}``. Vectorised: :func:`scipy.ndimage.median` and
    :func:`numpy.bincount` over the region labels.
    """
    from scipy import ndimage as ndi

    obj = np.asarray(obj, bool)
    err = np.asarray(err_mm, np.float64)
    if err.shape != obj.shape:
        raise InputError(f"error_split: error map {err.shape} and object mask {obj.shape} differ")
    labels, n = object_regions(obj)
    nan = float("nan")
    out = {"rmse_mm": nan, "level_rmse_mm": nan, "relief_rmse_mm": nan, "level_rmse_mean_mm": nan,
           "relief_rmse_mean_mm": nan, "regions": 0, "small_regions": 0, "small_region_fraction": nan,
           "per_region": []}
    if n == 0:
        return out
    lab = labels[obj]
    e = err[obj]
    area = np.bincount(lab, minlength=n + 1)[1:]
    big = area >= min_region_px
    out.update(regions=int(big.sum()), small_regions=int((~big).sum()),
               small_region_fraction=float(area[~big].sum() / area.sum()))
    if not np.all(np.isfinite(e)):
        return out
    median = np.asarray(ndi.median(err, labels, index=np.arange(1, n + 1)), np.float64)
    mean = np.bincount(lab, weights=e, minlength=n + 1)[1:] / area
    lvl_med, lvl_mean = median[lab - 1], mean[lab - 1]

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    out.update(rmse_mm=rms(e), level_rmse_mm=rms(lvl_med), relief_rmse_mm=rms(e - lvl_med),
               level_rmse_mean_mm=rms(lvl_mean), relief_rmse_mean_mm=rms(e - lvl_mean))
    order = np.argsort(-area, kind="stable")
    out["per_region"] = [{"area_px": int(area[k]), "median_mm": float(median[k]), "mean_mm": float(mean[k])}
                         for k in order if big[k]]
    return out


def real_metrics(pred: np.ndarray, label: np.ndarray, valid: np.ndarray, units_per_mm: float = 6.0,
                 object_mm: float = 1.0, invalid_threshold: float | None = None, min_region_px: int = 50) -> dict:
    """Metrics of one predicted label map against the real label map (all label units, H x W); a predicted
    label at or below ``invalid_threshold`` (None: only NaN) is a pixel the prediction does not cover.
    Every value is a number (the level/relief split's per-region list: :func:`error_split`)."""
    pred = np.asarray(pred, np.float64)
    label = np.asarray(label, np.float64)
    valid = np.asarray(valid, bool)
    obj, plane = object_mask(label, valid, units_per_mm, object_mm)
    err = (pred - label) / units_per_mm

    def rms(e, m):
        return float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else float("nan")

    covered = np.isfinite(pred) if invalid_threshold is None else np.isfinite(pred) & (pred > invalid_threshold)
    flat = (plane - label) / units_per_mm
    above_t = (label - plane) / units_per_mm
    above_p = (pred - plane) / units_per_mm
    out = {
        "object_rmse_mm": rms(err, obj),
        "valid_rmse_mm": rms(err, valid),
        "background_rmse_mm": rms(err, valid & ~obj),
        "flat_object_rmse_mm": rms(flat, obj),
        "flat_valid_rmse_mm": rms(flat, valid),
        "true_object_mean_mm": float(above_t[obj].mean()) if obj.any() else float("nan"),
        "pred_object_mean_mm": float(above_p[obj].mean()) if obj.any() else float("nan"),
        "object_bias_mm": float(err[obj].mean()) if obj.any() else float("nan"),
        "object_fraction": float(obj.mean()),
        "valid_fraction": float(valid.mean()),
        "plane_label": plane,
        "object_median_abs_mm": float(np.median(np.abs(err[obj]))) if obj.any() else float("nan"),
        "object_within_1mm": float(np.mean(np.abs(err[obj]) <= 1.0)) if obj.any() else float("nan"),
        "object_coverage": float(np.mean(covered[obj])) if obj.any() else float("nan"),
    }
    split = error_split(err, obj, min_region_px)
    out.update({"object_level_rmse_mm": split["level_rmse_mm"], "object_relief_rmse_mm": split["relief_rmse_mm"],
                "object_level_rmse_mean_mm": split["level_rmse_mean_mm"],
                "object_relief_rmse_mean_mm": split["relief_rmse_mean_mm"], "object_regions": split["regions"],
                "object_small_regions": split["small_regions"],
                "object_small_region_fraction": split["small_region_fraction"]})
    return out


def _wblur(x: np.ndarray, w: np.ndarray, sigma: float) -> np.ndarray:
    from scipy import ndimage as ndi

    return ndi.gaussian_filter(x * w, sigma) / np.maximum(ndi.gaussian_filter(w, sigma), 1e-6)


def fringe_twins(fringe: np.ndarray, valid: np.ndarray, plane: np.ndarray, degree: int = 3,
                 envelope_sigma: float = 6.0, smooth: float = 4.0) -> dict[str, np.ndarray]:
    """Twins of a fringe image with its envelope but without its relief (no rig needed).

    fringe : (H, W) in [-1, 1] (dataset encoding). valid : (H, W) bool, pixels with a fringe.
    plane : (H, W) bool, pixels of the bare reference plane (e.g. valid and within 2 mm of it).
    The local background ``m`` and modulation ``a`` are Gaussian-weighted (``envelope_sigma`` px)
    moments over the valid pixels. The carrier is the dominant column frequency ``w``; the image is
    demodulated with ``exp(-i w x)``, low-passed (``smooth`` px), unwrapped on the plane and fitted
    there with a ``degree`` polynomial ``q(x, y)``. Returns ``{"flat": m + a cos(w x + q),
    "envelope": m}``, each (H, W) float32 in [-1, 1] with the invalid pixels at -1.
    """
    from scipy import ndimage as ndi
    from skimage.restoration import unwrap_phase

    f = np.asarray(fringe, np.float64)
    valid = np.asarray(valid, bool)
    plane = np.asarray(plane, bool) & valid
    if plane.sum() < 100:
        raise Sim2RealError("fringe_twins: fewer than 100 plane pixels to fit the carrier on")
    w = valid.astype(np.float64)
    m = _wblur(f, w, envelope_sigma)
    ac = np.where(valid, f - m, 0.0)
    a = np.sqrt(2.0 * np.maximum(_wblur(ac ** 2, w, envelope_sigma), 0.0))
    hgt, wid = f.shape
    rows = np.where(plane, ac, 0.0)
    spec = np.abs(np.fft.rfft(rows * np.hanning(wid)[None, :], axis=1)).sum(axis=0)
    k = int(np.argmax(spec[2:])) + 2  # cycles across the width (skip the DC and the window's own)
    x = np.arange(wid, dtype=np.float64)[None, :]
    c = ac * np.exp(-2j * np.pi * k * x / wid)
    wp = plane.astype(np.float64)
    cs = lowpass(c, smooth, wp)
    inner = ndi.binary_erosion(plane, iterations=int(np.ceil(smooth)))
    fit_on = inner if inner.sum() >= 100 else plane
    d = np.asarray(unwrap_phase(np.ma.array(np.angle(cs), mask=~fit_on)))
    basis = poly_basis(hgt, wid, degree)
    coef = np.linalg.lstsq(basis[fit_on.ravel()], d[fit_on], rcond=None)[0]
    carrier = 2 * np.pi * k * x / wid + (basis @ coef).reshape(hgt, wid)

    def enc(img):
        return np.where(valid, np.clip(img, -1.0, 1.0), -1.0).astype(np.float32)

    return {"flat": enc(m + a * np.cos(carrier)), "envelope": enc(m)}


def level_response(model, samples, units_per_mm: float = 6.0, object_mm: float = 5.0, min_pixels: int = 500,
                   size=None) -> dict:
    """Does the predicted object *level* follow the true one? Measured on labelled (synthetic) samples.

    For each sample (a dict with ``fringe`` (1, H, W), ``height`` (1, H, W) labels and ``mask``) with at
    least ``min_pixels`` object pixels (valid and more than ``object_mm`` above the plane,
    :func:`object_mask`): the object's true mean height above the plane ``h`` and the mean error of
    the prediction there ``b`` (mm). A least-squares line ``b = slope * h + intercept`` summarises them:
    slope 0 means the level is read from the image; slope -1 means a constant predicted level, the
    training prior, at ``prior_level_mm = -intercept / slope``. ``model`` maps a (1, 1, H, W) tensor to
    labels (``uhrnet.checkpoint.model_from_checkpoint``). Returns ``{"slope", "intercept_mm",
    "prior_level_mm", "shape_rmse_mm" (RMS over objects of the error's standard deviation, i.e. the
    error without each object's bias), "n_objects", "objects": [[h, b], ...]}`` (NaN without 2 objects).
    """
    rows = []
    for s in samples:
        label = s["height"][0].numpy()
        valid = s["mask"][0].numpy() > 0.5
        obj, plane = object_mask(label, valid, units_per_mm, object_mm)
        if obj.sum() < min_pixels:
            continue
        pred = predict_labels(model, s["fringe"][None], size)[0, 0].cpu().numpy()
        err = (pred[obj].astype(np.float64) - label[obj]) / units_per_mm
        rows.append((float((label[obj] - plane).mean() / units_per_mm), float(err.mean()), float(err.std())))
    out = {"slope": float("nan"), "intercept_mm": float("nan"), "prior_level_mm": float("nan"),
           "shape_rmse_mm": float("nan"), "n_objects": len(rows), "objects": [[h, b] for h, b, _ in rows]}
    if len(rows) >= 2:
        h, b, sd = (np.array(c) for c in zip(*rows))
        slope, intercept = np.polyfit(h, b, 1)
        out.update(slope=float(slope), intercept_mm=float(intercept),
                   prior_level_mm=float(-intercept / slope) if slope < -1e-6 else float("nan"),
                   shape_rmse_mm=float(np.sqrt(np.mean(sd ** 2))))
    return out


def twin_metrics(model, fringe: np.ndarray, pred: np.ndarray, label: np.ndarray, valid: np.ndarray,
                 units_per_mm: float, object_mm: float, plane: float, size=None) -> dict:
    """``relief_effect_mm`` and the twins' object RMSE (module docstring) of one real image; NaN when
    the image has too little bare plane to fit the carrier on.

    ``model`` maps (1, 1, H, W) fringes to labels; ``fringe`` (H, W) in [-1, 1]; ``pred`` its predicted
    labels and ``label`` / ``valid`` the real ones (H, W); ``plane``: the plane label
    (:func:`real_metrics`' ``plane_label``); ``size``: the network's input size (None: the image's).
    """
    import torch


    obj, _ = object_mask(label, valid, units_per_mm, object_mm, plane)
    near = valid & (np.abs(np.asarray(label, np.float64) - plane) <= 2.0 * units_per_mm)
    try:
        twins = fringe_twins(fringe, valid, near)
    except Sim2RealError:
        return {"relief_effect_mm": float("nan"), "flat_twin_object_rmse_mm": float("nan"),
                "envelope_twin_object_rmse_mm": float("nan")}
    out = {}
    with torch.no_grad():
        for name, img in twins.items():
            p = predict_labels(model, torch.from_numpy(img)[None, None], size)[0, 0].cpu().numpy()
            out[f"{name}_twin_object_rmse_mm"] = real_metrics(p, label, valid, units_per_mm, object_mm)["object_rmse_mm"]
            if name == "flat":
                d = (np.asarray(pred, np.float64) - p) / units_per_mm
                out["relief_effect_mm"] = float(np.sqrt(np.mean(d[obj] ** 2))) if obj.any() else float("nan")
    return out
