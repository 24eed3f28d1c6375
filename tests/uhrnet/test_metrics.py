"""uhrnet.scoring.metrics: SSIM against scikit-image, RMSE in mm, parameters."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from uhrnet.models import count_parameters
from uhrnet.scoring.metrics import rmse_mm, ssim


def skimage_ssim(a: np.ndarray, b: np.ndarray, data_range: float) -> float:
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=data_range
    )


def image_pairs():
    rng = np.random.default_rng(0)
    noisy = rng.random((48, 72))
    yield "random", noisy, np.clip(noisy + 0.3 * rng.standard_normal(noisy.shape), 0, 1), 1.0
    smooth = gaussian_filter(rng.random((48, 72)), 5)
    yield "smooth", smooth, smooth + 0.01 * gaussian_filter(rng.standard_normal(smooth.shape), 2), 1.0
    # height-map-like: smooth, offset far from zero, label range 80
    heights = 40 * gaussian_filter(rng.random((40, 64)), 6) - 120
    yield "offset heights", heights, heights + gaussian_filter(rng.standard_normal(heights.shape), 1.5), 80.0


@pytest.mark.parametrize(("kind", "a", "b", "data_range"), list(image_pairs()), ids=lambda v: v if isinstance(v, str) else "")
def test_ssim_matches_skimage(kind, a, b, data_range):
    t = lambda z: torch.tensor(z, dtype=torch.float32)[None, None]  # noqa: E731
    assert float(ssim(t(a), t(b), data_range)) == pytest.approx(skimage_ssim(a, b, data_range), abs=1e-4)


def test_ssim_per_image_batch_and_masks():
    pairs = [(a, b) for _, a, b, _ in list(image_pairs())[:2]]
    pred = torch.tensor(np.stack([b for _, b in pairs]), dtype=torch.float32)[:, None]
    target = torch.tensor(np.stack([a for a, _ in pairs]), dtype=torch.float32)[:, None]
    per_image = ssim(pred, target, 1.0, reduction="none")
    expected = [skimage_ssim(a, b, 1.0) for a, b in pairs]
    assert per_image.tolist() == pytest.approx(expected, abs=1e-4)
    assert float(ssim(pred, target, 1.0)) == pytest.approx(np.mean(expected), abs=1e-4)
    ones = torch.ones_like(pred, dtype=torch.bool)
    assert float(ssim(pred, target, 1.0, ones)) == pytest.approx(float(ssim(pred, target, 1.0)), abs=1e-6)
    empty = ones.clone()
    empty[1] = False
    masked = ssim(pred, target, 1.0, empty, reduction="none")
    assert masked[0].item() == pytest.approx(per_image[0].item(), abs=1e-6) and torch.isnan(masked[1])
    assert float(ssim(pred, target, 1.0, empty)) == pytest.approx(per_image[0].item(), abs=1e-6)
    assert float(ssim(target, target, 1.0)) == pytest.approx(1.0, abs=1e-6)


def test_ssim_needs_a_data_range_and_a_large_enough_image():
    x = torch.rand(1, 1, 16, 16)
    with pytest.raises(ValueError, match="data_range"):
        ssim(x, x, None)
    with pytest.raises(ValueError, match="smaller than"):
        ssim(x[..., :8, :], x[..., :8, :], 1.0)


def test_rmse_mm_is_eq_11_over_valid_pixels():
    pred = np.zeros((2, 1, 2, 2))
    target = np.array([[[[3.0, 4.0], [0.0, 99.0]]], [[[1.0, 1.0], [1.0, 1.0]]]])
    mask = np.array([[[[1, 1], [1, 0]]], [[[0, 0], [0, 0]]]], dtype=bool)
    per_image = rmse_mm(pred, target, mask, 0.5, reduction="none")
    assert per_image[0].item() == pytest.approx(0.5 * np.sqrt(25 / 3)) and np.isnan(per_image[1].item())
    assert rmse_mm(pred, target, mask, 0.5) == pytest.approx(0.5 * np.sqrt(25 / 3))  # empty image skipped
    assert rmse_mm(torch.zeros(1, 1, 2, 2), torch.full((1, 1, 2, 2), 2.0), None, 6.0) == pytest.approx(12.0)


def test_count_parameters():
    layer = torch.nn.Linear(3, 2)
    assert count_parameters(layer) == 8
    layer.bias.requires_grad_(False)
    assert count_parameters(layer) == 6 and count_parameters(layer, trainable_only=False) == 8


def test_ssim_of_low_precision_inputs_is_computed_in_float32():
    torch.manual_seed(0)
    target = 40 * torch.rand(1, 1, 32, 32) - 120
    pred = target + torch.randn_like(target)
    reference = ssim(pred, target, 40.0)
    low = ssim(pred.bfloat16(), target.bfloat16(), 40.0)
    assert low.dtype == torch.float32 and float(low) == pytest.approx(float(reference), abs=1e-2)
