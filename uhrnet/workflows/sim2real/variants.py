"""The variant grammar of ``uhrnet sim2real``: an ablation row written as command-line flags -> a :class:`Variant`.

``--variant SPEC`` (:data:`VARIANT_SYNTAX`, :func:`parse_variant`) and ``--ablation FILE``
(:func:`load_variants`) give :class:`VariantFlags`: the row's name, its extra ``fppsim generate`` /
``uhrnet train`` / ``uhrnet adapt`` flags and its refinement methods. :func:`variant_from_flags` appends
each side to the recipe's command line (:func:`generate_flags`, :func:`train_flags`), reads both through
that command's own parser and keeps the config fields that differ: the :class:`Variant`'s overrides. The
parsers are the command layer's: it passes them in (:class:`FlagReader`; ``uhrnet.cli.variant_commands()``),
so nothing here imports a command line. :func:`recipe_commands` writes a variant's stages back as the
command lines that run them (``report.json``'s ``recipe``).

    from uhrnet.cli import variant_commands
    from uhrnet.workflows.sim2real.variants import parse_variant, variant_from_flags

    variant = variant_from_flags(cfg, parse_variant("ph: | --head phase | refine relief"), variant_commands())
"""

from __future__ import annotations

import contextlib
import io
import argparse
import shlex
from pathlib import Path
from typing import Callable, Mapping, NamedTuple

from uhrnet.errors import Sim2RealError, UsageError
from uhrnet.run_folder import LAST_PT
from uhrnet.workflows.sim2real.config import SCALES, Variant, generate_workers
from uhrnet.workflows.sim2real.run import adapt_config, variant_error
from uhrnet.workflows.stages import read_config_file

__all__ = ["VariantFlags", "VARIANT_SYNTAX", "FlagReader", "parse_variant", "load_variants", "generate_flags",
           "train_flags", "variant_from_flags", "recipe_commands"]


class FlagReader(NamedTuple):
    """How the command layer reads one command's flags: its parser (built when needed) and the config
    fields its parsed flags give (e.g. ``uhrnet.cli.train_options``)."""

    parser: Callable[[], argparse.ArgumentParser]
    options: Callable[[argparse.Namespace], dict]


class VariantFlags(NamedTuple):
    """An ablation row as written: its name, its extra ``fppsim generate`` / ``uhrnet train`` flags, the
    ``uhrnet adapt`` flags of its adaptation step (None: no adaptation) and its refinement methods."""

    name: str
    generate: list[str]
    train: list[str]
    adapt: list[str] | None = None
    refine: tuple[str, ...] = ()


VARIANT_SYNTAX = "NAME[: GENERATE FLAGS [| TRAIN FLAGS [| adapt [ADAPT FLAGS]] [| refine [METHOD,...]]]]"


def parse_variant(text: str) -> VariantFlags:
    """``NAME`` or ``NAME: generate flags | train flags | step | step`` (shell-quoted; any part may be empty),
    a step being ``adapt [uhrnet adapt flags]`` (adapt the trained model on the unlabelled real images) or
    ``refine [METHOD[,METHOD...]]`` (extra rows after ``--refine phase``; bare ``refine``: relief).

    ``"aug-off: | --no-augment"`` -> VariantFlags("aug-off", [], ["--no-augment"]);
    ``"ph: | --head phase | adapt --epochs 20 | refine relief,orders"`` -> VariantFlags("ph", [],
    ["--head", "phase"], ["--epochs", "20"], ("relief", "orders")).
    """
    name, sep, rest = text.partition(":")
    name = name.strip()
    Variant(name)  # the name is checked before the flags
    if not sep:
        return VariantFlags(name, [], [])
    gen, bar, tail = rest.partition("|")
    parts = tail.split("|") if bar else []
    adapt, refine = None, []
    try:
        for step in (shlex.split(p) for p in parts[1:]):
            if step and step[0] == "adapt" and adapt is None:
                adapt = step[1:]
            elif step and step[0] == "refine":
                refine += [m for m in ",".join(step[1:]).split(",") if m] or ["relief"]
            elif step:
                raise Sim2RealError(f"variant {name!r}: a step after the train flags is 'adapt [FLAGS]' or 'refine "
                                    f"[METHOD,...]' (once each), got {shlex.join(step)!r}")
        return VariantFlags(name, shlex.split(gen), shlex.split(parts[0]) if parts else [], adapt, tuple(refine))
    except ValueError as exc:
        raise Sim2RealError(f"variant {name!r}: {exc}") from None


