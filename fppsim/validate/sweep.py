"""Optics sweeps: the grid of settings ``fppsim validate-psp --sweep`` renders, and the generation
settings of an existing dataset (to re-render its scenes under each setting).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import fields

from fppsim.errors import ValidateError, ValidateUsageError
from fppsim.rendering.optics import OpticsRanges
from fppsim.rendering.synth import SynthConfig

__all__ = ["SWEEP_ALIASES", "DEFAULT_SWEEP", "parse_sweep", "sweep_settings", "ranges_with", "config_from_settings"]

SWEEP_ALIASES = {"noise": "noise_sigma", "gamma": "projector_gamma", "blur": "projector_blur"}
DEFAULT_SWEEP = ("noise=0,0.5,1,2", "gamma=1,2.2")


# ====================================================================== sweep
def _optics_fields() -> dict:

    return {f.name: getattr(OpticsRanges(), f.name) for f in fields(OpticsRanges)}


def parse_sweep(items) -> list[tuple[str, list]]:
    """``["noise=0,0.5", "gamma=1,2.2"]`` -> ``[("noise_sigma", [0.0, 0.5]), ("projector_gamma", [1.0, 2.2])]``.

    An empty list means :data:`DEFAULT_SWEEP`. Raises :class:`ValidateUsageError` (a :class:`ValidateError`, exit 2) on unknown names, bad
    values or a name given twice.
    """
    items = list(items) or list(DEFAULT_SWEEP)
    known = _optics_fields()
    out, seen = [], set()
    for item in items:
        key, sep, vals = str(item).partition("=")
        key = key.strip()
        name = SWEEP_ALIASES.get(key, key)
        if not sep or not vals.strip():
            raise ValidateUsageError(f"--sweep expects NAME=V1,V2,..., got '{item}'")
        if name not in known:
            raise ValidateUsageError(f"--sweep: unknown optics parameter '{key}' (use noise, gamma, blur or one of: "
                                f"{', '.join(known)})")
        if name in seen:
            raise ValidateUsageError(f"--sweep: '{key}' given twice")
        seen.add(name)
        values = []
        for v in vals.split(","):
            try:
                x = float(v)
            except ValueError:
                raise ValidateUsageError(f"--sweep {key}: '{v}' is not a number") from None
            if not math.isfinite(x) or x < 0 or (name.endswith("gamma") and x <= 0):
                raise ValidateUsageError(f"--sweep {key}: {v} is out of range (>= 0; gammas > 0)")
            default = known[name]
            if isinstance(default, bool):
                x = bool(x)
            elif isinstance(default, int):
                x = int(round(x))
            if x not in values:
                values.append(x)
        out.append((name, values))
    return out


def sweep_settings(grid: list[tuple[str, list]], base: dict | None = None) -> list[tuple[str, dict]]:
    """All combinations (the grid) as ``(folder_name, {field: value})``.

    ``base`` holds the user's explicit optics overrides; with ``noise_sigma`` swept, ``shot_noise`` is
    fixed to 0 unless swept or overridden.
    """
    base = base or {}
    names = [n for n, _ in grid]
    out = []
    for combo in itertools.product(*(v for _, v in grid)):
        fixed = dict(zip(names, combo))
        if "noise_sigma" in fixed and "shot_noise" not in fixed and "shot_noise" not in base:
            fixed["shot_noise"] = 0.0
        label = "__".join(f"{n}={_num(v)}" for n, v in zip(names, combo))
        out.append((label, fixed))
    return out


def _num(v) -> str:
    return str(v) if isinstance(v, bool) else f"{v:g}"


def ranges_with(ranges, fixed: dict):

    d = ranges.to_dict()
    d.update(fixed)
    return OpticsRanges.from_dict(d)


# ====================================================================== sources
def config_from_settings(settings: dict, where="dataset.json"):
    """SynthConfig, meshes, seed, noise_free of a dataset's ``dataset.json`` (to re-render its scenes);
    :class:`ValidateError` naming ``where`` when it cannot be read back (a data problem, not a usage error)."""
    try:
        config = SynthConfig.from_settings(settings)
        return config, list(settings["meshes"]), int(settings["seed"]), bool(settings.get("noise_free", False))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValidateError(f"{where} cannot be turned back into generation settings ({exc})") from None


