"""Plaster and board appearance beyond the Lambertian model: texture, dirt, specular, subsurface, vignetting.

Each effect is one field of :class:`fppsim.optics.Optics` (0 = off, the default) and one plain function
here; :func:`apply_appearance` combines them on the irradiance parts of :func:`fppsim.synth.render_images`
(``E = base + modulated * pattern``, gray levels on the camera grid) and :func:`subsurface_pattern` blurs
the pattern seen on the objects.

- ``albedo_texture`` (relative std): smooth albedo variation, a few mm to a few cm in size;
- ``dirt`` (0..1): dark stains covering about that fraction of the image, up to 60 % darker;
- ``specular`` (relative to the diffuse term): a weak Blinn-Phong lobe (exponent 30) of the projector
  light, strongest where the surface normal bisects the projector and camera directions;
- ``subsurface`` (camera px): light entering plaster leaves it nearby: the fringes on the objects are
  blurred by a Gaussian of this sigma (the plane is not);
- ``vignetting`` (relative): intensity falls by this fraction at the image corners (cos^4-like, r^2).

Lens distortion within calibration tolerance is geometric, not photometric: it lives in the rig jitter.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, zoom

__all__ = ["smooth_field", "albedo_field", "dirt_field", "specular_term", "vignetting_field",
           "subsurface_pattern", "apply_appearance"]


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


def dirt_field(shape, rng: np.random.Generator, amount: float, scale: int = 1) -> np.ndarray:
    """Multiplicative stains (H, W) in [0.4, 1]: about ``amount`` of the pixels darkened."""
    if amount <= 0:
        return np.ones(shape)
    f = smooth_field(shape, rng, 12.0 * scale)
    thr = np.quantile(f, 1.0 - amount)
    stain = np.clip((f - thr) / 0.5, 0.0, 1.0)
    return 1.0 - 0.6 * stain


def specular_term(points: np.ndarray, normals: np.ndarray, cam_center: np.ndarray, proj_center: np.ndarray,
                  exponent: float = 30.0) -> np.ndarray:
    """Blinn-Phong lobe (n . h)^exponent (H, W) for world points/normals (H, W, 3); 0 where undefined."""
    P = np.nan_to_num(points)
    to_p = proj_center - P
    to_c = cam_center - P
    h = to_p / np.linalg.norm(to_p, axis=-1, keepdims=True) + to_c / np.linalg.norm(to_c, axis=-1, keepdims=True)
    h /= np.linalg.norm(h, axis=-1, keepdims=True) + 1e-12
    return np.clip(np.einsum("...i,...i->...", normals, h), 0.0, 1.0) ** exponent


def vignetting_field(shape, strength: float) -> np.ndarray:
    """1 - strength * r^2 (H, W), r = distance from the centre relative to the corner distance."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return 1.0 - strength * r2


def subsurface_pattern(pattern: np.ndarray, on_object: np.ndarray, sigma: float) -> np.ndarray:
    """The pattern blurred by ``sigma`` pixels inside the objects only (normalised convolution)."""
    if sigma <= 0 or not on_object.any():
        return pattern
    m = on_object.astype(np.float32)
    num = gaussian_filter(pattern * m, sigma, mode="nearest")
    den = gaussian_filter(m, sigma, mode="nearest")
    return np.where(on_object, num / np.maximum(den, 1e-6), pattern).astype(pattern.dtype)


def apply_appearance(parts: tuple[np.ndarray, np.ndarray], geom, rig, optics, rng: np.random.Generator,
                     scale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(base, modulated) with texture, dirt, specular and vignetting of ``optics`` applied.

    ``scale`` is the supersampling factor of the grid (feature sizes are in camera pixels).
    Draws from ``rng`` only for the effects that are on.
    """
    base, modulated = (np.asarray(a, np.float64) for a in parts)
    shape = base.shape
    mult = np.ones(shape)
    if optics.albedo_texture > 0:
        mult *= albedo_field(shape, rng, optics.albedo_texture, scale)
    if optics.dirt > 0:
        mult *= dirt_field(shape, rng, optics.dirt, scale)
    if optics.vignetting > 0:
        mult *= vignetting_field(shape, optics.vignetting)
    base, modulated = base * mult, modulated * mult
    if optics.specular > 0:
        lobe = specular_term(geom.points, geom.normals, rig.camera.center, rig.projector.center)
        modulated = modulated * (1.0 + optics.specular * lobe)
    return base.astype(np.float32), modulated.astype(np.float32)
