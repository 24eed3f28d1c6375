"""Declarations of the optics parameters and effects, and the classes derived from them.

Every effect of the image formation declares its parameters once, in its own module, as :class:`Param`
(name, default, randomisation range, validity limits) inside an :class:`Effect` (the stage step it
performs and where it acts, one of :data:`SITES`). :class:`OpticsModel` derives everything else from
an ordered list of effects: the per-sample parameters (``Optics``), their per-sample randomisation
(``OpticsRanges``) and the limits table. :mod:`fppsim.rendering.optics` builds the default model from
:data:`fppsim.rendering.optics.EFFECTS`; a test can build another one with a toy effect added.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field, fields, make_dataclass
from functools import lru_cache
from typing import Any, Callable

import numpy as np
from fppsim.errors import InputError

__all__ = ["Param", "Effect", "Context", "OpticsModel", "SITES", "interval"]

# Where an effect acts, in the order the stage visits them, with what ``Effect.apply(value, optics, ctx)``
# receives and returns there. Effects of one site run in the order of the model's effect list.
SITES = {
    # projector: the 1-D pattern along projector columns, float64, ctx.scale samples per projector pixel
    "projector_pixels": "positions (n,) in projector px at which the cosine 0.5 + 0.5 cos(...) is evaluated",
    "pattern_levels": "pattern (n,) in [0, 1] as the projector encodes it",
    "projector_response": "pattern (n,) as the projector emits it",
    "projector_optics": "pattern (n,) after the projector lens",
    # camera grid (H, W) (x ctx.scale when supersampled), gray levels
    "irradiance": "(base, modulated) float64 gray levels, E = base + modulated * pattern (None before the first)",
    "albedo": "multiplier (H, W) float64 of both irradiance parts (starts at 1)",
    "projector_light": "modulated (H, W) float64, after the albedo multiplier",
    "camera_pattern": "pattern (H, W) float32 as the camera sees it on the surfaces",
    "camera_optics": "image E (H, W) before the pixels integrate it",
    "sensor": "image E (H, W) per camera pixel, before saturation (ctx.noise_rng: None = noise-free)",
    "response": "image E (H, W) in [0, 255] after saturation, before 8-bit quantisation",
}

Limits = tuple  # (lo, lo_inclusive, hi or None, hi_inclusive), the format of OPTICS_LIMITS


@lru_cache(maxsize=None)
def interval(text: str) -> Limits:
    """``"(0, inf)"``, ``"[0, 1)"``, ... -> ``(lo, lo_inclusive, hi, hi_inclusive)`` (hi None: no bound)."""
    m = re.fullmatch(r"\s*([\[(])\s*([-+.\w]+)\s*,\s*([-+.\w]+)\s*([\])])\s*", text)
    if not m:
        raise InputError(f"interval must look like '[0, 1)' or '(0, inf)', got {text!r}")
    hi = None if m[3] == "inf" else float(m[3])
    return float(m[2]), m[1] == "[", hi, None if hi is None else m[4] == "]"


def _describe(limits: Limits) -> str:
    lo, lo_incl, hi, hi_incl = limits
    return ("[" if lo_incl else "(") + f"{lo:g}, " + (f"{hi:g}" + ("]" if hi_incl else ")") if hi is not None else "inf)")


@dataclass(frozen=True)
class Param:
    """One optics parameter, declared once.

    name : field of ``Optics`` and ``OpticsRanges`` (and ``--optics NAME=LO,HI``).
    default : its value in ``Optics()``.
    sample : the ``(lo, hi)`` range ``OpticsRanges()`` draws it from per sample (uniform; lo == hi fixes
        it); ``None`` for a setting (bool/int), which ``OpticsRanges`` holds as a fixed value.
    limits : the valid values of a number, as an interval ``"(0, inf)"``, ``"[0, 1]"``, ... (refused
        outside: e.g. a negative noise variance would make NaN images).
    check, expect : a setting's validity test, and what the error says it must be.
    off : the value at which the parameter does nothing; ``None``: it always acts.
    unit : shown in ``--help`` beside the name (only where the name leaves it open).
    doc : one line for the ``Optics`` docstring.
    """

    name: str
    default: Any
    sample: tuple[float, float] | None = None
    limits: str | None = None
    off: Any = None
    unit: str = ""
    doc: str = ""
    check: Callable[[Any], bool] | None = None
    expect: str = ""

    def __post_init__(self):
        if (self.sample is None) != (self.limits is None) or (self.sample is None) == (self.check is None):
            raise InputError(f"optics parameter '{self.name}' must declare sample + limits (a number) "
                             f"or check (a setting)")

    @property
    def is_number(self) -> bool:
        return self.sample is not None

    def validate(self, v):
        """``v`` as stored (a float for numbers); ValueError naming the parameter when invalid."""
        if not self.is_number:
            if not self.check(v):
                raise InputError(f"optics '{self.name}' must be {self.expect}, got {v!r}")
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InputError(f"optics '{self.name}' must be a number, got {v!r}")
        v = float(v)
        lo, lo_incl, hi, hi_incl = limits = interval(self.limits)
        ok = np.isfinite(v) and (v >= lo if lo_incl else v > lo)
        if hi is not None:
            ok = ok and (v <= hi if hi_incl else v < hi)
        if not ok:
            raise InputError(f"optics '{self.name}' must be in {_describe(limits)}, got {v:g}")
        return v


@dataclass
class Context:
    """What a stage step may need besides its value and the optics.

    geom : :class:`fppsim.rendering.render.Geometry` of the camera grid (None on the projector side).
    rig : the :class:`fppsim.geometry.rig.Rig`.
    scale : samples per pixel of the grid the value lives on (supersampling factor on the camera grid,
        :data:`fppsim.rendering.optics.projector.OVERSAMPLE` on the projector profile): sizes in pixels times this.
    rng : generator of the appearance effects (texture, dirt, ...).
    noise_rng : generator of the camera noise (None = noise-free).
    """

    geom: Any = None
    rig: Any = None
    scale: int = 1
    rng: np.random.Generator | None = None
    noise_rng: Any = None


@dataclass(frozen=True)
class Effect:
    """One optics effect: its parameters and the step of the stage it performs.

    name : short name (documentation).
    site : where it acts, a key of :data:`SITES`.
    params : its parameters, fields of ``Optics`` in this order.
    apply : ``apply(value, optics, ctx) -> value`` with ``value`` as :data:`SITES` says for ``site`` and
        ``ctx`` a :class:`Context`; may work in place on ``value`` where the site allows (the images).
    on : ``on(optics) -> bool``, whether the step runs; default: some parameter differs from its ``off``.
    margin : ``margin(ranges) -> float``, the camera pixels beyond the image border the step reads (a
        blur's reach) for any optics drawn from ``OpticsRanges`` ``ranges``: the scene is rendered that
        much larger and cropped (a clamped edge would shift the fringes of the outer columns).
    """

    name: str
    site: str
    params: tuple[Param, ...]
    apply: Callable[[Any, Any, Context], Any]
    on: Callable[[Any], bool] | None = None
    margin: Callable[[Any], float] | None = None

    def __post_init__(self):
        if self.site not in SITES:
            raise InputError(f"optics effect '{self.name}': unknown site '{self.site}' (known: {', '.join(SITES)})")

    def is_on(self, optics) -> bool:
        if self.on is not None:
            return bool(self.on(optics))
        return any(p.off is None or getattr(optics, p.name) != p.off for p in self.params)


class _OpticsMethods:
    """Methods of the derived ``Optics`` classes (``model``: their :class:`OpticsModel`)."""

    model: "OpticsModel"

    def __post_init__(self):
        # numbers first, then settings: the first error reported is the same as ever
        for p in self.model.numbers + self.model.settings:
            setattr(self, p.name, p.validate(getattr(self, p.name)))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise InputError(f"unknown optics parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)

    def noise_free(self):
        """The same optics without noise (the sensor effects off; for exactness checks)."""
        d = self.to_dict()
        d.update({p.name: p.off for e in self.model.at("sensor") for p in e.params})
        return type(self)(**d)


class _RangesMethods:
    """Methods of the derived ``OpticsRanges`` classes."""

    model: "OpticsModel"

    def __post_init__(self):
        for p in self.model.numbers:
            v = getattr(self, p.name)
            if not isinstance(v, (tuple, list)) or len(v) != 2:
                raise InputError(f"optics range '{p.name}' must be a number or [lo, hi], got {v!r}")
            lo, hi = p.validate(v[0]), p.validate(v[1])
            if lo > hi:
                raise InputError(f"optics range '{p.name}' must have lo <= hi, got [{lo:g}, {hi:g}]")
            setattr(self, p.name, (lo, hi))
        for p in self.model.settings:
            p.validate(getattr(self, p.name))

    def sample(self, rng: np.random.Generator):
        """Draw one ``Optics`` (fields in declaration order, one uniform draw each unless lo == hi)."""
        values = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple):
                lo, hi = float(v[0]), float(v[1])
                values[f.name] = lo if lo == hi else float(rng.uniform(lo, hi))
            else:
                values[f.name] = v
        return self.model.Optics(**values)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def render_margin(self) -> int:
        """Camera pixels to render beyond each image border: the widest reach of the effects (int)."""
        return int(np.ceil(max([e.margin(self) for e in self.model.effects if e.margin], default=0.0)))

    @classmethod
    def range_names(cls) -> list[str]:
        """Names of the (lo, hi) range fields, in declaration order (what --optics/--sweep accept)."""
        return [p.name for p in cls.model.numbers]

    @classmethod
    def from_dict(cls, d: dict):
        known = cls.model.params
        out = {}
        for k, v in d.items():
            if k not in known:
                raise InputError(f"unknown optics parameter '{k}' (known: {', '.join(known)})")
            if known[k].is_number:
                if isinstance(v, (list, tuple)):
                    if len(v) != 2:
                        raise InputError(f"optics range '{k}' must be a number or [lo, hi], got {list(v)}")
                    v = (known[k].validate(v[0]), known[k].validate(v[1]))
                else:
                    v = (known[k].validate(v),) * 2
            out[k] = v
        return cls(**out)

    @classmethod
    def fixed(cls, optics):
        """Ranges that always return ``optics``."""
        return cls(**{k: (v, v) if cls.model.params[k].is_number else v for k, v in optics.to_dict().items()})


class OpticsModel:
    """The image-formation model of an ordered list of effects, and the classes derived from it.

    Attributes
    ----------
    effects : the effects; their parameters become the fields of ``Optics`` in this order, which is
        also the order of the random draws of ``OpticsRanges.sample`` (append new effects at the end).
    params : {name: Param}; numbers / settings: the numeric parameters and the flags.
    limits : {name: (lo, lo_inclusive, hi or None, hi_inclusive)} of the numbers.
    units : {name: unit} of the numbers that show one in ``--help``.
    Optics : dataclass, one value per parameter (validated on construction).
    OpticsRanges : dataclass, a ``(lo, hi)`` range per number and the settings; ``sample(rng)`` draws
        an ``Optics``.

    ``module`` is where the two classes can be imported from (pickling, e.g. to worker processes).
    """

    def __init__(self, effects, module: str | None = None):
        self.effects = tuple(effects)
        params = [p for e in self.effects for p in e.params]
        self.params = {}
        for p in params:
            if p.name in self.params:
                raise InputError(f"optics parameter '{p.name}' is declared twice")
            for v in (p.default, *(p.sample if p.is_number else ())):
                p.validate(v)
            self.params[p.name] = p
        self.numbers = [p for p in params if p.is_number]
        self.settings = [p for p in params if not p.is_number]
        self.limits = {p.name: interval(p.limits) for p in self.numbers}
        self.units = {p.name: p.unit for p in self.numbers if p.unit}
        self._at = {s: tuple(e for e in self.effects if e.site == s) for s in SITES}
        ns = {"model": self, "__module__": module or __name__}
        self.Optics = make_dataclass(
            "Optics", [(p.name, float if p.is_number else type(p.default), field(default=p.default)) for p in params],
            bases=(_OpticsMethods,), namespace=ns | {"__doc__": self._doc_optics()})
        self.OpticsRanges = make_dataclass(
            "OpticsRanges", [(p.name, tuple[float, float] if p.is_number else type(p.default),
                              field(default=tuple(map(float, p.sample)) if p.is_number else p.default)) for p in params],
            bases=(_RangesMethods,), namespace=ns | {"__doc__": self._doc_ranges()})
        # Python >= 3.12's make_dataclass sets __module__ to its caller (this module) over the namespace's;
        # pickling (spawned generator workers) looks the classes up where they are published
        self.Optics.__module__ = self.OpticsRanges.__module__ = ns["__module__"]

    def at(self, site: str) -> tuple[Effect, ...]:
        """The effects acting at ``site``, in order."""
        return self._at[site]

    def _doc_optics(self) -> str:
        lines = ["One sample's image-formation parameters (declared by the effects of :mod:`fppsim.rendering.optics`).", ""]
        for p in self.params.values():
            lines.append(f"{p.name} : {p.doc} Default {p.default!r}"
                         + (f", valid {_describe(interval(p.limits))}." if p.is_number else "."))
        return "\n".join(lines)

    def _doc_ranges(self) -> str:
        lines = ["Per-sample randomisation: each number is a (lo, hi) uniform range (lo == hi fixes it); the",
                 "settings are fixed values. The defaults give dark images like the real figshare sample (8-bit",
                 "median about 40, 99th percentile about 185): bright plaster objects on a darker plane.", ""]
        lines += [f"{p.name} : default {list(p.sample) if p.is_number else p.default!r}" for p in self.params.values()]
        return "\n".join(lines)
