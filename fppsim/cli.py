"""`fppsim` command line: git-style subcommands over the library (the only module that parses flags).

Every command turns its flags into a config dataclass of the library, which validates itself, and
calls one plain function a Python user can call too:

    generate      -> fppsim.generate(GenerateConfig)            (fppsim.generation)
    merge         -> fppsim.generation.merge(out, shards)
    compare-real  -> fppsim.stats.compare_real(real, synthetic)
    validate-psp  -> fppsim.validate.validate_psp(ValidateConfig)
    fit-rig       -> fppsim.fit_rig.fit_baseline / fit_rig(...)
    fit-optics    -> fppsim.fit_optics.fit_optics(...)

Units: millimetres and radians; images are 8-bit. Usage errors (bad flags, and a library
:class:`fppsim.errors.UsageError`) exit 2; other errors of the library (:mod:`fppsim.errors`), bad
values and I/O errors exit 1 with a one-line reason; SIGTERM/SIGINT stop like Ctrl-C (workers
terminated, temp files removed) and exit ``128 + signum``. The same design serves ``uhrnet``
(:mod:`uhrnet.cli` uses :func:`run_commands`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

__all__ = ["main", "build_parser", "run_commands", "build_command_parser", "one_line", "Command", "COMMANDS"]


# ============================================================================ one CLI design (both tools)
@dataclass(frozen=True)
class Command:
    """A subcommand: ``add(parser)`` declares its flags, ``run(args) -> exit code`` calls the library."""

    add: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str


def build_command_parser(prog: str, description: str, commands: dict[str, Command],
                         globals_: Callable[[argparse.ArgumentParser], None] | None = None,
                         load: str | None = None) -> argparse.ArgumentParser:
    """One sub-parser per command; with ``load`` only that command declares its flags (the others
    keep name and help: a CLI whose commands import heavy modules stays fast)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    if globals_ is not None:
        globals_(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, cmd in commands.items():
        p = sub.add_parser(name, help=cmd.help, description=cmd.help)
        if load is None or load == name:
            cmd.add(p)
    return parser


def one_line(exc: BaseException) -> str:
    """The one-line message of an error, also when a DataLoader worker re-raised it.

    A worker's error arrives as ``Caught DatasetError in DataLoader worker process 0.`` followed by the
    worker's traceback, whose last line (``fppsim.errors.DatasetError: <file>: ...``) names the culprit.
    """
    lines = [line for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    if len(lines) > 1 and lines[0].startswith("Caught ") and "worker" in lines[0]:
        last = lines[-1].strip()
        head, sep, rest = last.partition(": ")
        return rest if sep and "." in head and " " not in head else last
    return lines[0]


def run_commands(parser: argparse.ArgumentParser, commands: dict[str, Command], argv: list[str] | None,
                 errors: tuple[type[BaseException], ...], setup: Callable[[argparse.Namespace], None] | None = None,
                 resume_hint: dict[str, str] | str = " (re-run the same command to resume)") -> int:
    """Parse ``argv``, run the chosen command and report how it ended, one line on stderr:

    * ``errors`` and ``OSError`` -> ``prog command: error: <one line>`` (``file: strerror`` for I/O
      errors such as a full disk), exit 1; a ``UsageError`` (of :mod:`fppsim.errors` or
      :mod:`uhrnet.errors`) exits 2 like argparse's own errors; no command is a usage error too;
    * SIGTERM (e.g. a Slurm timeout) and SIGINT -> ``prog command: terminated|interrupted<hint>``, exit
      ``128 + signum``; the library's clean-up ran on the way (pools terminated, temp files removed);
    * anything else is a bug: traceback.

    ``resume_hint``: text after the interruption line, or ``{command: text}``.
    """
    from ._fs import signals_raise

    args = parser.parse_args(argv)
    if setup is not None:
        setup(args)
    if args.command is None:
        parser.print_usage(sys.stderr)
        print(f"{parser.prog}: error: choose a command: " + ", ".join(commands), file=sys.stderr)
        return 2
    where = f"{parser.prog} {args.command}"
    try:
        with signals_raise():  # SIGTERM stops like Ctrl-C: exit 128 + signum
            return int(commands[args.command].run(args) or 0)
    except Exception as exc:
        if isinstance(exc, OSError) and exc.strerror:  # disk full, read-only file system, missing file ...
            msg = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
        elif isinstance(exc, errors + (OSError,)):
            msg = one_line(exc)
        else:
            raise
        print(f"{where}: error: {msg}", file=sys.stderr)
        return 2 if _is_usage_error(exc) else 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        hint = resume_hint.get(args.command, "") if isinstance(resume_hint, dict) else resume_hint
        print(f"{where}: {'terminated' if signum == 15 else 'interrupted'}{hint}", file=sys.stderr)
        return 128 + signum


def _is_usage_error(exc: BaseException) -> bool:
    """A library's UsageError (either package's; matched by name so fppsim needs no uhrnet import)."""
    return any(c.__name__ == "UsageError" and c.__module__ in ("fppsim.errors", "uhrnet.errors")
               for c in type(exc).__mro__)


# ============================================================================ argument types
def _range_int(text: str) -> tuple[int, int]:
    try:
        parts = [int(p) for p in text.split("-")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI, got '{text}'") from None
    lo, hi = (parts[0], parts[0]) if len(parts) == 1 else parts if len(parts) == 2 else (0, -1)
    if not 1 <= lo <= hi:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI with 1 <= LO <= HI, got '{text}'")
    return lo, hi


def _shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(p) for p in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N, got '{text}'") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"shard I/N needs 0 <= I < N, got '{text}'")
    return i, n


def _freqs(text: str) -> tuple[int, ...]:
    try:
        f = tuple(int(p) for p in text.split(",") if p.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None
    if not f or f[0] != 1 or any(b <= a for a, b in zip(f, f[1:])):
        raise argparse.ArgumentTypeError(f"ladder must start at 1 and increase, got '{text}'")
    return f


def _min_int(lowest: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got '{text}'") from None
        if v < lowest:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lowest}, got {v}")
        return v
    return parse


_positive_int = _min_int(1)


def _optics_override(text: str) -> tuple[str, list[float]]:
    key, sep, val = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE or NAME=LO,HI, got '{text}'")
    try:
        nums = [float(v) for v in val.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"optics value for '{key}' must be numbers, got '{val}'") from None
    return key.strip(), nums


def _optics_names() -> str:
    from .optics import OPTICS_UNITS, OpticsRanges

    return ", ".join(f"{k} ({OPTICS_UNITS[k]})" if k in OPTICS_UNITS else k for k in OpticsRanges.range_names())


def _overrides(pairs) -> dict:
    return {k: (v[0] if len(v) == 1 else v) for k, v in pairs}


def _add_scene_flags(p: argparse.ArgumentParser, suffix: str = "") -> None:
    """Flags shared by `generate` and `validate-psp --meshes` (same names, same parsing)."""
    from .generation import SUPERSAMPLE

    p.add_argument("--seed", type=int, default=0, help="global seed; sample i depends only on (seed, i) (default 0)")
    p.add_argument("--rig", help="rig calibration (fppsim JSON/YAML or OpenCV stereo FileStorage YAML); "
                                 "default: the packaged default rig, assets/default_rig.json" + suffix)
    p.add_argument("--objects", type=_range_int, default=(1, 3), metavar="LO-HI",
                   help="objects per scene, e.g. 1-3 (default) or 2" + suffix)
    p.add_argument("--workers", type=_positive_int, default=1, help="worker processes (default 1; same samples for any K)")
    p.add_argument("--supersample", type=int, default=1, choices=SUPERSAMPLE,
                   help="render intensities at KxK sub-pixels and average (ground truth stays at pixel centres)" + suffix)
    p.add_argument("--optics", action="append", type=_optics_override, default=[], metavar="NAME=LO[,HI]",
                   help="override an optics range, e.g. noise_sigma=0 or gain=120,200 (repeatable); names: "
                        + _optics_names() + suffix)
    p.add_argument("--noise-free", action="store_true", help="no camera noise (exactness checks)" + suffix)
    p.add_argument("--psp-steps", type=_min_int(3), default=4,
                   help="phase-shifting steps per frequency (>= 3, default 4)" + suffix)
    p.add_argument("--psp-freqs", type=_freqs, default=(1, 8, 80), metavar="F1,F2,...",
                   help="temporal unwrapping ladder in periods across the projector, starting at 1 (default 1,8,80)" + suffix)


# ============================================================================ generate
def add_generate(p: argparse.ArgumentParser) -> None:
    from .generation import FORMATS
    from .render import BACKENDS

    p.add_argument("--meshes", nargs="+", required=True, metavar="PATH",
                   help="mesh files or folders (any format trimesh reads: OBJ, PLY, STL, OFF, GLB); "
                        "unusable meshes are skipped and reported")
    p.add_argument("--out", required=True, help="output folder (created; re-running resumes it)")
    p.add_argument("--count", type=_positive_int, required=True, help="number of samples in the whole dataset")
    _add_scene_flags(p)
    p.add_argument("--format", choices=FORMATS, default="native",
                   help="native: one folder per sample (default); figshare: also f1_80.npy + Z.npy (N,H,W,1)")
    p.add_argument("--shard", type=_shard, metavar="I/N", help="generate only shard I of N (0-based, round robin)")
    p.add_argument("--optics-file", help="JSON/YAML mapping of optics ranges (same names as --optics)")
    p.add_argument("--no-psp", action="store_true", help="skip the phase-shifting images and PSP decoding")
    p.add_argument("--label-scale", type=float, default=6.0, help="figshare label units per mm (default 6)")
    p.add_argument("--label-offset", type=float, default=-97.0,
                   help="figshare label of the reference plane (default -97, like the real data)")
    p.add_argument("--label-invalid", type=float, default=-105.0, help="figshare label of invalid pixels (default -105)")
    p.add_argument("--label-threshold", type=float, default=-100.0,
                   help="labels <= this count as invalid when read back (reference code: -100)")
    add_realism_arguments(p)
    p.add_argument("--preview", action=argparse.BooleanOptionalAction, default=True,
                   help="write preview.png (fringe | height | mask) of the first samples (default on)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="off-screen GL: osmesa (software, default) or egl (headless GPU; Mesa's software "
                        "device without one); default $PYOPENGL_PLATFORM, else osmesa")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got '{text}'") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {v}")
    return v


def _jitter(text: str) -> tuple[float, float]:
    try:
        nums = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected YAW,FOCAL (e.g. 0.02,0.03) or 0, got '{text}'") from None
    if len(nums) == 1 and nums[0] == 0:
        nums = [0.0, 0.0]
    if len(nums) != 2 or not (0 <= nums[0] < 0.5 and 0 <= nums[1] < 0.5):
        raise argparse.ArgumentTypeError(f"expected YAW,FOCAL with 0 <= YAW, FOCAL < 0.5, got '{text}'")
    return nums[0], nums[1]


def add_realism_arguments(p: argparse.ArgumentParser) -> None:
    """Sim-to-real options (opt-in until measured on real data): procedural sculptures, per-sample rig jitter."""
    p.add_argument("--procedural-share", type=_fraction, default=None, metavar="P",
                   help="chance that each object is a procedural sculpture (fppsim.shapes.procedural: busts, "
                        "masks, figurines, animals, reliefs, vases with multi-scale surface detail) instead of "
                        "one of --meshes (default 0; 1 when --meshes is just 'procedural')")
    p.add_argument("--procedural-pool", type=_positive_int, default=96, metavar="N",
                   help="number of distinct procedural sculptures (seeds 0..N-1; any N) (default 96)")
    p.add_argument("--pedestal", type=_fraction, default=None, metavar="P",
                   help="chance that each object stands on a prism pedestal (its outline shrunk 0.7-1x, 10-35 mm "
                        "high, object + pedestal at most 55 mm), like plaster casts on thick flat backs "
                        "(default 0.5; 0 = the scenes of fppsim before 2026-11-23)")
    p.add_argument("--rig-jitter", type=_jitter, default=(0.0, 0.0), metavar="YAW,FOCAL",
                   help="per-sample projector jitter: yaw +-YAW rad and focal length +-FOCAL (relative), so the "
                        "fringe period map varies like real rigs, e.g. 0.02,0.03 (default 0 = off)")


def run_generate(args) -> int:
    from .formats import PRESETS, LabelTransform
    from .generation import GenerateConfig, generate, read_optics_file
    from .rig import load_rig

    rig = load_rig(args.rig)  # a bad rig file is named first, before anything else is checked
    optics = read_optics_file(args.optics_file) if args.optics_file else {}
    optics.update(_overrides(args.optics))
    fig = PRESETS["figshare"]
    label = LabelTransform(units_per_mm=args.label_scale, plane_offset=args.label_offset,
                           invalid_value=args.label_invalid, invalid_threshold=args.label_threshold)
    label = fig if label.same_labels(fig) else LabelTransform(**{**label.to_dict(), "name": "custom"})
    config = GenerateConfig(
        meshes=list(args.meshes), out=args.out, count=args.count, seed=args.seed, rig=rig,
        objects=tuple(args.objects), workers=args.workers, format=args.format, shard=args.shard,
        supersample=args.supersample, optics=optics, noise_free=args.noise_free, psp_steps=args.psp_steps,
        psp_freqs=() if args.no_psp else tuple(args.psp_freqs), label=label,
        procedural_share=args.procedural_share, procedural_pool=args.procedural_pool, rig_jitter=args.rig_jitter,
        pedestal=args.pedestal,
        preview=args.preview, backend=args.backend, progress=not args.quiet)
    summary = generate(config)
    for line in summary.lines():
        print(line)
    return 0


# ============================================================================ merge
def add_merge(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="merged dataset folder")
    p.add_argument("shards", nargs="+", metavar="SHARD_DIR", help="folders written with --shard I/N")
    p.add_argument("--copy", action="store_true", help="copy files instead of hard-linking them")


def run_merge(args) -> int:
    from .generation import merge

    n, fig, missing = merge(args.out, args.shards, link=not args.copy)
    print(f"merged {n} samples into {args.out}" + (f" (figshare arrays in {fig})" if fig else ""))
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        print(f"fppsim merge: warning: {len(missing)} sample index(es) missing (a shard not merged yet?): {shown}",
              file=sys.stderr)
    return 0


# ============================================================================ compare-real
def add_compare_real(p: argparse.ArgumentParser) -> None:
    p.add_argument("real", metavar="REAL_DIR", help="real data: figshare folder (f1_80.npy + Z.npy) or a "
                                                    "fringe_pattern.npy + height_map.npy pair")
    p.add_argument("synthetic", metavar="SYN_DIR", help="synthetic data: native fppsim folder or figshare folder")
    p.add_argument("--max-samples", type=_positive_int, default=50, help="samples read per side (default 50)")
    p.add_argument("--json", metavar="FILE", help="also write the statistics as JSON")


def run_compare_real(args) -> int:
    import json

    from .formats import atomic_write_text, json_default
    from .stats import compare_real, format_comparison

    result = compare_real(args.real, args.synthetic, max_samples=args.max_samples)
    print(format_comparison(result))
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1, default=json_default))
    return 0


# ============================================================================ validate-psp
def add_validate(p: argparse.ArgumentParser) -> None:
    from .validate import DEFAULT_SWEEP

    p.description = (
        "Measure how far phase-shifting (PSP) ground truth is from the exact height: per sample RMSE, "
        "99th percentile and max |error| (mm), fringe-order errors and PSP rejections, on the pixels the "
        "exact mask calls valid. Writes OUT/report.json, OUT/maps/<id>.png and prints a table. Give a "
        "dataset folder, or --meshes to render a fresh set into OUT/samples (resumable). "
        "--sweep renders the same scenes once per combination of the given optics values (full grid) "
        "into OUT/sweep/<setting>/ and tabulates the error per setting. No pass/fail thresholds.")
    p.add_argument("dataset", nargs="?", metavar="DATASET",
                   help="generated dataset folder (native layout, or a figshare output with native/)")
    p.add_argument("--out", required=True, help="output folder for report.json, maps/ (and samples/, sweep/)")
    p.add_argument("--meshes", nargs="+", metavar="PATH", help="render a fresh set from these meshes instead")
    p.add_argument("--count", type=_positive_int, help="samples to render with --meshes")
    _add_scene_flags(p, suffix=" (with --meshes)")
    p.add_argument("--tmp-samples", action="store_true",
                   help="render into a temporary folder that is deleted afterwards (not resumable)")
    p.add_argument("--sweep", nargs="*", metavar="NAME=V1,V2",
                   help="optics sweep, full grid of all given values; alone: " + " ".join(DEFAULT_SWEEP) +
                        ". Names: noise (noise_sigma, gray levels; shot_noise 0 unless given), gamma "
                        "(projector_gamma), blur (projector_blur, projector px), or any optics range name")
    p.add_argument("--edge-px", type=int, default=3,
                   help="width of the edge region (px) for the edge/interior RMSE split (0: off)")
    p.add_argument("--no-maps", action="store_true", help="skip the per-sample error-map PNGs")
    p.add_argument("--max-rows", type=int, default=20, help="per-sample rows printed (all are in report.json)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def run_validate(args) -> int:
    from .validate import ValidateConfig, format_sweep_table, format_table, validate_psp

    config = ValidateConfig(
        out=args.out, dataset=args.dataset, meshes=args.meshes, count=args.count, seed=args.seed, rig=args.rig,
        objects=tuple(args.objects), optics=_overrides(args.optics), noise_free=args.noise_free,
        supersample=args.supersample, psp_steps=args.psp_steps, psp_freqs=tuple(args.psp_freqs),
        workers=args.workers, tmp_samples=args.tmp_samples, sweep=args.sweep, edge_px=args.edge_px,
        maps=not args.no_maps, progress=not args.quiet)
    report = validate_psp(config, echo=print)
    out = Path(args.out)
    if "rows" in report:
        print(format_sweep_table(report["rows"]))
        print(f"report: {out / 'report.json'} (per setting: {out / 'sweep'}/<setting>/report.json)")
    else:
        print(format_table(report, args.max_rows))
        print(f"report: {out / 'report.json'}")
    return 0


# ============================================================================ fit-rig, fit-optics
def _params(text: str) -> tuple[str, ...]:
    from .fit_rig import PARAMETERS

    names = tuple(p.strip() for p in text.split(",") if p.strip())
    bad = [p for p in names if p not in PARAMETERS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown parameter(s) {', '.join(bad) or '(none)'}; "
                                         f"choose from {', '.join(PARAMETERS)}")
    return names


def _check_out(path: str, force: bool) -> Path:
    out = Path(path)
    if out.exists() and not force:
        raise ValueError(f"{out} exists; pass --force to replace it")
    if not out.parent.is_dir():
        raise ValueError(f"{out.parent}: output folder does not exist")
    return out


def add_fit_rig(p: argparse.ArgumentParser) -> None:
    p.add_argument("real", metavar="REAL_DIR",
                   help="real fringe images: figshare folder (f1_80.npy + Z.npy), the real-sample pair, native "
                        "fppsim folder, PSin/PCos/Fringe/iPattern folders, or a folder of 8-bit images")
    p.add_argument("--out", required=True, metavar="RIG", help="fitted rig file (.json, or .yaml/.yml)")
    p.add_argument("--base", metavar="RIG", help="rig to start from (camera kept fixed) [assets/default_rig.json]")
    p.add_argument("--params", type=_params, default=("yaw", "roll", "periods"), metavar="P1,P2,...",
                   help="projector parameters to fit: yaw, pitch, roll (rad, about the projector centre; roll "
                        "sets the fringes' lean, which pitch also changes: fit one of the two), baseline (mm), "
                        "periods (across the projector), focal (projector px) [yaw,roll,periods]")
    p.add_argument("--col-bands", type=int, default=4, help="column bands measured (full height each) [4]")
    p.add_argument("--row-bands", type=int, default=3, help="row bands measured (full width each) [3]")
    p.add_argument("--max-images", type=int, default=20, help="evenly spaced images read [20]")
    p.add_argument("--sensitivity", choices=("auto", "off"), default="auto",
                   help="auto: when the images have height labels, first choose the baseline whose fringe shift "
                        "per mm matches them (re-projected labels vs the real fringes; fppsim.fit_rig.fit_baseline), "
                        "then fit --params at that baseline; off: keep the base rig's baseline [auto]")
    p.add_argument("--json", metavar="FILE", help="also write measured / base / fitted band periods as JSON")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")


def run_fit_rig(args) -> int:
    from .formats import atomic_write_text
    from .fit_rig import fit_baseline, fit_rig, format_baseline_fit, format_fit, load_fringe_images, measure_bands
    from .rig import load_rig

    if args.col_bands < 1 or args.row_bands < 1 or args.max_images < 1:
        raise ValueError("--col-bands, --row-bands and --max-images must be >= 1")
    out = _check_out(args.out, args.force)
    base = load_rig(args.base)
    images, layout = load_fringe_images(args.real, args.max_images)
    measured = measure_bands(images, args.col_bands, args.row_bands)
    print(f"{args.real}: {len(images)} image(s), layout {layout}")
    bfit = fit_baseline(images, measured, base, args.params) if args.sensitivity == "auto" else None
    if bfit is not None:
        print(format_baseline_fit(bfit))
        print()
        fit = bfit.fit  # the period fit at the chosen baseline: nothing to refit
    else:
        if args.sensitivity == "auto":
            print("height sensitivity: no labelled images with enough object pixels; baseline kept")
        fit = fit_rig(measured, base, args.params)
    print(format_fit(fit))
    fit.rig.save(out)
    print(f"rig: {out}")
    if args.json:
        doc = fit.to_dict()
        if bfit is not None:
            doc["sensitivity"] = bfit.to_dict()
        atomic_write_text(args.json, json.dumps(doc, indent=1))
    return 0


def add_fit_optics(p: argparse.ArgumentParser) -> None:
    p.add_argument("real", metavar="REAL_DIR",
                   help="real fringe images (same layouts as fit-rig); with height labels the plane and object "
                        "pixels are told apart")
    p.add_argument("--out", required=True, metavar="YAML", help="optics ranges for `fppsim generate --optics-file`")
    p.add_argument("--rig", metavar="RIG", help="rig of the images (e.g. from fit-rig) [assets/default_rig.json]")
    p.add_argument("--max-images", type=int, default=20, help="evenly spaced images read [20]")
    p.add_argument("--compare", type=int, default=4, metavar="N",
                   help="render N samples with the default and with the fitted ranges and print compare-real "
                        "before/after (0: skip) [4]")
    p.add_argument("--meshes", nargs="+", metavar="PATH", help="meshes for --compare [assets/meshes]")
    p.add_argument("--seed", type=int, default=0, help="seed of the --compare renders [0]")
    p.add_argument("--json", metavar="FILE", help="also write the per-image estimates as JSON")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")


def run_fit_optics(args) -> int:
    from .formats import atomic_write_text
    from .fit_optics import compare_before_after, fit_optics, format_optics_fit, ranges_yaml
    from .fit_rig import load_fringe_images
    from .rig import load_rig

    if args.max_images < 1 or args.compare < 0:
        raise ValueError("--max-images must be >= 1 and --compare >= 0")
    out = _check_out(args.out, args.force)
    rig = load_rig(args.rig)
    images, layout = load_fringe_images(args.real, args.max_images)
    fit = fit_optics(images, rig)
    print(f"{args.real}: {len(images)} image(s), layout {layout}")
    print(format_optics_fit(fit))
    atomic_write_text(out, ranges_yaml(fit))
    print(f"optics ranges: {out}")
    if args.json:
        atomic_write_text(args.json, json.dumps(fit.to_dict(), indent=1))
    if args.compare:
        print()
        print(compare_before_after(args.real, fit, rig, args.compare, meshes=args.meshes, seed=args.seed))
    return 0


# ============================================================================ main
COMMANDS: dict[str, Command] = {
    "generate": Command(add_generate, run_generate, "render a synthetic FPP dataset from meshes"),
    "merge": Command(add_merge, run_merge, "join datasets generated as shards (--shard I/N) into one"),
    "compare-real": Command(add_compare_real, run_compare_real,
                            "print real vs synthetic statistics side by side (fringe period, intensity, shadows, heights)"),
    "validate-psp": Command(add_validate, run_validate, "measure how far PSP ground truth is from the exact height"),
    "fit-rig": Command(add_fit_rig, run_fit_rig,
                       "fit the projector pose / fringe period of a rig to real fringe images"),
    "fit-optics": Command(add_fit_optics, run_fit_optics,
                          "fit the optics ranges (gain, albedo, blur, noise) to real fringe images"),
}


def _global_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="store_true", help="log details (skipped meshes, failed samples)")


def _setup_logging(args) -> None:
    # only our logger gets INFO with -v: PyOpenGL logs noise at INFO on the root logger
    logging.basicConfig(level=logging.WARNING, format="fppsim: %(levelname)s: %(message)s")
    logging.getLogger("fppsim").setLevel(logging.INFO if args.verbose else logging.WARNING)


def build_parser() -> argparse.ArgumentParser:
    return build_command_parser(
        "fppsim", "Calibrated virtual fringe projection profilometry rig. Units: mm, radians, 8-bit images.",
        COMMANDS, _global_flags)


def main(argv: list[str] | None = None) -> int:
    from .errors import FppsimError

    # ValueError/OSError: bad values and unreadable/unwritable files surface as one line, like ours
    return run_commands(build_parser(), COMMANDS, argv, (FppsimError, ValueError), _setup_logging)


if __name__ == "__main__":
    sys.exit(main())
