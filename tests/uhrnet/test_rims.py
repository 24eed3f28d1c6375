"""uhrnet.physics.rims.split_rims on an analytic scene through the default rig: a disc standing 27-30 mm on the plane
(fppsim's forward model, fppsim.fitting.height_sensitivity.surface_phase, is the truth), its fringe image
rendered as A + B cos(phase), and a band around its silhouette left to a network-like ramp, as the orders path
leaves it. The truth says which side of the cliff every pixel is on."""

import numpy as np
import pytest
from scipy import ndimage as ndi

from _helpers import disc_shadow
from fppsim.fitting.height_sensitivity import surface_phase
from fppsim.geometry.rig import make_default_rig
from uhrnet.physics.orders import choose_orders
from uhrnet.physics.rig_layer import RigLayer
from uhrnet.physics.rims import min_cut_sides, split_rims

pytestmark = pytest.mark.usefixtures("one_thread")

ORIGIN = 72.0  # rad: the image's phase counted from another origin than the rig's


def _scene(ledge_mm: float = 0.0):
    rig = make_default_rig()
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    r = np.hypot(xx - 360, yy - 176)
    disc = r < 70
    h = np.where(disc, 27.0 + 3.0 * np.cos(r / 25.0), 0.0)  # not a whole number of periods (30 mm is 4.0)
    h = np.where(disc & (r >= 66), h - ledge_mm, h)  # the outer ring steps down
    phase = surface_phase(rig, h)
    plane_phase = surface_phase(rig, np.zeros_like(h))
    shadow = disc_shadow(disc, phase, plane_phase)
    # the rim turns away from the camera: darker fringes on the disc's outer 4 px
    mod = np.where(disc & (r > 66), 0.15, np.where(disc, 0.5, 0.7)) * (1.0 + 0.2 * xx / cam.width)
    bg = 0.1 + 0.05 * yy / cam.height
    image = np.where(shadow, -1.0, bg + mod * np.cos(phase + ORIGIN))
    wrapped = np.angle(np.exp(1j * (phase + ORIGIN)))
    band = (np.abs(r - 70) < 6) & ~shadow  # what the path left out around the silhouette
    ramp = ndi.gaussian_filter(h, 4.0)  # a network's heights: a ramp where the truth is a cliff
    path = np.where(band, ramp, h)
    return rig, RigLayer(rig), h, disc, shadow, image, bg, mod, wrapped, band, path


@pytest.fixture(scope="module")
def scene():
    return _scene()


def test_each_rim_pixel_lands_on_its_side_of_the_cliff(scene):
    rig, layer, h, disc, shadow, image, bg, mod, wrapped, band, path = scene
    before = np.abs(path - h)[band]
    assert (before > 3.0).mean() > 0.5  # the ramp: most of the band is far off either side
    moved = ~band & ~shadow
    got, placed, stats = split_rims(path, moved, wrapped, np.ones(h.shape), ~shadow, image, bg, mod, layer, ORIGIN)
    err = np.abs(got - h)
    # rows and columns that meet the plane on both sides of the band are split; those ending in the shadow are not
    split = np.isfinite(got) & (got != path)
    assert stats["rim_runs"] > 100 and stats["rim_to_plane"] > 0 and stats["rim_to_object"] > 0
    assert not (split & ~placed).any() and placed.sum() == stats["rim_to_plane"] + stats["rim_to_object"]
    assert split[band].mean() > 0.6
    assert (err[split] < 0.05).mean() > 0.85
    # where the disc's intensity differs from what the plane would show by more than 0.4 of the plane's modulation,
    # one pixel tells the sides apart, and those land on their own side (elsewhere, e.g. a dark rim pixel where
    # the plane's fringe crosses its background, the image cannot tell)
    yy, xx = np.mgrid[0:h.shape[0], 0:h.shape[1]]
    top = 27.0 + 3.0 * np.cos(np.hypot(xx - 360, yy - 176) / 25.0)  # the disc's surface, continued
    plane_mod = 0.7 * (1.0 + 0.2 * xx / h.shape[1])
    as_plane = bg + plane_mod * np.cos(surface_phase(rig, np.zeros_like(h)) + ORIGIN)
    as_disc = bg + np.where(np.hypot(xx - 360, yy - 176) > 66, 0.15, 0.5) * (1.0 + 0.2 * xx / h.shape[1]) \
        * np.cos(surface_phase(rig, top) + ORIGIN)
    differ = np.abs(as_disc - as_plane) > 0.4 * plane_mod
    assert (split & differ).sum() > 1000 and (err[split & differ] < 0.05).mean() > 0.99
    # the dark outer ring of the disc (modulation 0.15 against the plane's 0.7) goes to the disc
    ring = split & differ & disc & (np.hypot(xx - 360, yy - 176) > 66)
    assert ring.sum() > 50 and (err[ring] < 0.05).all()
    # nothing else moves
    np.testing.assert_array_equal(got[~band], path[~band])


