"""Links between phase regions' fringe orders that need no network: seams and walls the image's phase crosses.

:func:`uhrnet.physics.orders.choose_orders` takes them (with :func:`fppsim.phase.unwrap.shadow_bridges`) into
components, each of which gets one order. A :class:`Link` says region ``b``'s order is region ``a``'s plus
``delta``; :func:`seam_links` votes them along rows and columns across thin gaps of unreliable phase, or (with
``through``) across the walls where the network's estimate steps and the image's phase does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from fppsim.phase import TWO_PI, wrap
from fppsim.phase.unwrap import PhaseRegions

__all__ = ["Link", "seam_links"]


@dataclass(frozen=True)
class Link:
    """Region ``b``'s order is region ``a``'s plus ``delta`` (absolute phase ``U - 2 pi k`` equal across the link).

    ``via``: ``"bridge"`` (across a projector shadow), ``"seam"`` (across unreliable pixels) or ``"wall"`` (across
    a step the network sees and the image's phase does not: :func:`seam_links` with ``through``);
    ``votes``: lines that crossed; ``agreement``: share of them within the tolerance of ``delta``."""

    a: int
    b: int
    delta: int
    votes: int
    agreement: float
    via: str

    @property
    def strength(self) -> float:
        return self.votes * self.agreement


def _local_slope(wrapped: np.ndarray, usable: np.ndarray, axis: int, size: int = 7) -> np.ndarray:
    """Phase slope (rad / px) along ``axis``, averaged over the usable pixels of a ``size`` window."""
    d = wrap(np.diff(wrapped, axis=axis, append=np.take(wrapped, [-1], axis=axis)))
    ok = usable & np.roll(usable, -1, axis=axis) & np.isfinite(d)
    last = [slice(None)] * ok.ndim
    last[axis] = -1
    ok[tuple(last)] = False  # the last pixel has no step forward (its 0 above, its roll the first pixel's)
    num = ndi.uniform_filter(np.where(ok, d, 0.0), size)
    den = ndi.uniform_filter(ok.astype(np.float64), size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def seam_links(regions: PhaseRegions, wrapped: np.ndarray, usable: np.ndarray, blocked: np.ndarray,
               max_gap: int = 8, tolerance: float = 0.25, min_votes: int = 5,
               min_agreement: float = 0.7, through: np.ndarray | None = None) -> list[Link]:
    """Order differences across thin seams of unreliable phase, voted along rows and columns.

    A seam crossing is a pair of region pixels ``p < q`` on one row (or column), of different regions,
    with 1 to ``max_gap`` pixels between them that belong to no region and none of which is ``blocked``
    (a shadow, an invalid pixel, or a step the network sees as a wall: across those the phase does not
    continue). Its vote is ``(U[p] + s (q - p) - U[q]) / 2 pi`` periods, ``s`` the mean local phase slope
    of both ends (over ``usable`` pixels, never ``through`` ones); a pair of regions is linked when at least
    ``min_votes`` crossings vote and ``min_agreement`` of them lie within ``tolerance`` periods of the rounded median.

    With ``through`` ((H, W) bool, the network's walls) only the crossings whose gap holds at least one
    ``through`` pixel vote, and the links are ``via="wall"``: where the network sees a step of whole periods
    and the image's fringes run on across it, a false wall continues the phase on nearly every line; a real
    cliff breaks it by one fraction of a period along its length, so one of random height is crossed with
    about ``2 tolerance`` chance, on nearly every line too, and then at a wrong order difference (by its whole
    periods): only the caller's misfit rule against the network's levels can refuse it. The caller passes a
    tight ``tolerance`` and more ``min_votes`` there. Walls wider than ``max_gap`` are never crossed.

    Returns :class:`Link` s (``via="seam"``, or ``"wall"`` with ``through``), ``b``'s order = ``a``'s + ``delta``.
    """
    lab, U = regions.labels, regions.unwrapped
    w = np.asarray(wrapped, np.float64)
    # the slopes from each side's own phase: a wall's pixels are usable (a cut, not unreliable phase), and a real
    # cliff inside the band would bend a slope averaged across it towards continuing the phase
    sloped = np.asarray(usable, bool) if through is None else np.asarray(usable, bool) & ~np.asarray(through, bool)
    votes: dict[tuple[int, int], list[np.ndarray]] = {}
    for axis in (1, 0):
        L = lab if axis == 1 else lab.T
        B = np.asarray(blocked, bool) if axis == 1 else np.asarray(blocked, bool).T
        UU = U if axis == 1 else U.T
        S = _local_slope(w, sloped, axis) if axis == 1 else _local_slope(w, sloped, axis).T
        rows, cols = np.nonzero(L > 0)  # row-major: consecutive entries of one row are its labelled pixels
        same_row = rows[1:] == rows[:-1]
        p, q = cols[:-1], cols[1:]
        gap = q - p - 1
        la, lb = L[rows[:-1], p], L[rows[1:], q]
        pick = same_row & (gap <= max_gap) & (la != lb)
        if not pick.any():
            continue
        cb = np.cumsum(B, axis=1)  # blocked pixels strictly between p and q: cb[q-1] - cb[p]
        r, p, q, la, lb = rows[:-1][pick], p[pick], q[pick], la[pick], lb[pick]
        clear = (cb[r, q - 1] - cb[r, p]) == 0
        if through is not None:  # a wall pixel in the gap (none when touching: walls belong to no region)
            ct = np.cumsum(np.asarray(through, bool) if axis == 1 else np.asarray(through, bool).T, axis=1)
            clear &= (q - p > 1) & ((ct[r, q - 1] - ct[r, p]) > 0)
        r, p, q, la, lb = r[clear], p[clear], q[clear], la[clear], lb[clear]
        s = 0.5 * (S[r, p] + S[r, q])
        WW = w if axis == 1 else w.T
        step = np.where(q - p == 1, wrap(WW[r, q] - WW[r, p]), s * (q - p))  # touching: the exact wrapped step
        v = (UU[r, p] + step - UU[r, q]) / TWO_PI
        fin = np.isfinite(v)
        lo, hi = np.minimum(la, lb), np.maximum(la, lb)
        sign = np.where(la == lo, 1.0, -1.0)  # v is a's order minus b's in periods, stored for (lo, hi)
        for key in set(zip(lo[fin].tolist(), hi[fin].tolist())):
            m = fin & (lo == key[0]) & (hi == key[1])
            votes.setdefault(key, []).append(v[m] * sign[m])
    out = []
    for (a, b), parts in votes.items():
        v = np.concatenate(parts)
        k = int(np.round(np.median(v)))
        agree = float(np.mean(np.abs(v - k) <= tolerance))
        if len(v) >= min_votes and agree >= min_agreement:
            # v = (U_a - U_b) / 2 pi across the seam: k_b = k_a - v (absolute U - 2 pi k equal)
            out.append(Link(a, b, -k, int(len(v)), agree, "seam" if through is None else "wall"))
    return out
