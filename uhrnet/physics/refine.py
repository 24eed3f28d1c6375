"""Make a height map consistent with its own fringe image's phase, region by region (:func:`refine_relief`).

A single-shot fringe image fixes the projector phase of every pixel up to whole periods (the wrapped
phase ``phi``, :func:`fppsim.phase.single_shot.single_shot_phase`); a network's height estimate ``h`` says which
period. Through the calibrated rig (:class:`uhrnet.physics.rig_layer.RigLayer`) the estimate implies the phase
``Phi(h)``. :func:`refine_relief` unwraps the phase inside regions where it is continuous and takes
their relief from it, their level from the estimate (``relief``); :func:`uhrnet.physics.orders.choose_orders`
gives every region a whole fringe order instead (``orders``).

Phase origin. Real frames may count phase from another origin (the public real data count fringe
orders from the first fringe the camera sees: DESIGN.md §9, about +72 rad): measured = fppsim phase +
``o``, mod 2 pi. ``o`` is estimated per image as the circular median of ``wrap(phi - Phi(h))`` over the
reliable pixels (:func:`fppsim.phase.circular_median`; robust to the object's pixels where ``h`` is wrong as long as
most reliable pixels are right, e.g. the reference plane).

Snapping each pixel to the nearest phase-consistent height (``--refine-method nearest``,
``refine_height``) was removed on 2026-11-26: on the real pair it made the recipe model worse (6.92 mm
against 6.06 mm unrefined; relief 5.57 mm, docs/experiments/physics.md).

Geometry once per rig: a rig (or its dictionary) given to :func:`refine_relief` is turned into a float64
:class:`~uhrnet.physics.rig_layer.RigLayer` on its camera's grid once and kept (:func:`layer_for`, the last
few rigs), so predicting or evaluating many images through one rig builds it once (about 0.1 s and 15 MB
for 640 x 352); a layer passed in is used as it is.

numpy in, numpy out (torch float64 inside).
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from fppsim.geometry.rig import Rig
from fppsim.phase import circular_median, wrap
from fppsim.phase.unwrap import phase_regions, step_conflicts
from uhrnet.errors import InputError
from uhrnet.physics.rig_layer import RigLayer

__all__ = ["refine_relief", "layer_for", "estimate_phases", "EstimatePhases", "REFINE_METHODS"]

REFINE_METHODS = ("orders", "relief")
"""``orders`` (the default): :func:`uhrnet.physics.orders.choose_orders`, every phase region at one whole fringe
order chosen for the image at once (shadow bridges, seams, the network's priors), levels from the phase through
the rig; ``relief``: :func:`refine_relief`, each region's level from the estimate, its relief from the phase."""

TWO_PI = 2.0 * math.pi


_LAYERS: OrderedDict = OrderedDict()  # rig document (JSON) -> its RigLayer on the camera grid, newest last
MAX_CACHED_LAYERS = 4


def layer_for(rig_or_layer, shape):
    """The :class:`~uhrnet.physics.rig_layer.RigLayer` :func:`refine_relief` works through for a height map of
    ``shape`` (``(..., H, W)``): a layer as it is; a rig (or its dictionary) as the float64 layer on its
    camera's grid, built on the first call for that rig and kept for the next ones (the last
    :data:`MAX_CACHED_LAYERS` rigs, keyed by the rig's whole document: a changed rig gets its own layer).
    The layer is read only (``torch.no_grad``), so a kept one gives the same numbers as a new one.
    ValueError when the layer's grid is not ``(H, W)``."""

    if isinstance(rig_or_layer, RigLayer):
        layer = rig_or_layer
    else:
        rig = rig_or_layer if isinstance(rig_or_layer, Rig) else Rig.from_dict(rig_or_layer)
        key = json.dumps(rig.to_dict(), sort_keys=True)
        layer = _LAYERS.pop(key, None)
        _LAYERS[key] = layer = RigLayer(rig) if layer is None else layer
        while len(_LAYERS) > MAX_CACHED_LAYERS:
            _LAYERS.popitem(last=False)
    if tuple(shape[-2:]) != layer.grid_shape:
        raise InputError(f"height map is {shape[-1]} x {shape[-2]} px but the layer's grid is "
                         f"{layer.grid_shape[1]} x {layer.grid_shape[0]}: pass a RigLayer built for this grid "
                         "(RigLayer(rig, height=..., width=..., pixels=...))")
    return layer


@dataclass
class EstimatePhases:
    """What both ways of levelling a height map to its image's phase start from (:func:`estimate_phases`).

    h : (H, W) float64 estimate (NaN = none); finite : where it is finite; ok : finite and ``valid``;
    rel : reliability (NaN -> 0; ones without one); w : the wrapped phase, float64; usable : ``ok`` pixels with
    a finite phase of at least ``min_reliability``; filled : the estimate with every NaN replaced by the nearest
    finite value (so smoothing does not drag edges to 0); phi, sens : the rig's phase of ``filled`` (rad) and its
    sensitivity (rad / mm); expected : the phase of ``filled`` smoothed over ``smooth_px`` (the step check's);
    layer : the :class:`~uhrnet.physics.rig_layer.RigLayer` they came through."""

    h: np.ndarray
    finite: np.ndarray
    ok: np.ndarray
    rel: np.ndarray
    w: np.ndarray
    usable: np.ndarray
    filled: np.ndarray
    phi: np.ndarray
    sens: np.ndarray
    expected: np.ndarray
    layer: object


def estimate_phases(height_mm, wrapped_phase, reliability, rig_or_layer, valid=None, min_reliability: float = 0.5,
                    smooth_px: float = 3.0) -> EstimatePhases:
    """The checked inputs of :func:`refine_relief` and :func:`uhrnet.physics.orders.choose_orders` and the
    estimate's phases through ``rig_or_layer`` (its layer on their grid: :func:`layer_for`, kept as ``layer``).
    ValueError when the height and the phase are not one (H, W), or the layer sees another grid."""
    import torch  # torch: imported when refining, not with the module
    from scipy import ndimage as ndi

    h = np.asarray(height_mm).astype(np.float64)
    if h.ndim != 2 or np.shape(wrapped_phase) != h.shape:
        raise InputError(f"height {h.shape} and wrapped phase {np.shape(wrapped_phase)} must be the same (H, W)")
    layer = layer_for(rig_or_layer, h.shape)
    finite = np.isfinite(h)
    ok = finite if valid is None else finite & np.asarray(valid, bool)
    rel = np.ones(h.shape) if reliability is None else np.nan_to_num(np.asarray(reliability, np.float64))
    w = np.asarray(wrapped_phase, np.float64)
    usable = ok & (rel >= min_reliability) & np.isfinite(w)
    filled = np.where(finite, h, 0.0)
    if not finite.all() and finite.any():
        idx = ndi.distance_transform_edt(~finite, return_distances=False, return_indices=True)
        filled = h[tuple(idx)]
    t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=layer.A.device)  # noqa: E731
    with torch.no_grad():
        phi = layer.phase_from_height(t(filled)).cpu().numpy()
        sens = layer.sensitivity(t(filled)).cpu().numpy()
        expected = layer.phase_from_height(t(ndi.gaussian_filter(filled, smooth_px))).cpu().numpy()
    return EstimatePhases(h, finite, ok, rel, w, usable, filled, phi, sens, expected, layer)


