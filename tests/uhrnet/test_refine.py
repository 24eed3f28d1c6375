"""uhrnet.refine.refine_height: snapping heights to the image's own wrapped phase, against analytic truth."""

import numpy as np
import pytest
import torch

from fppsim.height_sensitivity import surface_phase
from fppsim.rig import make_default_rig
from uhrnet.refine import circular_median, refine_height
from uhrnet.rig_layer import RigLayer

pytestmark = pytest.mark.usefixtures("one_thread")


def wrap_phase(x):
    """Wrap rad into (-pi, pi] (independent of the code under test)."""
    return np.angle(np.exp(1j * np.asarray(x, dtype=np.float64)))


@pytest.fixture(scope="module")
def scene():
    """The default rig, a smooth 30 mm bump on the plane, its exact phase (fppsim's own forward model)
    and the height of half a fringe period at every pixel."""
    rig = make_default_rig()
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    h = 30.0 * np.exp(-((xx - 330) ** 2 + (yy - 170) ** 2) / (2 * 70.0 ** 2))
    layer = RigLayer(rig)
    half = np.pi / np.abs(layer.sensitivity(0.0).numpy())  # ~3.6 mm
    return rig, layer, h, surface_phase(rig, h), half, (xx, yy)


def _off_by(layer, h, dphi):
    """The height whose phase differs from that of ``h`` by ``dphi`` rad (an error of dphi / 2 pi periods)."""
    Phi = layer.phase_from_height(torch.from_numpy(h))
    return layer.height_from_phase(Phi + torch.as_tensor(dphi)).numpy()


def _symmetric(xx, amplitude):
    """amplitude * sin(2 pi 3 x / W): three whole periods across the image, so its values form a
    symmetric set whose median is exactly 0 (a constant would be indistinguishable from a phase offset)."""
    return amplitude * np.sin(2 * np.pi * 3 * xx / xx.shape[1])


def test_small_errors_are_removed_exactly(scene):
    rig, layer, h, phase, half, (xx, yy) = scene
    err = 0.4 * half * np.sin(xx / 50.0) * np.cos(yy / 40.0)  # smooth, within the default margin (0.5)
    refined, moved, stats = refine_height(h + err, wrap_phase(phase), None, layer)
    assert moved.all() and stats["moved_fraction"] == 1.0
    assert np.abs(refined - h).max() < 1e-6  # float64: the exact surface back
    assert stats["offset_rad"] == 0.0 and abs(stats["offset_estimate_rad"]) < 1e-9
    # the same from the rig (the layer is built inside) and in float32
    r32, _, _ = refine_height((h + err).astype(np.float32), wrap_phase(phase).astype(np.float32),
                              np.ones(h.shape, np.float32), rig)
    assert r32.dtype == np.float32 and np.abs(r32 - h).max() < 1e-3


def test_errors_beyond_half_a_period_are_not_fixed_wrongly(scene):
    rig, layer, h, phase, half, _ = scene
    pred = _off_by(layer, h, 0.7 * 2 * np.pi)  # 0.7 periods off: the nearest consistent height is a period off
    refined, moved, stats = refine_height(pred, wrap_phase(phase), None, layer)
    assert not moved.any() and np.array_equal(refined, pred)  # the move (0.3 periods) exceeds the margin
    assert stats["beyond_margin_fraction"] == pytest.approx(1.0) and stats["moved_fraction"] == 0.0
    # without a margin the move happens, to the wrong period (as documented)
    refined, moved, _ = refine_height(pred, wrap_phase(phase), None, layer, max_move_fraction=1.0)
    assert moved.all()
    assert np.abs(refined - _off_by(layer, h, 2 * np.pi)).max() < 1e-6
    # an absolute margin in mm
    small = h + 0.1 * half
    _, moved, _ = refine_height(small, wrap_phase(phase), None, layer, max_move_mm=0.05 * half.min())
    assert not moved.any()


