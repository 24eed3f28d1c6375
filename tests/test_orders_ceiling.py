"""pipelines/orders_ceiling.py: a region put whole orders off comes back to the truth, right regions stay."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _helpers import load_pipeline

C = load_pipeline("orders_ceiling")


def _disc(shape, centre, radius):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 < radius ** 2


@pytest.fixture(scope="module")
def layer():
    from fppsim.geometry.rig import make_default_rig
    from uhrnet.physics.rig_layer import RigLayer
    return RigLayer(make_default_rig(), height=88, width=160)


def test_pair_ceiling_undoes_a_region_put_one_order_high_and_keeps_the_rest(layer):
    shape = layer.grid_shape
    disc, other = _disc(shape, (40, 50), 18), _disc(shape, (40, 120), 12)
    truth = np.where(disc, 20.0, 0.0) + np.where(other, 12.0, 0.0)
    labels = np.where(disc, 2, np.where(other, 3, 1)).astype(np.int32)
    labels[:, :3] = 0  # pixels in no region keep their heights
    with torch.no_grad():
        phi = layer.phase_from_height(torch.as_tensor(truth, dtype=torch.float64))
        high = layer.height_from_phase(phi + 2 * np.pi).numpy()
    path = np.where(disc, high, truth)
    path[:, :3] = 7.0
    assert np.all(np.abs(path - truth)[disc] > 2.0)  # the disc is a whole period (several mm) off
    obj = truth > 1.0
    out = C.pair_ceiling(path, labels, truth, obj, layer)
    np.testing.assert_allclose(out[disc], truth[disc], atol=1e-6)
    np.testing.assert_array_equal(out[~disc], path[~disc])


def test_frame_ceiling_finds_the_region_a_period_off_and_leaves_right_ones(layer):
    from types import SimpleNamespace
    from uhrnet.scoring.phase_residual import fit_phase
    shape = layer.grid_shape
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    disc, other = _disc(shape, (44, 50), 15), _disc(shape, (44, 120), 20)
    dome = 30.0 * np.sqrt(np.clip(1 - ((yy - 44.0) ** 2 + (xx - 120.0) ** 2) / 400.0, 0, 1))
    truth = np.where(disc, 25.0, 0.0) + np.where(other, dome, 0.0)
    labels = np.where(disc, 2, np.where(other, 3, 1)).astype(np.int32)
    with torch.no_grad():
        phi = layer.phase_from_height(torch.as_tensor(truth, dtype=torch.float64)).numpy()
        high = layer.height_from_phase(torch.as_tensor(phi + 2 * np.pi)).numpy()
    origin = 0.7
    # the reference numbers its orders from anywhere: 4 periods added everywhere change nothing
    phase = phi + origin + 8 * np.pi + np.random.default_rng(0).normal(0, 0.01, shape)
    scored, slipped = np.ones(shape, bool), np.zeros(shape, bool)
    best = fit_phase(phase, truth, scored).rmse_rad

    def choice(h):
        return SimpleNamespace(height=h, labels=labels, rim=None, moved=np.ones(shape, bool), offset_rad=origin)

    right = C.frame_ceiling(choice(truth), phase, scored, slipped, layer)
    assert right["regions_moved"] == 0 and right["ceiling_rad"] == pytest.approx(best)
    got = C.frame_ceiling(choice(np.where(disc, high, truth)), phase, scored, slipped, layer)
    assert got["residual_rad"] > 3 * best
    assert got["regions_moved"] == 1 and got["ceiling_rad"] == pytest.approx(best, rel=1e-6)
    assert got["parts"]["no_region"]["pixels"] == 0 and got["parts"]["reference_slipped"]["share"] == 0.0
    assert got["parts"]["region_order_off"]["rad_without"] <= got["residual_rad"]


def _scene(layer):
    """A plane (region 1) and a 25 mm disc (region 2); the reference phase of the truth, origin anywhere."""
    shape = layer.grid_shape
    disc = _disc(shape, (44, 50), 15)
    truth = np.where(disc, 25.0, 0.0)
    labels = np.where(disc, 2, 1).astype(np.int32)
    with torch.no_grad():
        phi = layer.phase_from_height(torch.as_tensor(truth, dtype=torch.float64)).numpy()
        high = layer.height_from_phase(torch.as_tensor(phi + 2 * np.pi)).numpy()
    phase = phi + 0.7 + np.random.default_rng(0).normal(0, 0.01, shape)
    return disc, truth, labels, high, phase


def test_a_region_moved_keeps_its_pixels_without_a_height(layer):
    from types import SimpleNamespace
    from uhrnet.scoring.phase_residual import fit_phase
    disc, truth, labels, high, phase = _scene(layer)
    path = np.where(disc, high, truth)
    hole = _disc(layer.grid_shape, (44, 50), 4)
    path[hole] = np.nan  # no height there: a shift of whole orders does not give it one
    out = C.pair_ceiling(path, labels, truth, truth > 1.0, layer)
    assert np.isnan(out[hole]).all() and np.allclose(out[disc & ~hole], 25.0, atol=1e-6)
    scored, slipped = np.ones(disc.shape, bool), np.zeros(disc.shape, bool)
    choice = SimpleNamespace(height=path, labels=labels, rim=None, moved=np.ones(disc.shape, bool), offset_rad=0.7)
    got = C.frame_ceiling(choice, phase, scored, slipped, layer)
    assert got["regions_moved"] == 1
    assert got["ceiling_rad"] == pytest.approx(fit_phase(phase, np.where(hole, np.nan, truth), scored).rmse_rad, rel=1e-6)


@pytest.mark.parametrize("plane_px", [0, 9])
def test_without_a_plane_the_frame_ceiling_says_so_rather_than_zero_regions(layer, plane_px):
    from types import SimpleNamespace
    disc, truth, labels, high, phase = _scene(layer)
    path = np.where(disc, high, truth)  # the disc a whole order off
    moved = disc.copy()  # the plane's pixels not placed by the path: no plane to read the orders against ...
    moved[:3, :3] = plane_px == 9  # ... or a handful of them
    choice = SimpleNamespace(height=path, labels=labels, rim=None, moved=moved, offset_rad=0.7)
    got = C.frame_ceiling(choice, phase, np.ones(disc.shape, bool), np.zeros(disc.shape, bool), layer)
    assert got["plane_px"] == plane_px and got["regions_moved"] is None and np.isnan(got["ceiling_rad"])
    assert np.isfinite(got["residual_rad"]) and got["parts"]["no_region"]["pixels"] == 0
