"""uhrnet.augment: seeded photometric jitter of synthetic fringes; invalid pixels stay exactly -1."""

import numpy as np
import pytest
import torch

from uhrnet.augment import AugmentConfig, augment_fringe, augment_sample


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
                blur=(0.0, 0.0), noise=(0.0, 0.0), shot=(0.0, 0.0))
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


def test_prepared_augments_synthetic_samples_only_and_only_with_a_seed():
    from uhrnet.data import Prepared

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
