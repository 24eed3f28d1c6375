#!/usr/bin/env python
"""Benchmark the generator: samples/s at 640 x 352 against the rendering floor, and 2-worker throughput.

The floor is the two bare depth renders every sample needs (camera and projector shadow map) of the
same scenes; the ratio "sample time / floor" is the cost of everything else (geometry, 13 images,
PSP decode, PNG + npz writing). Samples run as ``fppsim generate`` runs them: each sample's folder is
written on the background writer thread while the next one renders. The machine may be shared, so
the run alternates blocks (``--block`` samples through the pipeline, then the floor renders of the
same scenes, writer idle) and reports the median over blocks of the wall-time ratio
(``cost_over_floor``) and of the process CPU-time ratio (``cpu_cost_over_floor``, all threads
including the rasteriser's: less sensitive to other processes).

``--workers-count N`` (default 400, 0 skips) also times the whole command
``fppsim generate --meshes ../shared/meshes assets/meshes --count N --seed 100 --workers 2 --no-psp
--format figshare`` in a fresh process (start-up, mesh loading, export included): ``workers2_samples_per_s``
(wall) and ``workers2_cpu_bound_samples_per_s`` (2 / CPU seconds per sample: what two idle cores give).
Uses ../shared/meshes/ogre.obj when present, else assets/meshes.

    python pipelines/bench_generate.py [--mesh PATH] [--samples 15] [--no-psp] [--no-write] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _pipeline_block(indices, assets, config, renderer, writer, tmp, write):
    """Wall and CPU seconds to produce (and write, on the writer thread) the samples ``indices``."""
    try:
        from fppsim.dataio.writers import write_sample_folder
    except ImportError:  # trees before fppsim.dataio.writers (fppsim.dataio.formats), or before the contract module (fppsim.dataset)
        try:
            from fppsim.dataio.formats import write_sample_folder
        except ImportError:
            from fppsim.dataset import write_sample_folder
    from fppsim.rendering.synth import synthesize

    attempts = {}
    w0, c0 = time.perf_counter(), time.process_time()
    for i in indices:
        images, arrays, meta = synthesize(i, 0, assets, config, renderer)
        attempts[i] = meta["attempt"]
        if write:
            writer.submit(write_sample_folder, tmp, f"{i:06d}", images, arrays, meta)
    if write:
        writer.flush()
    return time.perf_counter() - w0, time.process_time() - c0, attempts


def _floor_block(indices, attempts, assets, config, renderer):
    """Wall and CPU seconds of the two bare depth renders of the same scenes."""
    import numpy as np

    from fppsim.rendering.scene import sample_scene

    rig = config.rig
    scenes = []
    for i in indices:
        ss = np.random.SeedSequence([0, i, attempts[i]]).spawn(3)[0]
        scenes.append([o.instance() for o in sample_scene(assets, rig, np.random.default_rng(ss), config.scene).objects])
    w0, c0 = time.perf_counter(), time.process_time()
    for inst in scenes:
        renderer.depth(rig.camera, inst, config.supersample)
        renderer.depth(rig.projector, inst, 1)
    return time.perf_counter() - w0, time.process_time() - c0


def _workers_run(count: int, backend: str | None) -> tuple[float, float]:
    """(samples/s, CPU seconds per sample) of the 2-worker single-shot figshare command, timed as a
    whole; the CPU time covers the command and its workers (all threads)."""
    import resource

    meshes = [str(p) for p in (ROOT.parent / "shared" / "meshes", ROOT / "fppsim" / "data" / "meshes") if p.is_dir()]
    out = Path(tempfile.mkdtemp(prefix="bench_generate_w2_"))
    cmd = [sys.executable, "-m", "fppsim.cli", "generate", "-q", "--meshes", *meshes, "--out", str(out / "ds"),
           "--count", str(count), "--seed", "100", "--workers", "2", "--no-psp", "--format", "figshare"]
    if backend:
        cmd += ["--backend", backend]
    try:
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        return count / wall, cpu / count
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main(argv=None) -> int:
    default_mesh = ROOT.parent / "shared" / "meshes" / "ogre.obj"
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", default=str(default_mesh if default_mesh.is_file() else ROOT / "fppsim" / "data" / "meshes"),
                   help="mesh file or folder (default: ../shared/meshes/ogre.obj, else assets/meshes)")
    p.add_argument("--samples", type=int, default=15, help="timed samples (after one warm-up), in blocks")
    p.add_argument("--block", type=int, default=5, help="samples per timed block (default 5)")
    p.add_argument("--no-psp", action="store_true", help="single-shot image only")
    p.add_argument("--no-write", action="store_true", help="do not write the sample folders")
    p.add_argument("--supersample", type=int, default=1, choices=[1, 3, 5])
    p.add_argument("--backend", choices=["osmesa", "egl"], default=None,
                   help="GL backend (default: $PYOPENGL_PLATFORM, else osmesa)")
    p.add_argument("--workers-count", type=int, default=400,
                   help="samples of the timed 2-worker single-shot figshare run (default 400; 0 skips it)")
    p.add_argument("--json", help="write the numbers as JSON here")
    args = p.parse_args(argv)
    if args.backend:
        os.environ["PYOPENGL_PLATFORM"] = args.backend

    try:
        from fppsim.generation import load_assets
    except ImportError:  # trees before the library/CLI split (fppsim.generate was the module)
        from fppsim.generate import load_assets
    try:
        from fppsim.dataio.writers import BackgroundWriter
    except ImportError:  # trees before fppsim.dataio.writers
        from fppsim.pipeline import BackgroundWriter
    from fppsim.rendering.render import DepthRenderer
    from fppsim.geometry.rig import Rig
    from fppsim.rendering.synth import SynthConfig, synthesize

    assets, skipped = load_assets([args.mesh])
    if not assets:
        print(f"bench: no usable mesh in {args.mesh}", file=sys.stderr)
        return 1
    rig = Rig.default()
    config = SynthConfig(rig=rig, supersample=args.supersample, psp_freqs=() if args.no_psp else (1, 8, 80))
    renderer = DepthRenderer(backend=args.backend) if args.backend else DepthRenderer()
    writer = BackgroundWriter()
    faces = sum(len(a.faces) for a in assets)
    tmp = Path(tempfile.mkdtemp(prefix="bench_generate_"))
    try:
        synthesize(0, 0, assets, config, renderer)  # warm-up: GL context, mesh upload, caches
        blocks = []
        indices = list(range(1, args.samples + 1))
        for b in range(0, len(indices), max(1, args.block)):
            block = indices[b:b + max(1, args.block)]
            pw, pc, attempts = _pipeline_block(block, assets, config, renderer, writer, tmp, not args.no_write)
            fw, fc = _floor_block(block, attempts, assets, config, renderer)
            blocks.append((pw / len(block), pc / len(block), fw / len(block), fc / len(block)))
        writer.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s = statistics.median(b[0] for b in blocks)
    f = statistics.median(b[2] for b in blocks)
    result = {
        "mesh": args.mesh, "faces": faces, "samples": args.samples, "block": args.block, "psp": not args.no_psp,
        "write": not args.no_write, "supersample": args.supersample, "backend": getattr(renderer, "backend", "osmesa"),
        "sample_s_median": s, "samples_per_s": 1.0 / s, "two_depth_renders_s_median": f,
        "cost_over_floor": statistics.median(b[0] / b[2] for b in blocks),
        "cpu_cost_over_floor": statistics.median(b[1] / b[3] for b in blocks),
        "blocks": [dict(zip(("sample_s", "sample_cpu_s", "floor_s", "floor_cpu_s"), b)) for b in blocks],
    }
    print(f"mesh: {args.mesh} ({faces} faces), 640 x 352, psp={'on' if result['psp'] else 'off'}, "
          f"write={'on' if result['write'] else 'off'}, supersample={args.supersample}, backend={result['backend']}")
    print(f"sample:              {1000 * s:8.1f} ms median  ({result['samples_per_s']:.2f} samples/s, one process)")
    print(f"two bare depth renders: {1000 * f:5.1f} ms median  (camera + projector)")
    print(f"cost over the rendering floor: {result['cost_over_floor']:.2f} x wall, "
          f"{result['cpu_cost_over_floor']:.2f} x CPU time (median of {len(blocks)} blocks)")
    if args.workers_count > 0:
        result["workers2_count"] = args.workers_count
        rate, cpu = _workers_run(args.workers_count, args.backend)
        result["workers2_samples_per_s"] = rate
        result["workers2_cpu_s_per_sample"] = cpu
        # what two otherwise idle cores would give: the run's CPU time spread over both
        result["workers2_cpu_bound_samples_per_s"] = 2.0 / cpu
        print(f"--workers 2 --no-psp --format figshare, {args.workers_count} samples: {rate:.2f} samples/s wall; "
              f"{1000 * cpu:.0f} ms CPU per sample = {2.0 / cpu:.2f} samples/s on two idle cores")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, allow_nan=False))  # strict; runs in old trees too
    return 0


if __name__ == "__main__":
    sys.exit(main())
