"""The image-formation stage: geometry + optics -> 8-bit camera images, one effect at a time.

The stage owns the fixed skeleton (the cosine, the pattern lookup on the camera grid, pixel integration,
saturation, quantisation) and runs the effects of the optics' model (``type(optics).model``) at their
sites, in the order of :data:`fppsim.rendering.optics.model.SITES`; it names no effect itself.
"""

from __future__ import annotations

import numpy as np

from fppsim.rendering.optics.model import Context
from fppsim.rendering.optics.projector import OVERSAMPLE

__all__ = ["pattern_profile", "projector_radiance", "surface_irradiance", "form_images", "form_image",
           "optical_image", "sensor_image"]


def _run(site: str, value, optics, ctx: Context):
    """``value`` through the effects of ``optics`` at ``site`` that are on."""
    for effect in optics.model.at(site):
        if effect.is_on(optics):
            value = effect.apply(value, optics, ctx)
    return value


def pattern_profile(width: int, periods: float, shift: float, optics) -> tuple[np.ndarray, np.ndarray]:
    """Emitted projector radiance along projector columns, in [0, 1].

    Returns ``(u, value)``: float64 (width * OVERSAMPLE,) sample positions in projector pixel coordinates
    (from -0.5 to width-0.5) and the emitted, defocused pattern there. The pattern varies only along
    columns, so the whole projector image is this 1-D profile.
    """
    ctx = Context(scale=OVERSAMPLE)
    n = width * OVERSAMPLE
    u = (np.arange(n) + 0.5) / OVERSAMPLE - 0.5
    where = _run("projector_pixels", u, optics, ctx)
    p = 0.5 + 0.5 * np.cos(2.0 * np.pi * periods * where / width + shift)
    for site in ("pattern_levels", "projector_response", "projector_optics"):
        p = _run(site, p, optics, ctx)
    return u, p


def projector_radiance(u_p: np.ndarray, width: int, periods: float, shift: float, optics) -> np.ndarray:
    """Pattern value P(u_p) in [0, 1] at projector columns ``u_p`` (any shape, float)."""
    u, p = pattern_profile(width, periods, shift, optics)
    return np.interp(u_p, u, p)


def surface_irradiance(geom, rig, optics, scale: int = 1,
                       rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(base, modulated)`` float32 (H, W) gray levels on the camera grid, ``E = base + modulated * P``.

    The irradiance effects on ``geom`` (:class:`fppsim.rendering.render.Geometry`, ``scale``-times supersampled),
    then, when any is on, the albedo multipliers (drawing from ``rng``; None = a fixed generator) and the
    projector-light effects, in float64.
    """
    ctx = Context(geom=geom, rig=rig, scale=scale)
    parts = tuple(a.astype(np.float32) for a in _run("irradiance", None, optics, ctx))
    albedo = [e for e in optics.model.at("albedo") if e.is_on(optics)]
    light = [e for e in optics.model.at("projector_light") if e.is_on(optics)]
    if not (albedo or light):
        return parts
    ctx.rng = rng if rng is not None else np.random.default_rng(0)
    base, modulated = (np.asarray(a, np.float64) for a in parts)
    mult = np.ones(base.shape)
    for effect in albedo:
        mult = effect.apply(mult, optics, ctx)
    base, modulated = base * mult, modulated * mult
    for effect in light:
        modulated = effect.apply(modulated, optics, ctx)
    return base.astype(np.float32), modulated.astype(np.float32)


def form_images(geom, rig, optics, patterns: list[tuple[float, float]], noise_rng, scale: int = 1,
                appearance_rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """uint8 camera images (H, W) for ``patterns`` = [(periods, phase shift rad), ...] on one geometry.

    Parameters
    ----------
    geom : :class:`fppsim.rendering.render.Geometry` on the ``scale``-times supersampled camera grid.
    rig : the :class:`fppsim.geometry.rig.Rig` it was computed with.
    optics : ``Optics`` of the sample (its class's model says which effects run).
    noise_rng : camera noise generator (None = noise-free); each image gets its own realisation.
    appearance_rng : generator of the appearance effects (texture, dirt, ...).
    """
    parts = surface_irradiance(geom, rig, optics, scale, appearance_rng)
    ctx = Context(geom=geom, rig=rig, scale=scale)
    # Linear interpolation weights into the oversampled 1-D pattern profile, shared by all patterns.
    x = (np.where(geom.lit, geom.u_p, 0.0) + 0.5) * OVERSAMPLE - 0.5
    n = rig.projector.width * OVERSAMPLE
    i0 = np.clip(np.floor(x), 0, n - 2).astype(np.intp)
    w = np.clip(x - i0, 0.0, 1.0).astype(np.float32)
    out = []
    for periods, shift in patterns:
        prof = pattern_profile(rig.projector.width, periods, shift, optics)[1].astype(np.float32)
        # prof[i0] + w * (prof[i0 + 1] - prof[i0]), the differences taken once on the profile (the same
        # float32 values) instead of per pixel; np.take: faster than fancy indexing
        pattern = np.diff(prof).take(i0)
        pattern *= w
        pattern += prof.take(i0)
        pattern = _run("camera_pattern", pattern, optics, ctx)
        out.append(form_image(parts, pattern, optics, noise_rng, scale))
    return out


def optical_image(irradiance_parts: tuple, pattern: np.ndarray, optics, scale: int = 1) -> np.ndarray:
    """The image the camera pixels integrate: ``E = base + modulated * pattern`` through the camera
    optics, averaged over ``scale`` x ``scale`` blocks. Float (H, W), gray levels, not saturated."""
    base, modulated = irradiance_parts
    # In-place steps compute exactly E = base + modulated * pattern without temporaries.
    E = modulated * pattern
    E += base
    E = _run("camera_optics", E, optics, Context(scale=scale))
    if scale > 1:
        H, W = E.shape[0] // scale, E.shape[1] // scale
        E = E.reshape(H, scale, W, scale).mean(axis=(1, 3))
    return E


def sensor_image(E: np.ndarray, optics, rng) -> np.ndarray:
    """uint8 (H, W) recorded from the float image ``E`` (modified in place): the sensor effects (noise
    from ``rng``; None = noise-free), saturation at 0 and 255, the response, 8-bit quantisation."""
    ctx = Context(noise_rng=rng)
    E = _run("sensor", E, optics, ctx)
    E = np.clip(E, 0.0, 255.0, out=E)
    E = _run("response", E, optics, ctx)
    return np.rint(E, out=E).astype(np.uint8)


def form_image(irradiance_parts: tuple[np.ndarray, np.ndarray], pattern: np.ndarray, optics,
               rng: np.random.Generator | None, scale: int = 1) -> np.ndarray:
    """Camera image (uint8, H x W) from the pattern seen at each (sub)pixel.

    Parameters
    ----------
    irradiance_parts : ``(base, modulated)`` float arrays (H*scale, W*scale) in gray levels:
        ``E = base + modulated * pattern`` (:func:`surface_irradiance`).
    pattern : P(u_p) on the same grid.
    rng : noise generator (None = noise-free).
    scale : supersampling factor of the grid; blocks of scale x scale are averaged.
    """
    return sensor_image(optical_image(irradiance_parts, pattern, optics, scale), optics, rng)
