"""Training-time photometric augmentation of synthetic fringe images.

A network learns as a constant whatever it never sees varied: one gain, one gamma, one blur, one noise
level of the simulator. Real cameras differ in all of them, and real plaster lit at grazing angles
shows very dark, low-contrast fringes next to bright ones. Each synthetic training sample is therefore
re-exposed with a seeded random draw of:

- gain: a global factor times a smooth low-frequency gain field (uneven lighting, albedo);
- gamma: ``I' = 255 (I/255)^gamma`` (camera/projector response);
- contrast: the fringe modulation around a local (blurred) background is scaled;
- envelope: the local background and the fringe modulation are each multiplied by their own finer
  smooth random field (object-sized, 20-90 px), so shading cannot stand in for the fringe phase;
- blur: a Gaussian of random width (focus);
- noise: Gaussian read noise plus shot noise, then 8-bit quantisation (the data are 8-bit).

The fringe arrives in the dataset encoding (8-bit intensity / 127.5 - 1, in [-1, 1]); invalid pixels
(mask 0) are exactly -1 before and after. Same sample and seed -> identical output.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from uhrnet.errors import InputError

__all__ = ["AugmentConfig", "AUGMENTS", "augment_kind", "augment_config", "augment_fringe", "augment_sample"]


@dataclass(frozen=True)
class AugmentConfig:
    """Ranges of the photometric jitter (uniform draws; ``gamma`` log-uniform).

    probability : chance that a sample is augmented at all (the rest are shown unchanged).
    gain : global intensity factor. field : amplitude of the smooth gain field (relative, +-).
    gamma : response exponent range. contrast : factor on the fringe modulation around the local mean.
    blur : Gaussian sigma range, pixels. noise : read-noise sigma range, gray levels.
    shot : shot-noise variance per gray level range.
    envelope : largest log-amplitude of the two smooth fields on background and modulation (factors
        ``exp(+-envelope)``);
        0 turns them off (and leaves the other draws exactly as without them).
    envelope_scale : range of their feature size as a fraction of the image height.
    """

    probability: float = 0.8
    gain: tuple[float, float] = (0.6, 1.4)
    field: float = 0.35
    gamma: tuple[float, float] = (0.6, 1.5)
    contrast: tuple[float, float] = (0.6, 1.2)
    blur: tuple[float, float] = (0.0, 1.2)
    noise: tuple[float, float] = (0.0, 3.0)
    shot: tuple[float, float] = (0.0, 0.1)
    envelope: float = 0.9
    envelope_scale: tuple[float, float] = (0.06, 0.25)

    def to_dict(self) -> dict:
        return asdict(self)


AUGMENTS = {
    "shading": AugmentConfig(),                   # photometric jitter + random shading fields
    "photometric": AugmentConfig(envelope=0.0),   # the jitter alone (the default before the shading fields)
    "off": None,
}


def augment_kind(value):
    """The name in :data:`AUGMENTS` of a train option value; older runs stored a boolean (True:
    ``photometric``, False: ``off``). Other values come back unchanged."""
    if isinstance(value, bool):
        return "photometric" if value else "off"
    return value


def augment_config(kind) -> AugmentConfig | None:
    """The :class:`AugmentConfig` of a train option value (see :func:`augment_kind`)."""
    try:
        return AUGMENTS[augment_kind(kind)]
    except (KeyError, TypeError):
        raise InputError(f"augmentation {kind!r}: choose from {', '.join(AUGMENTS)}") from None


def _gauss(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(x, sigma, mode="nearest") if sigma > 0 else x


def _smooth_field(shape, rng: np.random.Generator, scale: float = 0.25) -> np.ndarray:
    """Zero-mean smooth random field in [-1, 1] varying over about ``scale`` of the image width."""
    h, w = shape
    gh, gw = max(2, int(round(1 / scale)) + 1), max(2, int(round(w / h / scale)) + 1)
    coarse = rng.uniform(-1.0, 1.0, (gh, gw))
    import torch.nn.functional as F

    t = torch.from_numpy(coarse)[None, None]
    return F.interpolate(t, size=(h, w), mode="bicubic", align_corners=True)[0, 0].clamp(-1, 1).numpy()


def augment_fringe(fringe: np.ndarray, valid: np.ndarray, rng: np.random.Generator,
                   cfg: AugmentConfig = AugmentConfig()) -> np.ndarray:
    """Augmented copy of one fringe image.

    Parameters
    ----------
    fringe : (H, W) float in [-1, 1] (8-bit intensity / 127.5 - 1).
    valid : (H, W) bool, False where the label is invalid; those pixels come back exactly -1.
    rng : the sample's generator (all draws come from it).

    Returns (H, W) float32 in [-1, 1], quantised to the 8-bit grid.
    """
    x = np.asarray(fringe, np.float64)
    valid = np.asarray(valid, bool)
    if rng.random() >= cfg.probability:
        out = x.astype(np.float32)
        out[~valid] = -1.0
        return out
    gain = rng.uniform(*cfg.gain)
    field_amp = rng.uniform(0.0, cfg.field)
    gamma = float(np.exp(rng.uniform(np.log(cfg.gamma[0]), np.log(cfg.gamma[1]))))
    contrast = rng.uniform(*cfg.contrast)
    blur = rng.uniform(*cfg.blur)
    noise = rng.uniform(*cfg.noise)
    shot = rng.uniform(*cfg.shot)
    I = (x + 1.0) * 127.5
    if cfg.envelope > 0 or contrast != 1.0:
        # the fringe around its local background (about two periods wide): contrast scales it, and the
        # shading fields vary background and modulation apart, unrelated to height (the phase must
        # carry the relief); without them both factors are exactly 1
        scale_b = scale_m = 1.0
        if cfg.envelope > 0:
            amp_b, amp_m = rng.uniform(0.0, cfg.envelope, 2)
            scale_b = np.exp(amp_b * _smooth_field(I.shape, rng, rng.uniform(*cfg.envelope_scale)))
            scale_m = np.exp(amp_m * _smooth_field(I.shape, rng, rng.uniform(*cfg.envelope_scale)))
        background = _gauss(I, 6.0)
        I = background * scale_b + contrast * scale_m * (I - background)
    I = I * gain * (1.0 + field_amp * _smooth_field(I.shape, rng))
    I = 255.0 * (np.clip(I, 0.0, None) / 255.0) ** gamma
    I = _gauss(I, blur)
    var = noise ** 2 + shot * np.clip(I, 0.0, None)
    I = I + rng.standard_normal(I.shape) * np.sqrt(var)
    I = np.rint(np.clip(I, 0.0, 255.0))
    out = (I / 127.5 - 1.0).astype(np.float32)
    out[~valid] = -1.0
    return out


def augment_sample(sample: dict, seed: int, cfg: AugmentConfig = AugmentConfig()) -> dict:
    """The uhrnet sample dict with its ``fringe`` (1, H, W) augmented from ``seed``; other keys shared."""
    rng = np.random.default_rng([int(seed), 0xA467])
    fringe = sample["fringe"][0].numpy()
    valid = sample["mask"][0].numpy() > 0.5
    out = dict(sample)
    out["fringe"] = torch.from_numpy(augment_fringe(fringe, valid, rng, cfg))[None]
    return out
