"""uhrnet.physics.islands.continue_islands on analytic scenes through the default rig: fppsim's own forward model
(fppsim.fitting.height_sensitivity.surface_phase) gives the truth's phase, the path's heights are the truth with a
patch put one whole order off (as a growth route across a hidden cliff leaves it)."""

import numpy as np
import pytest
import torch

from _helpers import wrap_phase
from fppsim.fitting.height_sensitivity import surface_phase
from fppsim.geometry.rig import make_default_rig
from uhrnet.physics.islands import continue_islands, continued_components
from uhrnet.physics.orders import choose_orders
from uhrnet.physics.rig_layer import RigLayer

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scene():
    """A smooth mound 20-26 mm high over the whole view (no cliff), the measured phase from another origin."""
    rig = make_default_rig()
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    h = 20.0 + 6.0 * np.exp(-((xx - 330) ** 2 + (yy - 170) ** 2) / (2 * 90.0 ** 2))
    wrapped = wrap_phase(surface_phase(rig, h) + 72.0)
    return rig, RigLayer(rig), h, wrapped, (xx, yy)


def _off_by(layer, h, patch, periods):
    """``h`` with ``patch`` moved by whole fringe periods of phase (the path's slip)."""
    t = torch.as_tensor(h, dtype=torch.float64)
    with torch.no_grad():
        moved = layer.height_from_phase(layer.phase_from_height(t) + 2 * np.pi * periods).numpy()
    return np.where(patch, moved, h)


