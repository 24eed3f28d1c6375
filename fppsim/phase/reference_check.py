"""Order slips of a phase-shifting reference: patches whose temporal fringe order is whole periods off their
surroundings while the wrapped phase AND its gradient run on across their border.

A phase-shifting "ground truth" (wrapped phase ``w`` from the phase-shifted images, absolute phase
``P = w + 2 pi k`` with ``k`` from temporal unwrapping) is only as right as its orders. Temporal unwrapping fails in
patches (low modulation beside a shadow, saturation): there ``k`` jumps by whole periods where the surface is
smooth. A real cliff can jump by whole periods too, but then its wrapped step is that of a random height: the
chance that it continues the fringes' own gradient to within ``max_bend`` all along a patch's border is small.

Between 4-neighbours ``a, b`` (both valid), along each image axis (rad)::

    dw   = wrap(w_b - w_a)                          the wrapped step
    n    = round((P_b - P_a - dw) / 2 pi)           the order jump beyond the wrap
    bend = |dw - g|,  g = median of the ordinary steps within 2 px along the same axis (both sides)

An *ordinary* step has ``n == 0`` and ``|dw| < max_step``; ordinary steps join pixels into components. A *slip* has
``n != 0``, ``|dw| < max_step`` and ``bend < max_bend``: the reference's order jumps where its phase and gradient
continue. A component no larger than ``max_fraction`` of the valid pixels is flagged when at least ``min_seams`` slips
join it to one larger component, they are at least ``min_share`` of its border steps (less those to a smaller
component inside it alone: that one is judged against it) and at least ``agree`` of them say the same ``n``; its shift
(periods) makes it continue that neighbour (after the neighbour's own shift, largest components first).

Measured (2026-11-30): on FP1523/1201 ordinary steps bend by 0.012 rad (median; 90 % under 0.035); slips with a bend
under 0.15 rad are 188 of 544 order jumps along the rows where a step of random height would give about 45. The
flagged patch (213 px in 8 components, a band 4 periods off beside the right figurine's shadow, its modulation
0.37-0.44 of the frame's) is the band stop 65 found 3-4 orders above the surface beside it; its patches' borders are
slips on 80-100 % of their steps. FP672/541 and FP147/109: nothing flagged. Rendered scenes decoded by fppsim's own
phase-shifting chain (64 frames, noise 1-10 gray levels, ladders 1,4,80 / 1,80 / 1,8,80; its temporal errors there are
isolated pixels among rejected ones): nothing flagged; a 5-px sliver beside a real cliff of 3.06 periods (its border
half slips, half a steep slope) was, at ``min_share`` 0.5, hence 0.75. Limits: a real step of a whole number of
periods (to within ``max_bend``) all along a patch's border reads as a slip (exact rendered phase, 180 default
scenes: once, 198 px of floor between a pedestal's edge 1.02 periods high, a shadow and the image's edge); a slip seam
that does not close around a patch (the component stays joined elsewhere) is not flagged, nor a slipped ring with
fewer pixels than the right patch it surrounds.

Time (2 shared cores, 2026-11-30): FP1523/1201 about 0.6 s; a 5-MP frame 3-9 s (30 % of its pixels invalid, or 1 %
of its orders wrong, at random); 2 % of a 1.4-MP frame's orders wrong at random about 2 s.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.csgraph import connected_components

from fppsim.phase import TWO_PI, wrap

__all__ = ["OrderSlips", "order_slips", "slip_periods", "slips_words"]


@dataclass
class OrderSlips:
    """Result of :func:`order_slips`.

    mask : bool (H, W), the pixels of flagged patches. shift : int64 (H, W), whole periods to add to the
    reference's order there (0 elsewhere). patches : one dict per flagged component (``pixels``,
    ``shift_periods``, ``slips``, ``border_steps``, ``rows``, ``cols``: inclusive bounding box), largest first.
    labels : int32 (H, W), ``i + 1`` on the pixels of ``patches[i]``, 0 elsewhere (None: not given).
    """

    mask: np.ndarray
    shift: np.ndarray
    patches: list = field(default_factory=list)
    labels: np.ndarray | None = None

    @property
    def pixels(self) -> int:
        return int(self.mask.sum())

    def repaired(self, phase: np.ndarray) -> np.ndarray:
        """``phase`` (rad) with each flagged patch moved by its shift."""
        return np.asarray(phase, dtype=np.float64) + TWO_PI * self.shift


def _near(a: np.ndarray, k: int, axis: int) -> np.ndarray:
    """``a`` moved by ``k`` along ``axis``, NaN where that leaves the array (no wrap-around)."""
    out = np.full(a.shape, np.nan)
    n = a.shape[axis]
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    src[axis] = slice(max(0, -k), n - max(0, k))
    dst[axis] = slice(max(0, k), n - max(0, -k))
    out[tuple(dst)] = a[tuple(src)]
    return out


def _axis_steps(wrapped, phase, valid, axis: int, max_step: float, max_bend: float):
    """Flat pixel indices of each step's two ends, and which steps are ordinary / slips (with their ``n``)."""
    lo = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1), slice(None))
    hi = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
    idx = np.arange(valid.size).reshape(valid.shape)
    ok = valid[lo] & valid[hi]
    dw = wrap(np.where(ok, wrapped[hi] - wrapped[lo], 0.0))
    with np.errstate(invalid="ignore"):
        n = np.where(ok, np.rint((phase[hi] - phase[lo] - dw) / TWO_PI), 0).astype(np.int64)
    small = ok & (np.abs(dw) < max_step)
    ordinary = small & (n == 0)
    beside = np.stack([_near(np.where(ordinary, dw, np.nan), k, axis) for k in (-2, -1, 1, 2)])
    with warnings.catch_warnings():  # no ordinary step nearby: no gradient, no slip
        warnings.simplefilter("ignore", RuntimeWarning)
        g = np.nanmedian(beside, axis=0)
    bend = np.where(np.isfinite(g), np.abs(dw - g), np.inf)
    slip = small & (n != 0) & (bend < max_bend)
    return idx[lo].ravel(), idx[hi].ravel(), ordinary.ravel(), (ok & ~ordinary).ravel(), slip.ravel(), n.ravel()


