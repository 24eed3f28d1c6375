"""Lambertian shading: the irradiance parts of every camera pixel from the scene geometry.

``E = base + modulated * pattern`` in gray levels, with

    base = gain * albedo * ambient                                   where a surface is seen
    modulated = gain * albedo * cos_incidence * falloff             where the projector lights it

``falloff`` is the projector's irradiance per unit cos(incidence) (equal flux per projector pixel,
:meth:`fppsim.geometry.rig.Device.irradiance_falloff`), which :func:`fppsim.rendering.render.scene_geometry` puts in the
geometry beside ``cos_incidence``; albedo is ``albedo_object`` on the objects, ``albedo_plane`` elsewhere.
"""

from __future__ import annotations

import numpy as np

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["SHADING", "irradiance_parts", "fringe_pixels"]


def irradiance_parts(geom, optics) -> tuple[np.ndarray, np.ndarray]:
    """``(base, modulated)`` float64 (H, W) gray levels of :class:`fppsim.rendering.render.Geometry` ``geom``."""
    albedo = _albedo(geom, optics)
    seen = geom.seen
    base = np.where(seen, optics.gain * albedo * optics.ambient, 0.0)
    modulated = np.where(geom.lit, optics.gain * albedo * geom.cos_incidence * geom.falloff, 0.0)
    return base, modulated


def fringe_pixels(geom, optics) -> np.ndarray:
    """(H, W) bool: the pixels that return the pattern, lit and of a surface that reflects (albedo above 0).

    Only these have a phase, so only these carry a label. A black plane (``albedo_plane`` 0: objects on a
    black background, as fit-optics measures frames with no plane in view) is left out like a shadow: real
    frames mark it invalid too, and a network asked for the unseen plane's height there learns to ramp every
    rim down to it (docs/own_rig.md)."""
    return geom.lit & (_albedo(geom, optics) > 0)


def _albedo(geom, optics) -> np.ndarray:
    """(H, W) float: ``albedo_object`` on the objects, ``albedo_plane`` elsewhere."""
    return np.where(geom.on_object, optics.albedo_object, optics.albedo_plane)


def _shade(parts, optics, ctx):
    return irradiance_parts(ctx.geom, optics)  # the first irradiance step: nothing before it to add to


SHADING = Effect("Lambertian shading", "irradiance", (
    Param("gain", 150.0, (190.0, 270.0), "(0, inf)",
          doc="gray levels for albedo 1 under the full-white pattern at the world origin."),
    Param("ambient", 0.05, (0.005, 0.04), "[0, inf)", doc="ambient light relative to the projector's full white."),
    Param("albedo_plane", 0.5, (0.25, 0.36), "[0, 1]",
          doc="diffuse reflectance of the reference plane (0: no plane in view, objects on a black background)."),
    Param("albedo_object", 0.8, (0.80, 1.00), "(0, 1]", doc="diffuse reflectance of the objects."),
), _shade)
