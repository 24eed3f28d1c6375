#!/usr/bin/env python
"""Benchmark the generator: samples/s at 640 x 352 against the rendering floor.

The floor is the two bare depth renders every sample needs (camera and projector shadow map) of the
same scene; the ratio "sample time / floor" is the cost of everything else (geometry, 13 images,
PSP decode, PNG + npz writing). Uses ../shared/meshes/ogre.obj when present, else fppsim/data/meshes.

    python pipelines/bench_generate.py [--mesh PATH] [--samples 10] [--no-psp] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None) -> int:
    from fppsim.formats import write_sample_folder
    from fppsim.generation import load_assets
    from fppsim.render import DepthRenderer
    from fppsim.rig import Rig
    from fppsim.scene import sample_scene
    from fppsim.synth import SynthConfig, synthesize

    default_mesh = ROOT.parent / "shared" / "meshes" / "ogre.obj"
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", default=str(default_mesh if default_mesh.is_file() else ROOT / "fppsim" / "data" / "meshes"),
                   help="mesh file or folder (default: ../shared/meshes/ogre.obj, else fppsim/data/meshes)")
    p.add_argument("--samples", type=int, default=10, help="timed samples (after one warm-up)")
    p.add_argument("--no-psp", action="store_true", help="single-shot image only")
    p.add_argument("--no-write", action="store_true", help="do not write the sample folders")
    p.add_argument("--supersample", type=int, default=1, choices=[1, 3, 5])
    p.add_argument("--json", help="write the numbers as JSON here")
    args = p.parse_args(argv)

    assets, skipped = load_assets([args.mesh])
    if not assets:
        print(f"bench: no usable mesh in {args.mesh}", file=sys.stderr)
        return 1
    rig = Rig.default()
    config = SynthConfig(rig=rig, supersample=args.supersample, psp_freqs=() if args.no_psp else (1, 8, 80))
    renderer = DepthRenderer()
    faces = sum(len(a.faces) for a in assets)
    tmp = Path(tempfile.mkdtemp(prefix="bench_generate_"))
    sample_t, floor_t = [], []
    for i in range(args.samples + 1):
        t0 = time.perf_counter()
        images, arrays, meta = synthesize(i, 0, assets, config, renderer)
        if not args.no_write:
            write_sample_folder(tmp, f"{i:06d}", images, arrays, meta)
        t1 = time.perf_counter()
        # the floor: two bare depth renders of the very same scene
        import numpy as np

        ss = np.random.SeedSequence([0, i, meta["attempt"]]).spawn(3)[0]
        scene = sample_scene(assets, rig, np.random.default_rng(ss), config.scene)
        inst = [o.instance() for o in scene.objects]
        t2 = time.perf_counter()
        renderer.depth(rig.camera, inst, args.supersample)
        renderer.depth(rig.projector, inst, 1)
        t3 = time.perf_counter()
        if i > 0:  # first sample warms up GL buffers and caches
            sample_t.append(t1 - t0)
            floor_t.append(t3 - t2)
    s, f = statistics.median(sample_t), statistics.median(floor_t)
    result = {
        "mesh": args.mesh, "faces": faces, "samples": args.samples, "psp": not args.no_psp,
        "write": not args.no_write, "supersample": args.supersample,
        "sample_s_median": s, "samples_per_s": 1.0 / s, "two_depth_renders_s_median": f, "cost_over_floor": s / f,
    }
    print(f"mesh: {args.mesh} ({faces} faces), 640 x 352, psp={'on' if result['psp'] else 'off'}, "
          f"write={'on' if result['write'] else 'off'}, supersample={args.supersample}")
    print(f"sample:              {1000 * s:8.1f} ms median  ({result['samples_per_s']:.2f} samples/s, one process)")
    print(f"two bare depth renders: {1000 * f:5.1f} ms median  (camera + projector)")
    print(f"cost over the rendering floor: {result['cost_over_floor']:.1f} x")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
