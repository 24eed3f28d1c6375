"""Image formation: projector pattern, Lambertian shading, camera blur, noise, gamma, 8-bit quantisation.

Intensity model, per camera pixel, in 8-bit gray levels before noise::

    E = gain * albedo * (ambient + lit * cos_incidence * falloff * P(u_p))
    P(u_p) = blur_p( gamma_p( q8( 0.5 + 0.5 * cos(2*pi*f*c/W_p + delta) ) ) )(u_p)

where ``c`` runs over projector columns (each DMD pixel emits a constant value when ``pixelated``),
``q8`` is the projector's 8-bit pattern quantisation, ``gamma_p`` the projector's power-law response,
``blur_p`` a Gaussian defocus in projector pixels. The camera then blurs ``E`` (Gaussian, camera
pixels), averages supersampled pixels, adds Gaussian read noise and shot noise
(variance ``noise_sigma**2 + shot_noise * E``), applies its response ``255*(x/255)**(1/camera_gamma)``,
saturates at 255 and quantises to uint8.

All parameters live in :class:`Optics`; :class:`OpticsRanges` holds a (lo, hi) range per parameter and
draws one :class:`Optics` per sample from a seeded generator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy.ndimage import gaussian_filter, gaussian_filter1d

__all__ = ["Optics", "OpticsRanges", "OPTICS_UNITS", "pattern_profile", "projector_radiance", "form_image",
           "OPTICS_LIMITS"]

# Units of the optics ranges that have one (help texts list the names from OpticsRanges itself).
OPTICS_UNITS = {"projector_blur": "projector px", "camera_blur": "camera px", "noise_sigma": "gray levels"}

# Physical range of every numeric parameter: (lowest, highest, lowest allowed, highest allowed) as
# inclusive/exclusive flags. A value outside makes garbage images (negative noise variance -> NaN ->
# zeros; gain 0 -> black), so it is refused where optics enter (from_dict / construction).
OPTICS_LIMITS = {
    "gain": (0.0, False, None, None),             # > 0 gray levels
    "ambient": (0.0, True, None, None),           # >= 0
    "albedo_plane": (0.0, False, 1.0, True),      # (0, 1]
    "albedo_object": (0.0, False, 1.0, True),
    "projector_gamma": (0.0, False, None, None),  # > 0
    "camera_gamma": (0.0, False, None, None),
    "projector_blur": (0.0, True, None, None),    # >= 0 px
    "camera_blur": (0.0, True, None, None),
    "noise_sigma": (0.0, True, None, None),       # >= 0 gray levels
    "shot_noise": (0.0, True, None, None),
    "albedo_texture": (0.0, True, None, None),    # >= 0, relative std
    "dirt": (0.0, True, 1.0, True),               # [0, 1] stained fraction
    "specular": (0.0, True, None, None),          # >= 0, relative to diffuse
    "subsurface": (0.0, True, None, None),        # >= 0 camera px
    "vignetting": (0.0, True, 1.0, False),        # [0, 1) relative fall-off at the corners
}


def _check_value(name: str, v) -> float:
    """One optics number, validated against :data:`OPTICS_LIMITS` (ValueError names the parameter)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f"optics '{name}' must be a number, got {v!r}")
    v = float(v)
    lo, lo_incl, hi, hi_incl = OPTICS_LIMITS[name]
    ok = np.isfinite(v) and (v >= lo if lo_incl else v > lo)
    if hi is not None:
        ok = ok and (v <= hi if hi_incl else v < hi)
    if not ok:
        rng = ("[" if lo_incl else "(") + f"{lo:g}, " + (f"{hi:g}" + ("]" if hi_incl else ")") if hi is not None else "inf)")
        raise ValueError(f"optics '{name}' must be in {rng}, got {v:g}")
    return v


def _check_flags(pixelated, pattern_bits) -> None:
    if not isinstance(pixelated, (bool, np.bool_)):
        raise ValueError(f"optics 'pixelated' must be true or false, got {pixelated!r}")
    if isinstance(pattern_bits, bool) or not isinstance(pattern_bits, (int, np.integer)) or not 0 <= pattern_bits <= 16:
        raise ValueError(f"optics 'pattern_bits' must be an integer in 0..16, got {pattern_bits!r}")