def test_runs_that_end_in_a_shadow_or_are_too_long_are_left_alone(scene):
    rig, layer, h, disc, shadow, image, bg, mod, wrapped, band, path = scene
    moved = ~band & ~shadow
    got, _, _ = split_rims(path, moved, wrapped, np.ones(h.shape), ~shadow, image, bg, mod, layer, ORIGIN,
                        max_run_periods=0.1)
    np.testing.assert_array_equal(got, path)
    near_shadow = band & ndi.binary_dilation(shadow, iterations=2)
    got, _, _ = split_rims(path, moved, wrapped, np.ones(h.shape), ~shadow, image, bg, mod, layer, ORIGIN)
    rows_to_shadow = near_shadow & ~ndi.binary_dilation(band & ~near_shadow, structure=np.ones((3, 1)), iterations=3)
    np.testing.assert_array_equal(got[rows_to_shadow], path[rows_to_shadow])


def test_no_plane_in_view_changes_nothing_and_says_so(scene):
    rig, layer, h, disc, shadow, image, bg, mod, wrapped, band, path = scene
    moved = disc & ~band  # only the disc was ordered: no plane pixels
    got, placed, stats = split_rims(path, moved, wrapped, np.ones(h.shape), ~shadow, image, bg, mod, layer, ORIGIN)
    np.testing.assert_array_equal(got, path)
    assert stats["rim_runs"] == 0 and "no plane" in stats["rim_skipped"]


def test_choose_orders_with_the_fringe_puts_the_rim_on_the_cliff(scene):
    """End to end: the estimate is the ramp everywhere; in the band the phase is a blend of both sides' fringes
    (the complex fringe blurred over 2.5 px, as a single-shot filter sees a cliff) and unreliable. The path alone
    leaves the band to the ramp or to a blended phase; with the fringe most band pixels land on their side."""
    rig, layer, h, disc, shadow, image, bg, mod, wrapped, band, path = scene
    estimate = ndi.gaussian_filter(h, 4.0)
    z = np.where(shadow, 0.0, np.exp(1j * wrapped))
    blend = np.angle(ndi.gaussian_filter(z.real, 2.5) + 1j * ndi.gaussian_filter(z.imag, 2.5))
    w = np.where(band, blend, wrapped)
    rel = np.where(shadow, 0.0, np.where(band, 0.05, 1.0))
    plain = choose_orders(estimate, w, rel, layer, valid=~shadow, shadow=shadow)
    with_rims = choose_orders(estimate, w, rel, layer, valid=~shadow, shadow=shadow, fringe=(image, bg, mod))
    e0, e1 = np.abs(plain.height - h)[band], np.abs(with_rims.height - h)[band]
    assert "rim_runs" not in plain.stats and with_rims.stats["rim_runs"] > 100
    assert plain.rim is None and with_rims.rim[band].mean() > 0.5 and not with_rims.rim[shadow].any()
    assert (e0 < 1.0).mean() < 0.15 and (e1 < 1.0).mean() > 0.55
    away = ~ndi.binary_dilation(band, iterations=3)
    np.testing.assert_array_equal(with_rims.height[away], plain.height[away])


