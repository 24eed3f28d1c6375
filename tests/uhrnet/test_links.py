"""uhrnet.physics.links.seam_links across walls (``through``): a linear phase ramp, unwrapped in two regions cut
by a band of wall pixels, the order difference known from the ramp itself."""

import numpy as np
import pytest

from _helpers import wrap_phase
from fppsim.phase.unwrap import phase_regions
from uhrnet.physics.links import seam_links

H, W = 40, 120


def _two_halves(phi):
    usable = np.ones((H, W), bool)
    usable[:, 60:64] = False
    walls = ~usable
    reg = phase_regions(wrap_phase(phi), usable)
    assert reg.count == 2
    return reg, usable, walls


def _true_delta(reg, phi):
    return round(((reg.unwrapped[0, 100] - phi[0, 100]) - (reg.unwrapped[0, 10] - phi[0, 10])) / (2 * np.pi))


def test_a_wall_the_phase_runs_on_across_links_the_halves_at_their_order_difference():
    phi = np.tile(0.55 * np.arange(W, dtype=float), (H, 1))
    reg, usable, walls = _two_halves(phi)
    blocked = np.zeros((H, W), bool)
    links = seam_links(reg, wrap_phase(phi), usable, blocked, tolerance=0.05, min_votes=10, through=walls)
    assert len(links) == 1 and links[0].via == "wall"
    lk = links[0]
    left, right = int(reg.labels[0, 10]), int(reg.labels[0, 100])
    assert (lk.delta if (lk.a, lk.b) == (left, right) else -lk.delta) == _true_delta(reg, phi)
    assert lk.votes == H and lk.agreement == 1.0
    # without ``through`` the same gap is a seam; a gap of no wall pixel is not a wall crossing
    assert [x.via for x in seam_links(reg, wrap_phase(phi), usable, blocked)] == ["seam"]
    assert seam_links(reg, wrap_phase(phi), usable, blocked, through=np.zeros((H, W), bool)) == []
    # a shadow in the gap blocks it as it blocks a seam
    shade = np.zeros((H, W), bool)
    shade[:, 61] = True
    assert seam_links(reg, wrap_phase(phi), usable, shade, tolerance=0.05, through=walls) == []


def test_a_real_step_inside_the_wall_is_not_crossed():
    """A step of 0.3 periods inside the band on every row: the phase does not continue (votes 0.3 off a whole
    order), so no link at the wall's tolerance."""
    x = np.arange(W, dtype=float)
    phi = np.tile(0.55 * x + np.where(x >= 62, 0.3 * 2 * np.pi, 0.0), (H, 1))
    reg, usable, walls = _two_halves(phi)
    assert seam_links(reg, wrap_phase(phi), usable, np.zeros((H, W), bool), tolerance=0.05, min_votes=10,
                      through=walls) == []


@pytest.mark.parametrize("fraction", [0.12, -0.12, 0.15])
def test_a_real_step_inside_the_wall_does_not_bend_the_slopes_the_votes_extrapolate_with(fraction):
    """A step of 0.12-0.15 period inside the band: the votes are that far off a whole order, outside 0.05. As in
    choose_orders the wall's own pixels are usable (a wall is a cut between regions, not unreliable phase): a slope
    averaged over a window reaching into the band took the step in, and the votes came out 2/7 of it off."""
    x = np.arange(W, dtype=float)
    phi = np.tile(0.55 * x + np.where(x >= 62, fraction * 2 * np.pi, 0.0), (H, 1))
    usable = np.ones((H, W), bool)
    walls = np.zeros((H, W), bool)
    walls[:, 60:64] = True
    reg = phase_regions(wrap_phase(phi), usable, cut=walls)
    assert reg.count == 2
    assert seam_links(reg, wrap_phase(phi), usable, np.zeros((H, W), bool), tolerance=0.05, min_votes=10,
                      through=walls) == []


@pytest.mark.parametrize("transpose", [False, True])
def test_the_slopes_at_the_image_border_are_the_phases(transpose):
    """A wall 3 px from the last row (or column): the region beyond it is 3 px deep, and its slope window reaches
    the border, where the forward difference had a made-up 0 (the last pixel's step to itself, or to the first
    pixel round the image): the votes came out 0.06 period off and the wall was not crossed."""
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    phi = 0.3 * yy + 0.2 * xx
    walls = np.zeros((H, W), bool)
    walls[H - 7:H - 3] = True
    if transpose:
        phi, walls = phi.T.copy(), walls.T.copy()
    usable = np.ones(phi.shape, bool)
    reg = phase_regions(wrap_phase(phi), usable, cut=walls, min_size=50)
    assert reg.count == 2
    links = seam_links(reg, wrap_phase(phi), usable, np.zeros(phi.shape, bool), tolerance=0.05, min_votes=10,
                       through=walls)
    assert len(links) == 1 and links[0].agreement == 1.0
    lk = links[0]
    k = [np.median((reg.unwrapped - phi)[reg.labels == i]) / (2 * np.pi) for i in (lk.a, lk.b)]
    assert lk.delta == round(k[1] - k[0])