@dataclass
class Optics:
    """One sample's image-formation parameters.

    gain : gray levels for albedo 1 under the full-white pattern at the world origin.
    ambient : ambient light relative to the projector's full white.
    albedo_plane, albedo_object : diffuse reflectance of the reference plane and of the objects.
    projector_gamma : emitted = pattern**projector_gamma (1 = linear projector).
    camera_gamma : recorded = 255*(E/255)**(1/camera_gamma) (1 = linear sensor).
    projector_blur : defocus sigma in projector pixels (0 = sharp).
    camera_blur : optical blur sigma in camera pixels (0 = sharp).
    noise_sigma : Gaussian read noise, gray levels.
    shot_noise : shot-noise variance per gray level of signal (gray levels).
    pixelated : the projector shows one constant value per DMD column (True) or an ideal continuous cosine.
    pattern_bits : bit depth of the projected pattern (8 for a DLP projector; 0 = no quantisation).
    albedo_texture, dirt, specular, subsurface, vignetting : appearance effects, see :mod:`fppsim.appearance`
        (relative albedo std, stained fraction, specular lobe strength, fringe blur sigma on objects in camera
        px, relative fall-off at the corners); 0 = off.
    """

    gain: float = 150.0
    ambient: float = 0.05
    albedo_plane: float = 0.5
    albedo_object: float = 0.8
    projector_gamma: float = 1.0
    camera_gamma: float = 1.0
    projector_blur: float = 1.0
    camera_blur: float = 0.5
    noise_sigma: float = 1.0
    shot_noise: float = 0.05
    pixelated: bool = True
    pattern_bits: int = 8
    # appearance beyond the Lambertian model (fppsim.appearance); 0 = off
    albedo_texture: float = 0.0
    dirt: float = 0.0
    specular: float = 0.0
    subsurface: float = 0.0
    vignetting: float = 0.0

    def __post_init__(self):
        for name in OPTICS_LIMITS:
            setattr(self, name, _check_value(name, getattr(self, name)))
        _check_flags(self.pixelated, self.pattern_bits)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Optics":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown optics parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)

    def noise_free(self) -> "Optics":
        """The same optics without noise (for exactness checks)."""
        d = self.to_dict()
        d.update(noise_sigma=0.0, shot_noise=0.0)
        return Optics(**d)


@dataclass
class OpticsRanges:
    """Per-sample randomisation: each numeric field is a (lo, hi) uniform range (lo == hi fixes it).

    The defaults give dark images like the real figshare sample (8-bit median about 40, 99th
    percentile about 185): bright plaster objects on a darker plane.
    """

    gain: tuple[float, float] = (190.0, 270.0)
    ambient: tuple[float, float] = (0.005, 0.04)
    albedo_plane: tuple[float, float] = (0.25, 0.36)
    albedo_object: tuple[float, float] = (0.80, 1.00)
    projector_gamma: tuple[float, float] = (1.0, 1.0)
    camera_gamma: tuple[float, float] = (1.0, 1.0)
    projector_blur: tuple[float, float] = (0.8, 1.6)
    camera_blur: tuple[float, float] = (0.3, 0.8)
    noise_sigma: tuple[float, float] = (0.5, 1.5)
    shot_noise: tuple[float, float] = (0.02, 0.08)
    pixelated: bool = True
    pattern_bits: int = 8
    # appearance (fppsim.appearance), off by default: not yet measured on real data
    albedo_texture: tuple[float, float] = (0.0, 0.0)
    dirt: tuple[float, float] = (0.0, 0.0)
    specular: tuple[float, float] = (0.0, 0.0)
    subsurface: tuple[float, float] = (0.0, 0.0)
    vignetting: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        for name in OPTICS_LIMITS:
            v = getattr(self, name)
            if not isinstance(v, (tuple, list)) or len(v) != 2:
                raise ValueError(f"optics range '{name}' must be a number or [lo, hi], got {v!r}")
            lo, hi = _check_value(name, v[0]), _check_value(name, v[1])
            if lo > hi:
                raise ValueError(f"optics range '{name}' must have lo <= hi, got [{lo:g}, {hi:g}]")
            setattr(self, name, (lo, hi))
        _check_flags(self.pixelated, self.pattern_bits)

    def sample(self, rng: np.random.Generator) -> Optics:
        """Draw one :class:`Optics` (fields in declaration order, one uniform draw each)."""
        values = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple):
                lo, hi = float(v[0]), float(v[1])
                values[f.name] = lo if lo == hi else float(rng.uniform(lo, hi))
            else:
                values[f.name] = v
        return Optics(**values)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def range_names(cls) -> list[str]:
        """Names of the (lo, hi) range fields, in declaration order (what --optics/--sweep accept)."""
        return [f.name for f in fields(cls) if isinstance(f.default, tuple)]

    @classmethod
    def from_dict(cls, d: dict) -> "OpticsRanges":
        known = {f.name: f for f in fields(cls)}
        out = {}
        for k, v in d.items():
            if k not in known:
                raise ValueError(f"unknown optics parameter '{k}' (known: {', '.join(known)})")
            if k in OPTICS_LIMITS:
                if isinstance(v, (list, tuple)):
                    if len(v) != 2:
                        raise ValueError(f"optics range '{k}' must be a number or [lo, hi], got {list(v)}")
                    v = (_check_value(k, v[0]), _check_value(k, v[1]))
                else:
                    v = (_check_value(k, v),) * 2
            out[k] = v
        return cls(**out)

    @classmethod
    def fixed(cls, optics: Optics) -> "OpticsRanges":
        """Ranges that always return ``optics``."""
        d = optics.to_dict()
        return cls(**{k: v if k in ("pixelated", "pattern_bits") else (v, v) for k, v in d.items()})


