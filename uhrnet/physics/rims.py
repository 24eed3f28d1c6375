"""Where each raised object meets the plane: the rim pixels no phase region could order (:func:`split_rims`).

After :func:`uhrnet.physics.orders.choose_orders` a band of a few pixels along each silhouette is left out or
reached only by the last growth. There the surface turns away from the camera, its fringes compress, and the
single-shot phase blends both sides' fringes. The network's heights ramp down over the band while the truth is
a cliff, so each pixel put on the wrong side is the whole cliff off.

One image does show the plane's own fringe. The plane's phase is smooth over the whole image (a cubic through
the plane's moved pixels), and its background ``A`` and modulation ``B`` are those of the plane pixels nearby.
So the intensity of a plane pixel is predicted, ``I = A + B cos(Phi_p + o)``. An object pixel follows another
phase, and at a rim that turns away it is darker than the plane. Along each image row and each column, a run of
undecided pixels with a raised moved pixel at one end and a moved plane pixel at the other is a rim crossing; the
pixels of all crossings take their sides together, by the labelling that minimises

    sum over the plane side of (r^2 - kappa^2) + lambda x (4-neighbours on different sides),
    r = (I - A - B cos(Phi_p + o)) / B,

the raised and plane pixels beside the runs fixed to their sides (:func:`min_cut_sides`, a minimum cut:
exact): the plane side is where the plane's fringe explains the image to about ``kappa`` of its modulation, in
few pieces. The plane side takes the plane's phase at the plane's order; the object side takes the raised end's
phase, continued pixel by pixel along its run (the wrapped phase's steps; a column's where a row and a column
reach it). An object-side pixel continued more than 0.5 mm above the raised end's height takes one order lower: towards a rim the surface falls away, and a fall of more
than half a fringe over one pixel reads, wrapped, as a small rise, one order high (on FP1523/1201, 99 % of the
object-side pixels at a wrong order were one order high, and they rose where the right ones fell).

Measured (docs/experiments/orders.md, 3 seeds of the recipe, after the path's mirrored margin): the real pair's
object RMSE through the depth-fitted rig 3.69 +- 0.03 -> 2.14 +- 0.29 mm (all its valid pixels 1.70 -> 1.09 mm);
FP1523/1201 0.79 of the network before and after; FP672 through its own rig 0.321 -> 0.336 of flat (its moved object
pixels are mostly whole orders off, and the split extends them).
The fall read as a rise (stop 58, 4 seeds): FP1523 0.754 / 0.827 / 0.777 / 0.869 -> 0.730 / 0.801 / 0.754 / 0.843,
the pair 1.95 / 1.99 / 2.47 / 3.14 -> 1.86 / 1.92 / 2.42 / 3.14 mm.
The sides of all crossings at once (stop 61; until then each run was split at one point on its own, a column's split
replacing a row's): the pair 1.798 / 1.799 / 2.228 -> 1.589 / 1.602 / 2.083 mm, FP1523/1201 0.709 / 0.785 / 0.738 ->
0.678 / 0.743 / 0.703 of the network (3 seeds, each lower). ``lambda`` 0.1 was chosen on those two images
(0.05: 1.764 mm / 0.711; 0.2: 1.763 / 0.749; 0.5: 1.706 / 0.835, the objects taking plane pixels).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy import ndimage as ndi
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from fppsim.phase import wrap
from fppsim.phase.plane import poly_basis

__all__ = ["split_rims", "min_cut_sides"]


def split_rims(height_mm: np.ndarray, moved: np.ndarray, wrapped: np.ndarray, reliability: np.ndarray,
               lit: np.ndarray, image: np.ndarray, background: np.ndarray, modulation: np.ndarray, layer,
               offset: float, *, flat_mm: float = 1.0, kappa: float = 0.2, max_run_periods: float = 4.0,
               redecide_below: float = 0.2, min_plane_share: float = 0.05,
               max_rise_mm: float | None = 0.5, smooth: float = 0.1) -> tuple[np.ndarray, np.ndarray, dict]:
    """Rim pixels between raised objects and the plane put on one side or the other (module docstring).

    Parameters
    ----------
    height_mm : (H, W) float, the orders path's heights (mm above the reference plane; NaN = none).
    moved : (H, W) bool, pixels whose height came from the phase at a chosen order.
    wrapped, reliability : (H, W) the image's single-shot phase (rad) and its reliability [0, 1].
    lit : (H, W) bool, pixels that carry fringes (not shadows, not invalid).
    image, background, modulation : (H, W) the fringe image and the single-shot phase's ``A`` and ``B``
        (:class:`fppsim.phase.single_shot.SingleShotPhase`), in the image's own units.
    layer : the rig's :class:`~uhrnet.physics.rig_layer.RigLayer` on this grid; ``offset``: the image's phase
        origin (rad, :attr:`~uhrnet.physics.orders.OrderChoice.offset_rad`).
    flat_mm : moved pixels within this of height 0 are the plane; more than this above it, raised.
    kappa : the plane's fringe explains a pixel when its residual is about this share of ``B``.
    max_run_periods : longer runs (in fringe periods along the run) are left as they are.
    redecide_below : moved pixels of lower reliability (reached by the last growth) may change side too.
    min_plane_share : below this share of the lit pixels at plane level nothing is split (no plane in view).
    max_rise_mm : an object-side pixel continued more than this above its raised end takes one order lower
        (``None``: never). It assumes the surface falls towards its silhouette: a rim that truly rises more than
        this (a lip) is put one order low. Not 0: a phase blended across the cliff can rise a little where no
        step aliased (in the end-to-end test 0.5 mm still lowers 247 such pixels, 1 mm 68, 0 mm 644).
    smooth : ``lambda``, the cost of two 4-neighbours on different sides, in units of ``r^2`` (0: each pixel alone).

    Returns
    -------
    ``(heights, placed, stats)``: a float64 copy of ``height_mm`` with the split runs' heights, the (H, W) bool
    mask of the pixels it placed, and counts
    ``rim_runs``, ``rim_to_plane``, ``rim_to_object``, ``rim_lowered`` (object-side pixels taken one order
    lower) (pixels), ``rim_fraction`` (of the finite pixels; ``rim_skipped`` says why nothing was split).
    """
    h = np.asarray(height_mm, np.float64)
    finite = np.isfinite(h)
    moved = np.asarray(moved, bool) & finite
    lit = np.asarray(lit, bool) & finite
    plane = moved & (np.abs(h) < flat_mm)
    if plane.sum() < max(min_plane_share * lit.sum(), 100):
        return h.copy(), np.zeros(h.shape, bool), {"rim_runs": 0, "rim_to_plane": 0, "rim_to_object": 0,
                                                   "rim_lowered": 0, "rim_fraction": 0.0,
                                                   "rim_skipped": "no plane in view"}
    t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=layer.A.device)  # noqa: E731
    with torch.no_grad():
        phase = layer.phase_from_height(t(np.where(finite, h, 0.0))).cpu().numpy()
        plane_phase = layer.plane_phase().cpu().numpy().astype(np.float64)
    period = _period_px(plane_phase)
    basis = poly_basis(*h.shape, 3)  # the plane's phase: a cubic through its moved pixels
    coef = np.linalg.lstsq(basis[plane.ravel()], (phase - plane_phase)[plane], rcond=None)[0]
    phi_p = plane_phase + (basis @ coef).reshape(h.shape)
    r2 = _plane_misfit(np.asarray(image, np.float64), background, modulation, phi_p + offset, plane, period / 2.0)
    r2 = np.minimum(np.nan_to_num(r2, nan=4.0, posinf=4.0), 4.0)  # a misfit of twice B is as bad as it gets
    w = np.asarray(wrapped, np.float64)
    on_plane = phi_p + wrap(w - phi_p - offset)  # the plane's order, wherever the plane is
    undecided = lit & (~moved | (np.asarray(reliability, np.float64) < redecide_below))
    raised = moved & ~undecided & (h > flat_mm)
    plane_end = plane & ~undecided
    continued = np.full(h.shape, np.nan)  # the raised end's phase continued along the run, every run pixel
    anchor = np.full(h.shape, np.nan)  # that raised end's height (mm)
    in_run = np.zeros(h.shape, bool)
    max_run = max(int(round(max_run_periods * period)), 1)
    runs = 0
    for axis in (1, 0):  # rows, then columns (a column's continuation replaces a row's where both reach a pixel)
        runs += _runs_axis(undecided, raised, plane_end, w, (phase, h), (continued, anchor, in_run), max_run, axis)
    # all crossings' sides at once: split one run at a time, a column's split replacing a row's, the pair was
    # 1.94 mm and FP1523/1201 0.744 of the network (3 seeds), against 1.76 and 0.708 now
    side = min_cut_sides(in_run, r2 - kappa ** 2, raised, plane_end, smooth)
    target = np.where(in_run, np.where(side, continued, on_plane), np.nan)
    out = h.copy()
    done = np.isfinite(target)
    lowered = np.zeros(h.shape, bool)
    height_at = lambda d: layer.height_from_phase(t(np.where(done, target + d, 0.0))).cpu().numpy()  # noqa: E731
    with torch.no_grad():
        if done.any():
            out[done] = height_at(0.0)[done]
        if max_rise_mm is not None:
            lowered = done & side & (out > anchor + max_rise_mm)
        if lowered.any():  # one order lower, whichever sign the rig's is
            out[lowered] = np.minimum(height_at(-2.0 * math.pi), height_at(2.0 * math.pi))[lowered]
    return out, done, {"rim_runs": int(runs), "rim_to_plane": int((done & ~side).sum()),
                       "rim_to_object": int((done & side).sum()), "rim_lowered": int(lowered.sum()),
                       "rim_fraction": float(done.sum() / max(finite.sum(), 1))}


def _period_px(plane_phase: np.ndarray) -> float:
    """The fringe period in px: 2 pi over the median magnitude of the plane phase's gradient."""
    gy, gx = np.gradient(plane_phase)
    g = np.hypot(gx, gy)
    g = g[np.isfinite(g) & (g > 0)]
    return float(2.0 * math.pi / np.median(g)) if g.size else 8.0


