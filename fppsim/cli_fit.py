"""`fppsim fit-rig` and `fppsim fit-optics`: argument parsing and printing only.

The work is done by :mod:`fppsim.fit_rig` and :mod:`fppsim.fit_optics`; errors are raised as
ValueError / RigError and printed as one line by :func:`fppsim.cli.main` (exit 1).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_fit_rig", "run_fit_rig", "add_fit_optics", "run_fit_optics"]


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
    p.add_argument("--params", type=_params, default=("yaw", "pitch", "periods"), metavar="P1,P2,...",
                   help="projector parameters to fit: yaw, pitch, roll (rad, about the projector centre), "
                        "baseline (mm), periods (across the projector), focal (projector px) [yaw,pitch,periods]")
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
    from .fit_rig import adjust_rig, fit_baseline, fit_rig, format_baseline_fit, format_fit, load_fringe_images, measure_bands
    from .rig import load_rig

    if args.col_bands < 1 or args.row_bands < 1 or args.max_images < 1:
        raise ValueError("--col-bands, --row-bands and --max-images must be >= 1")
    out = _check_out(args.out, args.force)
    base = load_rig(args.base)
    images, layout = load_fringe_images(args.real, args.max_images)
    measured = measure_bands(images, args.col_bands, args.row_bands)
    print(f"{args.real}: {len(images)} image(s), layout {layout}")
    params, bfit = args.params, None
    if args.sensitivity == "auto":
        rest = tuple(p for p in params if p != "baseline")
        bfit = fit_baseline(images, measured, base, rest or ("yaw",))
        if bfit is None:
            print("height sensitivity: no labelled images with enough object pixels; baseline kept")
        else:
            print(format_baseline_fit(bfit))
            print()
            base = adjust_rig(base, baseline=bfit.baseline)
            params = rest
    fit = fit_rig(measured, base, params or ("yaw",))
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
