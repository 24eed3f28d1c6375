"""Order slips of a phase-shifting reference (fppsim.phase.reference_check), against references built with known
errors: a smooth surface whose temporal orders are shifted in a patch, and real cliffs that must not be flagged."""

import numpy as np
import pytest

from fppsim.phase import TWO_PI, wrap
from fppsim.phase.reference_check import order_slips

from tests._helpers import SHARED

H, W = 120, 200


def smooth_phase(seed: int = 0) -> np.ndarray:
    """Absolute phase of a plane seen through vertical fringes (0.785 rad / px, the figshare frames') plus a
    smooth bump of a few periods."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W].astype(np.float64)
    bump = 9.0 * np.exp(-((xx - 90) ** 2 + (yy - 60) ** 2) / (2 * 30.0 ** 2))
    return TWO_PI * 80 * xx / 640 + 0.002 * yy ** 1.5 + bump + rng.normal(0, 0.01, (H, W))


def disk(cy, cx, r):
    yy, xx = np.mgrid[:H, :W]
    return (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r


@pytest.mark.parametrize("periods", [3, -2, 1])
def test_a_patch_whose_orders_slipped_is_found_and_repaired_exactly(periods):
    truth = smooth_phase()
    valid = np.ones((H, W), bool)
    patch = disk(50, 120, 7)
    given = truth + TWO_PI * periods * patch  # temporal unwrapping off by whole periods there; wrapped phase right
    slips = order_slips(wrap(truth), given, valid)
    assert np.array_equal(slips.mask, patch)
    assert np.all(slips.shift[patch] == -periods)
    np.testing.assert_allclose(slips.repaired(given), truth, atol=1e-9)
    assert len(slips.patches) == 1 and slips.patches[0]["pixels"] == int(patch.sum())
    assert slips.patches[0]["rows"] == [43, 57] and slips.patches[0]["cols"] == [113, 127]


def test_the_labels_name_each_patch_largest_first():
    truth = smooth_phase()
    small, large = disk(50, 120, 5), disk(100, 60, 8)
    slips = order_slips(wrap(truth), truth + TWO_PI * (2 * small - 3 * large), np.ones((H, W), bool))
    assert [p["pixels"] for p in slips.patches] == [int(large.sum()), int(small.sum())]
    assert np.array_equal(slips.labels == 1, large) and np.array_equal(slips.labels == 2, small)
    assert np.array_equal(slips.labels > 0, slips.mask) and slips.labels.dtype == np.int32


def test_a_right_reference_has_no_slips():
    truth = smooth_phase(1)
    valid = np.ones((H, W), bool)
    valid[:, 150:153] = False  # an unscored gap (a shadow) splits nothing into slips
    slips = order_slips(wrap(truth), truth, valid)
    assert slips.pixels == 0 and slips.patches == [] and not slips.shift.any()


@pytest.mark.parametrize("step_periods", [0.25, 1.6, 2.37, 3.5, 4.85])
def test_real_cliffs_are_not_slips(step_periods):
    """A raised disk (an object over a plane) whose phase step is not a whole number of periods: its orders are
    right and its wrapped step does not continue the fringes' gradient, so nothing is flagged."""
    obj = disk(60, 100, 20)
    truth = smooth_phase(2) + TWO_PI * step_periods * obj
    slips = order_slips(wrap(truth), truth, np.ones((H, W), bool))
    assert slips.pixels == 0


def test_a_cliff_of_whole_periods_reads_as_a_slip():
    """The documented limit: a real step of exactly whole periods all along a patch's border looks like a slip."""
    obj = disk(60, 100, 8)
    truth = smooth_phase(3) + TWO_PI * 2 * obj
    slips = order_slips(wrap(truth), truth, np.ones((H, W), bool))
    assert np.array_equal(slips.mask, obj)


def test_large_patches_are_left_alone():
    """A patch over max_fraction of the valid pixels is a surface, not a slip: never moved."""
    truth = smooth_phase(4)
    half = np.zeros((H, W), bool)
    half[:, 100:] = True
    given = truth + TWO_PI * half
    assert order_slips(wrap(truth), given, np.ones((H, W), bool)).pixels == 0


@pytest.mark.parametrize("inner", [6, 12])
def test_a_slipped_ring_is_found_and_the_right_surface_inside_it_is_not_moved(inner):
    """A ring of orders 3 periods off around a right disk: the ring is the slip (its steps to the smaller disk inside
    are that disk's to judge, not a border against the ring); the disk, right, is neither masked nor listed."""
    truth = smooth_phase(5)
    ring = disk(60, 100, 20) & ~disk(60, 100, inner)
    slips = order_slips(wrap(truth), truth + TWO_PI * 3 * ring, np.ones((H, W), bool))
    assert np.array_equal(slips.mask, ring) and np.all(slips.shift[ring] == -3)
    assert [p["pixels"] for p in slips.patches] == [int(ring.sum())]


def test_many_small_candidates_are_each_judged_on_their_own_votes():
    """Orders wrong at 2 % of the pixels at random (salt from low modulation): thousands of components with a slip
    on their border, each judged on its own slice of the votes (the time it takes lives in the benchmark of the
    module docstring, not here); what is flagged is wrong and repaired right."""
    h, w = 400, 400
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    truth = TWO_PI * 80 * xx / 640 + 0.0005 * yy ** 1.5
    bad = np.random.default_rng(0).random((h, w)) < 0.02
    slips = order_slips(wrap(truth), truth + TWO_PI * bad, np.ones((h, w), bool))
    assert slips.pixels > 50 and np.all(bad[slips.mask])
    np.testing.assert_allclose(slips.repaired(truth + TWO_PI * bad)[slips.mask], truth[slips.mask], atol=1e-9)
    box = slips.patches[0]
    assert slips.mask[box["rows"][0]:box["rows"][1] + 1, box["cols"][0]:box["cols"][1] + 1].sum() >= box["pixels"]


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="one 2-D shape"):
        order_slips(np.zeros((4, 5)), np.zeros((4, 6)), np.ones((4, 5), bool))


@pytest.mark.skipif(not (SHARED / "real-phase" / "FP1523").is_dir(), reason="../shared/real-phase absent")
def test_real_references():
    """FP1523/1201: the band beside the right figurine's shadow whose order is 4 periods off (modulation under half
    the frame's); the other two rigs' frames: nothing."""
    from fppsim.dataio.readers.psp_mat import load_psp_folder_sample

    s = load_psp_folder_sample(SHARED / "real-phase" / "FP1523", "1201")
    slips = order_slips(s.wrapped, s.phase, s.valid)
    assert 150 <= slips.pixels <= 400
    big = slips.patches[0]
    assert big["pixels"] >= 100 and 270 <= big["rows"][0] <= big["rows"][1] <= 345 and 270 <= big["cols"][0]
    assert {p["shift_periods"] for p in slips.patches} == {4}
    mod = np.hypot(s.psin, s.pcos)
    assert np.median(mod[slips.mask]) < 0.5 * np.median(mod[s.valid])
    assert order_slips(s.wrapped, slips.repaired(s.phase), s.valid).pixels == 0
    for rig, sid in (("FP672", "541"), ("FP147", "109")):
        s = load_psp_folder_sample(SHARED / "real-phase" / rig, sid)
        assert order_slips(s.wrapped, s.phase, s.valid).pixels == 0
