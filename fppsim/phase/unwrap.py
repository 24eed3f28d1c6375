"""Spatial unwrapping of a single-shot phase: regions, their unwrapped phase, and shadow bridges.

A single fringe image gives the phase only modulo 2 pi (:func:`fppsim.phase.single_shot.single_shot_phase`).
Inside a smooth, well-lit surface the phase is continuous and can be unwrapped spatially; across a
step whose fringes alias (a near-vertical wall) or across a shadow it cannot, so the image falls into
*regions*, each unwrapped up to its own multiple of 2 pi (the fringe order).

Two things fix a region's order:

* a height estimate (a network's prediction) within half a fringe period of the truth on average
  over the region (``uhrnet.physics.refine``);
* a **shadow bridge**: the projector ray that grazes an object's edge lands on the plane at the far
  side of the shadow the object casts, and one projector ray carries one phase. So along a camera row
  (the epipolar direction of a side-by-side rig), the absolute phase just before a shadow equals the
  absolute phase just after it, where the region after the shadow is the surface that casts it. Each
  row crossing a shadow votes for the order difference between the two regions; a bridge is trusted
  when enough rows agree. Measured on the real phase-shifting frame FP1523 (exact PSP phase): most
  rows agree within 0.3–1 rad; rows where the shadow is cast by a taller part further along do not,
  which the vote rejects.

Plain numpy/scipy/scikit-image; phases in radians, images (H, W).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from fppsim.errors import InputError
from fppsim.phase import wrap

__all__ = ["PhaseRegions", "phase_regions", "phase_quality", "step_conflicts", "Bridge", "shadow_runs", "shadow_bridges"]


def phase_quality(wrapped: np.ndarray) -> np.ndarray:
    """Phase-discontinuity measure (rad), (H, W) float64: the sum of the absolute wrapped second
    differences along rows and columns, averaged over 3 x 3. Near 0 on smooth fringes; large on
    steps, aliasing walls and noise (the quality map of reliability-guided unwrapping)."""
    w = np.asarray(wrapped, np.float64)
    dx = wrap(np.diff(w, axis=1, append=w[:, -1:]))
    dy = wrap(np.diff(w, axis=0, append=w[-1:]))
    q = np.abs(wrap(np.diff(dx, axis=1, prepend=dx[:, :1]))) + np.abs(wrap(np.diff(dy, axis=0, prepend=dy[:1])))
    return ndi.uniform_filter(q, 3)


def step_conflicts(wrapped: np.ndarray, expected: np.ndarray, max_step: float = 1.5) -> np.ndarray:
    """Pixels where the image's phase step to a neighbour disagrees with an expected phase map's.

    ``expected`` (H, W) is an absolute phase the caller believes approximately (e.g. a smoothed height
    estimate seen through the rig). On a smooth surface both steps agree; at a wall whose fringes
    alias, the image steps by a fraction of a period while the estimate steps by several, so the two
    pixels of that pair are returned (True) and the wall becomes a region boundary.

    Returns (H, W) bool.
    """
    w = np.asarray(wrapped, np.float64)
    e = np.asarray(expected, np.float64)
    out = np.zeros(w.shape, bool)
    for axis in (0, 1):
        bad = np.abs(wrap(np.diff(w, axis=axis)) - np.diff(e, axis=axis)) > max_step
        bad &= np.isfinite(np.diff(e, axis=axis))
        if axis == 0:
            out[:-1] |= bad
            out[1:] |= bad
        else:
            out[:, :-1] |= bad
            out[:, 1:] |= bad
    return out


@dataclass
class PhaseRegions:
    """Regions of a wrapped phase map and their spatially unwrapped phase.

    labels : (H, W) int32, 0 = in no region, 1..n the regions (largest first).
    unwrapped : (H, W) float64 rad, NaN outside the regions; each region's phase is exact up to its
        own multiple of 2 pi.
    sizes : (n,) pixels per region.
    """

    labels: np.ndarray
    unwrapped: np.ndarray
    sizes: np.ndarray

    @property
    def count(self) -> int:
        return int(len(self.sizes))


def phase_regions(wrapped: np.ndarray, usable: np.ndarray, cut: np.ndarray | None = None,
                  max_quality: float = 1.0, min_size: int = 50) -> PhaseRegions:
    """Split ``usable`` pixels into regions the phase can be unwrapped in, and unwrap each.

    Parameters
    ----------
    wrapped : (H, W) wrapped phase, rad.
    usable : (H, W) bool, pixels whose phase is trusted (e.g. reliability above a threshold).
    cut : (H, W) bool, extra boundaries (e.g. where a height estimate jumps); None: none.
    max_quality : pixels whose :func:`phase_quality` exceeds this (rad) are boundaries too.
    min_size : regions smaller than this many pixels are dropped (label 0).
    """
    from skimage.restoration import unwrap_phase

    w = np.asarray(wrapped, np.float64)
    finite = np.isfinite(w)  # NaN would spread along whole rows through the quality filter's running sums
    ok = np.asarray(usable, bool) & finite & (phase_quality(np.where(finite, w, 0.0)) <= max_quality)
    if cut is not None:
        ok &= ~np.asarray(cut, bool)
    labels, n = ndi.label(ok)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    order = np.argsort(-sizes, kind="stable")
    keep = order[sizes[order] >= min_size]
    relabel = np.zeros(n + 1, np.int32)
    relabel[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
    labels = relabel[labels]
    unwrapped = np.full(w.shape, np.nan)
    if len(keep):
        inside = labels > 0
        # disconnected regions come out independently, each with its own multiple of 2 pi
        # (masked values must be finite: skimage's unwrapper never returns on NaN, even masked)
        unwrapped[inside] = np.asarray(unwrap_phase(np.ma.array(np.where(inside, w, 0.0), mask=~inside)).data)[inside]
    return PhaseRegions(labels, unwrapped, sizes[keep].astype(np.int64))


@dataclass
class Bridge:
    """Rows crossing one shadow from region ``a`` (before, in the row direction) to region ``b``.

    ``periods``: the trusted order difference ``k`` such that the absolute phase of ``b`` is its
    unwrapped phase plus ``2 pi k`` more than ``a``'s offset (:func:`shadow_bridges`); ``votes``: rows
    that crossed; ``agreement``: share of them within ``tolerance`` periods of ``periods`` (``about="order"``) or of
    their median (``"median"``, ``"image"``: after the image's offset).
    """

    a: int
    b: int
    periods: int
    votes: int
    agreement: float


def shadow_runs(shadow: np.ndarray) -> np.ndarray:
    """Every crossing of a shadow along an image row: (n, 3) int64 rows ``(row, x_before, x_after)``, the
    last lit pixel before a run of ``shadow`` pixels and the first lit pixel after it, in row-major
    order. Runs touching the left or right image border (nothing lit on one side) are not crossings.
    The one shadow walker of the depth fit's shadow edges and the shadow bridges."""
    sh = np.asarray(shadow, bool)
    W = sh.shape[1]
    starts = np.argwhere(~sh[:, :-1] & sh[:, 1:])  # (row, x): x lit, x + 1 in shadow
    ends = np.argwhere(sh[:, :-1] & ~sh[:, 1:])  # (row, x): x in shadow, x + 1 lit
    if not len(starts) or not len(ends):
        return np.zeros((0, 3), np.int64)
    fs, fe = starts[:, 0] * W + starts[:, 1], ends[:, 0] * W + ends[:, 1]
    j = np.searchsorted(fe, fs)  # each run's end is the first end after its start, in the same row
    j = np.minimum(j, len(fe) - 1)
    same = (fe[j] > fs) & (ends[j, 0] == starts[:, 0])
    return np.stack([starts[same, 0], starts[same, 1], ends[j[same], 1] + 1], axis=1).astype(np.int64)


def shadow_bridges(regions: PhaseRegions, shadow: np.ndarray, max_gap: int = 80, step: float = -1, reach: int = 10,
                   tolerance: float = 0.25, min_votes: int = 5, min_agreement: float = 0.6,
                   about: str = "image", max_offset: float = 0.5) -> list[Bridge]:
    """Order differences across shadows, voted row by row (module docstring).

    Parameters
    ----------
    regions : from :func:`phase_regions`.
    shadow : (H, W) bool, pixels without projector light (invalid, black in the dataset encoding).
    max_gap : widest shadow (px) bridged along a row. reach : how far (px) from the shadow a region
        pixel may start (the phase right at an edge is rarely trusted). step : where each side's phase is
        read, in px past its last lit pixel towards the shadow, extrapolated with the local phase slope from the
        region's nearest pixel: -1 reads the pixel beside the last lit one, whose light the shadow does not
        share (the last lit pixel's own phase is pulled by the dark run beside it). Reading there shifts every
        vote by minus the two sides' phase steps per pixel (periods), a part of the offset ``about="image"``
        removes.
    tolerance, min_votes, min_agreement : a bridge is returned when at least ``min_votes`` rows
        crossed it and ``min_agreement`` of them lie within ``tolerance`` periods of the rounded median
        (``about="order"``), of the median itself (``about="median"``), or of the median once the image's
        common offset is removed (``about="image"``: the circular mean of the votes of every region pair that
        would make a bridge on its own, where their resultant length is at least 0.3 and the offset within
        ``max_offset``).
        The single-shot phase beside a shadow is biased, so votes cluster a fraction of a period off the whole
        order, the same for the image's shadows: read at the last lit pixels (``step=0``) +0.12 on the labelled
        pair, +0.16 on FP1523/1201 and +0.2 to +0.4 on rendered scenes; one pixel further in (``step=-1``)
        -0.05, -0.01 and +0.04 to +0.23. With ``median`` or ``image`` the (corrected) median must lie within
        ``max_offset`` periods of the order it rounds to.

    Returns
    -------
    list of :class:`Bridge`; ``periods`` satisfies
    ``U_b + 2 pi (m_a + periods) == U_a + 2 pi m_a`` at the shadow, i.e. if region ``a`` is made
    absolute by adding ``2 pi m_a``, region ``b`` is by adding ``2 pi (m_a + periods)``.

    Measured (docs/experiments/orders.md, stop 64): on 16 held-out rendered scenes of 1-3 objects through the
    figshare depth rig the orders path put 0.30 / 0.32 / 0.21 of the object pixels at the right order with
    ``step=1, about="median"`` and 0.51 / 0.50 / 0.47 with these defaults (3 networks); on the real frames (6
    networks) every bridge and score stayed the same.
    """
    if about not in ("order", "median", "image"):
        raise InputError(f"about must be 'order', 'median' or 'image', got {about!r}")
    lab, U = regions.labels, regions.unwrapped
    sh = np.asarray(shadow, bool)
    H, W = lab.shape
    votes: dict[tuple[int, int], list[float]] = {}
    for r, x0, x1 in shadow_runs(sh):  # x0: last lit pixel before the shadow, x1: first lit after it
        if x1 - x0 - 1 > max_gap:
            continue
        # walk back / forward to the nearest region pixels (the phase right at an edge is unreliable)
        a_idx = [x0 - i for i in range(0, reach) if x0 - i - 1 >= 0 and lab[r, x0 - i] > 0 and lab[r, x0 - i - 1] == lab[r, x0 - i]]
        b_idx = [x1 + i for i in range(0, reach) if x1 + i + 1 < W and lab[r, x1 + i] > 0 and lab[r, x1 + i + 1] == lab[r, x1 + i]]
        if not a_idx or not b_idx:
            continue
        xa, xb = a_idx[0], b_idx[0]
        a, b = int(lab[r, xa]), int(lab[r, xb])
        if a == b:
            continue
        ua = U[r, xa] + (U[r, xa] - U[r, xa - 1]) * (x0 - xa + step)
        ub = U[r, xb] - (U[r, xb + 1] - U[r, xb]) * (xb - x1 + step)
        vote = (ua - ub) / (2 * np.pi)
        if np.isfinite(vote):
            votes.setdefault((a, b), []).append(vote)
    votes = {ab: np.asarray(v) for ab, v in votes.items()}
    median = {ab: float(np.median(v)) for ab, v in votes.items()}
    # rows agreeing about their pair's median (an offset common to the votes does not change it)
    around = {ab: float(np.mean(np.abs(v - median[ab]) <= tolerance)) for ab, v in votes.items()}
    steady = [ab for ab, v in votes.items() if len(v) >= min_votes and around[ab] >= min_agreement]
    bias = _common_offset([votes[ab] for ab in steady], max_offset) if about == "image" else 0.0
    out = []
    for ab, v in votes.items():
        k = int(np.round(median[ab] - bias))
        agree = float(np.mean(np.abs(v - k) <= tolerance)) if about == "order" else around[ab]
        if len(v) >= min_votes and agree >= min_agreement and abs(median[ab] - bias - k) <= max_offset:
            out.append(Bridge(*ab, k, int(len(v)), agree))
    return out


def _common_offset(steady: list[np.ndarray], max_offset: float) -> float:
    """The image's common vote offset (periods): the circular mean of the votes of the region pairs that would make
    a bridge on their own (``steady``), so that short dark runs and pairs whose rows disagree do not pull it; 0 where
    those votes hardly share one (resultant length under 0.3) or it exceeds ``max_offset``."""
    if not steady:
        return 0.0
    z = np.mean(np.exp(2j * np.pi * np.concatenate(steady)))
    offset = float(np.angle(z) / (2 * np.pi))
    return offset if abs(z) >= 0.3 and abs(offset) <= max_offset else 0.0
