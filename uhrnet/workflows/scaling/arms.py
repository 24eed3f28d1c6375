"""The scaling study's arms: the arms file (``pipelines/scaling_arms.yaml``) read and checked, what an arm
is called in tables and records, the folder of one (arm, seed), its sim2real variant and its optimizer steps.

Arms file (YAML/JSON): ``{defaults: {...}, arms: [{name, description, series, count, epochs, batch_size, lr,
base_channels, model, loss, workers, scale, generate, train}, ...]}``; ``defaults`` apply to every arm,
``generate`` / ``train`` are flag strings (or lists) of ``fppsim generate`` / ``uhrnet train``. ``series``:
the figures the arm is a point of (``samples``: x = its sample count; ``steps``: x = its optimizer steps).
"""

from __future__ import annotations

import math
import shlex
from dataclasses import replace
from pathlib import Path
from typing import Mapping

from uhrnet.data.splits import MIN_REFERENCE_SPLIT, split_indices
from uhrnet.workflows.sim2real import Sim2RealConfig
from uhrnet.workflows.sim2real.variants import FlagReader, VariantFlags, variant_from_flags
from uhrnet.workflows.stages import read_config_file

__all__ = ["UsageProblem", "CONFIG_FLAGS", "ARM_KEYS", "SERIES", "load_arms", "select_arms", "arm_config",
           "seed_folder", "variant_of", "steps_of", "arm_line", "arm_label", "arm_key"]

# arm keys that are Sim2RealConfig fields, with their `uhrnet sim2real` flags
CONFIG_FLAGS = {"scale": "--scale", "count": "--count", "epochs": "--epochs", "batch_size": "--batch-size",
                "lr": "--lr", "base_channels": "--base-channels", "model": "--model", "loss": "--loss",
                "workers": "--workers"}
ARM_KEYS = {"name", "description", "series", "generate", "train", *CONFIG_FLAGS}
SERIES = {"samples": ("count", "synthetic samples generated"), "steps": ("steps", "optimizer steps")}


class UsageProblem(Exception):
    """Bad input, found before anything runs (``pipelines/scaling.py`` exits 2)."""


