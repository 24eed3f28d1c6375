"""The projector: DMD pixels, pattern bit depth, response (gamma) and lens defocus.

They shape the 1-D pattern profile along projector columns (:func:`fppsim.rendering.optics.pattern_profile`),
``OVERSAMPLE`` samples per projector pixel::

    P = defocus( gamma( q_bits( 0.5 + 0.5 cos(2 pi f c / W_p + delta) ) ) )

where ``c`` is the DMD column centre the sample falls in (``pixelated``) or the sample position itself.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["OVERSAMPLE", "PIXELS", "LEVELS", "GAMMA", "DEFOCUS"]

OVERSAMPLE = 8  # samples per projector pixel of the 1-D pattern profile


def _pixels(u, optics, ctx):
    return np.rint(u)  # every DMD column emits one constant value over its width


def _levels(p, optics, ctx):
    levels = 2 ** int(optics.pattern_bits) - 1
    return np.rint(p * levels) / levels


def _gamma(p, optics, ctx):
    return p ** optics.projector_gamma


def _defocus(p, optics, ctx):
    return gaussian_filter1d(p, optics.projector_blur * ctx.scale, mode="nearest")


def _is_bool(v) -> bool:
    return isinstance(v, (bool, np.bool_))


def _is_bits(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, np.integer)) and 0 <= v <= 16


PIXELS = Effect("DMD pixels", "projector_pixels", (
    Param("pixelated", True, check=_is_bool, expect="true or false", off=False,
          doc="the projector shows one constant value per DMD column (True) or an ideal continuous cosine."),
), _pixels)

LEVELS = Effect("pattern bit depth", "pattern_levels", (
    Param("pattern_bits", 8, check=_is_bits, expect="an integer in 0..16", off=0,
          doc="bit depth of the projected pattern (8 for a DLP projector; 0 = no quantisation)."),
), _levels)

GAMMA = Effect("projector gamma", "projector_response", (
    Param("projector_gamma", 1.0, (1.0, 1.0), "(0, inf)",
          doc="emitted = pattern**projector_gamma (1 = linear projector)."),
), _gamma)  # always applied (x**1 is x): as the images have always been made

DEFOCUS = Effect("projector defocus", "projector_optics", (
    Param("projector_blur", 1.0, (0.8, 1.6), "[0, inf)", off=0.0, unit="projector px",
          doc="defocus sigma in projector pixels (0 = sharp)."),
), _defocus)
