"""Specular reflection: a weak Blinn-Phong lobe (exponent 30) of the projector light.

It is strongest where the surface normal bisects the directions to the projector and the camera and
multiplies the projector term only: ``modulated * (1 + specular * lobe)``; 0 (the default) = off.
"""

from __future__ import annotations

import numpy as np

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["SPECULAR", "specular_term"]


def specular_term(points: np.ndarray, normals: np.ndarray, cam_center: np.ndarray, proj_center: np.ndarray,
                  exponent: float = 30.0) -> np.ndarray:
    """Blinn-Phong lobe (n . h)^exponent (H, W) for world points/normals (H, W, 3); 0 where undefined."""
    P = np.nan_to_num(points)
    to_p = proj_center - P
    to_c = cam_center - P
    h = to_p / np.linalg.norm(to_p, axis=-1, keepdims=True) + to_c / np.linalg.norm(to_c, axis=-1, keepdims=True)
    h /= np.linalg.norm(h, axis=-1, keepdims=True) + 1e-12
    return np.clip(np.einsum("...i,...i->...", normals, h), 0.0, 1.0) ** exponent


def _specular(modulated, optics, ctx):
    g, rig = ctx.geom, ctx.rig
    return modulated * (1.0 + optics.specular * specular_term(g.points, g.normals, rig.camera.center,
                                                              rig.projector.center))


SPECULAR = Effect("specular lobe", "projector_light", (
    Param("specular", 0.0, (0.0, 0.0), "[0, inf)", off=0.0,
          doc="strength of the specular lobe relative to the diffuse term (0 = off)."),
), _specular)
