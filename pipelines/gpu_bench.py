#!/usr/bin/env python
"""GPU benchmark steps driven by pipelines/gpu_bench.sh (each writes JSON into OUT).

    python pipelines/gpu_bench.py bench OUT      uhrnet bench: fp32, bf16, fp16, channels_last, compiled (batch 1)
                                                 and images/s over batch sizes
    python pipelines/gpu_bench.py epoch OUT      one AMP training epoch of UHRNet on 1,500 SYNTHETIC RANDOM tensors
                                                 (352 x 640; inputs uniform in [-1, 1], targets N(0, 1)); fp16
                                                 finiteness of loss and weights
    python pipelines/gpu_bench.py data OUT/DIR   a small figshare-layout set (random fringes and labels) for torchrun
    python pipelines/gpu_bench.py collect OUT    merge the step JSONs into OUT/gpu_bench.json

GPU_BENCH_TINY=1 shrinks every size (32 x 64 inputs, base width 4, 16 samples, 1 repeat) so the
plumbing can be dry-run on a CPU; without CUDA every step runs on the CPU (tiny) or is skipped.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

TINY = os.environ.get("GPU_BENCH_TINY", "0") not in ("", "0")
H, W = (32, 64) if TINY else (352, 640)


def _bench(out: Path, tag: str, extra: list[str]) -> dict | None:
    from uhrnet.cli import main

    path = out / f"bench_{tag}.json"
    size = ["--height", str(H), "--width", str(W)]
    reps = ["--repeats", "1", "--warmup", "1"] if TINY else ["--repeats", "20", "--warmup", "5"]
    base = ["--base-channels", "4"] if TINY else []
    rc = main(["bench", "--models", "uhrnet", "unet", *size, *reps, *base, *extra, "--json", str(path)])
    return json.loads(path.read_text()) if rc == 0 and path.is_file() else None


def step_bench(out: Path) -> dict:
    import torch

    cuda = torch.cuda.is_available()
    device = ["--device", "cuda" if cuda else "cpu"]
    configs = {"fp32": [], "bf16": ["--amp", "bf16"], "fp16": ["--amp", "fp16"],
               "fp16_channels_last": ["--amp", "fp16", "--channels-last"],
               "fp32_compiled": ["--compile"], "fp16_channels_last_compiled": ["--amp", "fp16", "--channels-last", "--compile"]}
    if not cuda:
        # fp16 convs are GPU-only; inductor's CPU compile of even tiny models takes minutes on a busy machine
        configs = {k: v for k, v in configs.items() if "fp16" not in k and "compiled" not in k}
        if not TINY:
            return {"skipped": "no CUDA device"}
    summary = {}
    for tag, extra in configs.items():
        t0 = time.perf_counter()
        try:
            report = _bench(out, tag, [*device, "--no-train", *extra])
        except Exception as exc:  # one failing configuration must not stop the others
            report, summary[tag] = None, {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}
        if report is not None:
            by = {r["model"]: r for r in report["results"]}
            summary[tag] = {"uhrnet_ms": by["uhrnet"]["forward_ms"], "unet_ms": by["unet"]["forward_ms"],
                            "ratio": report["uhrnet_unet_forward_ratio"], "seconds": time.perf_counter() - t0}
    best = min((k for k in summary if "uhrnet_ms" in summary[k]), key=lambda k: summary[k]["uhrnet_ms"], default=None)
    throughput = {}
    if best is not None:
        for batch in ([1, 2] if TINY else [1, 4, 8, 16, 32]):
            try:
                report = _bench(out, f"{best}_b{batch}", [*device, "--no-train", "--batch-size", str(batch), *configs[best]])
            except Exception as exc:  # out of memory at a large batch ends the sweep
                throughput[batch] = {"error": f"{type(exc).__name__}: {str(exc)[:120]}"}
                break
            if report is None:
                break
            by = {r["model"]: r for r in report["results"]}
            throughput[batch] = {m: 1000 * batch / by[m]["forward_ms"] for m in ("uhrnet", "unet")}
    return {"batch1": summary, "best_config": best, "images_per_s_by_batch": throughput,
            "paper_ms": {"uhrnet": 22.4, "unet": 8.1, "gpu": "RTX 2080 Ti"}}


def step_epoch(out: Path) -> dict:
    import torch

    from uhrnet.models import build_model

    cuda = torch.cuda.is_available()
    if not cuda and not TINY:
        return {"skipped": "no CUDA device"}
    device = torch.device("cuda" if cuda else "cpu")
    dtype = torch.float16 if cuda else torch.bfloat16
    n, batch = (16, 4) if TINY else (1500, 8)
    g = torch.Generator().manual_seed(0)
    model = build_model("uhrnet", **({"base_channels": 4} if TINY else {})).to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    scaler = torch.amp.GradScaler(device.type, enabled=cuda)
    losses, skipped = [], 0
    t0 = time.perf_counter()
    for start in range(0, n, batch):
        b = min(batch, n - start)
        x = (torch.rand((b, 1, H, W), generator=g) * 2 - 1).to(device, non_blocking=True)
        y = torch.randn((b, 1, H, W), generator=g).to(device, non_blocking=True)
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=dtype):
            loss = torch.nn.functional.mse_loss(model(x).float(), y)
        scale_before = scaler.get_scale() if scaler.is_enabled() else 1.0
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
        if scaler.is_enabled() and scaler.get_scale() < scale_before:
            skipped += 1  # an inf/nan gradient: the scaler skipped this step
        losses.append(float(loss.detach()))
    if cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    finite_weights = all(bool(torch.isfinite(p).all()) for p in model.parameters())
    return {"data": "synthetic random tensors (inputs uniform [-1, 1], targets N(0, 1)), generated on the fly",
            "samples": n, "batch_size": batch, "input": [H, W], "amp_dtype": str(dtype), "device": str(device),
            "epoch_seconds": seconds, "samples_per_s": n / seconds, "loss_first": losses[0], "loss_last": losses[-1],
            "all_losses_finite": all(map(lambda v: v == v and abs(v) != float("inf"), losses)),
            "weights_finite": finite_weights, "scaler_skipped_steps": skipped,
            "peak_memory_bytes": torch.cuda.max_memory_allocated() if cuda else None}


def step_data(folder: Path) -> dict:
    import numpy as np

    n = 12 if TINY else 48
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    xx = np.arange(W, dtype=np.float32)
    fringe = np.empty((n, H, W, 1), np.float32)
    label = np.empty((n, H, W, 1), np.float32)
    for i in range(n):
        height = rng.uniform(0, 30, (1, 1)) * np.hanning(H)[:, None] * np.hanning(W)[None, :]
        fringe[i, ..., 0] = np.cos(2 * np.pi * xx / 11.6 + 0.2 * height)
        label[i, ..., 0] = 6 * height - 97  # the figshare label preset
    np.save(folder / "f1_80.npy", fringe)
    np.save(folder / "Z.npy", label)
    return {"samples": n, "folder": str(folder)}


def collect(out: Path) -> dict:
    import platform

    try:
        import torch

        device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu (no CUDA device)"
        versions = {"torch": torch.__version__, "cuda": torch.version.cuda}
    except ImportError:
        device, versions = "unknown", {}
    steps = {}
    for name in ("bench", "epoch", "torchrun"):
        f = out / f"step_{name}.json"
        steps[name] = json.loads(f.read_text()) if f.is_file() else {"skipped": "did not run or failed"}
    report = {"kind": "gpu_bench", "device": device, "tiny_dry_run": TINY, "python": platform.python_version(),
              **versions, "steps": steps}
    from fppsim.files import json_text  # lazily, as uhrnet: the checkout comes on PYTHONPATH

    (out / "gpu_bench.json").write_text(json_text(report, indent=1) + "\n")
    return report


def shown(doc, limit: int | None = None, **dumps) -> str:
    """``doc`` as printed to stdout: strict JSON as the step files (a NaN timing is null, not a bare NaN), cut to
    ``limit`` characters (a preview in the step's log)."""
    from fppsim.files import json_text  # lazily, as uhrnet: the checkout comes on PYTHONPATH

    return json_text(doc, **dumps)[:limit]


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in ("bench", "epoch", "data", "collect"):
        print(__doc__, file=sys.stderr)
        return 2
    step, target = argv[0], Path(argv[1])
    if step == "collect":
        print(shown(collect(target), 4000, indent=1))
        return 0
    if step == "data":
        print(shown(step_data(target)))
        return 0
    target.mkdir(parents=True, exist_ok=True)
    result = step_bench(target) if step == "bench" else step_epoch(target)
    from fppsim.files import json_text  # lazily, as uhrnet: the checkout comes on PYTHONPATH

    (target / f"step_{step}.json").write_text(json_text(result, indent=1) + "\n")
    print(shown(result, 3000, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
