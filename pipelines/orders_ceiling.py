"""What choosing each region's fringe order can still win, and where the rest of a path's error sits.

Issue 46's levers 2 and 4 (a learned order, one global choice per image) change nothing but the whole-order
offset of each phase region the path forms. Their ceiling is that of a perfect choice: every region shifted by the
whole orders the truth says (the median over the region's pixels), the path's heights inside a region and the
pixels in no region left as they are.

* :func:`pair_ceiling`: the labelled pair; the truth is its label (mm), the shift is in the rig's phase.
* :func:`frame_ceiling`: a phase-shifting frame; the truth is the reference phase, read through the rig (each
  region's median order against the reference, relative to the plane's), the result scored as the issue scores it
  (phase regressed on a degree-3 plane plus ``a h + b h^2``, :func:`uhrnet.scoring.phase_residual.fit_phase`). It
  also splits the path's squared residual into the pixels in no region, the rim split's pixels a whole order off,
  region pixels a whole order off (|residual| > pi; the rim's left out) and the pixels where the reference's own
  temporal order slipped, with the residual each part would leave if its residual were zero and the fit kept (not
  refitted: a rule that put those pixels right would let the fit move too, so not a strict bound on what it can
  win; on FP1523/1201 the refit is lower by at most 0.008 of the network's residual, each part alone, 4 seeds).

The orders are read through the rig: where its phase does not follow the reference's at the objects' heights (a
rig fitted to the frame alone, FP672/541: its objects read 5-8 orders off), right regions read whole orders off
and the "ceiling" can lie above the path's residual. Pixels without a height keep none.

Used by ``pipelines/orders_study.py`` (keys ``ceiling`` in its orders.json).
"""

from __future__ import annotations

import numpy as np
import torch

from uhrnet.scoring.phase_residual import fit_phase

TWO_PI = 2.0 * np.pi