def _flags(value, where: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            raise UsageProblem(f"{where}: {exc}") from None
    if isinstance(value, list):
        return [str(v) for v in value]
    raise UsageProblem(f"{where}: expected a flag string or a list, got {type(value).__name__}")


def _resolve_paths(flags: list[str], root: Path | None) -> list[str]:
    """Relative paths in flags that do not exist from the current folder but do from ``root`` (the
    repository root: e.g. ``assets/figshare_depth_rig.json``) become absolute."""
    out = []
    for f in flags:
        if root is not None and not f.startswith("-") and not Path(f).is_absolute() and not Path(f).exists() \
                and (root / f).exists():
            f = str(root / f)
        out.append(f)
    return out


def _typed(key: str, value, where: str):
    """An arm's sim2real option as its flag would parse it (YAML reads ``5e-4`` as text, ``lr: 5e-4`` is meant)."""
    kind = float if key == "lr" else str if key in ("scale", "model", "loss") else int
    try:
        if kind is int and (isinstance(value, bool) or float(value) != int(float(value))):
            raise ValueError
        return kind(int(float(value))) if kind is int else kind(value)
    except (TypeError, ValueError):
        what = {float: "a number", int: "an integer", str: "text"}[kind]
        raise UsageProblem(f"{where}: {key} must be {what}, got {value!r}") from None


def load_arms(path: str | Path, root: str | Path | None = None) -> list[dict]:
    """The arms of an arms file (module docstring), each with ``generate`` / ``train`` as flag lists (relative
    paths in them that exist only from ``root`` made absolute), ``series`` as a list and the ``defaults``
    applied; :class:`UsageProblem` names what is wrong."""
    p, root = Path(path), Path(root) if root is not None else None
    doc = read_config_file(p, "arms file", UsageProblem)
    if not isinstance(doc, dict) or not isinstance(doc.get("arms"), list) or not doc["arms"]:
        raise UsageProblem(f"{p}: expected a mapping with a non-empty list 'arms' (and optional 'defaults')")
    unknown = set(doc) - {"arms", "defaults"}
    defaults = doc.get("defaults") or {}
    if unknown or not isinstance(defaults, dict):
        raise UsageProblem(f"{p}: top-level keys are 'arms' and 'defaults' (a mapping), got {sorted(doc)}")
    arms, names = [], set()
    for i, item in enumerate(doc["arms"]):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise UsageProblem(f"{p}: arm {i} must be a mapping with a 'name'")
        item = {**defaults, **item}
        name = item["name"]
        bad = sorted(set(item) - ARM_KEYS)
        if bad:
            raise UsageProblem(f"{p}: arm {name!r} has unknown keys {bad} (known: {sorted(ARM_KEYS)})")
        if not name or name in names or any(c in name for c in "/\\ \t:|") or name.startswith("."):
            raise UsageProblem(f"{p}: arm name {name!r} must be a unique word without slashes, spaces, ':' or '|'")
        names.add(name)
        series = item.get("series") or []
        series = [series] if isinstance(series, str) else list(series)
        if any(s not in SERIES for s in series):
            raise UsageProblem(f"{p}: arm {name!r}: series must be of {sorted(SERIES)}, got {series}")
        arm = {"name": name, "description": str(item.get("description") or ""), "series": series,
               "generate": _resolve_paths(_flags(item.get("generate"), f"{p}: arm {name!r}: generate"), root),
               "train": _resolve_paths(_flags(item.get("train"), f"{p}: arm {name!r}: train"), root)}
        for key in CONFIG_FLAGS:
            if item.get(key) is not None:
                arm[key] = _typed(key, item[key], f"{p}: arm {name!r}")
        arms.append(arm)
    return arms


def select_arms(arms: list[dict], names: list[str] | None, arms_file) -> list[dict]:
    """The arms ``names`` (``--arms``) of ``arms``, in that order; every arm without names. An unknown or
    repeated name is refused (:class:`UsageProblem`, listing the arms of ``arms_file``)."""
    if not names:
        return arms
    by_name = {a["name"]: a for a in arms}
    unknown = [n for n in names if n not in by_name]
    if unknown or len(set(names)) != len(names):
        raise UsageProblem(f"--arms: unknown or repeated arm(s) {', '.join(unknown) or 'repeated'} "
                           f"(arms of {arms_file}: {', '.join(by_name)})")
    return [by_name[n] for n in names]


def arm_config(arm: dict, seed: int, options,
               commands: Mapping[str, FlagReader]) -> tuple[Sim2RealConfig, list[str]]:
    """``(Sim2RealConfig, argv)``: the sim-to-real experiment of ``arm`` at training ``seed`` (its one variant
    ``s<seed>``, in ``OUT/<arm>``) and the ``uhrnet sim2real`` command line that runs exactly the same.
    ``options``: the study's options for every arm (``pipelines/scaling.py``'s parsed flags ``out``, ``real``,
    ``real_phase``, ``meshes``, ``device``, ``workers``, ``resize``, ``threads``, ``no_figures``); ``commands``:
    how ``--variant`` flags are read (the command layer's parsers, ``uhrnet.cli.variant_commands()``)."""
    out = Path(options.out) / arm["name"]
    given = {k: arm[k] for k in CONFIG_FLAGS if k in arm}
    if options.device:
        given["device"] = options.device
    if options.workers is not None:
        given["workers"] = options.workers
    cfg = Sim2RealConfig(out=str(out), real=list(options.real), meshes=list(options.meshes),
                         real_phase=list(options.real_phase), figures=not options.no_figures, **given)
    train = (list(arm["train"]) + (["--resize", options.resize] if options.resize else [])
             + (["--threads", str(options.threads)] if options.threads else []) + ["--seed", str(seed)])
    flags = VariantFlags(f"s{seed}", list(arm["generate"]), train)
    variant = variant_from_flags(cfg, flags, commands)
    cfg = replace(cfg, variants=[variant])
    argv = ["uhrnet", "sim2real", "--real", *cfg.real, "--out", str(out), "--meshes", *cfg.meshes]
    for key, flag in CONFIG_FLAGS.items():
        if key in given:
            argv += [flag, str(given[key])]
    if "device" in given:
        argv += ["--device", given["device"]]
    if cfg.real_phase:
        argv += ["--real-phase", *cfg.real_phase]
    if options.no_figures:
        argv.append("--no-figures")
    argv += ["--variant", f"{flags.name}: {shlex.join(flags.generate)} | {shlex.join(flags.train)}"]
    return cfg, argv


def seed_folder(out: Path, arm: dict, seed: int) -> Path:
    """``OUT/<arm>/s<seed>``: the folder of one (arm, seed)."""
    return Path(out) / arm["name"] / f"s{seed}"


def variant_of(cfg, seed: int):
    """The sim2real variant of training ``seed`` (``s<seed>``) in ``cfg``."""
    return next(v for v in cfg.variants if v.name == f"s{seed}")


def steps_of(cfg, variant) -> int:
    """Optimizer steps of the variant's training run: epochs x ceil(draws per epoch / batch size), the draws
    being ``--samples-per-epoch`` or the reference split's training samples (80 % of the count)."""
    tr = variant.train
    epochs, batch = int(tr.get("epochs") or cfg.epochs), int(tr.get("batch_size") or cfg.batch_size)
    draws = tr.get("samples_per_epoch")
    if not draws:
        draws = len(split_indices(cfg.count, "train")) if cfg.count >= MIN_REFERENCE_SPLIT else cfg.count
    return epochs * math.ceil(int(draws) / batch)


def arm_line(arm: dict, cfg, variant) -> str:
    """An arm in one line (``--list``): its name, samples, optimizer steps, series and description."""
    return (f"{arm['name']}: {cfg.count} samples, {steps_of(cfg, variant)} steps, series "
            f"{', '.join(arm['series']) or '-'}; {arm['description']}")


def arm_label(entry: dict) -> str:
    """An arm's name in tables and figures: its name, the resize and a device other than the CPU."""
    return entry["name"] + (f" @{entry['resize']}" if entry.get("resize") else "") + \
        (f" [{entry['device']}]" if entry.get("device", "cpu") != "cpu" else "")


def arm_key(entry: dict) -> tuple:
    """What a study record keys an arm by: (name, resize, device)."""
    return entry["name"], entry.get("resize"), entry.get("device", "cpu")