def test_a_patch_one_order_off_where_the_fringes_run_on_takes_their_order(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    patch = ((xx - 300) ** 2 / 30.0 ** 2 + (yy - 200) ** 2 / 18.0 ** 2) < 1.0
    for periods in (1, -1):
        path = _off_by(layer, h, patch, periods)
        assert np.abs(path - h)[patch].min() > 3.0  # a whole fringe of height off
        got, shifted, stats = continue_islands(path, np.ones(h.shape, bool), wrapped, layer)
        assert np.array_equal(shifted, patch)
        assert stats == {"island_pixels": int(patch.sum()), "islands": 1}
        np.testing.assert_allclose(got, h, atol=1e-6)


def test_a_true_cliff_a_small_patch_and_a_large_one_stay(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    # a real step of 0.3 fringe: the fringes break along its border, so nothing there is continuous
    square = (np.abs(xx - 450) < 25) & (np.abs(yy - 120) < 25)
    period_mm = float(2 * np.pi / np.abs(layer.sensitivity(torch.as_tensor(h)).numpy()).mean())
    cliff = h + np.where(square, 0.3 * period_mm, 0.0)
    w_cliff = wrap_phase(surface_phase(rig, cliff) + 72.0)
    for path in (cliff, _off_by(layer, cliff, square, 1)):  # right, or an order off: no continuous step says which
        got, shifted, _ = continue_islands(path, np.ones(h.shape, bool), w_cliff, layer)
        assert not shifted.any() and np.array_equal(got, path)
    # a 2 x 2 patch has 8 border steps: fewer than the 10 votes asked for
    tiny = (xx >= 200) & (xx < 202) & (yy >= 100) & (yy < 102)
    got, shifted, _ = continue_islands(_off_by(layer, h, tiny, 1), np.ones(h.shape, bool), wrapped, layer)
    assert not shifted.any()
    # more than max_fraction of the moved pixels: a whole object is not moved by its border
    half = xx < 320
    path = _off_by(layer, h, half, 1)
    got, shifted, _ = continue_islands(path, np.ones(h.shape, bool), wrapped, layer)
    assert not shifted.any() and np.array_equal(got, path)
    assert continue_islands(path, np.ones(h.shape, bool), wrapped, layer, max_fraction=0.6)[1].sum() == half.sum()


def test_pixels_not_moved_neither_vote_nor_move_and_shapes_must_agree(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    patch = ((xx - 300) ** 2 + (yy - 200) ** 2) < 20 ** 2
    path = _off_by(layer, h, patch, 1)
    ring = (((xx - 300) ** 2 + (yy - 200) ** 2) < 23 ** 2) & ~patch  # the patch's border is not moved: no votes
    got, shifted, stats = continue_islands(path, ~ring, wrapped, layer)
    assert not shifted.any() and stats["island_pixels"] == 0
    got, shifted, _ = continue_islands(path, ~patch, wrapped, layer)  # the patch itself was not moved
    assert not shifted.any()
    nothing = continue_islands(path, np.zeros(h.shape, bool), wrapped, layer)
    assert not nothing[1].any() and np.array_equal(nothing[0], path)
    with pytest.raises(ValueError, match="shapes differ"):
        continue_islands(path, np.ones((4, 4), bool), wrapped, layer)


def test_choose_orders_reports_the_islands_and_can_leave_them(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    est = h + 1.0  # a network a millimetre high everywhere: one region, one order
    on = choose_orders(est, wrapped, np.ones(h.shape), layer)
    off = choose_orders(est, wrapped, np.ones(h.shape), layer, islands=False)
    assert on.stats["island_pixels"] == 0 and "island_pixels" not in off.stats
    np.testing.assert_array_equal(on.height, off.height)


def test_continued_components_split_where_the_path_or_the_fringes_break(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    t = torch.as_tensor(h, dtype=torch.float64)
    with torch.no_grad():
        phase = layer.phase_from_height(t).numpy()
    mask = np.ones(h.shape, bool)
    mask[:, 100] = False  # a column off the mask cuts the view in two
    comp = continued_components(phase, wrapped, mask)
    assert (comp[:, 100] == -1).all() and len(np.unique(comp[:, :100])) == 1 and len(np.unique(comp[:, 101:])) == 1
    assert comp[0, 0] != comp[0, 101]
    patch = (np.abs(xx - 300) < 20) & (np.abs(yy - 200) < 20)
    comp = continued_components(phase + 2 * np.pi * patch, wrapped, np.ones(h.shape, bool))  # the path jumps there
    assert len(np.unique(comp[patch])) == 1 and comp[patch][0] != comp[0, 0] and len(np.unique(comp)) == 2
    with pytest.raises(ValueError, match="shapes differ"):
        continued_components(phase, wrapped[:, :10], mask)


def test_an_island_follows_its_largest_neighbour_where_it_ends_up(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    r = np.hypot(xx - 300, yy - 200)
    hole, ring = r < 15, (r >= 15) & (r < 40)
    # a ring one order off around a hole two orders off: the hole continues the ring, the ring the view
    path = _off_by(layer, _off_by(layer, h, ring | hole, 1), hole, 1)
    got, shifted, stats = continue_islands(path, np.ones(h.shape, bool), wrapped, layer)
    assert stats["islands"] == 2 and np.array_equal(shifted, ring | hole)
    np.testing.assert_allclose(got, h, atol=1e-6)
    # half a ring two orders off beside a disc one order off: the disc's votes are the view's (its largest
    # neighbour), not the half ring's, whose border with it is as long
    half = ring & (xx > 300)
    path = _off_by(layer, _off_by(layer, h, half | hole, 1), half, 1)
    got, shifted, stats = continue_islands(path, np.ones(h.shape, bool), wrapped, layer)
    assert np.array_equal(shifted, half | hole)
    np.testing.assert_allclose(got, h, atol=1e-6)


def test_a_patch_whose_steps_jump_only_inside_itself_stays(scene):
    rig, layer, h, wrapped, (xx, yy) = scene
    # a square cut off from the view by a ring of pixels not moved; in its lower half the path's phase climbs one
    # whole period over 8 px (continued: under half a period a step), so the lower right sits an order off the
    # upper right, one component joined around the climb: its 21 jumping steps (row 199 -> 200, x >= 304) jump
    # inside it, off no neighbour. Shifting it by them moved the whole patch a whole order (the half-grey pair).
    square = (np.abs(xx - 300) < 25) & (np.abs(yy - 200) < 25)
    ring = (np.abs(xx - 300) < 27) & (np.abs(yy - 200) < 27) & ~square
    climb = np.clip((xx - 300) / 8.0, 0.0, 1.0) * (yy >= 200) * square
    path = _off_by(layer, h, square, torch.as_tensor(climb))
    comp = continued_components(layer.phase_from_height(torch.as_tensor(path)).numpy(), wrapped, ~ring)
    assert len(np.unique(comp[square])) == 1  # one component, joined around the climb
    got, shifted, stats = continue_islands(path, ~ring, wrapped, layer)
    assert not shifted.any() and stats["island_pixels"] == 0
    np.testing.assert_array_equal(got, path)