OVERSAMPLE = 8  # samples per projector pixel for the 1-D pattern profile


def pattern_profile(width: int, periods: float, shift: float, optics: Optics) -> tuple[np.ndarray, np.ndarray]:
    """Emitted projector radiance along projector columns, in [0, 1].

    Returns ``(u, value)``: sample positions in projector pixel coordinates (from -0.5 to width-0.5)
    and the emitted, defocused pattern there. The pattern varies only along columns, so the whole
    projector image is this 1-D profile.
    """
    n = width * OVERSAMPLE
    u = (np.arange(n) + 0.5) / OVERSAMPLE - 0.5
    where = np.rint(u) if optics.pixelated else u  # DMD column centre or continuous position
    p = 0.5 + 0.5 * np.cos(2.0 * np.pi * periods * where / width + shift)
    if optics.pattern_bits:
        levels = 2 ** int(optics.pattern_bits) - 1
        p = np.rint(p * levels) / levels
    p = p ** optics.projector_gamma
    if optics.projector_blur > 0:
        p = gaussian_filter1d(p, optics.projector_blur * OVERSAMPLE, mode="nearest")
    return u, p


def projector_radiance(u_p: np.ndarray, width: int, periods: float, shift: float, optics: Optics) -> np.ndarray:
    """Pattern value P(u_p) in [0, 1] at projector columns ``u_p`` (any shape, float)."""
    u, p = pattern_profile(width, periods, shift, optics)
    return np.interp(u_p, u, p)


def form_image(irradiance_parts: tuple[np.ndarray, np.ndarray], pattern: np.ndarray, optics: Optics,
               rng: np.random.Generator | None, scale: int = 1) -> np.ndarray:
    """Camera image (uint8, H x W) from the pattern seen at each (sub)pixel.

    Parameters
    ----------
    irradiance_parts : ``(base, modulated)`` float arrays (H*scale, W*scale) in gray levels:
        ``E = base + modulated * pattern`` (``base = gain*albedo*ambient``,
        ``modulated = gain*albedo*lit*cos_incidence*falloff``).
    pattern : P(u_p) on the same grid.
    rng : noise generator (None = noise-free).
    scale : supersampling factor of the grid; blocks of scale x scale are averaged.
    """
    base, modulated = irradiance_parts
    # In-place steps below compute exactly E = base + modulated * pattern etc. without temporaries.
    E = modulated * pattern
    E += base
    if optics.camera_blur > 0:
        E = gaussian_filter(E, optics.camera_blur * scale, mode="nearest")
    if scale > 1:
        H, W = E.shape[0] // scale, E.shape[1] // scale
        E = E.reshape(H, scale, W, scale).mean(axis=(1, 3))
    if rng is not None and (optics.noise_sigma > 0 or optics.shot_noise > 0):
        sd = np.maximum(E, 0.0)
        sd *= optics.shot_noise
        sd += optics.noise_sigma ** 2
        np.sqrt(sd, out=sd)  # sqrt(noise_sigma**2 + shot_noise * max(E, 0))
        noise = rng.standard_normal(E.shape, dtype=np.float32)
        if noise.dtype == sd.dtype:
            noise *= sd  # a fresh array: scaled in place, the same values as noise * sd
        else:
            noise = noise * sd  # (float64 images: the product in float64, as ever)
        E += noise
    E = np.clip(E, 0.0, 255.0, out=E)
    if optics.camera_gamma != 1.0:
        E = 255.0 * (E / 255.0) ** (1.0 / optics.camera_gamma)
    return np.rint(E, out=E).astype(np.uint8)
