#!/usr/bin/env python
"""Training speed on this machine's GPU, before and after the speed options of issue 49, in one run
(``pipelines/gpu_check.sh``'s ``speed`` step; needs only torch and numpy).

    python pipelines/gpu_speed.py --out DIR [--tiny] [--bench-dir DIR] [--commit SHA] [--compile]

For each setting, ``before`` (every speed option off: float16 autocast with its scaler, DataLoader, the host
reading the loss and metrics every step, as the trainer ran before) and ``after`` (each option ``auto``: its
standard win on CUDA), it measures with the project's own trainer (:func:`uhrnet.train`):

- ``uhrnet_train_samples_per_s``: UHRNet at the paper's size (352 x 640), AMP, batch 8: training samples per
  second of whole epochs, validation included, the first epoch (warm-up, cuDNN's autotuning) left out;
- ``unet_recipe_seed_train_s``: one seed of the judged recipe (U-Net base 16, compound loss, 400 samples,
  10 epochs of 320 draws at batch 2 = 1,600 steps, lr 5e-4; the scaling study's seed): its epochs' seconds,
  validation included (``unet_recipe_seed_wall_s``: the whole call, data and model set-up too);
- ``uhrnet_step_share``: the share of a UHRNet step's time in data (the batch on the device), forward (with
  the loss), backward and optimizer, each phase timed apart (the device synchronised between phases: their
  sum is longer than an overlapped step; the shares say where the time goes).

The data are random scenes in the figshare layout (speed does not depend on what the images show). The report,
``DIR/speed.json``, is also written to ``--bench-dir`` (default ``docs/benchmarks/gpu``) as
``<date>_<card>.json``, with the commit it ran (``--commit``, else ``$STUDY_COMMIT``, else ``git rev-parse``).
``--tiny``: the plumbing at toy sizes, on a CPU too (the ``after`` options that run there asked for with
``on``, so their code runs); its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's uhrnet (run as a script)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from fppsim.files import json_text  # noqa: E402
from uhrnet.models import outputs_of  # noqa: E402
from uhrnet.training import builders  # noqa: E402
from uhrnet.training.distributed import DistInfo  # noqa: E402
from uhrnet.training.losses import STEP_FIELDS  # noqa: E402
from uhrnet.training.speed import to_layout  # noqa: E402
from uhrnet.training.trainer import TrainConfig, Trainer, train  # noqa: E402

KEYS = ("uhrnet_train_samples_per_s", "unet_recipe_seed_train_s", "device")
BEFORE = {"amp_dtype": "fp16", "channels_last": "off", "device_data": "off", "host_sync": "step", "fused_adam": "off",
          "compile": False}
AFTER = {"amp_dtype": "auto", "channels_last": "auto", "device_data": "auto", "host_sync": "auto", "fused_adam": "auto",
         "compile": False}
AFTER_ON_CPU = {**AFTER, "channels_last": "on", "device_data": "on", "host_sync": "epoch"}  # --tiny on a CPU
FULL = {"h": 352, "w": 640, "count": 400, "uhrnet_batch": 8, "uhrnet_epochs": 3, "uhrnet_draws": 400,
        "uhrnet_base": None, "recipe_epochs": 10, "recipe_draws": 320, "recipe_base": 16, "profile_steps": 30}
TINY = {"h": 32, "w": 64, "count": 12, "uhrnet_batch": 2, "uhrnet_epochs": 2, "uhrnet_draws": 4,
        "uhrnet_base": 4, "recipe_epochs": 2, "recipe_draws": 4, "recipe_base": 4, "profile_steps": 3}


def write_scenes(folder: Path, n: int, h: int, w: int, seed: int = 0) -> Path:
    """``n`` random scenes (a few smooth blobs on a plane, vertical fringes, a shadow) in the figshare layout."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    fr = np.lib.format.open_memmap(folder / "f1_80.npy", "w+", np.float32, (n, h, w, 1))
    z = np.lib.format.open_memmap(folder / "Z.npy", "w+", np.float32, (n, h, w, 1))
    for i in range(n):
        hmm = np.zeros((h, w), np.float32)
        for _ in range(rng.integers(1, 4)):
            cy, cx, r, a = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(0.1, 0.3) * h, rng.uniform(5, 40)
            hmm += a * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r))
        valid = ~((xx > w * 0.9) & (hmm < 1.0))
        f8 = np.rint(127.5 + 100 * np.cos(2 * np.pi * xx / 16 + 0.2 * hmm))
        fr[i, ..., 0] = np.where(valid, f8 / 127.5 - 1, -1.0)
        z[i, ..., 0] = np.where(valid, hmm * 6.0 - 97.0, -105.0)
    fr.flush()
    z.flush()
    return folder


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def step_shares(cfg: TrainConfig, steps: int) -> dict:
    """Seconds per phase of ``steps`` UHRNet steps of the run ``cfg`` (the trainer's own pieces), each phase
    timed apart; returns their shares and the mean step time."""
    t = Trainer(cfg, DistInfo())
    dev, ddp, opt = t.device, t.network.ddp, t.optimizer
    ddp.train()
    phases = dict.fromkeys(("data", "forward", "backward", "optimizer"), 0.0)
    batches = iter(t.data.loader)
    for k in range(steps + 1):  # the first step is a warm-up, not counted
        _sync(dev)
        t0 = time.perf_counter()
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(t.data.loader)
            batch = next(batches)
        x, y, m = (batch[f].to(dev, non_blocking=True) for f in STEP_FIELDS)
        x = to_layout(x, t.speed)
        _sync(dev)
        t1 = time.perf_counter()
        with builders.autocast(t.amp, dev, t.speed.amp_dtype):
            out = ddp(x)
        loss = sum(t.loss_fn(o.float(), y, m) for o in outputs_of(out))
        _sync(dev)
        t2 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        t.scaler.scale(loss).backward()
        _sync(dev)
        t3 = time.perf_counter()
        t.scaler.step(opt)
        t.scaler.update()
        _sync(dev)
        t4 = time.perf_counter()
        if k:
            for name, dt in zip(phases, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                phases[name] += dt
    total = sum(phases.values())
    return {"share": {k: v / total for k, v in phases.items()}, "step_ms": 1e3 * total / steps,
            "note": "phases timed apart (device synchronised between them), first step left out"}


def _steady(history: list) -> float:
    secs = [float(r["seconds"]) for r in history]
    steady = secs[1:] or secs
    return sum(steady) / len(steady)


def measure(setting: dict, data: Path, work: Path, sizes: dict, device: str, amp: bool, recipe_amp: bool = False) -> dict:
    """The numbers of one setting (module docstring); ``recipe_amp``: the recipe once more with ``--amp``
    (``unet_recipe_amp_seed_train_s``: whether a GPU seed may use it is for the seed spread to say)."""
    common = dict(synthetic=[str(data)], device=device, seed=0, progress=False, overwrite=True, **setting)
    uh = TrainConfig(out=str(work / "uhrnet"), model="uhrnet", base_channels=sizes["uhrnet_base"], loss="compound",
                     epochs=sizes["uhrnet_epochs"], batch_size=sizes["uhrnet_batch"], lr=3e-4,
                     samples_per_epoch=sizes["uhrnet_draws"], amp=amp, **common)
    res = train(uh)
    out = {"settings": dict(setting), "uhrnet_train_samples_per_s": sizes["uhrnet_draws"] / _steady(res["history"]),
           "uhrnet_epoch_seconds": [float(r["seconds"]) for r in res["history"]]}
    recipe = TrainConfig(out=str(work / "recipe"), model="unet", base_channels=sizes["recipe_base"], loss="compound",
                         epochs=sizes["recipe_epochs"], batch_size=2, lr=5e-4, samples_per_epoch=sizes["recipe_draws"],
                         threads=2, **common)
    t0 = time.perf_counter()
    res = train(recipe)
    out["unet_recipe_seed_wall_s"] = time.perf_counter() - t0
    secs = [float(r["seconds"]) for r in res["history"]]
    out["unet_recipe_seed_train_s"] = sum(secs)
    out["unet_recipe_steps"] = sizes["recipe_epochs"] * -(-sizes["recipe_draws"] // 2)
    out["unet_recipe_samples_per_s"] = sizes["recipe_draws"] / _steady(res["history"])
    if recipe_amp:
        res = train(dataclasses.replace(recipe, out=str(work / "recipe_amp"), amp=True))
        out["unet_recipe_amp_seed_train_s"] = sum(float(r["seconds"]) for r in res["history"])
    prof = TrainConfig(out=str(work / "profile"), model="uhrnet", base_channels=sizes["uhrnet_base"], loss="compound",
                       epochs=1, batch_size=sizes["uhrnet_batch"], lr=3e-4, amp=amp, **common)
    out["uhrnet_step"] = step_shares(prof, sizes["profile_steps"])
    return out


def commit_of(given: str | None) -> str:
    if given:
        return given
    if os.environ.get("STUDY_COMMIT"):
        return os.environ["STUDY_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (no git; give --commit or STUDY_COMMIT)"


def bench_name(device: str, when: float) -> str:
    """``<date>_<card>.json``: the UTC date and the card's name in lower case, runs of other characters as '-'."""
    card = re.sub(r"[^a-z0-9]+", "-", device.lower()).strip("-") or "unknown"
    return f"{time.strftime('%Y-%m-%d', time.gmtime(when))}_{card}.json"


def report(before: dict, after: dict, *, commit: str, device: str, tiny: bool, sizes: dict) -> dict:
    """The run's record: ``before`` and ``after`` each with :data:`KEYS`, the ``after`` numbers at the top too."""
    before, after = {**before, "device": device}, {**after, "device": device}
    return {"kind": "gpu_speed", "commit": commit, "device": device, "torch": torch.__version__,
            "cuda": torch.version.cuda, "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
            "tiny_dry_run": tiny, "amp": torch.cuda.is_available(), "sizes": sizes,
            **{k: after[k] for k in KEYS}, "before": before, "after": after,
            "speedup": {"uhrnet_train": after["uhrnet_train_samples_per_s"] / before["uhrnet_train_samples_per_s"],
                        "unet_recipe_seed": before["unet_recipe_seed_train_s"] / after["unet_recipe_seed_train_s"]}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="work folder; the report is OUT/speed.json")
    p.add_argument("--tiny", action="store_true", help="toy sizes (a CPU dry run of the plumbing)")
    p.add_argument("--bench-dir", type=Path, default=ROOT / "docs" / "benchmarks" / "gpu",
                   help="where the dated report goes too [docs/benchmarks/gpu]")
    p.add_argument("--commit", help="the commit measured [$STUDY_COMMIT, else git rev-parse HEAD]")
    p.add_argument("--compile", action="store_true", help="'after' with torch.compile too")
    p.add_argument("--recipe-amp", action="store_true", help="'after' also times the recipe with --amp")
    args = p.parse_args(argv)
    cuda = torch.cuda.is_available()
    if not cuda and not args.tiny:
        print("gpu_speed: no CUDA device here (--tiny dry-runs on the CPU)", file=sys.stderr)
        return 2
    device = torch.cuda.get_device_name(0) if cuda else "cpu"
    sizes = dict(TINY if args.tiny else FULL)
    after = {**(AFTER if cuda else AFTER_ON_CPU), "compile": bool(args.compile)}
    args.out.mkdir(parents=True, exist_ok=True)
    data = write_scenes(args.out / "data", sizes["count"], sizes["h"], sizes["w"])
    runs = {}
    for name, setting in (("before", BEFORE), ("after", after)):
        print(f"gpu_speed: {name}: {setting}", flush=True)
        runs[name] = measure(setting, data, args.out / name, sizes, "cuda" if cuda else "cpu", amp=cuda,
                             recipe_amp=args.recipe_amp and name == "after")
    rec = report(runs["before"], runs["after"], commit=commit_of(args.commit), device=device, tiny=args.tiny,
                 sizes=sizes)
    text = json_text(rec, indent=1) + "\n"
    (args.out / "speed.json").write_text(text)
    args.bench_dir.mkdir(parents=True, exist_ok=True)
    dest = args.bench_dir / bench_name(device, time.time())
    if dest.exists():  # a second run that day: its time too
        dest = dest.with_name(dest.stem + time.strftime("_%H%M%S", time.gmtime()) + ".json")
    dest.write_text(text)
    (args.out / "bench_name.txt").write_text(dest.name + "\n")
    print(f"gpu_speed: {args.out / 'speed.json'} and {dest}", flush=True)
    for name in ("before", "after"):
        r = rec[name]
        print(f"  {name}: UHRNet {r['uhrnet_train_samples_per_s']:.1f} samples/s, recipe seed "
              f"{r['unet_recipe_seed_train_s']:.1f} s, step shares "
              + ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["uhrnet_step"]["share"].items()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
