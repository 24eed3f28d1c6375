"""Dirt: dark stains covering about ``dirt`` of the image, up to 60 % darker; 0 (the default) = off."""

from __future__ import annotations

import numpy as np

from fppsim.rendering.optics.model import Effect, Param
from fppsim.rendering.optics.texture import smooth_field

__all__ = ["DIRT", "dirt_field"]


def dirt_field(shape, rng: np.random.Generator, amount: float, scale: int = 1) -> np.ndarray:
    """Multiplicative stains (H, W) in [0.4, 1]: about ``amount`` of the pixels darkened."""
    if amount <= 0:
        return np.ones(shape)
    f = smooth_field(shape, rng, 12.0 * scale)
    thr = np.quantile(f, 1.0 - amount)
    stain = np.clip((f - thr) / 0.5, 0.0, 1.0)
    return 1.0 - 0.6 * stain


def _dirt(mult, optics, ctx):
    return mult * dirt_field(mult.shape, ctx.rng, optics.dirt, ctx.scale)


DIRT = Effect("dirt", "albedo", (
    Param("dirt", 0.0, (0.0, 0.0), "[0, 1]", off=0.0, doc="stained fraction of the image (0 = off)."),
), _dirt)
