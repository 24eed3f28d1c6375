"""Patches the growth continued one way while the image's phase runs on another (:func:`continue_islands`).

After :func:`uhrnet.physics.orders.choose_orders` every moved pixel's phase comes from its region's unwrapped phase
at the region's order. The growth reaches a low-reliability patch by one route only; where that route crossed a
step the wrapped phase hides (a fall of more than half a fringe between two pixels), the whole patch sits one order
off its surroundings, although the image's phase runs on smoothly across the rest of the patch's border. There the
path's heights jump by a whole fringe where the image shows none.

Two 4-neighbours' step is *continuous* when the image's wrapped step ``d = wrap(w_q - w_p)`` is within ``max_dev``
fringe periods of the median wrapped step around it (a ``window`` x ``window`` median along that axis): the
fringes run on undisturbed, no cliff and no edge between them. The path *continues* such a step when its own phase
step ``Phi(h_q) - Phi(h_p)`` equals ``d``; otherwise it differs by ``k`` whole periods. The moved pixels joined by
continued continuous steps form components. A component holding at most ``max_fraction`` of the moved pixels whose
continuous steps to its largest such neighbour jump, at least ``min_votes`` of them, by one ``k`` (an ``agree``
share) takes the order that continues them: its phase moves by those whole periods, its heights with it.

A real cliff whose height is a whole number of fringes to within ``max_dev`` all along the patch's border would be
undone; a patch joined by one continued step to its neighbour is not a component of its own and stays. A jumping
step whose two pixels are in one component (joined around it) never votes: shifting the component cannot continue
it (they had made a component its own largest neighbour and moved it, compounding over the two
passes: the labelled pair with its right half washed to grey, 2 orders, 12.5 mm, through one recipe network).

Measured (docs/experiments/orders.md, "Islands", 6 seeds of the recipe, 2026-11-29; run after the rim split only): the
labelled pair's object RMSE 1.70 +- 0.19 -> 1.63 +- 0.07 mm (every seed lower, seed 2 2.08 -> 1.74), FP1523/1201
0.741 -> 0.737 of the network (5 seeds lower, one 0.005 higher), FP147 through the recipe's networks 0.758 -> 0.739,
FP672 and the own-rig networks unchanged (within 0.001). 33-1,094 pixels move on the pair, 148-624 on FP1523. Run
also before the level correction (as ``choose_orders`` does): 1.625 -> 1.621 mm, 0.734 -> 0.728.

:func:`continued_components` (the same steps, for any mask) also lets :func:`~uhrnet.physics.orders.choose_orders` move
reliable pixels beyond its margin that such steps join to moved ones (``join_min_moved``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy import ndimage as ndi
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from fppsim.phase import wrap

__all__ = ["continue_islands", "continued_components", "wrapped_steps"]

TWO_PI = 2.0 * math.pi


def continue_islands(height_mm: np.ndarray, moved: np.ndarray, wrapped: np.ndarray, layer, *, max_dev: float = 0.1,
                     min_votes: int = 10, agree: float = 0.8, max_fraction: float = 0.05,
                     window: int = 7, steps=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Moved patches one whole order off where the image's phase runs on across their border (module docstring).

    Parameters
    ----------
    height_mm : (H, W) float, the orders path's heights (mm above the reference plane; NaN = none).
    moved : (H, W) bool, pixels whose height came from the image's phase at a chosen order.
    wrapped : (H, W) the image's single-shot wrapped phase (rad; NaN = none).
    layer : the rig's :class:`~uhrnet.physics.rig_layer.RigLayer` on this grid.
    max_dev : a step is continuous when its wrapped step is within this many periods of the local median step.
    min_votes, agree : a component moves when at least this many of its continuous steps to its largest neighbour
        jump, and this share of them by the same whole order.
    max_fraction : components holding more of the moved pixels than this share never move.
    window : side (px) of the median that gives the local step.
    steps : :func:`wrapped_steps` of ``wrapped`` (``window``), when the caller has them (None: computed here).

    Returns
    -------
    ``(heights, shifted, stats)``: a float64 copy of ``height_mm`` with the moved patches' heights, the (H, W) bool
    mask of the pixels that moved, and ``island_pixels`` / ``islands`` (counts).
    """
    h = np.asarray(height_mm, np.float64)
    if h.shape != np.shape(moved) or h.shape != np.shape(wrapped):
        raise ValueError(f"continue_islands: shapes differ: height {h.shape}, moved {np.shape(moved)}, "
                         f"wrapped {np.shape(wrapped)}")
    w = np.asarray(wrapped, np.float64)
    mv = np.asarray(moved, bool) & np.isfinite(h) & np.isfinite(w)
    out, shifted = h.copy(), np.zeros(h.shape, bool)
    stats = {"island_pixels": 0, "islands": 0}
    if mv.sum() < 2:
        return out, shifted, stats
    t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=layer.A.device)  # noqa: E731
    with torch.no_grad():
        phase = layer.phase_from_height(t(np.where(mv, h, 0.0))).cpu().numpy()
    comp, jumps = _continued_steps(phase, wrapped_steps(w, window) if steps is None else steps, mv, max_dev)
    H, W = h.shape
    comp = comp.ravel()
    sizes = np.bincount(comp[comp >= 0], minlength=int(comp.max()) + 1)
    ja, jb, jk = jumps
    ca, cb = comp[ja], comp[jb]
    # a step that jumps inside one component (reached around by continued steps) says the component is not
    # continuous with itself, not that it is off a neighbour: it never votes (it moved a patch against itself)
    between = ca != cb
    ca, cb, jk = ca[between], cb[between], jk[between]
    b_smaller = sizes[cb] < sizes[ca]
    small, large = np.where(b_smaller, cb, ca), np.where(b_smaller, ca, cb)
    # periods the smaller side moves to continue the step: b continues a when its phase drops by k periods
    by = np.where(b_smaller, -jk, jk)
    shift = np.zeros(sizes.size, np.int64)
    limit = max_fraction * mv.sum()
    candidates = np.unique(small)
    for c in candidates[np.argsort(-sizes[candidates], kind="stable")]:  # largest first: a neighbour's shift is known
        if sizes[c] > limit:
            continue
        mine = small == c
        nbr = large[mine][np.argmax(sizes[large[mine]])]
        votes = by[mine & (large == nbr)]
        values, counts = np.unique(votes, return_counts=True)
        if counts.max() >= min_votes and counts.max() >= agree * votes.size:
            shift[c] = values[np.argmax(counts)] + shift[nbr]  # continue the neighbour where it ends up
    per_pixel = np.where(comp >= 0, shift[np.maximum(comp, 0)], 0).reshape(H, W)
    shifted = per_pixel != 0
    if shifted.any():
        with torch.no_grad():
            moved_h = layer.height_from_phase(t(phase + TWO_PI * per_pixel)).cpu().numpy()
        out[shifted] = moved_h[shifted]
        stats = {"island_pixels": int(shifted.sum()), "islands": int((shift != 0).sum())}
    return out, shifted, stats


