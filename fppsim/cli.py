"""`fppsim` command line: git-style subcommands over the library (the only module that parses flags).

Every command turns its flags into a config dataclass of the library, which validates itself, and
calls one plain function a Python user can call too:

    generate      -> fppsim.generate(GenerateConfig)            (fppsim.generation)
    merge         -> fppsim.generation.merge(out, shards)
    compare-real  -> fppsim.fitting.compare.compare_real(real, synthetic, json_path=...)
    validate-psp  -> fppsim.validate.validate_psp(ValidateConfig)
    fit-rig       -> fppsim.fitting.fit_rig.fit_rig_images(FitRigConfig)
    fit-optics    -> fppsim.fitting.fit_optics.fit_optics_images(FitOpticsConfig)
    label-real    -> fppsim.fitting.label_real.label_real(LabelRealConfig)

Units: millimetres and radians; images are 8-bit. Usage errors (bad flags, and a library
:class:`fppsim.errors.UsageError`) exit 2; other errors of the library (:mod:`fppsim.errors`), bad
values and I/O errors exit 1 with a one-line reason; SIGTERM/SIGINT stop like Ctrl-C (workers
terminated, temp files removed) and exit ``128 + signum``. The framework is :mod:`fppsim.commands`,
which ``uhrnet`` (:mod:`uhrnet.cli`) uses too.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

from fppsim.commands import Command, build_command_parser, parse_numbers, run_commands

__all__ = ["main", "build_parser", "COMMANDS"]


# ============================================================================ argument types
def _range_int(text: str) -> tuple[int, int]:
    parts = parse_numbers(text, int, "-")
    if parts is None:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI, got '{text}'")
    lo, hi = (parts[0], parts[0]) if len(parts) == 1 else parts if len(parts) == 2 else (0, -1)
    if not 1 <= lo <= hi:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI with 1 <= LO <= HI, got '{text}'")
    return lo, hi


def _shard(text: str) -> tuple[int, int]:
    parts = parse_numbers(text, int, "/")
    if parts is None or len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected I/N, got '{text}'")
    i, n = parts
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"shard I/N needs 0 <= I < N, got '{text}'")
    return i, n


def _freqs(text: str) -> tuple:
    from fppsim.dataio.formats import psp_freq  # lazy: the parser loads no data code until a command runs

    f = parse_numbers(text, psp_freq, ",", skip_empty=True)
    if f is None:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'")
    f = tuple(f)
    if not all(math.isfinite(v) for v in f):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got '{text}'")
    if not f or f[0] != 1 or any(b <= a for a, b in zip(f, f[1:])):
        raise argparse.ArgumentTypeError(f"ladder must start at 1 and increase, got '{text}'")
    return f


def _min_int(lowest: int):
    def parse(text: str) -> int:
        v = parse_numbers(text, int, None)
        if v is None:
            raise argparse.ArgumentTypeError(f"expected an integer, got '{text}'")
        v = v[0]
        if v < lowest:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lowest}, got {v}")
        return v
    return parse


_positive_int = _min_int(1)
_seed = _min_int(0)  # numpy's generators (SeedSequence) take any integer >= 0; a negative one failed mid-run


def _optics_override(text: str) -> tuple[str, list[float]]:
    key, sep, val = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE or NAME=LO,HI, got '{text}'")
    nums = parse_numbers(val, float, ",")
    if nums is None:
        raise argparse.ArgumentTypeError(f"optics value for '{key}' must be numbers, got '{val}'")
    return key.strip(), nums


def _optics_names() -> str:
    from fppsim.rendering.optics import OPTICS_UNITS, OpticsRanges

    return ", ".join(f"{k} ({OPTICS_UNITS[k]})" if k in OPTICS_UNITS else k for k in OpticsRanges.range_names())


def _overrides(pairs) -> dict:
    return {k: (v[0] if len(v) == 1 else v) for k, v in pairs}


def _add_scene_flags(p: argparse.ArgumentParser, suffix: str = "") -> None:
    """Flags shared by `generate` and `validate-psp --meshes` (same names, same parsing)."""
    from fppsim.generation import SUPERSAMPLE

    p.add_argument("--seed", type=_seed, default=0,
                   help="global seed, an integer >= 0; sample i depends only on (seed, i) (default 0)")
    p.add_argument("--rig", help="rig calibration (fppsim JSON/YAML or OpenCV stereo FileStorage YAML); "
                                 "default: the packaged default rig, assets/default_rig.json" + suffix)
    p.add_argument("--objects", type=_range_int, default=(1, 3), metavar="LO-HI",
                   help="objects per scene, e.g. 1-3 (default) or 2" + suffix)
    p.add_argument("--workers", type=_positive_int, default=1, help="worker processes (default 1; same samples for any K)")
    p.add_argument("--supersample", type=int, default=1, choices=SUPERSAMPLE,
                   help="render intensities at KxK sub-pixels and average (ground truth stays at pixel centres; "
                        "default 1)" + suffix)
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
    from fppsim.generation import FORMATS
    from fppsim.rendering.render import BACKENDS

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
                   help="labels <= this count as invalid when read back (default -100, the reference code's)")
    add_realism_arguments(p)
    p.add_argument("--preview", action=argparse.BooleanOptionalAction, default=True,
                   help="write preview.png (fringe | height | mask) of the first samples (default on)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="off-screen GL: osmesa (software, default) or egl (headless GPU; Mesa's software "
                        "device without one); default $PYOPENGL_PLATFORM, else osmesa")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _fraction(text: str) -> float:
    v = parse_numbers(text, float, None)
    if v is None:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got '{text}'")
    v = v[0]
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {v}")
    return v


def _jitter(text: str) -> tuple[float, float]:
    nums = parse_numbers(text, float, ",")
    if nums is None:
        raise argparse.ArgumentTypeError(f"expected YAW,FOCAL (e.g. 0.02,0.03) or 0, got '{text}'")
    if len(nums) == 1 and nums[0] == 0:
        nums = [0.0, 0.0]
    if len(nums) != 2 or not (0 <= nums[0] < 0.5 and 0 <= nums[1] < 0.5):
        raise argparse.ArgumentTypeError(f"expected YAW,FOCAL with 0 <= YAW, FOCAL < 0.5, got '{text}'")
    return nums[0], nums[1]


def add_realism_arguments(p: argparse.ArgumentParser) -> None:
    """Sim-to-real options (opt-in until measured on real data): procedural sculptures, per-sample rig jitter."""
    p.add_argument("--procedural-share", type=_fraction, default=None, metavar="P",
                   help="chance that each object is a procedural sculpture (fppsim.rendering.shapes.procedural: busts, "
                        "masks, figurines, animals, reliefs, vases with multi-scale surface detail) instead of "
                        "one of --meshes (default 0; 1 when --meshes is just 'procedural')")
    p.add_argument("--procedural-pool", type=_positive_int, default=96, metavar="N",
                   help="number of distinct procedural sculptures (seeds 0..N-1; any N) (default 96)")
    p.add_argument("--pedestal", type=_fraction, default=None, metavar="P",
                   help="chance that each object stands on a prism pedestal (its outline shrunk 0.7-1x, 10-35 mm "
                        "high, object + pedestal at most 55 mm, or as --scenes says), like plaster casts on thick flat backs "
                        "(default 0.5; 0 = the scenes of fppsim before 2026-11-23)")
    p.add_argument("--scenes", default="auto", metavar="auto|default|FILE",
                   help="the objects' sizes, relief caps and pedestal heights (mm): auto = the rig file's scenes "
                        "(fppsim fit-rig writes them to follow its frames), else the defaults, objects 70-140 mm "
                        "across, relief capped at 35-55 mm, pedestals 10-35 mm; default = those; FILE = a JSON/YAML "
                        "rig file with scenes, or a mapping footprint / max_relief / pedestal_height -> [lo, hi] "
                        "(default auto)")
    p.add_argument("--rig-jitter", type=_jitter, default=(0.0, 0.0), metavar="YAW,FOCAL",
                   help="per-sample projector jitter: yaw +-YAW rad and focal length +-FOCAL (relative), so the "
                        "fringe period map varies like real rigs, e.g. 0.02,0.03 (default 0 = off)")


def generate_options(args) -> dict:
    """The ``GenerateConfig`` fields the ``generate`` flags ``args`` give (``rig``: the file name or
    None, not loaded); ``uhrnet sim2real`` turns variant flags into overrides with it."""
    from fppsim.dataio.formats import PRESETS, LabelTransform
    from fppsim.generation import read_optics_file

    optics = read_optics_file(args.optics_file) if args.optics_file else {}
    optics.update(_overrides(args.optics))
    fig = PRESETS["figshare"]
    label = LabelTransform(units_per_mm=args.label_scale, plane_offset=args.label_offset,
                           invalid_value=args.label_invalid, invalid_threshold=args.label_threshold)
    label = fig if label.same_labels(fig) else LabelTransform(**{**label.to_dict(), "name": "custom"})
    return dict(
        meshes=list(args.meshes), out=args.out, count=args.count, seed=args.seed, rig=args.rig,
        objects=tuple(args.objects), workers=args.workers, format=args.format, shard=args.shard,
        supersample=args.supersample, optics=optics, noise_free=args.noise_free, psp_steps=args.psp_steps,
        psp_freqs=() if args.no_psp else tuple(args.psp_freqs), label=label,
        procedural_share=args.procedural_share, procedural_pool=args.procedural_pool, rig_jitter=args.rig_jitter,
        pedestal=args.pedestal, scenes=args.scenes,
        preview=args.preview, backend=args.backend, progress=not args.quiet)


def run_generate(args) -> int:
    from fppsim.generation import GenerateConfig, generate
    from fppsim.geometry.rig import load_rig

    load_rig(args.rig)  # a bad rig file is named first, before anything else is checked
    summary = generate(GenerateConfig(**generate_options(args)))
    for line in summary.lines():
        print(line)
    return 0


# ============================================================================ merge
def add_merge(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="merged dataset folder")
    p.add_argument("shards", nargs="+", metavar="SHARD_DIR", help="folders written with --shard I/N")
    p.add_argument("--copy", action="store_true", help="copy files instead of hard-linking them")


def run_merge(args) -> int:
    from fppsim.generation import merge

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
    p.add_argument("--force", action="store_true", help="replace an existing --json file")


def run_compare_real(args) -> int:
    from fppsim.fitting.compare import compare_real, format_comparison

    result = compare_real(args.real, args.synthetic, max_samples=args.max_samples, json_path=args.json,
                          force=args.force)
    print(format_comparison(result))
    return 0


# ============================================================================ validate-psp
def add_validate(p: argparse.ArgumentParser) -> None:
    from fppsim.validate import DEFAULT_SWEEP

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
    p.add_argument("--count", type=_positive_int, help="samples to render with --meshes (required with --meshes)")
    _add_scene_flags(p, suffix=" (with --meshes)")
    p.add_argument("--tmp-samples", action="store_true",
                   help="render into a temporary folder that is deleted afterwards (not resumable)")
    p.add_argument("--sweep", nargs="*", metavar="NAME=V1,V2",
                   help="optics sweep, full grid of all given values; alone: " + " ".join(DEFAULT_SWEEP) +
                        ". Names: noise (noise_sigma, gray levels; shot_noise 0 unless given), gamma "
                        "(projector_gamma), blur (projector_blur, projector px), or any optics range name")
    p.add_argument("--edge-px", type=_min_int(0), default=3,
                   help="width of the edge region (px) for the edge/interior RMSE split (default 3; 0: off)")
    p.add_argument("--no-maps", action="store_true", help="skip the per-sample error-map PNGs")
    p.add_argument("--max-rows", type=_min_int(0), default=20,
                   help="per-sample rows printed (default 20; all are in report.json)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def run_validate(args) -> int:
    from fppsim.validate import ValidateConfig, format_sweep_table, format_table, validate_psp

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
    from fppsim.fitting.fit_periods import PARAMETERS

    names = tuple(p.strip() for p in text.split(",") if p.strip())
    bad = [p for p in names if p not in PARAMETERS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown parameter(s) {', '.join(bad) or '(none)'}; "
                                         f"choose from {', '.join(PARAMETERS)}")
    return names


def add_phase_convention(p: argparse.ArgumentParser) -> None:
    """``--convention`` and ``--negate-sin``: how scans in the public layout (PSin/ PCos/ Fringe/) make their phase."""
    from fppsim.dataio.readers import READ_CONVENTIONS  # numpy only

    p.add_argument("--convention", choices=READ_CONVENTIONS, default="auto",
                   help="public layout: benchmark = atan2(-PSin,-PCos) + pi + 2 pi Order (as published); fppsim = "
                        "atan2(PSin,PCos) + 2 pi Order; auto = benchmark unless a scan's phase is clearly written "
                        "another way (it then jumps by pi every period or half period: read the smooth way, and said) "
                        "[auto]")
    p.add_argument("--negate-sin", action="store_true", help="public layout: PSin holds +sum I_n sin(delta_n)")


def add_fit_rig(p: argparse.ArgumentParser) -> None:
    p.add_argument("real", metavar="REAL_DIR",
                   help="real fringe images: figshare folder (f1_80.npy + Z.npy), the real-sample pair, native "
                        "fppsim folder, PSin/PCos/Fringe/iPattern folders, or a folder of 8-bit images")
    p.add_argument("--out", required=True, metavar="RIG", help="fitted rig file (.json, or .yaml/.yml)")
    p.add_argument("--base", metavar="RIG",
                   help="rig to start from (camera kept fixed), 'default' for assets/default_rig.json; without it the "
                        "rig is built from the images (camera size, fringe direction, projector side and pose "
                        "measured; see --fov, --focal, --distance, --baseline, --projector-side)")
    p.add_argument("--fov", type=float, metavar="DEG",
                   help="without --base: the camera's field of view across the image width [the default rig's, 29.2]")
    p.add_argument("--focal", type=float, metavar="PX", help="without --base: the camera's focal length, instead of --fov")
    p.add_argument("--distance", type=float, metavar="MM",
                   help="without --base: camera height above the reference plane (images cannot tell it; the rig "
                        "file's scenes follow the frames at any scale) [500]")
    p.add_argument("--baseline", type=float, metavar="MM",
                   help="without --base: camera-projector distance (images cannot tell it) [0.66 x --distance]")
    p.add_argument("--projector-side", choices=("left", "right", "above", "below"),
                   help="without --base: where the projector is seen from the camera (measured from phase-shifting "
                        "scans or shadows when not given)")
    p.add_argument("--fringe-period", type=float, metavar="PX",
                   help="without --base, for scans with no plane in view: the reference plane's fringe period at the "
                        "image centre (px; e.g. from any frame that shows the plane), instead of the objects' own, "
                        "which their surfaces widen or narrow [measured on the objects]")
    p.add_argument("--params", type=_params, default=None, metavar="P1,P2,...",
                   help="projector parameters to fit: yaw, pitch, roll (rad, about the projector centre; roll "
                        "sets the fringes' lean, which pitch also changes: fit one of the two), baseline (mm), "
                        "periods (across the projector), focal (projector px), distance (camera height, mm: with "
                        "height labels, fits how the sensitivity grows with height, and the baseline with it; "
                        "fppsim.fitting.fit_depth) [yaw,roll,periods]")
    p.add_argument("--col-bands", type=int, default=None, help="column bands measured (full height each) [4]")
    p.add_argument("--row-bands", type=int, default=None, help="row bands measured (full width each) [3]")
    p.add_argument("--max-images", type=int, default=20, help="evenly spaced images read [20]")
    add_phase_convention(p)
    p.add_argument("--sensitivity", choices=("auto", "off"), default=None,
                   help="auto: when the images have height labels, first choose the baseline whose fringe shift "
                        "per mm matches them (re-projected labels vs the real fringes; fppsim.fitting.fit_rig.fit_baseline), "
                        "then fit --params at that baseline; off: keep the base rig's baseline [auto]")
    p.add_argument("--json", metavar="FILE", help="also write measured / base / fitted band periods as JSON")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")


def run_fit_rig(args) -> int:
    from fppsim.errors import UsageError
    from fppsim.fitting.fit_rig import FitRigConfig, fit_rig_images

    fitting = {"params": args.params, "col_bands": args.col_bands, "row_bands": args.row_bands,
               "sensitivity": args.sensitivity}
    given = tuple(f"--{k.replace('_', '-')}" for k, v in fitting.items() if v is not None)
    defaults = {"params": ("yaw", "roll", "periods"), "col_bands": 4, "row_bands": 3, "sensitivity": "auto"}
    fitting = {k: tuple(v) if k == "params" and v is not None else v if v is not None else defaults[k]
               for k, v in fitting.items()}
    common = dict(real=args.real, out=args.out, max_images=args.max_images, json=args.json, **fitting,
                  force=args.force, convention=args.convention, negate_sin=args.negate_sin)
    start = {"fov": args.fov, "focal": args.focal, "distance": args.distance, "baseline": args.baseline,
             "projector_side": args.projector_side, "fringe_period": args.fringe_period}
    if args.base is None:  # no calibration: the rig from the images themselves
        from fppsim.fitting.rig_start import StartRigConfig, fit_rig_from_images

        fit_rig_from_images(StartRigConfig(**common, **start, label_options=given), echo=print)
        return 0
    given = [f"--{k.replace('_', '-')}" for k, v in start.items() if v is not None]
    if given:
        raise UsageError(f"{', '.join(given)}: these describe a rig built from the images; with --base the base "
                         "rig's camera and pose are used")
    fit_rig_images(FitRigConfig(**common, base=None if args.base == "default" else args.base), echo=print)
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
    add_phase_convention(p)
    p.add_argument("--meshes", nargs="+", metavar="PATH", help="meshes for --compare [assets/meshes]")
    p.add_argument("--seed", type=_seed, default=0, help="seed of the --compare renders, an integer >= 0 [0]")
    p.add_argument("--json", metavar="FILE", help="also write the per-image estimates as JSON")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")


def run_fit_optics(args) -> int:
    from fppsim.fitting.fit_optics import FitOpticsConfig, fit_optics_images

    fit_optics_images(FitOpticsConfig(
        real=args.real, out=args.out, rig=args.rig, max_images=args.max_images, compare=args.compare,
        meshes=args.meshes, seed=args.seed, json=args.json, force=args.force, convention=args.convention,
        negate_sin=args.negate_sin), echo=print)
    return 0


# ============================================================================ label-real
def add_label_real(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Turn phase-shifting scans into labelled samples in the figshare layout. Reads ROOT: the public layout "
        "(PSin/ PCos/ Fringe/ iPattern/ of <id>.mat) or an fppsim dataset generated with phase-shifting images "
        "(its psp/f{f}_s{n}.png are decoded here; the exact arrays are not read). The absolute phase (rad) is "
        "triangulated through the rig into height = mm above the reference plane, and written as DIR/f1_80.npy "
        "(float32 (N,H,W,1), 8-bit intensity/127.5 - 1, -1 where invalid) and DIR/Z.npy (float32 (N,H,W,1), "
        "figshare label preset: label = 6 * mm - 97, -105 where the phase is missing; `uhrnet train --real DIR` "
        "reads them), plus DIR/label_real.json (per scan: phase offset, plane level / RMS / tilt, valid share) "
        "and DIR/previews/<id>.png. Phase offset: a scan's phase origin need not be the rig's projector column 0 "
        "(public frames count fringe orders from the first fringe the camera sees); 'auto' fits one constant "
        "per scan so the reference plane (the dominant flat mode) lies at 0 mm, 'none' adds nothing, a number "
        "adds that many radians. The reference plane must come out flat at 0 mm: a scan whose plane is not "
        "(RMS or tilt over the limits), or whose phase is read in a convention its files are not written in, fails the "
        "run (exit 1, nothing written) unless --keep-unfit, which writes it, reports it and warns that the rig does "
        "not fit these scans. "
        "Files in DIR that label-real did not write are never replaced.")
    p.add_argument("root", metavar="ROOT", help="scans: public layout folder or native fppsim dataset (with PSP images)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created; a re-run replaces its own files)")
    p.add_argument("--rig", metavar="FILE",
                   help="rig calibration (fppsim JSON/YAML or OpenCV stereo FileStorage YAML); its camera size must "
                        "match the images; default: assets/default_rig.json for the public layout, each sample's "
                        "recorded rig (meta.json) for fppsim datasets")
    p.add_argument("--phase-offset", default=None, metavar="auto|none|RAD",
                   help="constant added to the absolute phase before triangulation: auto (fit per scan on the "
                        "reference plane), none, or radians; default auto for the public layout, none for fppsim "
                        "datasets (absolute in rig terms; the fitted offset is still reported)")
    p.add_argument("--periods", type=float, default=None,
                   help="fringe periods across the projector of the public layout's phase (default: the rig's, 80)")
    add_phase_convention(p)
    p.add_argument("--ids", nargs="+", metavar="ID", help="label only these scan ids, in this order (default: all)")
    p.add_argument("--plane-window", type=float, default=3.0, metavar="MM",
                   help="reference-plane pixels lie within this height of the plane (mm, default 3)")
    p.add_argument("--max-plane-rms", type=float, default=1.5, metavar="MM",
                   help="warn when the plane pixels' RMS about 0 mm exceeds this (default 1.5)")
    p.add_argument("--max-plane-tilt", type=float, default=3.0, metavar="MM",
                   help="warn when the fitted plane rises more than this across the image (default 3)")
    p.add_argument("--min-modulation", type=float, default=3.0, metavar="B",
                   help="fppsim datasets: PSP modulation threshold in gray levels (default 3, as generated)")
    p.add_argument("--no-preview", action="store_true", help="skip the previews/<id>.png figures")
    p.add_argument("--keep-unfit", action="store_true",
                   help="write the labels also when a scan does not fit (its plane not flat at 0 mm, or its phase read "
                        "in a convention its files are not written in); without it such a run fails (exit 1) naming "
                        "the scan, and writes nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run_label_real(args) -> int:
    from fppsim.fitting.label_real import LabelRealConfig, label_real

    config = LabelRealConfig(
        root=args.root, out=args.out, rig=args.rig, phase_offset=args.phase_offset, periods=args.periods,
        convention=args.convention, negate_sin=args.negate_sin, ids=args.ids, plane_window_mm=args.plane_window,
        max_plane_rms_mm=args.max_plane_rms, max_plane_tilt_mm=args.max_plane_tilt,
        min_modulation=args.min_modulation, previews=not args.no_preview, progress=not args.quiet,
        keep_unfit=args.keep_unfit)
    report = label_real(config)
    for line in report.lines():
        print(line)
    for w in report.warnings:
        print(f"fppsim label-real: warning: {w}", file=sys.stderr)
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
    "label-real": Command(add_label_real, run_label_real,
                          "label phase-shifting scans (public PSin/PCos/Fringe/iPattern or fppsim PSP) as figshare arrays"),
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
    from fppsim.errors import FppsimError, UsageError

    # only fppsim's own errors (bad input, every one an FppsimError) and OSError (unreadable / unwritable files)
    # are one line: any other exception, a bare ValueError included, is a bug and keeps its traceback
    return run_commands(build_parser(), COMMANDS, argv, (FppsimError,), _setup_logging,
                        usage_errors=(UsageError,))


if __name__ == "__main__":
    sys.exit(main())
