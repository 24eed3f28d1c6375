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
