#!/usr/bin/env python
"""Sim-to-real experiment: fppsim generate -> uhrnet train (synthetic only) -> evaluate on REAL data.

    python pipelines/sim2real.py --scale cpu --real ../shared/real-sample --out runs/sim2real
    python pipelines/sim2real.py --scale cpu --real REAL_DIR --out runs/abl \\
        --variant baseline --variant "no-aug: | --no-augment" --variant "no-jitter: --rig-jitter 0"
    python pipelines/sim2real.py --scale gpu --real REAL_DIR --out runs/gpu     # full UHRNet, 2000 samples

--scale cpu is the judged recipe (400 samples of ../shared/meshes + assets/meshes, seed 100, U-Net base
16, compound loss, 10 epochs, batch 2, lr 5e-4, CPU; under 60 minutes on 2 cores); --scale gpu is UHRNet
at 352 x 640 on 2000 samples. Each --variant NAME[: GENERATE ARGS | TRAIN ARGS] adds a row to the
ablation table (--ablation FILE reads a YAML list of {name, generate, train}); variants with the same
generate arguments share one dataset. Re-running the same command re-uses finished datasets, runs and
evaluations. Writes OUT/report.json, OUT/report.md and per variant OUT/<name>/eval/real_*.png.
Real data: figshare-format folders (f1_80.npy + Z.npy, or fringe_pattern.npy + height_map.npy);
labels <= -100 are invalid and mm = label / 6.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uhrnet.sim2real import (  # noqa: E402
    SCALES, Sim2RealConfig, Sim2RealError, Variant, load_variants, parse_variant, run_sim2real,
)


def default_meshes() -> list[str]:
    shared = ROOT.parent / "shared" / "meshes"
    return ([str(shared)] if shared.is_dir() else []) + [str(ROOT / "fppsim" / "data" / "meshes")]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scale", choices=sorted(SCALES), default="cpu", help="recipe size [cpu]")
    p.add_argument("--real", nargs="+", required=True, metavar="DIR",
                   help="real figshare-format folder(s); evaluation only, never trained on")
    p.add_argument("--out", required=True, help="experiment folder (re-running resumes it)")
    p.add_argument("--meshes", nargs="+", metavar="PATH",
                   help="meshes for fppsim generate [../shared/meshes (if present) and assets/meshes]")
    for name, typ, what in (("count", int, "synthetic samples"), ("seed", int, "generator seed"),
                            ("workers", int, "generator processes (0: all cores)"), ("epochs", int, "epochs"),
                            ("batch-size", int, "batch size"), ("lr", float, "learning rate"),
                            ("base-channels", int, "model width"), ("model", str, "architecture"),
                            ("loss", str, "training loss"), ("device", str, "cpu or cuda")):
        p.add_argument(f"--{name}", type=typ, help=f"{what} [the scale's value]")
    p.add_argument("--variant", action="append", default=[], metavar="SPEC",
                   help="NAME or 'NAME: GENERATE ARGS | TRAIN ARGS' (repeatable) [one variant 'default']")
    p.add_argument("--ablation", metavar="FILE", help="YAML/JSON list of variants {name, generate, train}")
    p.add_argument("--object-mm", type=float, default=1.0,
                   help="object pixels: valid and more than this many mm above the plane [1]")
    p.add_argument("--no-figures", action="store_true", help="skip the per-image figures")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        variants: list[Variant] = [parse_variant(v) for v in args.variant]
        if args.ablation:
            variants += load_variants(args.ablation)
        cfg = Sim2RealConfig(
            out=args.out, real=args.real, meshes=args.meshes or default_meshes(), scale=args.scale,
            count=args.count, seed=args.seed, workers=args.workers, model=args.model,
            base_channels=args.base_channels, loss=args.loss, epochs=args.epochs, batch_size=args.batch_size,
            lr=args.lr, device=args.device, variants=variants or [Variant("default")],
            object_mm=args.object_mm, figures=not args.no_figures)
        report = run_sim2real(cfg, log=lambda m: print(m, flush=True))
    except Sim2RealError as exc:
        print(f"sim2real: error: {exc}", file=sys.stderr)
        return 1
    from uhrnet.sim2real import markdown_report

    print(markdown_report(report))
    print(f"report: {Path(args.out) / 'report.md'} and report.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