def test_unreliable_and_missing_pixels_are_untouched(scene):
    rig, layer, h, phase, half, (xx, yy) = scene
    pred = h + 0.3 * half
    pred[:10] = np.nan
    rel = np.ones_like(h)
    rel[:, :100] = 0.2
    rel[200:210] = np.nan
    wrapped = wrap_phase(phase)
    wrapped[300:] = np.nan
    refined, moved, stats = refine_height(pred, wrapped, rel, layer, min_reliability=0.5)
    keep = np.zeros(h.shape, bool)
    keep[:, :100] = keep[200:210] = keep[300:] = True
    assert np.array_equal(refined[keep], pred[keep], equal_nan=True)
    assert np.isnan(refined[:10]).all() and not moved[:10].any()
    sel = ~keep & np.isfinite(pred)
    assert moved[sel].all() and np.abs(refined[sel] - h[sel]).max() < 1e-6
    assert stats["moved_fraction"] == pytest.approx(moved.sum() / np.isfinite(pred).sum())
    assert stats["n_pixels"] == np.isfinite(pred).sum()


def test_global_phase_offset_is_estimated(scene):
    rig, layer, h, phase, half, (xx, yy) = scene
    offset = 72.0  # the public real frames' phase origin (DESIGN.md §9)
    wrapped = wrap_phase(phase + offset)
    pred = _off_by(layer, h, _symmetric(xx, 0.3 * np.pi))
    refined, moved, stats = refine_height(pred, wrapped, None, layer, phase_offset="estimate")
    assert stats["offset_rad"] == pytest.approx(float(wrap_phase(offset)), abs=1e-9)
    assert moved.all() and np.abs(refined - h).max() < 1e-6
    # the known offset does the same; offset 0 moves almost nothing (the shift is 2.9 rad)
    r2, _, s2 = refine_height(pred, wrapped, None, layer, phase_offset=offset)
    assert np.abs(r2 - h).max() < 1e-6
    assert s2["offset_estimate_rad"] == pytest.approx(stats["offset_rad"], abs=1e-12)
    _, m0, _ = refine_height(pred, wrapped, None, layer)
    assert m0.mean() < 0.1
    # a quarter of the pixels with garbage phase: the circular median barely moves
    rng = np.random.default_rng(0)
    bad = rng.random(h.shape) < 0.25
    wrapped[bad] = rng.uniform(-np.pi, np.pi, bad.sum())
    refined, moved, stats = refine_height(pred, wrapped, None, layer, phase_offset="estimate")
    assert stats["offset_rad"] == pytest.approx(float(wrap_phase(offset)), abs=0.02)
    ok = moved & ~bad
    assert ok.mean() > 0.7 and np.abs(refined[ok] - h[ok]).max() < 0.03


def test_batch_has_one_offset_per_image(scene):
    rig, layer, h, phase, half, (xx, _) = scene
    wrapped = np.stack([wrap_phase(phase + 1.0), wrap_phase(phase - 2.0)])
    pred = np.stack([_off_by(layer, h, _symmetric(xx, 0.2 * np.pi)), _off_by(layer, h, _symmetric(xx, -0.4 * np.pi))])
    refined, moved, stats = refine_height(pred, wrapped, None, layer, phase_offset="estimate")
    assert stats["offset_rad"] == pytest.approx([1.0, -2.0], abs=1e-9)
    assert moved.all() and np.abs(refined - h).max() < 1e-6


def test_circular_median_and_errors():
    rng = np.random.default_rng(3)
    a = wrap_phase(3.0 + 0.1 * rng.standard_normal(5000))  # straddles the +-pi cut
    a = np.concatenate([a, rng.uniform(-np.pi, np.pi, 2000)])
    assert abs(wrap_phase(circular_median(a) - 3.0)) < 0.02
    assert np.isnan(circular_median(np.array([np.nan])))
    layer = RigLayer(make_default_rig(), pixels=(slice(0, 4), slice(0, 5)))
    with pytest.raises(ValueError, match="grid"):
        refine_height(np.zeros((5, 5)), np.zeros((5, 5)), None, layer)
    with pytest.raises(ValueError, match="estimate"):
        refine_height(np.zeros((4, 5)), np.zeros((4, 5)), None, layer, phase_offset="median")