def _judge(votes, size, border, room, min_seams, min_share, agree):
    """Each component's shift (periods) and the flagged ones ``[(component, slips)]``, from the slips' ``votes``
    (component, neighbour, periods), largest components first."""
    shift = np.zeros(size.size, dtype=np.int64)
    flagged = []
    if not len(votes):
        return shift, flagged
    keys, counts = np.unique(votes, axis=0, return_counts=True)  # sorted by component: each one's rows a slice
    cands, first = np.unique(keys[:, 0], return_index=True)  # components with a slip on their border
    last = np.r_[first[1:], len(keys)]
    for i in np.argsort(-size[cands], kind="stable"):
        comp = cands[i]
        if not 0 < size[comp] <= room:
            continue
        kk, cc = keys[first[i]:last[i]], counts[first[i]:last[i]]
        mine = size[kk[:, 1]] > size[comp]
        if not mine.any():
            continue
        best = np.flatnonzero(mine)[np.argmax(cc[mine])]
        nbr, k, v = kk[best, 1], kk[best, 2], cc[best]
        total = cc[mine & (kk[:, 1] == nbr)].sum()
        if v >= min_seams and v >= min_share * border[comp] and v >= agree * total:
            shift[comp] = k + shift[nbr]
            if shift[comp]:  # else right after all: inside a patch, as far off as the patch around it
                flagged.append((comp, v))
    return shift, flagged


