"""uhrnet.data.augment: seeded photometric jitter of synthetic fringes; invalid pixels stay exactly -1."""

import numpy as np
import pytest
import torch

from uhrnet.data.augment import AugmentConfig, augment_fringe, augment_sample


def _fringe(h=64, w=96, seed=0):
    rng = np.random.default_rng(seed)
    xx = np.arange(w)[None, :]
    I = 40 + 30 * np.cos(2 * np.pi * xx / 11.6) + np.zeros((h, 1))
    I = np.rint(np.clip(I + rng.normal(0, 1, (h, w)), 0, 255))
    valid = np.ones((h, w), bool)
    valid[10:20, 30:50] = False
    f = (I / 127.5 - 1).astype(np.float32)
    f[~valid] = -1.0
    return f, valid


def test_same_seed_same_output_other_seed_other_output():
    f, v = _fringe()
    a = augment_fringe(f, v, np.random.default_rng(3))
    b = augment_fringe(f, v, np.random.default_rng(3))
    c = augment_fringe(f, v, np.random.default_rng(4))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    s = {"fringe": torch.from_numpy(f)[None], "mask": torch.from_numpy(v.astype(np.float32))[None], "id": "x"}
    torch.testing.assert_close(augment_sample(s, 11)["fringe"], augment_sample(s, 11)["fringe"])


def test_invalid_pixels_exactly_minus_one_and_output_on_the_8bit_grid():
    f, v = _fringe()
    for seed in range(10):
        out = augment_fringe(f, v, np.random.default_rng(seed))
        assert out.dtype == np.float32 and out.shape == f.shape
        assert np.all(out[~v] == -1.0)
        assert out.min() >= -1 and out.max() <= 1
        levels = (out.astype(np.float64) + 1) * 127.5
        np.testing.assert_allclose(levels, np.rint(levels), atol=1e-3)


def _only(**kw):
    """A config that changes only the given parameters (the others at their identity value)."""
    base = dict(probability=1.0, gain=(1.0, 1.0), field=0.0, gamma=(1.0, 1.0), contrast=(1.0, 1.0),
                blur=(0.0, 0.0), noise=(0.0, 0.0), shot=(0.0, 0.0), envelope=0.0)
    base.update(kw)
    return AugmentConfig(**base)


def test_identity_config_returns_the_input():
    f, v = _fringe()
    np.testing.assert_allclose(augment_fringe(f, v, np.random.default_rng(0), _only()), f, atol=1e-6)
    np.testing.assert_allclose(augment_fringe(f, v, np.random.default_rng(0), AugmentConfig(probability=0.0)), f)


def test_each_jitter_changes_the_statistic_it_should():
    f, v = _fringe()
    I0 = (f[v].astype(np.float64) + 1) * 127.5
    rng = lambda: np.random.default_rng(5)  # noqa: E731
    I = lambda cfg: (augment_fringe(f, v, rng(), cfg)[v].astype(np.float64) + 1) * 127.5  # noqa: E731
    assert I(_only(gain=(1.5, 1.5))).mean() == pytest.approx(1.5 * I0.mean(), rel=0.01)
    # gamma < 1 lifts dark levels: the median of a dark image rises
    assert np.median(I(_only(gamma=(0.6, 0.6)))) > np.median(I0) + 10
    # contrast halves the fringe amplitude (std of the carrier) but keeps the mean
    half = I(_only(contrast=(0.5, 0.5)))
    assert half.std() == pytest.approx(0.5 * I0.std(), rel=0.1) and half.mean() == pytest.approx(I0.mean(), abs=1)
    # blur lowers the fringe amplitude (an 11.6 px period through a sigma 1.2 Gaussian: exp(-2 pi^2 s^2/T^2))
    blurred = I(_only(blur=(1.2, 1.2)))
    assert blurred.std() < I0.std() * 0.95
    # noise: the difference to the input has the requested spread
    noisy = I(_only(noise=(3.0, 3.0)))
    assert np.std(noisy - I0) == pytest.approx(np.sqrt(3.0 ** 2 + 1 / 12), rel=0.15)
    # the smooth gain field varies the local brightness over the image
    field = augment_fringe(f, v, rng(), _only(field=0.35)).astype(np.float64)
    cols = [(field[:, i:i + 24] + 1).mean() for i in range(0, 96, 24)]
    assert np.ptp(cols) > 0.01