def test_a_fall_read_as_a_rise_takes_one_order_lower():
    """The disc's outer ring (66-70 px) is 5 mm lower than its top: across that one-pixel fall the phase changes by
    more than pi (the default rig: 0.54 rad/px of carrier, -0.93 to -0.97 rad/mm at 19-24 mm; 5.4 rad leaving the
    disc rightwards, 4.3 leftwards), so the wrapped step reads as a rise of about 1.6 mm (one order, 6.6 mm at this
    height, less the 5 mm fall) and the continued phase lands one order high. Continued above its raised end, such
    a pixel is taken one order lower, and lands on the truth; max_rise_mm=None keeps the continuation."""
    rig, layer, h, disc, shadow, image, bg, mod, wrapped, band, path = _scene(ledge_mm=5.0)
    moved = ~band & ~shadow
    args = (path, moved, wrapped, np.ones(h.shape), ~shadow, image, bg, mod, layer, ORIGIN)
    kept, placed0, s0 = split_rims(*args, max_rise_mm=None)
    got, placed, s1 = split_rims(*args)
    yy, xx = np.mgrid[0:h.shape[0], 0:h.shape[1]]
    ring = disc & (np.hypot(xx - 360, yy - 176) >= 66.5) & placed & (got > 1.0) & (kept > 1.0)
    assert ring.sum() > 100
    e0, e1 = (kept - h)[ring], (got - h)[ring]
    high = (e0 > 6.0) & (e0 < 7.5)  # a whole order at this height: 6.6 mm
    assert high.mean() > 0.7  # the continuation: one order high
    assert (np.abs(e1) < 0.05).mean() > 0.9
    assert s0["rim_lowered"] == 0 and s1["rim_lowered"] >= high.sum()
    # only the object side is lowered: the plane side and everything unplaced keep their heights
    np.testing.assert_array_equal(got[kept <= 1.0], kept[kept <= 1.0])
    # the pixels before the fall did not rise and keep their continuation
    inner = placed & disc & (np.hypot(xx - 360, yy - 176) < 65.5)
    assert inner.sum() > 50
    np.testing.assert_array_equal(got[inner], kept[inner])


def _energy(side, nodes, cost, object_end, plane_end, smooth):
    """The labelling's energy, written out: plane-side costs plus ``smooth`` per 4-neighbour pair on different
    sides (a node's neighbour in object_end / plane_end counts as object / plane)."""
    fixed = np.where(object_end, 1, np.where(plane_end, 0, -1))
    lab = np.where(nodes, side.astype(int), fixed)
    e = cost[nodes & ~side].sum()
    for a, b in ((lab[:, :-1], lab[:, 1:]), (lab[:-1], lab[1:])):
        node_pair = (a >= 0) & (b >= 0)
        e += smooth * (node_pair & (a != b)).sum()
    return e


def test_the_sides_are_the_exact_minimum_of_their_energy():
    """min_cut_sides against every labelling of a few nodes (2^12 of them), on random costs and fixed ends."""
    rng = np.random.default_rng(0)
    for trial in range(20):
        nodes = np.zeros((5, 6), bool)
        cells = rng.choice(30, 12, replace=False)
        nodes.flat[cells] = True
        rest = ~nodes
        object_end = rest & (rng.random((5, 6)) < 0.4)
        plane_end = rest & ~object_end & (rng.random((5, 6)) < 0.6)
        cost = np.round(rng.normal(0.0, 1.0, (5, 6)), 3)
        smooth = [0.0, 0.1, 0.5, 1.5][trial % 4]
        got = min_cut_sides(nodes, cost, object_end, plane_end, smooth)
        assert not got[~nodes].any()
        ys, xs = np.nonzero(nodes)
        best = np.inf
        for code in range(2 ** 12):
            side = np.zeros(nodes.shape, bool)
            side[ys, xs] = (code >> np.arange(12)) & 1 == 1
            best = min(best, _energy(side, nodes, cost, object_end, plane_end, smooth))
        assert _energy(got, nodes, cost, object_end, plane_end, smooth) == pytest.approx(best, abs=2e-3)


def test_the_sides_hold_for_a_pixel_fixed_both_ways_large_costs_and_say_what_is_not_finite():
    nodes = np.zeros((3, 4), bool)
    nodes[1, 1:3] = True
    both = np.zeros_like(nodes)
    both[1, 0] = True  # beside the left node, in both masks: the object's
    # a little cheaper on the plane's side, but its only fixed neighbour is the object's
    got = min_cut_sides(nodes, np.full(nodes.shape, -0.02), both, both, 0.1)
    assert got[1, 1] and got[1, 2]
    # capacities past int32 are scaled down, not wrapped round
    assert min_cut_sides(nodes, np.full(nodes.shape, 3e6), np.zeros_like(nodes), np.zeros_like(nodes), 0.1)[nodes].all()
    plane = ~nodes
    assert not min_cut_sides(nodes, np.full(nodes.shape, -1.0), np.zeros_like(nodes), plane, 6e5)[nodes].any()
    assert min_cut_sides(nodes, np.full(nodes.shape, -1.0), plane, np.zeros_like(nodes), 6e5)[nodes].all()
    bad = np.zeros(nodes.shape)
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        min_cut_sides(nodes, bad, both, both, 0.1)
