"""The photometric augmentation of :mod:`uhrnet.data.augment` on the device, for samples that live there
(:mod:`uhrnet.data.device_data`): the same distribution, without a round trip through the host.

Every draw but the per-pixel noise is the CPU's own: :func:`draw` walks a sample's generator
(``default_rng([seed, 0xA467])``, as :func:`uhrnet.data.augment.augment_sample`) through the same calls in
the same order, so a sample gets the CPU's gain, gamma, contrast, blur, noise levels and smooth fields. The
arithmetic is float32 on the device (float64 on the CPU) and the read/shot noise comes from the device's
generator, so the images are the CPU's up to the last 8-bit level and the noise itself. The CPU path never
calls this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from uhrnet.data.augment import AugmentConfig

__all__ = ["Draw", "draw", "gaussian_blur", "augment_fringes"]

BACKGROUND_SIGMA = 6.0  # the local background's blur (uhrnet.data.augment.augment_fringe)


@dataclass
class Draw:
    """One sample's draws: scalars and the coarse grids of its smooth fields (None: that field is off)."""
    gain: float
    field_amp: float
    gamma: float
    contrast: float
    blur: float
    noise: float
    shot: float
    amp_b: float = 0.0
    amp_m: float = 0.0
    coarse_b: np.ndarray | None = None
    coarse_m: np.ndarray | None = None
    coarse_gain: np.ndarray | None = None
    shading: bool = False


def _coarse(shape, rng: np.random.Generator, scale: float = 0.25) -> np.ndarray:
    """The coarse grid of a smooth field, drawn as :mod:`uhrnet.data.augment` draws it."""
    h, w = shape
    gh, gw = max(2, int(round(1 / scale)) + 1), max(2, int(round(w / h / scale)) + 1)
    return rng.uniform(-1.0, 1.0, (gh, gw))


def draw(seed: int, shape, cfg: AugmentConfig) -> Draw | None:
    """The draws of the sample with augmentation seed ``seed`` and image ``shape`` (H, W); None when the sample
    is shown unaugmented (its invalid pixels still set to -1)."""
    rng = np.random.default_rng([int(seed), 0xA467])
    if rng.random() >= cfg.probability:
        return None
    d = Draw(gain=rng.uniform(*cfg.gain), field_amp=rng.uniform(0.0, cfg.field),
             gamma=float(np.exp(rng.uniform(np.log(cfg.gamma[0]), np.log(cfg.gamma[1])))),
             contrast=rng.uniform(*cfg.contrast), blur=rng.uniform(*cfg.blur), noise=rng.uniform(*cfg.noise),
             shot=rng.uniform(*cfg.shot))
    if cfg.envelope > 0 or d.contrast != 1.0:
        d.shading = True
        if cfg.envelope > 0:
            d.amp_b, d.amp_m = rng.uniform(0.0, cfg.envelope, 2)
            d.coarse_b = _coarse(shape, rng, rng.uniform(*cfg.envelope_scale))
            d.coarse_m = _coarse(shape, rng, rng.uniform(*cfg.envelope_scale))
    d.coarse_gain = _coarse(shape, rng)
    return d


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """scipy's ``gaussian_filter(x, sigma, mode="nearest")`` (truncated at 4 sigma) of (N, 1, H, W) images."""
    if sigma <= 0:
        return x
    r = int(4.0 * sigma + 0.5)
    t = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))


def _field(coarse: np.ndarray, shape, device: torch.device) -> torch.Tensor:
    t = torch.from_numpy(coarse).to(torch.float32)
    if device.type == "cuda":  # pinned: the copy is queued, the host does not wait for the device
        t = t.pin_memory().to(device, non_blocking=True)
    return F.interpolate(t[None, None], size=tuple(shape), mode="bicubic", align_corners=True)[0].clamp(-1, 1)


def augment_fringes(fringe: torch.Tensor, valid: torch.Tensor, draws: list, generator: torch.Generator | None):
    """The fringes (N, 1, H, W) (float32 in [-1, 1]) of a batch, augmented by their :class:`Draw` (None: shown
    as they are, invalid pixels -1; the string ``"keep"``: not augmented at all, e.g. real samples)."""
    out = fringe.clone()
    shape, device = fringe.shape[-2:], fringe.device
    for b, d in enumerate(draws):
        if isinstance(d, str):
            continue
        if d is not None:
            I = (fringe[b:b + 1].float() + 1.0) * 127.5
            if d.shading:
                scale_b = scale_m = 1.0
                if d.coarse_b is not None:
                    scale_b = torch.exp(d.amp_b * _field(d.coarse_b, shape, device))
                    scale_m = torch.exp(d.amp_m * _field(d.coarse_m, shape, device))
                background = gaussian_blur(I, BACKGROUND_SIGMA)
                I = background * scale_b + d.contrast * scale_m * (I - background)
            I = I * d.gain * (1.0 + d.field_amp * _field(d.coarse_gain, shape, device))
            I = 255.0 * (I.clamp(min=0.0) / 255.0) ** d.gamma
            I = gaussian_blur(I, d.blur)
            var = d.noise ** 2 + d.shot * I.clamp(min=0.0)
            I = I + torch.randn(I.shape, generator=generator, device=device, dtype=I.dtype) * var.sqrt()
            out[b:b + 1] = (torch.round(I.clamp(0.0, 255.0)) / 127.5 - 1.0).to(out.dtype)
        out[b:b + 1] = torch.where(valid[b:b + 1], out[b:b + 1], torch.full_like(out[b:b + 1], -1.0))
    return out
