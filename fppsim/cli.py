"""`fppsim` command line: git-style subcommands (generate, merge, compare-real, validate-psp).

Units: millimetres and radians; images are 8-bit. Usage errors exit 2, input/IO errors exit 1 with a
one-line reason.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

__all__ = ["main", "build_parser"]


class CLIError(Exception):
    """Printed as one line; exit code 1."""


class UsageError(CLIError):
    """A bad command-line value: printed as one line; exit code 2 (like argparse's own errors)."""


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


def add_generate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--meshes", nargs="+", required=True, metavar="PATH",
                   help="mesh files or folders (any format trimesh reads: OBJ, PLY, STL, OFF, GLB); "
                        "unusable meshes are skipped and reported")
    p.add_argument("--out", required=True, help="output folder (created; re-running resumes it)")
    p.add_argument("--count", type=_positive_int, required=True, help="number of samples in the whole dataset")
    p.add_argument("--seed", type=int, default=0, help="global seed; sample i depends only on (seed, i) (default 0)")
    p.add_argument("--rig", help="rig calibration (fppsim JSON/YAML or OpenCV stereo FileStorage YAML); "
                                 "default: assets/default_rig.json")
    p.add_argument("--objects", type=_range_int, default=(1, 3), metavar="LO-HI",
                   help="objects per scene, e.g. 1-3 (default) or 2")
    p.add_argument("--workers", type=_positive_int, default=1, help="worker processes (default 1; same samples for any K)")
    p.add_argument("--format", choices=["native", "figshare"], default="native",
                   help="native: one folder per sample (default); figshare: also f1_80.npy + Z.npy (N,H,W,1)")
    p.add_argument("--shard", type=_shard, metavar="I/N", help="generate only shard I of N (0-based, round robin)")
    p.add_argument("--supersample", type=int, default=1, choices=[1, 3, 5],
                   help="render intensities at KxK sub-pixels and average (ground truth stays at pixel centres)")
    p.add_argument("--optics", action="append", type=_optics_override, default=[], metavar="NAME=LO[,HI]",
                   help="override an optics range, e.g. noise_sigma=0 or gain=120,200 (repeatable); "
                        "names: gain, ambient, albedo_plane, albedo_object, projector_gamma, camera_gamma, "
                        "projector_blur (projector px), camera_blur (camera px), noise_sigma (gray levels), shot_noise")
    p.add_argument("--optics-file", help="JSON/YAML mapping of optics ranges (same names as --optics)")
    p.add_argument("--noise-free", action="store_true", help="no camera noise (exactness checks)")
    p.add_argument("--psp-steps", type=_min_int(3), default=4, help="phase-shifting steps per frequency (>= 3, default 4)")
    p.add_argument("--psp-freqs", type=_freqs, default=(1, 8, 80), metavar="F1,F2,...",
                   help="temporal unwrapping ladder in periods across the projector, starting at 1 (default 1,8,80)")
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
    p.add_argument("--backend", choices=["osmesa", "egl"], default=None,
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


def realism_config(args) -> tuple[list[str], dict, object]:
    """(mesh paths without the 'procedural' token, SceneRanges procedural options, RigJitter)."""
    from .jitter import RigJitter

    meshes = [m for m in args.meshes if m != "procedural"]
    share = args.procedural_share
    if share is None:
        share = 1.0 if not meshes else 0.0
    if not meshes and share < 1.0:
        raise UsageError("--meshes procedural alone needs --procedural-share 1 (or give mesh files too)")
    scene = {"procedural_share": share, "procedural_pool": args.procedural_pool}
    if getattr(args, "pedestal", None) is not None:
        scene["pedestal_probability"] = args.pedestal
    return meshes, scene, RigJitter(*args.rig_jitter)


def run_generate(args) -> int:
    from .dataset import LabelTransform
    from .generate import generate
    from .optics import OpticsRanges
    from .rig import load_rig
    from .scene import SceneRanges
    from .synth import SynthConfig

    rig = load_rig(args.rig)
    ranges = {}
    if args.optics_file:
        ranges.update(_read_mapping(args.optics_file))
        try:
            OpticsRanges.from_dict(ranges)
        except ValueError as exc:
            raise CLIError(f"{args.optics_file}: {exc}") from None
    for key, nums in args.optics:
        ranges[key] = nums[0] if len(nums) == 1 else nums
    try:
        optics = OpticsRanges.from_dict(ranges)
    except ValueError as exc:
        raise UsageError(f"--optics: {exc}") from None
    freqs = () if args.no_psp else tuple(args.psp_freqs)
    if freqs and freqs[-1] != rig.periods:
        raise CLIError(f"--psp-freqs must end at the rig's single-shot frequency {rig.periods:g}, got {freqs[-1]}")
    meshes, procedural, jitter = realism_config(args)
    config = SynthConfig(rig=rig, optics=optics, scene=SceneRanges(objects=tuple(args.objects), **procedural),
                         supersample=args.supersample, psp_freqs=freqs, psp_steps=args.psp_steps,
                         rig_jitter=jitter)
    preset = (args.label_scale, args.label_offset, args.label_invalid, args.label_threshold)
    label = LabelTransform(scale=args.label_scale, offset=args.label_offset, invalid=args.label_invalid,
                           threshold=args.label_threshold,
                           name="figshare" if preset == (6.0, -97.0, -105.0, -100.0) else "custom")
    try:
        label.check()
    except ValueError as exc:
        raise UsageError(f"--label-*: {exc}") from None
    summary = generate(meshes, args.out, args.count, seed=args.seed, config=config, workers=args.workers,
                       fmt=args.format, shard=args.shard, label=label, noise_free=args.noise_free,
                       progress=not args.quiet, backend=args.backend)
    for line in summary.lines():
        print(line)
    if args.preview:
        from .preview import write_preview

        root = Path(args.out) / ("native" if args.format == "figshare" else "")
        print(f"preview: {write_preview(root, Path(args.out) / 'preview.png')}")
    return 0


def _read_mapping(path: str) -> dict:
    import json

    import yaml

    p = Path(path)
    if not p.is_file():
        raise CLIError(f"file not found: {p}")
    try:
        doc = yaml.safe_load(p.read_text()) if p.suffix.lower() in (".yaml", ".yml") else json.loads(p.read_text())
    except Exception as exc:
        raise CLIError(f"{p}: not valid JSON/YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise CLIError(f"{p}: expected a mapping of name -> value or [lo, hi]")
    return doc


def add_merge(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="merged dataset folder")
    p.add_argument("shards", nargs="+", metavar="SHARD_DIR", help="folders written with --shard I/N")
    p.add_argument("--copy", action="store_true", help="copy files instead of hard-linking them")


def run_merge(args) -> int:
    from .generate import merge

    n, fig, missing = merge(args.out, args.shards, link=not args.copy)
    print(f"merged {n} samples into {args.out}" + (f" (figshare arrays in {fig})" if fig else ""))
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        print(f"fppsim merge: warning: {len(missing)} sample index(es) missing (a shard not merged yet?): {shown}",
              file=sys.stderr)
    return 0


def add_compare_real(p: argparse.ArgumentParser) -> None:
    p.add_argument("real", metavar="REAL_DIR", help="real data: figshare folder (f1_80.npy + Z.npy) or a "
                                                    "fringe_pattern.npy + height_map.npy pair")
    p.add_argument("synthetic", metavar="SYN_DIR", help="synthetic data: native fppsim folder or figshare folder")
    p.add_argument("--max-samples", type=_positive_int, default=50, help="samples read per side (default 50)")
    p.add_argument("--json", metavar="FILE", help="also write the statistics as JSON")


def run_compare_real(args) -> int:
    import json

    from .dataset import atomic_write_text
    from .stats import compare_real, format_comparison

    try:
        result = compare_real(args.real, args.synthetic, max_samples=args.max_samples)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    print(format_comparison(result))
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1, default=float))
    return 0