def _plane_misfit(image, background, modulation, plane_wrapped, plane, spread) -> np.ndarray:
    """``r^2``: the squared residual of the plane's fringe model over its local modulation (module docstring);
    ``A`` and ``B`` are the plane pixels' own, carried by a normalised Gaussian of ``spread`` px."""
    wgt = ndi.gaussian_filter(plane.astype(np.float64), spread)

    def carried(v):
        return ndi.gaussian_filter(np.where(plane, np.nan_to_num(np.asarray(v, np.float64)), 0.0), spread) / np.maximum(wgt, 1e-9)

    a, b = carried(background), carried(modulation)
    return ((image - a - b * np.cos(plane_wrapped)) / np.maximum(b, 1e-9)) ** 2


def _runs_axis(undecided, raised, plane_end, w, phase_height, outputs, max_run, axis) -> int:
    """One pass of :func:`split_rims` along rows (``axis`` 1) or columns (0): every run of ``undecided`` pixels
    with a ``raised`` pixel at one end and a ``plane_end`` pixel at the other, at most ``max_run`` long, gets the
    raised end's phase continued along it by the wrapped phase's steps and that end's height; ``phase_height``:
    the path's (phase, height) pair; fills ``outputs`` = (``continued``, ``anchor``, ``in_run``). Returns the count
    of runs."""
    (phase, h0), (continued, anchor, in_run) = phase_height, outputs
    if axis == 0:
        undecided, raised, plane_end, w, phase, h0 = (a.T for a in (undecided, raised, plane_end, w, phase, h0))
        continued, anchor, in_run = continued.T, anchor.T, in_run.T  # views: written through
    n = undecided.shape[1]
    edges = np.diff(np.pad(undecided.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    runs = 0
    for y, x0 in zip(*np.nonzero(edges == 1)):
        x1 = x0 + int(np.argmax(edges[y, x0 + 1:] == -1)) + 1  # run [x0, x1)
        if x0 == 0 or x1 >= n or x1 - x0 > max_run:
            continue
        if raised[y, x0 - 1] and plane_end[y, x1]:
            path = np.arange(x0 - 1, x1)  # from the raised end
        elif plane_end[y, x0 - 1] and raised[y, x1]:
            path = np.arange(x1, x0 - 1, -1)
        else:
            continue
        runs += 1
        continued[y, path[1:]] = phase[y, path[0]] + np.cumsum(wrap(np.diff(w[y, path])))
        anchor[y, path[1:]] = h0[y, path[0]]
        in_run[y, path[1:]] = True
    return runs


def min_cut_sides(nodes, cost, object_end, plane_end, smooth, scale: float = 1000.0) -> np.ndarray:
    """(H, W) bool, True on the ``nodes`` that take the object's side: the labelling that minimises
    ``sum over plane-side nodes of cost + smooth x (4-neighbour pairs on different sides)``, every pixel of
    ``object_end`` / ``plane_end`` 4-adjacent to a node counting as a fixed side (object where it is in both).

    A minimum s-t cut (scipy's maximum flow on integer capacities): exact for this energy with ``cost`` and
    ``smooth`` rounded to ``1 / scale`` (``scale`` is lowered where a node's capacities would pass 2^30). A node
    nothing pulls either way is on the plane's side. ``cost`` must be finite on the nodes (ValueError)."""
    H, W = nodes.shape
    ys, xs = np.nonzero(nodes)
    n = ys.size
    index = np.full(nodes.shape, -1, np.int64)
    index[ys, xs] = np.arange(n)
    src, sink = n, n + 1
    cf = np.asarray(cost, np.float64)[ys, xs]
    if not np.isfinite(cf).all():
        raise ValueError("min_cut_sides: cost is not finite on every node")
    top = (np.abs(cf).max() if n else 0.0) + 4.0 * abs(smooth)  # the most one node's summed edges can carry
    scale = min(scale, 2.0 ** 30 / top) if top > 0 else scale
    c = np.round(cf * scale).astype(np.int64)
    ids = np.arange(n)
    tails, heads, caps = [np.full(n, src), ids], [ids, np.full(n, sink)], [np.maximum(c, 0), np.maximum(-c, 0)]
    lam = int(round(smooth * scale))
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < H) & (qx >= 0) & (qx < W)
        p, qy, qx = ids[inside], qy[inside], qx[inside]
        q = index[qy, qx]
        if dy + dx > 0:  # each pair of nodes once, both ways
            pair = q >= 0
            tails += [p[pair], q[pair]]
            heads += [q[pair], p[pair]]
            caps += [np.full(2 * int(pair.sum()), lam)]
        to_obj = (q < 0) & object_end[qy, qx]
        to_plane = (q < 0) & plane_end[qy, qx] & ~object_end[qy, qx]
        tails += [np.full(int(to_obj.sum()), src), p[to_plane]]
        heads += [p[to_obj], np.full(int(to_plane.sum()), sink)]
        caps += [np.full(int(to_obj.sum() + to_plane.sum()), lam)]
    t, hd, cp = np.concatenate(tails), np.concatenate(heads), np.concatenate(caps)
    keep = cp > 0
    graph = sparse.csr_matrix((cp[keep].astype(np.int32), (t[keep], hd[keep])), shape=(n + 2, n + 2))
    residual = graph - maximum_flow(graph, src, sink).flow
    residual.data = np.maximum(residual.data, 0)
    residual.eliminate_zeros()
    source_side = np.zeros(n + 2, bool)
    source_side[breadth_first_order(residual, src, directed=True, return_predecessors=False)] = True
    out = np.zeros(nodes.shape, bool)
    out[ys, xs] = source_side[:n]
    return out
