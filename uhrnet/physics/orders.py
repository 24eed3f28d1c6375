"""Every phase region at one fringe order, chosen for the whole image at once (:func:`choose_orders`).

One fringe image fixes the projector phase of every pixel up to whole periods. Inside a region where
that phase is continuous (:func:`fppsim.phase.unwrap.phase_regions`) the relief is exact; what one image
cannot tell is each region's fringe ORDER, i.e. its level. A network's height ``h`` seen through the rig
gives every region a continuous order estimate (its *prior*, in periods):

    m_r = median over r of (U - Phi(h) - o) / 2 pi

(``U`` the region's unwrapped phase, ``Phi`` the rig's phase of a height, ``o`` the image's phase origin).
Rounding each ``m_r`` alone puts a region whose network level is more than half a fringe period of height
off (about 3.6 mm on the figshare rig) a whole order wrong. Three kinds of *link* tie regions' orders
together without the network:

* **shadow bridges** (:func:`fppsim.phase.unwrap.shadow_bridges`): the projector ray that grazes an
  object's edge lands on the plane at the far side of its shadow; both carry one phase;
* **seams** (:func:`seam_links`): two regions separated by a few pixels whose phase is merely unreliable
  (low modulation, a dark patch, an FTP edge), not by a shadow nor by a step the network sees as a wall:
  the phase continues across, so extrapolating each side's phase over the gap gives their order difference;
* **walls the phase crosses** (:func:`seam_links` with ``through``): the same vote across a wall, where the network's
  estimate steps and the image's phase does not, taken when at least 10 lines cross and 0.7 of them continue the
  phase within 0.05 period (a network that puts a false cliff across a smooth surface floats the far side alone).
  A real cliff's fractional step is random, but a real cliff of whole periods (within 0.05) looks just the same: on
  the rendered disc (``tests/uhrnet/test_orders.py``'s scene) 3 of 150 random cliffs of 0.3-3 periods the
  network sees were linked, each with a phase step of 2.03-2.04 periods the network saw 0.19-0.27 period too low,
  their far side then 2 orders (12 mm) off; the misfit rule below refuses it only where the network's levels
  differ by over 2 periods across it. The same rule bounds what a wall link mends: a false step more than 2
  periods off the group it would join is refused (on that disc +2.0 periods stays off, -2.0 is mended), and one
  of about 3 periods makes a wall wider than the vote's 8 px gap.
  Stop 71 (docs/experiments/orders.md, "A wall the network put across a smooth surface"): a recipe network's false
  step of about 2 periods across the pair's lower right had left it floating two orders low, 4.75 -> 1.64 mm; a
  three-object rendered scene 0.25 -> 0.97 of its object pixels at the right order, FP147 0.741 -> 0.690 and
  0.979 -> 0.938 (2 of 5 networks); the pair through the 4 others, FP1523 / FP672 through all 5 and 95 rendered
  scene-network pairs the same.

Links are voted line by line and taken strongest first into components (a union-find that records each
region's order relative to its component's root and skips a link that contradicts the ones taken, or one
that would join two components whose priors disagree with it by more than ``max_link_misfit`` periods: a
seam across a cliff of whole periods, which the network's smooth heights do not show as a wall, looks
continuous to the phase but not to the network's levels).
Each component then gets ONE shift, the integer that best fits all its regions' priors together
(weighted by area), so a component's level is voted by every pixel it holds; its posterior under a
Gaussian prior of ``sigma`` periods on the network's level error decides: a component whose chosen order has a
posterior below ``min_confidence`` (its level nearly halfway between two orders) is undecided, its pixels keep
the network's heights, and the result says so. The region's *confidence* is the probability that its order is
right. A component holding a region the estimate puts on the plane (most of its reliable pixels within
``flat_mm`` of 0, where the phase origin was fitted on the plane) is *anchored*: its order rests on the plane's, and
its confidence is that posterior. (A raised object the network puts on the plane is anchored too, and at the plane's
order: the confidence cannot see that error.) A component with no piece of the plane (an
object no shadow or seam ties to it, or every region of a frame without a plane) is *floating*: its order is the
network's level alone, and its confidence is the posterior under ``sigma_network`` periods, the network's measured
level error (the order chosen is the same). On rendered scenes with exact truth (3 networks, 32 scenes) floating
raised regions were at the right order for 16-28 % of them while a posterior of ``sigma`` said 0.87-0.92.

numpy in, numpy out (the rig's float64 :class:`~uhrnet.physics.rig_layer.RigLayer` inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy import ndimage as ndi

from fppsim.phase import TWO_PI, circular_median, wrap
from fppsim.phase.unwrap import PhaseRegions, phase_regions, shadow_bridges, step_conflicts
from uhrnet.physics.islands import continue_islands, continued_components, wrapped_steps
from uhrnet.errors import InputError
from uhrnet.physics.links import Link, seam_links
from uhrnet.physics.refine import estimate_phases
from uhrnet.physics.rims import split_rims

__all__ = ["Link", "RegionOrder", "OrderChoice", "seam_links", "choose_orders"]

# The growth's reliability levels, most reliable first, a fortieth apart: within one level the regions grow by
# distance, so finer levels reach each pixel along the more reliable way (quality-guided unwrapping), before a
# route across a cliff the phase does not show. 0.4 / 0.3 / 0.2 and 0.1 / 0 until stop 60.
GROW_LEVELS = (0.475, 0.45, 0.425, 0.4, 0.375, 0.35, 0.325, 0.3, 0.275, 0.25, 0.225, 0.2)
FILL_LEVELS = (0.175, 0.15, 0.125, 0.1, 0.075, 0.05, 0.025, 0.0)


@dataclass(frozen=True)
class RegionOrder:
    """One phase region's choice. ``label``: its value in :attr:`OrderChoice.labels`; ``pixels``; ``prior``:
    the network's continuous order (periods, relative to the phase origin); ``order``: the whole order chosen;
    ``confidence``: the probability that this order is right (0..1; module docstring); ``decided``: its
    component's posterior under ``sigma`` is at least ``min_confidence`` (else the network's heights stay);
    ``component``: regions tied by links share one; ``links``: how many links tie it; ``moved_mm``: median height
    change of its moved pixels; ``anchored``: its component holds a piece of the plane (else its order is the
    network's level alone: floating)."""

    label: int
    pixels: int
    prior: float
    order: int
    confidence: float
    decided: bool
    component: int
    links: int
    moved_mm: float
    anchored: bool = False


@dataclass
class OrderChoice:
    """The result of :func:`choose_orders`.

    height : (H, W) mm, the chosen heights (the network's where not decided; NaN kept).
    moved : (H, W) bool, pixels whose height comes from the phase at the chosen order.
    labels : (H, W) int32, the phase regions (0: none; 1..n, largest first).
    regions : one :class:`RegionOrder` per region, in label order.
    links : the links taken; ``conflicts``: links skipped because they contradicted stronger ones.
    offset_rad : the image's phase origin ``o``.
    rim : (H, W) bool, pixels placed by the rim split (:func:`uhrnet.physics.rims.split_rims`; None: not run).
    """

    height: np.ndarray
    moved: np.ndarray
    labels: np.ndarray
    regions: list[RegionOrder]
    links: list[Link]
    conflicts: int
    offset_rad: float
    stats: dict = field(default_factory=dict)
    rim: np.ndarray | None = None

    def confidence_map(self) -> np.ndarray:
        """(H, W) float, each region's confidence (NaN outside the regions)."""
        table = np.r_[np.nan, [r.confidence for r in self.regions]]
        return table[self.labels]


def _components(n: int, links: list[Link], prior: np.ndarray, sizes: np.ndarray,
                max_misfit: float) -> tuple[np.ndarray, np.ndarray, list[Link], int, int]:
    """Union-find over regions 1..n with order offsets: (root (n+1,), relative order to the root (n+1,),
    links taken, conflicts skipped, links refused by the network). Strongest links first; a link contradicting
    the taken ones is skipped, and so is one that would join two components whose area-weighted priors
    (``prior``, ``sizes``: 0-based per region) differ from the link's order difference by more than
    ``max_misfit`` periods."""
    parent = np.arange(n + 1)
    rel = np.zeros(n + 1, np.int64)  # order of i minus order of parent[i]
    w = np.concatenate([[0.0], sizes])  # per root: its regions' area ...
    wv = np.concatenate([[0.0], sizes * prior])  # ... and sum of area x (prior - order relative to the root)

    def find(i):  # (root, order of i minus the root's); a few dozen regions: no path compression needed
        off = 0
        while parent[i] != i:
            off += rel[i]
            i = parent[i]
        return i, off

    taken, conflicts, refused = [], 0, 0
    for lk in sorted(links, key=lambda x: -x.strength):
        (ra, oa), (rb, ob) = find(lk.a), find(lk.b)
        if ra == rb:
            conflicts += int(ob - oa != lk.delta)
            continue
        # k_b = k_a + delta; k_a = k_ra + oa, k_b = k_rb + ob  =>  k_rb = k_ra + oa + delta - ob
        step = oa + lk.delta - ob
        if abs(step - (wv[rb] / w[rb] - wv[ra] / w[ra])) > max_misfit:
            refused += 1
            continue
        parent[rb], rel[rb] = ra, step
        wv[ra] += wv[rb] - w[rb] * step
        w[ra] += w[rb]
        taken.append(lk)
    found = [find(i) for i in range(n + 1)]
    roots = np.array([r for r, _ in found])
    offs = np.array([o for _, o in found], np.int64)
    return roots, offs, taken, conflicts, refused


def _plane_pixels(h: np.ndarray, usable: np.ndarray, flat_mm: float) -> np.ndarray | None:
    """The usable pixels the estimate puts on the plane (within ``flat_mm`` of 0), or None where they are fewer
    than a tenth of the usable pixels (no plane in view to fit the origin on)."""
    flat = usable & (np.abs(h) < flat_mm)
    return flat if flat.any() and flat.sum() >= 0.1 * usable.sum() else None


def _origin(layer, wrapped: np.ndarray, phi: np.ndarray, flat: np.ndarray | None, usable: np.ndarray) -> float:
    """The image's phase origin ``o`` (rad): measured = rig phase + o, mod 2 pi. Where the estimate says
    'plane' (``flat``: :func:`_plane_pixels`) the plane's own phase is the truth (height 0 by definition), so a
    network whose plane sits a little off does not lift every region by that much; otherwise (None) the
    estimate's phase ``phi`` over every usable pixel."""
    if flat is not None:
        with torch.no_grad():
            phi0 = layer.phase_from_height(torch.zeros(flat.shape, dtype=torch.float64, device=layer.A.device))
        return circular_median(wrap(wrapped - phi0.cpu().numpy())[flat])
    return circular_median(wrap(wrapped - phi)[usable]) if usable.any() else 0.0


def grow_regions(labels: np.ndarray, unwrapped: np.ndarray, wrapped: np.ndarray, reliability: np.ndarray,
                 allowed: np.ndarray, thresholds=GROW_LEVELS, max_steps: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Grow phase regions into less reliable pixels, most reliable first (quality-guided unwrapping).

    For each threshold in turn, every unlabelled ``allowed`` pixel of at least that reliability next to a
    region (4-neighbours, at most ``max_steps`` pixels deep a threshold) joins the first such neighbour's
    region, unwrapped from it: ``U(q) = U(p) + wrap(w(q) - w(p))``. A region's order is voted on its core
    only, so a slip here misplaces these pixels alone. Returns new ``(labels, unwrapped)``."""
    lab = labels.copy()
    U = unwrapped.copy()
    w = np.nan_to_num(np.asarray(wrapped, np.float64))
    rel = np.nan_to_num(np.asarray(reliability, np.float64))
    H, W = lab.shape
    for thr in thresholds:
        cand = allowed & (rel >= thr)
        for _ in range(max_steps):
            free = cand & (lab == 0)
            if not free.any():
                break
            grew = False
            for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                # neighbour p of q = (y, x) at (y - dy, x - dx)
                src = np.zeros_like(lab)
                ys, yd = (slice(0, H - dy), slice(dy, H)) if dy >= 0 else (slice(-dy, H), slice(0, H + dy))
                xs, xd = (slice(0, W - dx), slice(dx, W)) if dx >= 0 else (slice(-dx, W), slice(0, W + dx))
                src[yd, xd] = lab[ys, xs]
                take = free & (src > 0) & (lab == 0)
                if take.any():
                    Up = np.full(U.shape, np.nan)
                    Up[yd, xd] = U[ys, xs]
                    wp = np.zeros(w.shape)
                    wp[yd, xd] = w[ys, xs]
                    U[take] = Up[take] + wrap(w[take] - wp[take])
                    lab[take] = src[take]
                    grew = True
            if not grew:
                break
    return lab, U


def choose_orders(height_mm: np.ndarray, wrapped_phase: np.ndarray, reliability: np.ndarray | None, layer,
                  valid: np.ndarray | None = None, shadow: np.ndarray | None = None, *,
                  min_reliability: float = 0.5, max_step: float = 1.0, smooth_px: float = 3.0,
                  min_region: int = 50, grow=GROW_LEVELS, fill=FILL_LEVELS, seams: bool = True,
                  bridges: bool = True, bridge_offset: float = 0.35, sigma: float = 0.3, sigma_network: float = 1.0,
                  min_confidence: float = 0.6, flat_mm: float = 1.0, spread_px: float = 10.0,
                  max_move_fraction: float = 2.0, max_local_misfit: float | None = 1.0, max_link_misfit: float = 2.0,
                  join_min_moved: int | None = 50, fringe=None, islands: bool = True,
                  keep: np.ndarray | None = None, walls_crossed: tuple | None = (0.05, 10)) -> OrderChoice:
    """Heights whose every phase region sits at one whole fringe order (module docstring).

    Steps: (1) regions of reliable, continuous phase (reliability >= ``min_reliability``; boundaries where the
    phase step disagrees by more than ``max_step`` rad with the estimate's, smoothed over ``smooth_px``: a
    wall; fewer than ``min_region`` pixels dropped), each with its prior voted on these cores; (2) the regions
    grown into less reliable pixels (thresholds ``grow``, :func:`grow_regions`), which brings them close
    enough to shadows and to each other to link; (3) links: shadow bridges (votes agreeing within a quarter
    period of their median once the image's common vote offset is removed, the median within ``bridge_offset``
    periods of a whole order: :func:`fppsim.phase.unwrap.shadow_bridges`), seams (:func:`seam_links`) and walls
    the phase crosses; (4) components and one order each; (5) the regions grown further (``fill``: these pixels take
    their region's order, they tie nothing); (6) heights from the phase at the chosen orders (a
    pixel whose move exceeds ``max_move_fraction`` moves all the same when it agrees with its moved neighbours',
    ``max_local_misfit``, or the fringes run on to them, ``join_min_moved``); the pixels still left out (edges,
    walls, dark patches, lit pixels without a usable phase) take the network's height plus the level correction of
    the moved pixels around them (a Gaussian average over ``spread_px``), where those are near; the rest keep the network's height;
    (7) with ``fringe``, the rims between raised regions and the plane split by the plane's own fringe
    (:func:`uhrnet.physics.rims.split_rims`);
    (8) with ``islands``, a moved patch one whole order off where the image's phase runs on across its border takes
    the order that continues it (:func:`uhrnet.physics.islands.continue_islands`): before the level correction of
    step 6 (which carries the patch's moves) and again after the rim split.

    Parameters
    ----------
    height_mm : (H, W) float, the network's estimate, mm above the reference plane (NaN = none).
    wrapped_phase, reliability : (H, W) the image's single-shot phase (rad) and its reliability [0, 1].
    layer : :class:`~uhrnet.physics.rig_layer.RigLayer` on this grid (:func:`uhrnet.physics.refine.layer_for`).
    valid : (H, W) bool, pixels that may move (default: finite estimate).
    shadow : (H, W) bool, pixels without projector light (default: outside ``valid``).
    grow, fill : reliability thresholds of the two growth passes, most reliable first (``()``: none).
    seams, bridges : which links tie regions (off: each region rounds its own prior).
    sigma : the level error assumed by the decision and by an anchored component's confidence, in fringe periods.
    sigma_network : the network's level error, in fringe periods, for a floating component's confidence (module
        docstring). The recipe's networks: a region's level 0.67 periods (standard deviation) from the truth on the
        labelled pair, 1.25-1.41 on rendered held-out scenes.
    min_confidence : a component whose chosen order has a smaller posterior under ``sigma`` keeps the network's
        heights.
    flat_mm : the phase origin is fitted on the pixels the estimate puts within this of the plane (height 0)
        when they are at least a tenth of the usable pixels; else on all, to the estimate's phase.
    spread_px : Gaussian sigma (px) of the level correction carried to the pixels left out (0: none).
    max_move_fraction : a pixel moves at most this many fringe periods of height (else the network's stays).
    max_local_misfit : a pixel beyond that margin moves all the same when its move is within this many periods
        of its neighbours' (the level correction of the moved pixels around it, ``spread_px``): where the
        network is off by more than the margin over a patch (None: never). FP1523/1201 0.762 +- 0.036 ->
        0.749 +- 0.039 of the network's residual, the pair 2.06 -> 2.03 mm (3 seeds, docs/experiments/orders.md).
        One pass: it reaches about 1.6 ``spread_px`` into a patch. At 1 period it also admits a few pixels whose
        phase was continued one order wrong (on the pair, seed 0: 75 pixels put right, 13 put one order off).
    join_min_moved : a pixel of reliable phase (``min_reliability``) beyond the margin moves all the same when the
        image's fringes run on undisturbed, and the path's phase continues them, from it to at least this many moved
        pixels (:func:`uhrnet.physics.islands.continued_components`; None: never). 6 seeds (stop 62): the pair
        1.628 -> 1.625 mm, FP1523/1201 0.737 -> 0.734 (every seed lower or equal), FP672 through the recipe's
        networks 0.941 -> 0.631, FP147 0.739 -> 0.733; through their own rigs FP672 0.315 -> 0.305, FP147 0.332
        (unchanged: its chin, reached across an occlusion its single-shot phase bridges, is under the reliable grade).
    max_link_misfit : a link is refused when the two components it would join have area-weighted priors whose
        difference is further than this many periods from the link's order difference (a seam or shadow across
        a height step of whole periods). A safeguard: on FP147 through its own rig (3 seeds) 0.443 +- 0.191 ->
        0.370 +- 0.031 of flat, one seed losing a right link (0.06); the pair and FP1523 do not move.
    fringe : ``(image, background, modulation)``, the fringe image and its single-shot ``A`` and ``B``
        (:class:`fppsim.phase.single_shot.SingleShotPhase`): step (7). None: no rim split. ``islands``: step (8).
    keep : (H, W) mm, the heights the pixels the path leaves alone keep (undecided regions, pixels no moved pixel
        reaches); default ``height_mm``. ``uhrnet predict`` passes the network's own map there, while
        ``height_mm`` is the estimate the orders are chosen from (:func:`uhrnet.inference.prediction.path_estimate`).
    walls_crossed : ``(tolerance, votes)``: walls of step (1) linked across by at least ``votes`` lines, 0.7 of them
        continuing the image's phase within ``tolerance`` periods (module docstring); None: none.

    Measured (docs/experiments/orders.md, each step's numbers): defaults chosen on the labelled pair and FP1523/1201;
    the pair through the depth-fitted rig 5.4-8.2 mm object RMSE (the recipe's network) -> 1.59 +- 0.06 mm, median
    0.13-0.16 mm, FP1523/1201 0.727 +- 0.045 of the network's residual (6 seeds, stop 63).
    """
    h_in = np.asarray(height_mm)
    e = estimate_phases(h_in, wrapped_phase, reliability, layer, valid, min_reliability, smooth_px)
    g = _linked_regions(e, layer, shadow, max_step, min_region, flat_mm, grow, bridges, bridge_offset, seams,
                        max_link_misfit, walls_crossed)
    n = g.n
    order, post = _component_orders(n, g.roots, g.offs, g.prior, g.core_sizes, sigma)
    decided = post >= min_confidence
    anchored = _anchored(g.roots, g.anchors)
    conf = np.where(anchored, post, _component_orders(n, g.roots, g.offs, g.prior, g.core_sizes, sigma_network)[1]
                    if n else post)  # the same order: the argmax does not depend on the width
    refined, lab, usable, moved, move, carried, beyond, rim, rims, island_stats = _placed_heights(
        e, g, layer, order, decided, fill, max_move_fraction, spread_px, max_local_misfit, join_min_moved, islands,
        fringe, flat_mm, keep)
    out_dtype = h_in.dtype if np.issubdtype(h_in.dtype, np.floating) else np.float64
    refined = refined.astype(out_dtype, copy=False)
    table = _region_table(g, lab, order, conf, decided, anchored, moved, move)
    floating = decided & ~anchored
    stats = {**_choice_stats(e.finite, moved, g.core, usable, g.roots, n, decided, g.sizes, g.taken, g.conflicts,
                             g.refused, carried, move, g.offset), "beyond_margin_moved": beyond,
             "floating_regions": int(floating.sum()),
             "floating_fraction": float(g.sizes[floating].sum() / max(int(e.finite.sum()), 1)) if n else 0.0,
             **rims, **island_stats}
    return OrderChoice(refined, moved, lab, table, g.taken, g.conflicts, float(g.offset), stats, rim)


@dataclass
class _Linked:
    """Steps (1)-(4) of :func:`choose_orders`: the regions (grown), their priors on the reliable cores, the links
    taken and the components they make."""

    n: int
    offset: float
    walls: np.ndarray
    unlit: np.ndarray
    core: np.ndarray
    usable: np.ndarray
    labels: np.ndarray
    unwrapped: np.ndarray
    sizes: np.ndarray
    prior: np.ndarray
    core_sizes: np.ndarray
    anchors: np.ndarray
    roots: np.ndarray
    offs: np.ndarray
    taken: list
    conflicts: int
    refused: int


def _linked_regions(e, layer, shadow, max_step, min_region, flat_mm, grow, bridges, bridge_offset, seams,
                    max_link_misfit, crossed=None) -> _Linked:
    """Steps (1)-(4) of :func:`choose_orders` on the estimate's phases ``e``
    (:func:`uhrnet.physics.refine.estimate_phases`); ``crossed``: the wall links' ``(tolerance, votes)`` or None."""
    plane_px = _plane_pixels(e.h, e.usable, flat_mm)  # the origin is fitted there, and a region on it anchors its group
    offset = _origin(layer, e.w, e.phi, plane_px, e.usable)
    walls = step_conflicts(e.w, e.expected, max_step)
    regions = phase_regions(e.w, e.usable, cut=walls, min_size=min_region)
    n = regions.count
    unlit = ~e.ok if shadow is None else np.asarray(shadow, bool)
    core = e.usable.copy()
    prior = (np.asarray(ndi.median(np.nan_to_num(regions.unwrapped - e.phi - offset), regions.labels,
                                   index=np.arange(1, n + 1))) / TWO_PI if n else np.zeros(0))  # the reliable cores
    core_sizes = regions.sizes.astype(np.float64)
    anchors = ((np.asarray(ndi.mean(plane_px, regions.labels, index=np.arange(1, n + 1))) > 0.5)
               if n and plane_px is not None else np.zeros(n, bool))
    usable = e.usable
    if grow and n:
        lab, U = grow_regions(regions.labels, regions.unwrapped, e.w, e.rel,
                              e.ok & np.isfinite(e.w) & ~walls & ~unlit, thresholds=grow)
        usable = usable | (lab > 0)
        regions = PhaseRegions(lab, U, np.bincount(lab.ravel(), minlength=n + 1)[1:].astype(np.int64))
    links: list[Link] = []
    if n and bridges:
        links += [Link(b.a, b.b, -b.periods, b.votes, b.agreement, "bridge")
                  for b in shadow_bridges(regions, unlit, max_offset=bridge_offset)]
    if n and seams:
        links += seam_links(regions, e.w, usable, blocked=unlit | walls | ~e.finite)
        if crossed is not None:
            links += seam_links(regions, e.w, usable, blocked=unlit | ~e.finite, tolerance=crossed[0],
                                min_votes=crossed[1], through=walls)
    roots, offs, taken, conflicts, refused = _components(n, links, prior, core_sizes, max_link_misfit)
    return _Linked(n, offset, walls, unlit, core, usable, regions.labels, regions.unwrapped, regions.sizes, prior,
                   core_sizes, anchors, roots, offs, taken, conflicts, refused)


def _placed_heights(e, g: "_Linked", layer, order, decided, fill, max_move_fraction, spread_px, max_local_misfit,
                    join_min_moved, islands, fringe, flat_mm, keep):
    """Steps (5)-(8) of :func:`choose_orders` and the pixels left alone: ``(refined float64, labels, usable, moved,
    move, carried, beyond, rim, rim statistics, island statistics)``."""
    n = g.n
    lab, U, usable = g.labels, g.unwrapped, g.usable
    if fill and n:  # after the links: pixels grown here only take their region's order, they tie nothing
        lab, U = grow_regions(lab, U, e.w, e.rel, e.ok & np.isfinite(e.w) & ~g.unlit & ~g.walls, thresholds=fill)
        usable = usable | (lab > 0)
    steps = wrapped_steps(e.w) if n and (islands or join_min_moved is not None) else None  # the image's, once
    refined, moved, move, carried, beyond, island_stats = _moved_heights(
        e, layer, lab, U, g.offset, order, decided, usable, max_move_fraction, spread_px, max_local_misfit,
        join_min_moved, islands and bool(n), steps)
    rims, rim = {}, None
    if fringe is not None and n:
        refined, rim, rims = split_rims(refined, moved, e.w, e.rel, e.ok & ~g.unlit, *fringe, layer, g.offset,
                                        flat_mm=flat_mm)
    if islands and n and island_stats:  # again after the rim split, which re-decided the least reliable moved pixels
        refined, _, again = continue_islands(refined, moved, e.w, layer, steps=steps)
        island_stats = {k: island_stats[k] + again[k] for k in island_stats}
    if keep is not None:
        keep = np.asarray(keep, np.float64)
        if keep.shape != e.h.shape:
            raise InputError(f"keep {keep.shape} and height {e.h.shape} must be the same (H, W)")
        left = e.finite & ~moved & ~carried
        if rim is not None:
            left &= ~rim
        refined = np.where(left, keep, refined)
    return refined, lab, usable, moved, move, carried, beyond, rim, rims, island_stats


def _region_table(g: _Linked, lab, order, conf, decided, anchored, moved, move) -> list[RegionOrder]:
    """One :class:`RegionOrder` per region of ``g``, in label order (``lab``: the labels after the fill)."""
    n = g.n
    link_count = np.bincount([x for lk in g.taken for x in (lk.a, lk.b)], minlength=n + 1)
    moved_med = (np.asarray(ndi.median(np.where(moved, move, 0.0), np.where(moved, lab, 0), index=np.arange(1, n + 1)))
                 if n else np.zeros(0))
    return [RegionOrder(i + 1, int(g.sizes[i]), float(g.prior[i]), int(order[i]), float(conf[i]), bool(decided[i]),
                        int(g.roots[i + 1]), int(link_count[i + 1]), float(moved_med[i]), bool(anchored[i]))
            for i in range(n)]


def _component_orders(n, roots, offs, prior, sizes, sigma) -> tuple[np.ndarray, np.ndarray]:
    """Each region's whole order and its confidence: ONE shift per linked component, the integer that best fits
    all its regions' priors together (area-weighted), its posterior under a Gaussian of ``sigma`` periods."""
    order = np.zeros(n, np.int64)
    conf = np.zeros(n)
    for root in np.unique(roots[1:]) if n else []:
        members = np.nonzero(roots[1:] == root)[0]  # 0-based region indices
        resid = prior[members] - offs[members + 1]  # each member's vote for the component's shift
        wts = sizes[members] / sizes[members].sum()
        centre = float(np.round(np.sum(wts * resid)))
        cands = centre + np.arange(-3, 4)
        energy = np.array([np.sum(wts * (resid - c) ** 2) for c in cands]) / (2 * sigma ** 2)
        post = np.exp(-(energy - energy.min()))
        post /= post.sum()
        best = int(np.argmax(post))
        order[members] = int(cands[best]) + offs[members + 1]
        conf[members] = post[best]
    return order, conf


def _anchored(roots: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """(n,) bool per region (0-based): its component (``roots``, (n+1,)) holds an anchor region."""
    held = np.unique(roots[1:][anchors]) if anchors.any() else np.zeros(0, roots.dtype)
    return np.isin(roots[1:], held)


def _moved_heights(e, layer, lab, U, offset, order, decided, usable, max_move_fraction, spread_px,
                   max_local_misfit, join_min_moved=None, islands=False, steps=None):
    """Heights from the phase at the chosen orders where a decided region holds the pixel and the move is at
    most ``max_move_fraction`` periods of height, or within ``max_local_misfit`` periods of the moves around
    it, or (a pixel of reliable phase) the path continues the image's undisturbed fringes from it to at least
    ``join_min_moved`` such pixels (:func:`~uhrnet.physics.islands.continued_components`); the pixels left out
    (not undecided regions) take the level correction of the moved pixels around them (a
    normalised Gaussian of ``spread_px``), after the moved pixels' islands took their order (``islands``,
    :func:`~uhrnet.physics.islands.continue_islands`; ``steps``: the image's
    :func:`~uhrnet.physics.islands.wrapped_steps`): ``(refined float64, moved, move, carried, beyond, island_stats)``,
    ``beyond`` the count of pixels moved past the margin."""
    h, finite = e.h, e.finite
    t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=layer.A.device)  # noqa: E731
    target = np.full(h.shape, np.nan)
    inside = lab > 0
    li = lab[inside] - 1
    target[inside] = U[inside] - offset - TWO_PI * order[li]
    with torch.no_grad():
        h_new = layer.height_from_phase(t(np.nan_to_num(target, nan=0.0))).cpu().numpy()
    h_new[~np.isfinite(target)] = np.nan
    move = h_new - h
    with np.errstate(divide="ignore"):
        period = TWO_PI / np.abs(e.sens)
        # the margin as before stop 59, bit for bit: max_move_fraction * period equals it at the default 2 but can
        # differ by one ulp at fractions that are not powers of two
        margin = max_move_fraction * TWO_PI / np.abs(e.sens)
    can = usable & inside & np.isfinite(move)
    can[inside] &= decided[li]
    moved = can & (np.abs(move) <= margin)
    within = int(moved.sum())
    if max_local_misfit is not None and spread_px > 0 and moved.any():
        # where the network is off by more than the margin, its neighbours' moves say so: a pixel within
        # max_local_misfit periods of their level correction moves too
        wgt, corr = _level_correction(moved, move, spread_px)
        moved |= can & (wgt > 0.05) & (np.abs(move - corr) <= max_local_misfit * period)
    reach = can & ~moved & e.usable
    if join_min_moved is not None and moved.any() and reach.any():
        # where the fringes run on undisturbed from moved pixels into a patch of reliable phase, the network is
        # off there, not the phase (below the reliable grade the image's phase also bridges occlusions: FP147's chin)
        comp = continued_components(np.where(can, target, np.nan), e.w, can, steps=steps)
        held = np.bincount(comp[moved], minlength=int(comp.max()) + 1)
        moved |= reach & (comp >= 0) & (held[np.maximum(comp, 0)] >= join_min_moved)
    refined = np.where(moved, h_new, h).astype(np.float64)
    island_stats = {}
    if islands and moved.any():  # before the level correction below: it carries the islands' moves
        refined, shifted, island_stats = continue_islands(refined, moved, e.w, layer, steps=steps)
        move = np.where(shifted, refined - h, move)
    carried = np.zeros(h.shape, bool)
    if spread_px > 0 and moved.any():
        # the network's level error is smooth: pixels left out (edges, dark patches, dim pixels whose phase is not
        # usable) take the level correction of the moved pixels around them, a normalised Gaussian average of
        # their moves (a black pixel has no estimate: not finite)
        wgt, corr = _level_correction(moved, move, spread_px)
        undecided = np.zeros(h.shape, bool)
        undecided[inside] = ~decided[li]
        carried = finite & ~moved & ~undecided & (wgt > 0.05)
        refined[carried] = h[carried] + corr[carried]
    return refined, moved, move, carried, int(moved.sum()) - within, island_stats


def _level_correction(moved, move, spread_px):
    """``(weight, correction)``: the moves of the ``moved`` pixels averaged by a normalised Gaussian of
    ``spread_px`` (the weight is the Gaussian's share of moved pixels; the correction NaN where it is 0)."""
    wgt = ndi.gaussian_filter(moved.astype(np.float64), spread_px)
    corr = ndi.gaussian_filter(np.where(moved, move, 0.0), spread_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return wgt, corr / wgt


def _choice_stats(finite, moved, core, usable, roots, n, decided, sizes, taken, conflicts, refused, carried, move,
                  offset) -> dict:
    npx = int(finite.sum())
    return {
        "method": "orders",
        "n_pixels": npx,
        "moved_fraction": float(moved.sum() / npx) if npx else 0.0,
        "reliable_fraction": float(core.sum() / npx) if npx else 0.0,
        "grown_fraction": float((usable & ~core).sum() / npx) if npx else 0.0,
        "regions": n,
        "components": int(len(np.unique(roots[1:]))) if n else 0,
        "undecided_regions": int((~decided).sum()),
        "undecided_fraction": float(sizes[~decided].sum() / npx) if npx else 0.0,
        "links": {via: sum(lk.via == via for lk in taken) for via in ("bridge", "seam", "wall")},
        "conflicts": conflicts,
        "refused_links": refused,
        "carried_fraction": float(carried.sum() / npx) if npx else 0.0,
        "mean_abs_move_mm": float(np.abs(move[moved]).mean()) if moved.any() else 0.0,
        "offset_rad": float(offset),
    }