def load_variants(path: str | Path) -> list[VariantFlags]:
    """Variants from a YAML/JSON list of ``{name, generate: [...] or "...", train: [...] or "..."}`` (or of
    :func:`parse_variant` strings)."""
    p = Path(path)
    doc = read_config_file(p, "ablation file")
    if not isinstance(doc, list) or not doc:
        raise Sim2RealError(f"{p}: expected a non-empty list of variants")
    out = []
    for i, item in enumerate(doc):
        if isinstance(item, str):
            out.append(parse_variant(item))
            continue
        if not isinstance(item, dict) or "name" not in item:
            raise Sim2RealError(f"{p}: item {i} must be a string or a mapping with a 'name'")
        unknown = set(item) - {"name", "generate", "train", "adapt", "refine"}
        if unknown:
            raise Sim2RealError(f"{p}: item {i} has unknown keys {sorted(unknown)}")
        where = f"{p}: item {i} ({item['name']})"
        args = {k: _flags(item.get(k), k, where) for k in ("generate", "train", "adapt", "refine")}
        adapt = None if item.get("adapt") in (None, False) else ([] if item["adapt"] is True else args["adapt"])
        refine = tuple(args["refine"] or (["relief"] if item.get("refine") is True else []))
        Variant(str(item["name"]), refine=list(refine))
        out.append(VariantFlags(str(item["name"]), args["generate"], args["train"], adapt, refine))
    return out


def _flags(value, key: str, where: str) -> list[str]:
    """An ablation item's ``key`` as a list of words: a string of flags (shell-quoted; ``refine``: methods,
    commas allowed) or a list of them; ``adapt`` / ``refine`` may also be true (the defaults) or false; absent
    or null: none. Any other value is refused, never taken for the defaults."""
    switch = key in ("adapt", "refine")
    if value is None or (switch and isinstance(value, bool)):
        return []
    if isinstance(value, str):
        try:
            return shlex.split(value.replace(",", " ") if key == "refine" else value)
        except ValueError as exc:
            raise Sim2RealError(f"{where}: {key}: {exc}") from None
    if isinstance(value, list) and all(isinstance(a, (str, int, float)) and not isinstance(a, bool) for a in value):
        return [str(a) for a in value]
    what = "a string of method names (or a list of them, or true)" if key == "refine" else \
        "a string of flags (or a list of them" + (", or true)" if switch else ")")
    raise Sim2RealError(f"{where}: {key} must be {what}, got {value!r}")


def generate_flags(cfg, data) -> list[str]:
    """The recipe's ``fppsim generate`` command line for the dataset folder ``data`` (no variant)."""
    return ["generate", "--meshes", *cfg.meshes, "--out", str(data), "--count", str(cfg.count), "--seed",
            str(cfg.seed), "--workers", str(generate_workers(cfg)), "--no-psp", "--format", "figshare", "-q"]


