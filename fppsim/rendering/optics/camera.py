"""The camera: lens blur and the sensor's response curve (gamma).

The blur acts on the image that reaches the sensor, before its pixels integrate it (in camera pixels,
times the supersampling factor); the response bends the saturated signal before 8-bit quantisation:
``recorded = 255 * (E / 255) ** (1 / camera_gamma)``.
"""

from __future__ import annotations

from scipy.ndimage import gaussian_filter

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["BLUR", "GAMMA"]


def _blur(E, optics, ctx):
    return gaussian_filter(E, optics.camera_blur * ctx.scale, mode="nearest")


def _gamma(E, optics, ctx):
    return 255.0 * (E / 255.0) ** (1.0 / optics.camera_gamma)


BLUR = Effect("camera blur", "camera_optics", (
    Param("camera_blur", 0.5, (0.3, 0.8), "[0, inf)", off=0.0, unit="camera px",
          doc="optical blur sigma in camera pixels (0 = sharp)."),
), _blur, margin=lambda ranges: 4.0 * ranges.camera_blur[1])  # the Gaussian's reach: 4 sigma

GAMMA = Effect("camera gamma", "response", (
    Param("camera_gamma", 1.0, (1.0, 1.0), "(0, inf)", off=1.0,
          doc="recorded = 255*(E/255)**(1/camera_gamma) (1 = linear sensor)."),
), _gamma)
