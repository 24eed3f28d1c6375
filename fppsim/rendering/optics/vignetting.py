"""Vignetting: the image falls by ``vignetting`` (relative) at its corners, ``1 - vignetting * r^2``
(cos^4-like; ``r`` the distance from the centre over the corner distance); 0 (the default) = off.

It multiplies both irradiance parts with the albedo effects (the order of the products is kept)."""

from __future__ import annotations

import numpy as np

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["VIGNETTING", "vignetting_field"]


def vignetting_field(shape, strength: float) -> np.ndarray:
    """1 - strength * r^2 (H, W), r = distance from the centre relative to the corner distance."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return 1.0 - strength * r2


def _vignetting(mult, optics, ctx):
    return mult * vignetting_field(mult.shape, optics.vignetting)


VIGNETTING = Effect("vignetting", "albedo", (
    Param("vignetting", 0.0, (0.0, 0.0), "[0, 1)", off=0.0, doc="relative fall-off at the image corners (0 = off)."),
), _vignetting)