def order_slips(wrapped: np.ndarray, phase: np.ndarray, valid: np.ndarray, *, max_step: float = 1.0,
                max_bend: float = 0.15, min_seams: int = 5, min_share: float = 0.75, agree: float = 0.8,
                max_fraction: float = 0.05) -> OrderSlips:
    """Patches of a phase-shifting reference whose order slipped by whole periods (see the module docstring).

    wrapped : float (H, W), the reference's wrapped phase (rad). phase : float (H, W), its absolute phase
    ``wrapped + 2 pi order`` (rad). valid : bool (H, W), pixels with a phase. Thresholds in rad (``max_step``,
    ``max_bend``), steps (``min_seams``) and shares. Uses only the reference: no prediction, no label.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    phase = np.asarray(phase, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if wrapped.shape != valid.shape or phase.shape != valid.shape or valid.ndim != 2:
        raise ValueError(f"wrapped {wrapped.shape}, phase {phase.shape} and valid {valid.shape} must be one 2-D shape")
    valid = valid & np.isfinite(wrapped) & np.isfinite(phase)
    steps = [_axis_steps(wrapped, phase, valid, ax, max_step, max_bend) for ax in (0, 1)]
    a, b, ordinary, edge, slip, n = (np.concatenate(parts) for parts in zip(*steps))
    graph = sp.coo_matrix((np.ones(int(ordinary.sum())), (a[ordinary], b[ordinary])), shape=(valid.size,) * 2)
    lab = connected_components(graph, directed=False)[1]
    size = np.bincount(lab[valid.ravel()], minlength=lab.max() + 1)
    between = lab[a] != lab[b]
    la, lb = lab[a[edge & between]], lab[b[edge & between]]
    pairs = np.unique(np.c_[np.r_[la, lb], np.r_[lb, la]], axis=0)
    inside = np.bincount(pairs[:, 0], minlength=size.size) == 1  # one neighbour all round: judged against it, its
    border = np.bincount(np.r_[la[~inside[lb] | (size[lb] >= size[la])],  # steps do not dilute that one's share
                               lb[~inside[la] | (size[la] >= size[lb])]], minlength=size.size)
    s = slip & between  # each slip read from both sides: (component, neighbour, periods to add to the component)
    votes = np.c_[np.r_[lab[b[s]], lab[a[s]]], np.r_[lab[a[s]], lab[b[s]]], np.r_[-n[s], n[s]]]
    shift, flagged = _judge(votes, size, border, max_fraction * valid.sum(), min_seams, min_share, agree)
    flagged.sort(key=lambda f: -size[f[0]])  # largest first, ties as found
    tags = np.zeros(size.size, dtype=np.int32)
    tags[np.array([comp for comp, _ in flagged], dtype=np.int64)] = np.arange(1, len(flagged) + 1)
    labels = np.where(valid.ravel(), tags[lab], 0).reshape(valid.shape).astype(np.int32)
    boxes = ndimage.find_objects(labels, max_label=len(flagged))
    patches = [{"pixels": int(size[comp]), "shift_periods": int(shift[comp]), "slips": int(v),
                "border_steps": int(border[comp]), "rows": [box[0].start, box[0].stop - 1],
                "cols": [box[1].start, box[1].stop - 1]} for (comp, v), box in zip(flagged, boxes)]
    per_pixel = np.where(valid.ravel(), shift[lab], 0).reshape(valid.shape)
    return OrderSlips(mask=per_pixel != 0, shift=per_pixel, patches=patches, labels=labels)


def slips_words(patches: list, pixels: int | None = None) -> str:
    """``"by whole periods (4) in 8 patch(es), 213 px"``: the words every tool uses for :attr:`OrderSlips.patches`
    (``pixels``: the count to say, e.g. the scored ones; default all the patches')."""
    pixels = sum(p["pixels"] for p in patches) if pixels is None else pixels
    return f"by whole periods ({slip_periods(patches)}) in {len(patches)} patch(es), {pixels} px"


def slip_periods(patches: list) -> str:
    """The patches' shifts, ``"-3/4"``: each distinct ``shift_periods`` once, in order."""
    return "/".join(str(k) for k in sorted({p["shift_periods"] for p in patches}))
