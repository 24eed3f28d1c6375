"""Subsurface scattering: light entering plaster leaves it nearby, so the fringes on the objects are
blurred by a Gaussian of ``subsurface`` camera px (the plane is not); 0 (the default) = off."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["SUBSURFACE", "subsurface_pattern"]


def subsurface_pattern(pattern: np.ndarray, on_object: np.ndarray, sigma: float) -> np.ndarray:
    """The pattern blurred by ``sigma`` pixels inside the objects only (normalised convolution)."""
    if sigma <= 0 or not on_object.any():
        return pattern
    m = on_object.astype(np.float32)
    num = gaussian_filter(pattern * m, sigma, mode="nearest")
    den = gaussian_filter(m, sigma, mode="nearest")
    return np.where(on_object, num / np.maximum(den, 1e-6), pattern).astype(pattern.dtype)


def _subsurface(pattern, optics, ctx):
    return subsurface_pattern(pattern, ctx.geom.on_object, optics.subsurface * ctx.scale)


SUBSURFACE = Effect("subsurface scattering", "camera_pattern", (
    Param("subsurface", 0.0, (0.0, 0.0), "[0, inf)", off=0.0,
          doc="fringe blur sigma on the objects, camera px (0 = off)."),
), _subsurface)
