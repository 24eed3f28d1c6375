#!/usr/bin/env python
"""Sim-to-real experiment: fppsim generate -> uhrnet train (synthetic only) -> evaluate on REAL data.

A thin wrapper of ``uhrnet sim2real`` (same flags; see ``uhrnet sim2real --help``) whose meshes default
to ../shared/meshes (when present) and assets/meshes.

    python pipelines/sim2real.py --scale cpu --real ../shared/real-sample --out runs/sim2real
    python pipelines/sim2real.py --scale cpu --real REAL_DIR --out runs/abl \\
        --variant baseline --variant "no-aug: | --no-augment" --variant "no-jitter: --rig-jitter 0"
    python pipelines/sim2real.py --scale gpu --real REAL_DIR --out runs/gpu     # full UHRNet, 2000 samples

--scale cpu is the judged recipe (400 samples of ../shared/meshes + assets/meshes, seed 100, U-Net base
16, compound loss, 10 epochs, batch 2, lr 5e-4, CPU; under 60 minutes on 2 cores); --scale gpu is UHRNet
at 352 x 640 on 2000 samples. Each --variant NAME[: GENERATE ARGS | TRAIN ARGS [| adapt [ADAPT ARGS]]
[| refine [METHOD,...]]] adds a row to the ablation table, plus rows for the model adapted on the
unlabelled real images and for each refinement (--ablation FILE reads a YAML list of {name, generate,
train, adapt, refine}); variants with the same generate arguments share one dataset. --real-phase DIR
adds the phase residual on real phase-shifting frames; --reuse-run NAME=RUN_DIR takes a finished training
run instead of training. Re-running the same command re-uses finished datasets, runs, adaptations and
evaluations. Writes OUT/report.json, OUT/report.md and per variant OUT/<name>/eval/real_*.png.

    python pipelines/sim2real.py --real ../shared/real-sample --real-phase ../shared/real-phase/FP1523 \
        --out runs/phys --variant "base: | | adapt | refine relief" --variant "phase-head: | --head phase"
Real data: figshare-format folders (f1_80.npy + Z.npy, or fringe_pattern.npy + height_map.npy);
labels <= -100 are invalid and mm = label / 6.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uhrnet.cli import main as uhrnet_main  # noqa: E402
from uhrnet.run_folder import default_meshes  # noqa: E402


def main(argv=None) -> int:
    """``uhrnet sim2real`` with this script's default meshes (../shared/meshes when present)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--meshes" not in argv and not any(a in ("-h", "--help") for a in argv):
        argv += ["--meshes", *default_meshes(ROOT.parent / "shared")]
    return uhrnet_main(["sim2real", *argv])


if __name__ == "__main__":
    sys.exit(main())