def refine_relief(height_mm: np.ndarray, wrapped_phase: np.ndarray, reliability: np.ndarray | None, rig_or_layer,
                  valid: np.ndarray | None = None, min_reliability: float = 0.5, max_step: float = 1.0,
                  smooth_px: float = 3.0, max_move_mm=None, max_move_fraction: float = 2.0,
                  min_region: int = 50) -> tuple[np.ndarray, np.ndarray, dict]:
    """Relief from the image's phase, level from the estimate: the least move that makes a height map
    consistent with its own fringes, region by region.

    The wrapped phase is unwrapped spatially inside regions where it is continuous
    (:func:`fppsim.phase.unwrap.phase_regions`; boundaries where the phase is unreliable and where the phase
    step between neighbours disagrees by more than ``max_step`` rad with the step of the estimate,
    smoothed over ``smooth_px``, seen through the rig: an aliasing wall). Inside a region the unwrapped
    phase fixes the relief exactly, but not the region's fringe order; the level is taken from the
    estimate: each pixel moves to ``height_from_phase(Phi(h) + D - median_region(D))`` with
    ``D = U - Phi(h) - o`` (``U`` the region's unwrapped phase, ``o`` the image's phase origin,
    :func:`fppsim.phase.circular_median` over the reliable pixels). So the region's median move is 0: the estimate
    keeps its level, the phase replaces its shape. Unlike snapping each pixel to the nearest
    phase-consistent height this needs no estimate within half a period, and a rig whose height scale is slightly off changes the relief by that
    fraction only, not the level.

    A pixel moves only when reliable, inside a region, and when its move is within ``max_move_mm``
    (default ``max_move_fraction`` fringe periods of height at the pixel, ``2 pi / |dPhi/dh|``: a region that
    swallowed a wall is rejected where it moves pixels that far).

    Parameters
    ----------
    height_mm : (H, W) float, the estimate, mm above the reference plane (NaN = none).
    wrapped_phase, reliability : (H, W) the image's single-shot phase (rad) and its reliability [0, 1].
    rig_or_layer : :class:`fppsim.geometry.rig.Rig`, its dictionary or a :class:`uhrnet.physics.rig_layer.RigLayer`
        (a rig's layer is built once and kept: :func:`layer_for`).
    valid : (H, W) bool, pixels that may move (default: finite estimate).

    Returns
    -------
    (refined (H, W) float, moved (H, W) bool, stats dict: ``moved_fraction`` (of the finite estimate's
    pixels), ``reliable_fraction``, ``beyond_margin_fraction``, ``regions``, ``mean_abs_move_mm``,
    ``offset_rad``).
    """
    import torch
    from scipy import ndimage as ndi

    h_in = np.asarray(height_mm)
    e = estimate_phases(h_in, wrapped_phase, reliability, rig_or_layer, valid, min_reliability, smooth_px)
    layer = e.layer
    h, finite, w, usable, phi, sens = e.h, e.finite, e.w, e.usable, e.phi, e.sens
    t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=layer.A.device)  # noqa: E731
    offset = circular_median(wrap(w - phi)[usable]) if usable.any() else 0.0
    regions = phase_regions(w, usable, cut=step_conflicts(w, e.expected, max_step), min_size=min_region)
    lab = regions.labels
    d = regions.unwrapped - phi - offset
    target = np.full(h.shape, np.nan)
    if regions.count:
        med = np.asarray(ndi.median(np.nan_to_num(d), lab, index=np.arange(1, regions.count + 1)))
        inside = lab > 0
        target[inside] = phi[inside] + d[inside] - med[lab[inside] - 1]
    with torch.no_grad():
        h_new = layer.height_from_phase(t(np.nan_to_num(target, nan=0.0))).cpu().numpy()
    h_new[~np.isfinite(target)] = np.nan
    move = h_new - h
    if max_move_mm is None:
        with np.errstate(divide="ignore"):
            margin = max_move_fraction * 2 * math.pi / np.abs(sens)
    else:
        margin = np.broadcast_to(np.asarray(max_move_mm, dtype=np.float64), h.shape)
    within = np.isfinite(move) & (np.abs(move) <= margin)
    moved = usable & (lab > 0) & within
    out_dtype = h_in.dtype if np.issubdtype(h_in.dtype, np.floating) else np.float64
    refined = np.where(moved, h_new, h_in).astype(out_dtype, copy=False)
    n = int(finite.sum())
    stats = {
        "method": "relief",
        "n_pixels": n,
        "moved_fraction": float(moved.sum() / n) if n else 0.0,
        "reliable_fraction": float(usable.sum() / n) if n else 0.0,
        "beyond_margin_fraction": float((usable & (lab > 0) & ~within).sum() / n) if n else 0.0,
        "regions": regions.count,
        "mean_abs_move_mm": float(np.abs(move[moved]).mean()) if moved.any() else 0.0,
        "offset_rad": float(offset),
    }
    return refined, moved, stats