def _rig_phase(layer, h: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return layer.phase_from_height(torch.as_tensor(np.nan_to_num(h), dtype=torch.float64)).numpy()


def _rig_height(layer, phase: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return layer.height_from_phase(torch.as_tensor(phase, dtype=torch.float64)).numpy()


def reference_orders(choice, layer, phase: np.ndarray, flat_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(r, plane)`` of a path's ``choice`` (:class:`uhrnet.physics.orders.OrderChoice`) against a reference's absolute
    ``phase`` (rad, (H, W)): ``r`` the reference minus the rig phase of the path's height and its origin, in periods
    (NaN where the reference is), and ``plane`` the moved pixels of finite ``r`` the path puts within ``flat_mm`` of
    the plane, against whose median ``r`` reads whole orders (``layer``: the rig's RigLayer on this grid)."""
    h = np.asarray(choice.height, np.float64)
    r = (np.asarray(phase, np.float64) - _rig_phase(layer, h) - choice.offset_rad) / TWO_PI
    return r, np.asarray(choice.moved, bool) & np.isfinite(r) & (np.abs(h) < flat_mm)


def _regions_shifted(layer, height: np.ndarray, labels: np.ndarray, k: np.ndarray, counted: np.ndarray):
    """``(heights, regions moved)``: each region of ``labels`` with ``counted`` pixels shifted by the median of their
    whole orders ``k`` through the rig (one conversion for all); the rest, and pixels without a height, as they are."""
    h = np.array(height, dtype=np.float64)
    table = np.zeros(int(labels.max()) + 1 if labels.size else 1)
    for reg in np.unique(labels[counted]):
        table[reg] = np.round(np.median(k[counted & (labels == reg)]))
    shift = table[labels]
    move = (shift != 0) & np.isfinite(h)
    if move.any():
        h[move] = _rig_height(layer, _rig_phase(layer, h) + TWO_PI * shift)[move]
    return h, int(np.count_nonzero(table))


def pair_ceiling(height: np.ndarray, labels: np.ndarray, truth: np.ndarray, obj: np.ndarray, layer) -> np.ndarray:
    """The path's heights (mm, (H, W)) with each region (``labels`` 1..n) at the label's order: shifted by the median
    over its object pixels (``obj``, finite ``truth``) of ``round((Phi(truth) - Phi(height)) / 2 pi)`` periods of
    the rig (``layer``: :class:`uhrnet.physics.rig_layer.RigLayer` on this grid). A region without object pixels,
    and every pixel in no region, keeps its height (NaN stays NaN)."""
    k = np.round((_rig_phase(layer, truth) - _rig_phase(layer, height)) / TWO_PI)
    counted = obj & np.isfinite(truth) & np.isfinite(height) & (labels > 0)
    return _regions_shifted(layer, height, labels, k, counted)[0]


def frame_ceiling(choice, phase: np.ndarray, scored: np.ndarray, slipped: np.ndarray, layer,
                  flat_mm: float = 1.0) -> dict:
    """Ceiling and parts of a path's calibration-free residual on one phase-shifting frame (module docstring).

    choice : the path's :class:`uhrnet.physics.orders.OrderChoice` (its heights, regions, rim split, moved pixels
    and phase origin); phase : (H, W) the reference's absolute phase, rad; scored : (H, W) bool, the pixels the
    score counts; slipped : (H, W) bool, where the reference's temporal order slipped; layer : the rig's
    :class:`uhrnet.physics.rig_layer.RigLayer` on this grid.

    A region's whole-order offset is read in the rig's phase, as the study's ``right_order_moved``
    (:func:`reference_orders`): the reference minus the rig phase of the path's height and its origin, in periods,
    relative to the median over the moved pixels the path puts on the plane (within ``flat_mm``), then the median
    over the region's scored pixels. (The calibration-free fit would take part of a region's offset up in its plane
    and ``a h + b h^2``.) Those plane pixels (``plane_px``) must be at least a tenth of the scored moved pixels, as
    the path's own origin asks (:mod:`uhrnet.physics.orders`): else there is no order to read against, and
    ``ceiling_rad`` is NaN and ``regions_moved`` None.

    Returns ``{"residual_rad", "ceiling_rad", "regions_moved", "plane_px",
    "parts": {part: {"pixels", "share", "rad_without"}}}``:
    ``share`` of the squared residual, ``rad_without`` the residual with that part's set to zero (the parts may
    overlap: a slipped reference pixel is often also a region pixel a whole order off).
    """
    h = np.array(choice.height, dtype=np.float64)
    labels = choice.labels
    fit, res = fit_phase(phase, h, scored, return_residual=True)
    r, plane = reference_orders(choice, layer, phase, flat_mm)
    ok_r = scored & np.isfinite(r) & np.isfinite(h)
    plane &= scored
    moved, ceiling = None, float("nan")
    if plane.any() and plane.sum() >= 0.1 * (ok_r & choice.moved).sum():
        out, moved = _regions_shifted(layer, h, labels, np.round(r - np.median(r[plane])), ok_r & (labels > 0))
        ceiling = fit_phase(phase, out, scored).rmse_rad
    ok = np.isfinite(res)
    rim = np.zeros(ok.shape, bool) if choice.rim is None else np.asarray(choice.rim, bool)
    off = ok & (np.abs(np.where(ok, res, 0.0)) > np.pi)
    parts = {"no_region": ok & (labels == 0) & ~rim, "rim_split_order_off": off & rim,
             "region_order_off": off & (labels > 0) & ~rim, "reference_slipped": ok & np.asarray(slipped, bool)}
    total, n = float(np.sum(res[ok] ** 2)), int(ok.sum())
    return {"residual_rad": fit.rmse_rad, "ceiling_rad": ceiling, "regions_moved": moved, "plane_px": int(plane.sum()),
            "parts": {name: {"pixels": int(m.sum()), "share": float(np.sum(res[m] ** 2) / total) if total else 0.0,
                             "rad_without": float(np.sqrt(max(total - np.sum(res[m] ** 2), 0.0) / n))}
                      for name, m in parts.items()}}