def _local_envelope(img, period=12):
    """Per-block (12 x 12 px) mean and fringe amplitude of an image in gray levels."""
    I = (img.astype(np.float64) + 1) * 127.5
    h, w = (I.shape[0] // period) * period, (I.shape[1] // period) * period
    b = I[:h, :w].reshape(h // period, period, w // period, period)
    return b.mean(axis=(1, 3)), b.std(axis=(1, 3))


def test_shading_fields_vary_background_and_modulation_independently_and_keep_the_phase():
    h, w = 128, 192
    xx = np.arange(w)[None, :] + np.zeros((h, 1))
    I = 100 + 60 * np.cos(2 * np.pi * xx / 12.0)
    f = (np.rint(I) / 127.5 - 1).astype(np.float32)
    v = np.ones((h, w), bool)
    out = augment_fringe(f, v, np.random.default_rng(2), _only(envelope=0.9, envelope_scale=(0.1, 0.1)))
    mean0, amp0 = _local_envelope(f)
    mean1, amp1 = _local_envelope(out)
    rb, rm = mean1 / mean0, amp1 / amp0
    # both vary over the image by well over the 8-bit rounding, and not in lockstep
    assert np.ptp(np.log(rb)) > 0.2 and np.ptp(np.log(rm)) > 0.2
    assert abs(np.corrcoef(np.log(rb).ravel(), np.log(rm).ravel())[0, 1]) < 0.9
    # the fringe phase is untouched: demodulated against the carrier, it stays put
    carrier = np.exp(-2j * np.pi * xx / 12.0)
    ph0 = np.angle(np.sum(((f + 1) * 127.5 - 100) * carrier))
    ac = (out.astype(np.float64) + 1) * 127.5
    from scipy.ndimage import uniform_filter1d
    ac = ac - uniform_filter1d(ac, 12, axis=1)
    ph1 = np.angle(np.sum(ac * carrier))
    assert abs(np.angle(np.exp(1j * (ph1 - ph0)))) < 0.05


def test_augmentation_kinds_and_the_booleans_of_older_runs():
    from uhrnet.data.augment import AUGMENTS, augment_config

    assert augment_config("shading").envelope > 0 and augment_config("photometric").envelope == 0
    assert augment_config("off") is None and augment_config(False) is None
    assert augment_config(True) == AUGMENTS["photometric"]
    with pytest.raises(ValueError, match="choose from"):
        augment_config("strong")


def test_prepared_augments_synthetic_samples_only_and_only_with_a_seed():
    from uhrnet.data.datasets import Prepared

    f, v = _fringe()

    class DS(torch.utils.data.Dataset):
        transform, ids = None, ["a", "b"]

        def __len__(self):
            return 2

        def __getitem__(self, i):
            return {"fringe": torch.from_numpy(f)[None], "height": torch.zeros(1, *f.shape),
                    "mask": torch.from_numpy(v.astype(np.float32))[None], "id": "ab"[i],
                    "source": ("synthetic", "real")[i]}

    p = Prepared(DS(), augment=AugmentConfig(probability=1.0))
    assert not torch.equal(p[(0, 7)]["fringe"], torch.from_numpy(f)[None])  # synthetic, seeded: augmented
    assert torch.equal(p[(1, 7)]["fringe"], torch.from_numpy(f)[None])  # real: untouched
    assert torch.equal(p[0]["fringe"], torch.from_numpy(f)[None])  # no seed (validation): untouched
    assert torch.equal(Prepared(DS())[(0, 7)]["fringe"], torch.from_numpy(f)[None])  # --no-augment