def train_flags(cfg, data, run) -> list[str]:
    """The recipe's ``uhrnet train`` command line on ``data`` into ``run`` (no variant)."""
    flags = ["train", "--synthetic", str(data), "--model", cfg.model,
             *(["--base-channels", str(cfg.base_channels)] if cfg.base_channels is not None else []),
             "--loss", cfg.loss, "--epochs", str(cfg.epochs), "--batch-size", str(cfg.batch_size),
             "--lr", str(cfg.lr), "--device", cfg.device, "--out", str(run), "--no-progress"]
    for key, value in SCALES[cfg.scale]["train"].items():  # TrainConfig fields are the flags' names
        flag = "--" + key.replace("_", "-")
        flags += [flag] if value is True else [flag, *map(str, value)] if isinstance(value, (list, tuple)) \
            else [flag, str(value)]
    return flags


def _parse(parser: argparse.ArgumentParser, argv: list[str], where: str) -> argparse.Namespace:
    """``parser.parse_args(argv)``, its error as a :class:`UsageError` naming ``where`` (a flag the command does
    not take, or a value its parser refuses, is a usage error as on that command's own line: exit 2)."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args(argv)
    except SystemExit:
        lines = [line for line in err.getvalue().splitlines() if line.strip()]
        raise UsageError(f"{where}: {lines[-1].split(': error: ')[-1] if lines else 'bad flags'}") from None


def variant_from_flags(cfg, flags: VariantFlags, commands: Mapping[str, FlagReader]) -> Variant:
    """The :class:`~uhrnet.workflows.sim2real.config.Variant` of ``flags``: each side appended to the recipe's
    command line (:func:`generate_flags`, :func:`train_flags`) and parsed by that command's own parser
    (``commands["generate" | "train" | "adapt"]``, the command layer's); the config fields that then differ
    from the recipe's are the variant's overrides."""

    def changed(base: dict, given: dict) -> dict:
        return {k: v for k, v in given.items() if k not in base or v != base[k]}

    where = f"variant {flags.name!r}"
    gen, tr = {}, {}
    if flags.generate:
        head, parser, options = generate_flags(cfg, "DATA"), commands["generate"].parser(), \
            commands["generate"].options
        try:
            gen = changed(options(_parse(parser, head, f"{where}: generate")),
                          options(_parse(parser, head + flags.generate, f"{where}: generate")))
        except (Sim2RealError, UsageError):
            raise
        except (OSError, ValueError) as exc:  # e.g. an unreadable --optics-file
            raise variant_error(exc, f"{where}: generate") from None
    if flags.train:
        head, parser, options = train_flags(cfg, "DATA", "RUN"), commands["train"].parser(), commands["train"].options
        tr = changed(options(_parse(parser, head, f"{where}: train")),
                     options(_parse(parser, head + flags.train, f"{where}: train")))
    ad = None
    if flags.adapt is not None:
        head, parser, options = ["adapt", "RUN", "--images", "IMAGES", "--out", "OUT"], commands["adapt"].parser(), \
            commands["adapt"].options
        ad = changed(options(_parse(parser, head, f"{where}: adapt")),
                     options(_parse(parser, head + flags.adapt, f"{where}: adapt")))
    return Variant(flags.name, gen, tr, generate_flags=list(flags.generate), train_flags=list(flags.train),
                   adapt=ad, refine=list(flags.refine), adapt_flags=None if ad is None else list(flags.adapt))


def recipe_commands(cfg, variant, data, run) -> dict:
    """The stages of ``variant`` as the command lines that run them (``report.json``'s ``recipe``)."""
    out = {"generate": shlex.join(generate_flags(cfg, data) + list(variant.generate_flags or [])),
           "train": shlex.join(train_flags(cfg, data, run) + list(variant.train_flags or []))}
    if variant.adapt is not None:
        a = adapt_config(cfg, variant, Path(run) / LAST_PT, Path(cfg.out) / variant.name / "adapt")
        out["adapt"] = shlex.join(["adapt", str(a.checkpoint), "--images", *map(str, a.images), "--out", str(a.out),
                                   *(["--rig", str(a.rig)] if cfg.rig else []), "--device", a.device,
                                   "--no-progress", *([] if a.figures else ["--no-figures"]),
                                   *(variant.adapt_flags or [])])
    return out
