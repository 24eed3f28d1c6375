"""Image-formation model: pattern profile, parameter sampling, noise, saturation, gamma."""

import numpy as np
import pytest

from fppsim.optics import Optics, OpticsRanges, form_image, pattern_profile, projector_radiance


def test_pattern_profile_phase_period_and_quantisation():
    sharp = Optics(projector_blur=0.0, pixelated=True, pattern_bits=8, projector_gamma=1.0)
    u, p = pattern_profile(912, 80, 0.0, sharp)
    assert u[0] == pytest.approx(-0.5 + 0.5 / 8) and u[-1] == pytest.approx(911.5 - 0.5 / 8)
    assert p.min() >= 0 and p.max() <= 1
    assert np.allclose(np.unique(np.rint(p * 255)) / 255, np.unique(p))  # 8-bit DMD levels
    # DMD column c shows cos(2 pi f c / W) for its whole width
    cols = np.arange(912)
    np.testing.assert_allclose(projector_radiance(cols.astype(float), 912, 80, 0.0, sharp),
                               np.rint(255 * (0.5 + 0.5 * np.cos(2 * np.pi * 80 * cols / 912))) / 255, atol=1e-12)
    # continuous, unquantised, defocused: still a cosine of the right phase (amplitude reduced by the blur)
    smooth = Optics(projector_blur=1.0, pixelated=False, pattern_bits=0)
    x = np.linspace(100, 800, 2001)
    v = projector_radiance(x, 912, 80, 0.3, smooth)
    k = 2 * np.pi * 80 / 912
    design = np.stack([np.ones_like(x), np.cos(k * x + 0.3), np.sin(k * x + 0.3)], 1)
    c, *_ = np.linalg.lstsq(design, v, rcond=None)
    assert c[0] == pytest.approx(0.5, abs=1e-3) and abs(c[2]) < 1e-3
    assert c[1] == pytest.approx(0.5 * np.exp(-0.5 * k ** 2), rel=1e-2)  # Gaussian MTF at the fringe frequency


def test_projector_gamma_bends_the_pattern():
    g = Optics(projector_blur=0.0, pixelated=False, pattern_bits=0, projector_gamma=2.2)
    assert projector_radiance(np.array([912 / 80 / 4]), 912, 80, 0.0, g)[0] == pytest.approx(0.5 ** 2.2, rel=3e-3)  # linear interpolation of the 1/8-px profile


def test_ranges_sample_deterministic_and_fixed():
    r = OpticsRanges()
    a, b = r.sample(np.random.default_rng(3)), r.sample(np.random.default_rng(3))
    assert a == b
    assert r.gain[0] <= a.gain <= r.gain[1]
    fixed = OpticsRanges.fixed(a)
    assert fixed.sample(np.random.default_rng(99)) == a
    assert OpticsRanges.from_dict({"noise_sigma": 0}).noise_sigma == (0.0, 0.0)
    with pytest.raises(ValueError, match="unknown optics parameter"):
        OpticsRanges.from_dict({"gian": [1, 2]})
    with pytest.raises(ValueError, match="lo <= hi"):
        OpticsRanges.from_dict({"gain": [3, 1]})


def test_form_image_noise_saturation_gamma():
    H, W = 200, 300
    base = np.full((H, W), 50.0, np.float32)
    mod = np.full((H, W), 100.0, np.float32)
    pat = np.full((H, W), 0.5, np.float32)  # E = 100 gray levels
    o = Optics(camera_blur=0.0, noise_sigma=2.0, shot_noise=0.1)
    img = form_image((base, mod), pat, o, np.random.default_rng(0))
    assert img.dtype == np.uint8
    assert img.mean() == pytest.approx(100, abs=0.1)
    assert img.std() == pytest.approx(np.sqrt(2.0 ** 2 + 0.1 * 100 + 1 / 12), rel=0.03)
    assert np.array_equal(img, form_image((base, mod), pat, o, np.random.default_rng(0)))  # seeded
    assert np.all(form_image((base * 10, mod), pat, Optics(camera_blur=0), None) == 255)  # saturation
    gam = form_image((base, mod), pat, Optics(camera_blur=0, camera_gamma=2.0), None)
    assert gam[0, 0] == round(255 * (100 / 255) ** 0.5)
    # supersampled blocks are averaged
    ss = form_image((np.zeros((6, 9), np.float32), np.ones((6, 9), np.float32) * 90),
                    np.tile(np.array([0, 1, 2], np.float32), (6, 3)), Optics(camera_blur=0), None, scale=3)
    assert ss.shape == (2, 3) and np.all(ss == 90)