COMMANDS = {
    "generate": (add_generate, run_generate, "render a synthetic FPP dataset from meshes"),
    "merge": (add_merge, run_merge, "join datasets generated as shards (--shard I/N) into one"),
    "compare-real": (add_compare_real, run_compare_real,
                     "print real vs synthetic statistics side by side (fringe period, intensity, shadows, heights)"),
}


def _register_optional():
    from .cli_fit import add_fit_optics, add_fit_rig, run_fit_optics, run_fit_rig

    COMMANDS.setdefault("fit-rig", (add_fit_rig, run_fit_rig,
                                    "fit the projector pose / fringe period of a rig to real fringe images"))
    COMMANDS.setdefault("fit-optics", (add_fit_optics, run_fit_optics,
                                       "fit the optics ranges (gain, albedo, blur, noise) to real fringe images"))
    try:
        from .validate import add_arguments, run
    except ImportError:
        return
    COMMANDS["validate-psp"] = (add_arguments, run, "measure how far PSP ground truth is from the exact height")


def build_parser() -> argparse.ArgumentParser:
    _register_optional()
    parser = argparse.ArgumentParser(
        prog="fppsim",
        description="Calibrated virtual fringe projection profilometry rig. Units: mm, radians, 8-bit images.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details (skipped meshes, failed samples)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (add, _, help_) in COMMANDS.items():
        add(sub.add_parser(name, help=help_, description=help_))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # only our logger gets INFO with -v: PyOpenGL logs noise at INFO on the root logger
    logging.basicConfig(level=logging.WARNING, format="fppsim: %(levelname)s: %(message)s")
    logging.getLogger("fppsim").setLevel(logging.INFO if args.verbose else logging.WARNING)
    if args.command is None:
        parser.print_usage(sys.stderr)
        print("fppsim: error: choose a command: " + ", ".join(COMMANDS), file=sys.stderr)
        return 2
    from ._fs import FolderBusy, signals_raise
    from .dataset import DatasetError
    from .generate import GenerateError
    from .render import BackendError
    from .rig import RigError
    from .scene import MeshError

    try:
        with signals_raise():  # SIGTERM stops like Ctrl-C (workers terminated), exit 128 + signum
            return int(COMMANDS[args.command][1](args) or 0)
    except (CLIError, GenerateError, DatasetError, RigError, MeshError, FolderBusy, BackendError, ValueError,
            OSError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, OSError) and exc.filename and exc.strerror:
            msg = f"{exc.filename}: {exc.strerror}"
        print(f"fppsim {args.command}: error: {msg}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        name = "terminated" if signum == 15 else "interrupted"
        print(f"fppsim {args.command}: {name} (re-run the same command to resume)", file=sys.stderr)
        return 128 + signum


if __name__ == "__main__":
    sys.exit(main())
