#!/usr/bin/env python
"""Fringe orders on rendered scenes with exact truth: the network alone against ``uhrnet predict``'s orders path.

Real frames are few and their references are not exact (docs/experiments/orders.md); rendered scenes give every
pixel's height and projector phase. This renders (``--count N``) or reads (``--scenes DIR``, ``fppsim generate``'s
native layout WITH its phase-shifting images) scenes through a rig (default the figshare depth rig) and, for each
training run given, scores over the object pixels (valid, more than 1 mm above the plane):

* object RMSE and median |error| (mm) of the network's map and of the path's;
* the share at the right fringe order (|error| under half a fringe period of height at the pixel, as
  ``pipelines/orders_study.py`` scores the pair);
* the calibration-free phase residual ``uhrnet evaluate-phase`` computes (degree-3 plane + a h + b h^2), path over
  network, against the rendered phase-shifting phase (the judged reference kind) and the exact phase.

The order choice uses no truth. Writes OUT/rendered.json (every number per run and scene) and OUT/rendered.md.
About 4 s per scene and run on 2 cores, after rendering (about 2 s a scene).

    python pipelines/orders_rendered.py --runs runs/s2r0/default/run runs/seed1 --count 16 --seed 779 --out OUT
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "pipelines"))

from fppsim.dataio.encoding import encode_fringe  # noqa: E402
from fppsim.dataio.readers.samples import load_native_sample  # noqa: E402
from fppsim.dataio.rig_choice import dataset_rig  # noqa: E402
from fppsim.errors import FppsimError  # noqa: E402
from fppsim.files import atomic_write_text, json_text  # noqa: E402
from fppsim.owned import claim, output_folder, same_folder, stamp  # noqa: E402
from fppsim.geometry.rig import load_rig  # noqa: E402
from orders_study import network, pair_scores, path  # noqa: E402
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint  # noqa: E402
from uhrnet.errors import UhrnetError  # noqa: E402
from uhrnet.physics.refine import layer_for  # noqa: E402
from uhrnet.scoring.phase_residual import fit_phase  # noqa: E402

SHARED = ROOT.parent / "shared"
ARRAYS = ("height", "mask", "phase_psp", "mask_psp", "phase_true")  # a rendered scene's, with its PSP images
TOOL = "orders_rendered"  # its files' owner in the --out folder's ownership record (fppsim.owned)
KEYS = ("net_rmse_mm", "path_rmse_mm", "path_median_mm", "net_right_order", "path_right_order", "ratio_psp",
        "ratio_exact")


class BenchError(Exception):
    """Bad input, said in one line."""


def check_rig(scenes: Path, rig) -> None:
    """The scenes must have been rendered through ``rig`` (the rig their dataset records)."""
    recorded, _ = dataset_rig(scenes)
    if recorded is None:
        return
    same = all(np.allclose(getattr(getattr(recorded, d), k), getattr(getattr(rig, d), k), atol=1e-6)
               for d in ("camera", "projector") for k in ("K", "R", "t"))
    if not same or recorded.periods != rig.periods:
        raise BenchError(f"{scenes}: rendered through another rig than --rig ({recorded.name})")


def render(out: Path, count: int, seed: int, objects: str, rig: str, meshes: list[str]) -> Path:
    """``fppsim generate`` with its phase-shifting images (resumable: an existing folder is completed)."""
    scenes = out / "scenes"
    subprocess.run([sys.executable, "-m", "fppsim", "generate", "--meshes", *meshes, "--rig", rig, "--out", str(scenes),
                    "--count", str(count), "--seed", str(seed), "--objects", objects, "--supersample", "3", "-q",
                    "--no-preview"], check=True)
    return scenes


def scene_scores(model, transform, folder: Path, rig, layer) -> dict:
    """One rendered scene through one network: the numbers of :data:`KEYS`."""
    s = load_native_sample(folder, keys=ARRAYS, meta=False)
    missing = set(ARRAYS) - set(s)
    if missing:
        raise BenchError(f"{folder / 'arrays.npz'} lacks {', '.join(sorted(missing))} "
                         "(render with the phase-shifting images: fppsim generate without --no-psp)")
    fringe = encode_fringe(s["fringe"])
    truth = s["height"].astype(np.float64)
    h = network(model, transform, fringe, False)
    hp = path(h, fringe, rig, model, transform).height.astype(np.float64)
    obj = (s["mask"] > 0) & (truth > 1.0)
    net, pth = pair_scores(h, truth, obj, layer), pair_scores(hp, truth, obj, layer)
    lit = (s["mask_psp"] > 0) & (s["fringe"] > 0)
    ratio = {}
    for name, phase, m in (("psp", s["phase_psp"], lit), ("exact", s["phase_true"], lit & (s["mask"] > 0))):
        phase = phase.astype(np.float64)
        ratio[name] = fit_phase(phase, hp, m).rmse_rad / fit_phase(phase, h, m).rmse_rad
    return {"net_rmse_mm": net["object_rmse_mm"], "path_rmse_mm": pth["object_rmse_mm"],
            "path_median_mm": pth["median_abs_mm"], "net_right_order": net["right_order"],
            "path_right_order": pth["right_order"], "ratio_psp": ratio["psp"], "ratio_exact": ratio["exact"],
            "object_pixels": int(obj.sum())}


def summary(rows: list[dict]) -> dict:
    """Means over scenes; right-order shares pooled over the object pixels."""
    w = np.array([r["object_pixels"] for r in rows], float)
    out = {k: float(np.mean([r[k] for r in rows])) for k in KEYS}
    for k in ("net_right_order", "path_right_order"):
        out[k + "_pooled"] = float(np.sum(w * np.array([r[k] for r in rows])) / w.sum())
    return out


def report(result: dict) -> str:
    lines = ["# Fringe orders on rendered scenes", "",
             f"{result['scenes_count']} scenes from `{result['scenes']}` through `{result['rig']}`; object pixels: "
             "valid, more than 1 mm above the plane. Right order: |error| under half a fringe period of height. Ratio: "
             "the path's evaluate-phase residual over the network's (phase-shifting phase / exact phase).", "",
             "| run | network RMSE (mm) | path RMSE (mm) | path median (mm) | right order: network / path (pooled) "
             "| ratio (PSP) | ratio (exact) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for run, r in result["runs"].items():
        s = r["summary"]
        lines.append(f"| {run} | {s['net_rmse_mm']:.2f} | {s['path_rmse_mm']:.2f} | {s['path_median_mm']:.2f} | "
                     f"{s['net_right_order_pooled']:.3f} / {s['path_right_order_pooled']:.3f} | {s['ratio_psp']:.3f} | "
                     f"{s['ratio_exact']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, metavar="RUN", help="training runs (best.pt) or checkpoints")
    ap.add_argument("--out", required=True, metavar="DIR")
    ap.add_argument("--scenes", metavar="DIR", help="rendered scenes with phase-shifting images (default: render)")
    ap.add_argument("--count", type=int, default=16, help="scenes to render [16]")
    ap.add_argument("--seed", type=int, default=779, help="render seed [779]")
    ap.add_argument("--objects", default="1-3", metavar="LO-HI", help="objects per scene [1-3]")
    ap.add_argument("--meshes", nargs="+", default=[str(SHARED / "meshes"), str(ROOT / "assets" / "meshes")],
                    metavar="PATH", help="meshes to render [../shared/meshes assets/meshes]")
    ap.add_argument("--rig", default=str(ROOT / "assets" / "figshare_depth_rig.json"), metavar="FILE",
                    help="rig of the scenes and of the path [assets/figshare_depth_rig.json]")
    args = ap.parse_args(argv)
    try:
        return run(args)
    except (BenchError, FppsimError, UhrnetError, OSError, subprocess.CalledProcessError) as exc:
        print(f"orders_rendered: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("orders_rendered: interrupted; rendered.json / rendered.md not written", file=sys.stderr)
        return 130


def run(args) -> int:
    torch.set_num_threads(2)
    rig = load_rig(args.rig)
    models = {r: model_from_checkpoint(load_checkpoint(r), "cpu") for r in args.runs}  # every one checked first
    out = Path(args.out)
    if args.scenes and same_folder(out, args.scenes):
        raise BenchError(f"--out {out} is the --scenes folder: choose another --out")
    with output_folder(out, TOOL, error=BenchError):
        claim(out, TOOL, ["rendered.json", "rendered.md"])
        scenes = (Path(args.scenes) if args.scenes
                  else render(out, args.count, args.seed, args.objects, args.rig, args.meshes))
        if not scenes.is_dir():
            raise BenchError(f"--scenes {scenes}: no such folder")
        folders = sorted(p for p in scenes.iterdir() if (p / "arrays.npz").exists())
        if not folders:
            raise BenchError(f"no rendered scene (arrays.npz) in {scenes}")
        check_rig(scenes, rig)
        layer = layer_for(rig, (rig.camera.height, rig.camera.width))
        result = {"scenes": str(scenes), "scenes_count": len(folders), "rig": args.rig, "runs": {}}
        for run_name, (model, transform) in models.items():
            rows = []
            for f in folders:
                rows.append({"scene": f.name, **scene_scores(model, transform, f, rig, layer)})
                print(f"{run_name} {f.name}: right order {rows[-1]['net_right_order']:.3f} -> "
                      f"{rows[-1]['path_right_order']:.3f}", flush=True)
            result["runs"][run_name] = {"scenes": rows, "summary": summary(rows)}
        atomic_write_text(out / "rendered.json", json_text(result, indent=1))
        atomic_write_text(out / "rendered.md", report(result))
        stamp(out, ["rendered.json", "rendered.md"])  # edited later, they are no longer this tool's to replace
        print(report(result))
        return 0


if __name__ == "__main__":
    sys.exit(main())
