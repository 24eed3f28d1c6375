"""fppsim.phase: one wrap convention, the circular mean and median and masked demodulation, against analytic truth."""

import numpy as np
import pytest

from fppsim.phase import circular_mean, circular_median, demodulate, lowpass, mean_phasor, wrap


def test_wrap_range_and_identity():
    w = wrap(np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.5, 7.0, -7.0, np.nan]))
    np.testing.assert_allclose(w[:7], [np.pi, np.pi, np.pi, np.pi, 0.5, 7.0 - 2 * np.pi, 2 * np.pi - 7.0], atol=1e-12)
    assert np.isnan(w[7])
    inside = np.random.default_rng(0).uniform(-np.pi + 1e-9, np.pi, 1000)
    assert np.array_equal(wrap(inside), inside)  # already wrapped: unchanged, bit for bit
    x = np.random.default_rng(1).uniform(-50, 50, 1000)
    w = wrap(x)
    assert (w > -np.pi).all() and (w <= np.pi).all()
    np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(x), atol=1e-12)


def test_circular_mean_straddles_the_cut_and_honours_mask_and_weights():
    rng = np.random.default_rng(2)
    a = wrap(3.0 + 0.05 * rng.standard_normal(5000))  # around 3 rad: some samples wrapped to about -3.2
    assert abs(wrap(circular_mean(a) - 3.0)) < 0.01
    assert abs(mean_phasor(a)) == pytest.approx(np.exp(-0.05 ** 2 / 2), abs=0.01)  # coherence of a normal spread
    b = np.concatenate([np.full(10, 1.0), np.full(30, -1.0)])
    assert circular_mean(b, mask=b > 0) == pytest.approx(1.0)
    w = np.concatenate([np.full(10, 3.0), np.full(30, 1.0)])
    assert circular_mean(b, weights=w) == pytest.approx(0.0, abs=1e-12)  # equal total weight on +1 and -1
    assert np.isnan(circular_mean(b, mask=np.zeros(40, bool)))


def test_circular_median_straddles_the_cut_and_ignores_outliers():
    rng = np.random.default_rng(3)
    a = wrap(3.0 + 0.1 * rng.standard_normal(5000))  # straddles the +-pi cut
    a = np.concatenate([a, rng.uniform(-np.pi, np.pi, 2000)])
    assert abs(wrap(circular_median(a) - 3.0)) < 0.02
    assert np.isnan(circular_median(np.array([np.nan])))


def test_demodulate_recovers_a_phase_shift_inside_the_mask():
    H, W = 64, 96
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    carrier = 2 * np.pi * xx / 9.0
    shift = 0.3 + 0.004 * xx  # a slow phase the demodulation must return
    valid = np.ones((H, W), bool)
    valid[:, :10] = False
    signal = np.where(valid, np.cos(carrier + shift), 0.0)
    d = np.angle(demodulate(signal, carrier, 4.0, valid.astype(float)))
    inner = (slice(12, H - 12), slice(24, W - 12))
    np.testing.assert_allclose(d[inner], shift[inner], atol=0.02)
    z = np.exp(1j * carrier)
    assert np.array_equal(lowpass(z, 2.0), lowpass(z, 2.0, np.ones((H, W))))
