"""Image formation: scene geometry + optics -> 8-bit camera images, one declared effect at a time.

Intensity model, per camera pixel, in 8-bit gray levels before noise::

    E = gain * albedo * (ambient + lit * cos_incidence * falloff * P(u_p))
    P(u_p) = blur_p( gamma_p( q8( 0.5 + 0.5 * cos(2*pi*f*c/W_p + delta) ) ) )(u_p)

where ``c`` runs over projector columns (each DMD pixel emits a constant value when ``pixelated``),
``q8`` is the projector's 8-bit pattern quantisation, ``gamma_p`` the projector's power-law response,
``blur_p`` a Gaussian defocus in projector pixels. Appearance effects (albedo texture, dirt,
vignetting, a specular lobe, subsurface blur of the fringes on the objects) are off by default. The
camera then blurs ``E`` (Gaussian, camera pixels), averages supersampled pixels, adds Gaussian read
noise and shot noise (variance ``noise_sigma**2 + shot_noise * E``), saturates at 0 and 255, applies
its response ``255*(x/255)**(1/camera_gamma)`` and quantises to uint8.

Layout: one module per effect (or closely related group) declares its parameters and its step
(:class:`~fppsim.rendering.optics.model.Effect`); :data:`EFFECTS` lists them in the order they act (the one
list: ``OpticsRanges.range_names()``, ``--optics`` and ``--help`` read it, so it is not repeated here).
:mod:`.model` derives :class:`Optics` (one value per parameter), :class:`OpticsRanges` (a (lo, hi)
range per number, one :class:`Optics` drawn per sample from a seeded generator) and
:data:`OPTICS_LIMITS` from :data:`EFFECTS`; :mod:`.stage` runs the effects in order
(:func:`form_images`: one sample's images; :func:`form_image`: the camera half).

How to add an optics effect: write one module here with its step ``apply(value, optics, ctx)`` and an
``Effect(name, site, (Param(...), ...), apply)``, where the site (:data:`~fppsim.rendering.optics.model.SITES`)
says where in the chain it acts and what ``value`` is there, and each ``Param`` gives the name, the
default, the randomisation range, the valid interval and the value that turns it off (0 by convention,
with a default range of (0, 0), so existing datasets keep their images); a blur that reads beyond the
image border also declares its reach (``margin``). Then append the effect to :data:`EFFECTS` (at the
end: the parameters before it keep their random draws) and write one test that it changes the images
the way it should. ``Optics``, ``OpticsRanges``, the limits, ``--optics NAME=LO,HI``, ``--help`` and
the stage pick it up from there (``tests/fppsim/test_optics.py`` builds such a toy effect).
"""

from __future__ import annotations

from fppsim.rendering.optics import camera, dirt, noise, projector, shading, specular, subsurface, texture, vignetting
from fppsim.rendering.optics.model import Context, Effect, OpticsModel, Param, SITES
from fppsim.rendering.optics.noise import PrefetchedNormals, noise_source
from fppsim.rendering.optics.projector import OVERSAMPLE
from fppsim.rendering.optics.shading import fringe_pixels
from fppsim.rendering.optics.stage import (form_image, form_images, optical_image, pattern_profile, projector_radiance,
                    sensor_image, surface_irradiance)

__all__ = ["Optics", "OpticsRanges", "OPTICS_LIMITS", "OPTICS_UNITS", "EFFECTS", "MODEL", "OVERSAMPLE",
           "Effect", "Param", "Context", "OpticsModel", "SITES", "pattern_profile", "projector_radiance",
           "surface_irradiance", "form_images", "form_image", "optical_image", "sensor_image",
           "noise_source", "PrefetchedNormals", "fringe_pixels"]

# The effects in the order their parameters become fields of Optics, which is also the order of the
# per-sample random draws (OpticsRanges.sample): a new effect goes at the end.
EFFECTS = (
    shading.SHADING,
    projector.GAMMA,
    camera.GAMMA,
    projector.DEFOCUS,
    camera.BLUR,
    noise.NOISE,
    projector.PIXELS,
    projector.LEVELS,
    texture.TEXTURE,
    dirt.DIRT,
    specular.SPECULAR,
    subsurface.SUBSURFACE,
    vignetting.VIGNETTING,
)

MODEL = OpticsModel(EFFECTS, module=__name__)
Optics = MODEL.Optics
OpticsRanges = MODEL.OpticsRanges
# {name: (lowest, lowest inclusive, highest or None, highest inclusive)} of every numeric parameter: a
# value outside makes garbage images (negative noise variance -> NaN; gain 0 -> black) and is refused.
OPTICS_LIMITS = MODEL.limits
# Units of the optics ranges that show one in --help (the names come from OpticsRanges itself).
OPTICS_UNITS = MODEL.units