def continued_components(phase: np.ndarray, wrapped: np.ndarray, mask: np.ndarray, *, max_dev: float = 0.1,
                         window: int = 7, steps=None) -> np.ndarray:
    """(H, W) int64: the ``mask`` pixels' component ids (not consecutive; -1 outside ``mask``), joined by 4-neighbour
    steps that are continuous (the ``wrapped`` step within ``max_dev`` periods of the ``window`` x ``window`` median
    step around it) and that ``phase`` (rad, absolute: the path's) continues exactly (module docstring); ``steps``:
    :func:`wrapped_steps` of ``wrapped``, when the caller has them."""
    phase, w = np.asarray(phase, np.float64), np.asarray(wrapped, np.float64)
    if phase.shape != w.shape or phase.shape != np.shape(mask):
        raise ValueError(f"continued_components: shapes differ: phase {phase.shape}, wrapped {w.shape}, "
                         f"mask {np.shape(mask)}")
    mask = np.asarray(mask, bool) & np.isfinite(phase) & np.isfinite(w)
    return _continued_steps(phase, wrapped_steps(w, window) if steps is None else steps, mask, max_dev)[0]


def wrapped_steps(wrapped: np.ndarray, window: int = 7) -> tuple:
    """Per axis (rows' steps down the columns, then along the rows), ``(step, local)``: the wrapped phase's step
    to the next pixel (rad, NaN read as 0) and its ``window`` x ``window`` median, the local step. They depend on
    the image alone, so one image's path computes them once (the median is most of this module's time)."""
    w0 = np.asarray(wrapped, np.float64)
    w0 = np.where(np.isfinite(w0), w0, 0.0)
    out = []
    for axis in (0, 1):
        step = wrap(np.diff(w0, axis=axis))
        out.append((step, ndi.median_filter(step, window)))
    return tuple(out)


def _continued_steps(phase, steps, mask, max_dev):
    """``(components (H, W), jumps)``: the components of :func:`continued_components`, and the continuous steps the
    phase does not continue as ``(index a, index b, whole periods k)`` (flat indices, ``b`` the next pixel)."""
    phase = np.where(mask, phase, 0.0)  # steps off the mask are never taken; no NaN in their arithmetic
    H, W = mask.shape
    index = np.arange(H * W).reshape(H, W)
    joined, jumps = [], []
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        step, local = steps[axis]
        continuous = (np.abs(wrap(step - local)) < max_dev * TWO_PI) & mask[a] & mask[b]
        k = np.round((np.diff(phase, axis=axis) - step) / TWO_PI).astype(np.int64)
        same = continuous & (k == 0)
        jump = continuous & (k != 0)
        joined.append((index[a][same], index[b][same]))
        jumps.append((index[a][jump], index[b][jump], k[jump]))
    pa = np.concatenate([j[0] for j in joined])
    pb = np.concatenate([j[1] for j in joined])
    graph = sparse.csr_matrix((np.ones(pa.size, np.int8), (pa, pb)), shape=(H * W, H * W))
    _, comp = connected_components(graph, directed=False)
    comp = np.where(mask.ravel(), comp, -1).astype(np.int64).reshape(H, W)
    return comp, tuple(np.concatenate([j[i] for j in jumps]) for i in range(3))
