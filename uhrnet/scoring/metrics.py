"""Metrics of the paper: SSIM, RMSE in millimetres (eq. 11), parameter count (timing and memory:
:mod:`uhrnet.scoring.timing`).

Conventions: images are ``(N, C, H, W)`` tensors (numpy arrays are accepted by the scalar metrics);
``mask`` is ``None`` (every pixel valid) or a ``(N, 1, H, W)`` (or broadcastable) tensor, bool or
numeric with nonzero = valid. Per-image values are averaged over the batch, as the paper averages
per-image values over its test set.
"""

from __future__ import annotations

import numpy as np
import torch

import torch.nn.functional as F
from uhrnet.errors import InputError

ArrayLike = torch.Tensor | np.ndarray


def valid_mask(mask: ArrayLike | None, like: torch.Tensor) -> torch.Tensor | None:
    """``mask`` as a bool tensor on ``like``'s device broadcast to ``like``'s shape (None stays None)."""
    if mask is None:
        return None
    mask = torch.as_tensor(mask, device=like.device)
    if mask.dtype != torch.bool:
        mask = mask != 0
    return mask.expand_as(like)


def gaussian_window(size: int, sigma: float, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """Normalised 1-D Gaussian ``g_i ~ exp(-(i - (size-1)/2)^2 / (2 sigma^2))``, ``i = 0 .. size-1``.

    ``size = 11, sigma = 1.5`` equals scikit-image's ``gaussian_weights=True`` window
    (``truncate = 3.5`` gives radius ``int(3.5 * 1.5 + 0.5) = 5``).
    """
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def ssim_map(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> torch.Tensor:
    r"""Local SSIM of every full window: ``(N, C, H, W) -> (N, C, H - 2r, W - 2r)``, ``r = window // 2``.

    With ``G`` the separable Gaussian filter (:func:`gaussian_window`), ``mu_x = G*x``,
    ``s_x^2 = G*x^2 - mu_x^2``, ``s_xy = G*(xy) - mu_x mu_y``, ``C1 = (k1 L)^2``, ``C2 = (k2 L)^2``:

    .. math::
        \mathrm{SSIM} = \frac{(2\mu_x\mu_y + C_1)(2\sigma_{xy} + C_2)}
                             {(\mu_x^2 + \mu_y^2 + C_1)(\sigma_x^2 + \sigma_y^2 + C_2)}

    Only windows that lie fully inside the image are returned: this is exactly the part of scikit-image's
    map (``gaussian_weights=True, use_sample_covariance=False``) that its mean SSIM averages. Moments are
    taken about a per-image constant (the target's mean) so float32 stays accurate for offset data;
    the result is mathematically unchanged. Half-precision inputs are computed in float32 (also under
    autocast).
    """
    if window % 2 == 0:
        raise InputError(f"window must be odd, got {window}")
    if pred.shape != target.shape or pred.dim() != 4:
        raise InputError(f"pred and target must be equal (N, C, H, W) shapes, got {pred.shape} and {target.shape}")
    n, c, h, w = pred.shape
    if h < window or w < window:
        raise InputError(f"image {h}x{w} is smaller than the {window}x{window} SSIM window")
    dtype = torch.promote_types(pred.dtype, torch.float32)  # never filter in half precision
    with torch.autocast(pred.device.type, enabled=False):
        return _ssim_map(pred.to(dtype), target.to(dtype), data_range, window, sigma, k1, k2)


def _ssim_map(pred, target, data_range, window, sigma, k1, k2) -> torch.Tensor:
    offset = target.detach().mean(dim=(1, 2, 3), keepdim=True)
    x, y = pred - offset, target - offset
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    g = gaussian_window(window, sigma, device=pred.device, dtype=pred.dtype)
    groups = stack.shape[1]
    stack = F.conv2d(stack, g.view(1, 1, 1, -1).expand(groups, 1, 1, window), groups=groups)
    stack = F.conv2d(stack, g.view(1, 1, -1, 1).expand(groups, 1, window, 1), groups=groups)
    mu_x, mu_y, xx, yy, xy = stack.chunk(5, dim=1)
    var_x, var_y, cov = xx - mu_x * mu_x, yy - mu_y * mu_y, xy - mu_x * mu_y
    mu_x, mu_y = mu_x + offset, mu_y + offset
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    return ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float,
    mask: ArrayLike | None = None,
    *,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    reduction: str = "mean",
) -> torch.Tensor:
    """SSIM of ``pred`` against ``target`` (differentiable; ``float(ssim(...))`` for a number).

    ``data_range`` is the dynamic range ``L`` of the data (fixed per dataset, never estimated per batch).
    Per image, the :func:`ssim_map` is averaged over the windows whose centre pixel is valid; with a
    mask, invalid pixels of ``pred`` are first replaced by ``target`` (as the reference evaluation does),
    so they carry neither error nor gradient. ``target`` must be finite everywhere.

    ``reduction="mean"``: 0-dim tensor, the mean over images that have a valid window centre (1.0 when
    none has); ``"none"``: ``(N,)`` per-image values, NaN for an image without valid window centres.
    Without a mask and for one image this equals ``skimage.metrics.structural_similarity(...,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=L)``.
    """
    if data_range is None or not data_range > 0:
        raise InputError(f"data_range must be a positive number, got {data_range!r}")
    if reduction not in ("mean", "none"):
        raise InputError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    valid = valid_mask(mask, pred)
    if valid is not None:
        pred = torch.where(valid, pred, target)
    smap = ssim_map(pred, target, data_range, window, sigma, k1, k2)
    if valid is None:
        per_image = smap.mean(dim=(1, 2, 3))
        has_valid = torch.ones_like(per_image, dtype=torch.bool)
    else:
        r = window // 2
        weight = valid[..., r : valid.shape[-2] - r, r : valid.shape[-1] - r].to(smap.dtype)
        count = weight.sum(dim=(1, 2, 3))
        per_image = (smap * weight).sum(dim=(1, 2, 3)) / count.clamp(min=1)
        has_valid = count > 0
    if reduction == "none":
        return torch.where(has_valid, per_image, torch.full_like(per_image, float("nan")))
    n_valid = has_valid.sum()
    mean = (per_image * has_valid).sum() / n_valid.clamp(min=1)
    return torch.where(n_valid > 0, mean, torch.ones_like(mean))


def rmse(
    pred: ArrayLike, target: ArrayLike, mask: ArrayLike | None = None, *, reduction: str = "mean"
) -> float | torch.Tensor:
    """Root mean squared error over valid pixels, per image, in label units.

    ``RMSE = sqrt(sum_valid (pred - target)^2 / n_valid)`` per image (all channels). ``"mean"``: float,
    the mean of the per-image values over images with valid pixels (NaN if none); ``"none"``: ``(N,)``
    float64 tensor, NaN for an image without valid pixels. Computed in float64 without gradient.
    """
    if reduction not in ("mean", "none"):
        raise InputError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    with torch.no_grad():
        pred = torch.as_tensor(pred).detach().to(torch.float64)
        target = torch.as_tensor(target).to(device=pred.device, dtype=torch.float64)
        if pred.shape != target.shape:
            raise InputError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
        if pred.dim() < 2:
            raise InputError("expected a batch of images (N, ...)")
        valid = valid_mask(mask, pred)
        sq = (pred - target) ** 2
        if valid is None:
            per_image = sq.flatten(1).mean(dim=1).sqrt()
        else:
            sq = torch.where(valid, sq, torch.zeros_like(sq))
            count = valid.flatten(1).sum(dim=1)
            per_image = (sq.flatten(1).sum(dim=1) / count).sqrt()  # 0/0 -> NaN for empty images
        if reduction == "none":
            return per_image.cpu()
        return float(per_image.nanmean()) if not per_image.isnan().all() else float("nan")


def rmse_mm(
    pred: ArrayLike,
    target: ArrayLike,
    mask: ArrayLike | None,
    mm_per_unit: float,
    *,
    reduction: str = "mean",
) -> float | torch.Tensor:
    """Eq. 11 of the paper in millimetres: ``mm_per_unit * sqrt(mean_valid (pred - target)^2)``.

    ``pred`` and ``target`` are in label units; ``mm_per_unit`` is the scale of the dataset's label
    transform (millimetres per label unit; offsets cancel in the difference). See :func:`rmse` for
    ``mask`` and ``reduction`` (default: the mean of the per-image RMSEs, as a float).
    """
    return rmse(pred, target, mask, reduction=reduction) * mm_per_unit


def image_metrics(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, transform) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image RMSE (mm) and SSIM of label maps ``(N, 1, H, W)`` under a label ``transform``
    (:class:`fppsim.dataio.formats.LabelTransform`): float64 CPU tensors, NaN where an image has no valid pixel."""
    pred, target, mask = pred.detach().float(), target.float(), mask
    r = rmse_mm(pred, target, mask, transform.mm_per_unit, reduction="none").double().cpu()
    s = ssim(pred, target, transform.data_range, mask, reduction="none").detach().double().cpu()
    return r, s
