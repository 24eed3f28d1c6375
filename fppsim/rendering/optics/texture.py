"""Albedo texture: smooth reflectance variation of plaster and board, a few mm to a few cm in size.

``albedo_texture`` is the relative std of a multiplicative albedo field (two scales, 40 and 8 camera
px), acting on the ambient and projector light alike; 0 (the default) = off.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import zoom

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["TEXTURE", "smooth_field", "albedo_field"]


def smooth_field(shape: tuple[int, int], rng: np.random.Generator, cell: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field (H, W) with features about ``cell`` pixels across."""
    h, w = shape
    gh, gw = max(2, int(np.ceil(h / cell)) + 2), max(2, int(np.ceil(w / cell)) + 2)
    coarse = rng.standard_normal((gh, gw))
    f = zoom(coarse, (h / (gh - 2), w / (gw - 2)), order=3)[:h, :w]
    f = f - f.mean()
    return f / (f.std() + 1e-12)


def albedo_field(shape, rng: np.random.Generator, strength: float, scale: int = 1) -> np.ndarray:
    """Multiplicative albedo (H, W) >= 0.05: 1 + strength x (two-scale smooth field, 40 and 8 camera px)."""
    f = 0.7 * smooth_field(shape, rng, 40.0 * scale) + 0.3 * smooth_field(shape, rng, 8.0 * scale)
    return np.clip(1.0 + strength * f / np.sqrt(0.7 ** 2 + 0.3 ** 2), 0.05, None)


def _texture(mult, optics, ctx):
    return mult * albedo_field(mult.shape, ctx.rng, optics.albedo_texture, ctx.scale)


TEXTURE = Effect("albedo texture", "albedo", (
    Param("albedo_texture", 0.0, (0.0, 0.0), "[0, inf)", off=0.0,
          doc="relative std of a smooth albedo variation (0 = off)."),
), _texture)
