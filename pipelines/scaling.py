#!/usr/bin/env python
"""Scaling study of the sim-to-real recipe: arms x training seeds, resumable, one command (issue 32).

Each ARM is a set of ``uhrnet sim2real`` options (sample count, epochs, extra ``fppsim generate`` /
``uhrnet train`` flags) read from an arms file (default ``pipelines/scaling_arms.yaml``); each arm runs once
per training SEED (``uhrnet train --seed``; the synthetic data, generator seed 100, is the same for every
seed of an arm, so the spread is the training seed's). Every (arm, seed) is a sim-to-real experiment run in
this process through the workflow layer (``uhrnet.workflows.sim2real.run_sim2real(Sim2RealConfig)``):

    OUT/<arm>/                 the arm's sim2real folder: data/<key> (its synthetic set, shared by its seeds),
                               report.md / report.json (every finished seed of the arm)
    OUT/<arm>/s<seed>/         one (arm, seed): run/ (training), eval/ (real metrics, phase residuals), logs
    OUT/scaling.json           every arm: the exact equivalent command lines, per-seed results, mean +- std
    OUT/scaling_table.md       the same as a table (OUT: or beside --ledger FILE)
    OUT/scaling_samples.png    pair object RMSE (with its level / relief parts) and held-out phase residual
    OUT/scaling_steps.png      against synthetic samples (arms of series "samples") and training steps ("steps")

A killed study resumes with the same command: sim2real re-uses finished datasets, runs and evaluations and
continues an interrupted training run; a finished (arm, seed) is not touched. ``--report-only`` rebuilds
the JSON, table and figures from the finished folders without running anything.

    python pipelines/scaling.py --arms n100 n400 n1600 n6400 --seeds 0 1 2 \\
        --real ../shared/real-sample --real-phase ../shared/real-phase --out runs/scaling
    python pipelines/scaling.py --list                          # the arms and their commands; runs nothing
    python pipelines/scaling.py --out runs/scaling --report-only
    python pipelines/scaling.py --arms n100 n400 --device cuda --jobs 2 --deadline 500 --out runs/s  # on a GPU
    python pipelines/scaling.py --ledger docs/experiments/scaling.json --merge study.json  # a record from elsewhere

Results per seed (``scaling.json``): ``pair_object_rmse_mm`` (object RMSE on the labelled real pair(s), mean
over images), its split into ``pair_level_rmse_mm`` (each connected object region's median error) and
``pair_relief_rmse_mm`` (the rest), the exact mean split (``pair_level_rmse_mean_mm`` /
``pair_relief_rmse_mean_mm``: level^2 + relief^2 = RMSE^2; :func:`uhrnet.workflows.sim2real.metrics.error_split`) and
``phase_residual_rad`` (``uhrnet evaluate-phase``'s calibration-free residual on each held-out real
phase-shifting frame). Per arm: mean and sample standard deviation (ddof 1) over the finished seeds.

Arms file (YAML/JSON): ``{defaults: {...}, arms: [{name, description, series, count, epochs, batch_size, lr,
base_channels, model, loss, workers, scale, generate, train}, ...]}``; ``defaults`` apply to every arm,
``generate`` / ``train`` are flag strings (or lists) of ``fppsim generate`` / ``uhrnet train``, relative
paths in them are taken from the current folder, else from the repository root. ``series``: the figures the
arm is a point of (``samples``: x = its sample count; ``steps``: x = its optimizer steps).

Exit status: 0 done; 1 an (arm, seed) failed (the others still ran; its log is named); 2 bad usage (arms
file, arm names, seeds, real folders, flags), refused before anything runs.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared"
DEFAULT_ARMS = ROOT / "pipelines" / "scaling_arms.yaml"
# arm keys that are Sim2RealConfig fields, with their `uhrnet sim2real` flags
CONFIG_FLAGS = {"scale": "--scale", "count": "--count", "epochs": "--epochs", "batch_size": "--batch-size",
                "lr": "--lr", "base_channels": "--base-channels", "model": "--model", "loss": "--loss",
                "workers": "--workers"}
ARM_KEYS = {"name", "description", "series", "generate", "train", *CONFIG_FLAGS}
SERIES = {"samples": ("count", "synthetic samples generated"), "steps": ("steps", "optimizer steps")}
# what a seed reports (scaling.json key <- real_metrics mean key)
PAIR_KEYS = {"pair_object_rmse_mm": "object_rmse_mm", "pair_level_rmse_mm": "object_level_rmse_mm",
             "pair_relief_rmse_mm": "object_relief_rmse_mm", "pair_level_rmse_mean_mm": "object_level_rmse_mean_mm",
             "pair_relief_rmse_mean_mm": "object_relief_rmse_mean_mm", "pair_regions": "object_regions",
             "pair_valid_rmse_mm": "valid_rmse_mm", "pair_median_abs_mm": "object_median_abs_mm",
             "pair_within_1mm": "object_within_1mm", "pair_relief_effect_mm": "relief_effect_mm"}


class UsageProblem(Exception):
    """Bad input, found before anything runs (exit 2)."""


# ============================================================================================ arms file
def _flags(value, where: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            raise UsageProblem(f"{where}: {exc}") from None
    if isinstance(value, list):
        return [str(v) for v in value]
    raise UsageProblem(f"{where}: expected a flag string or a list, got {type(value).__name__}")


def _resolve_paths(flags: list[str]) -> list[str]:
    """Relative paths in flags that do not exist from the current folder but do from the repository root
    (e.g. ``assets/figshare_depth_rig.json``) become absolute."""
    out = []
    for f in flags:
        if not f.startswith("-") and not Path(f).is_absolute() and not Path(f).exists() and (ROOT / f).exists():
            f = str(ROOT / f)
        out.append(f)
    return out


def _typed(key: str, value, where: str):
    """An arm's sim2real option as its flag would parse it (YAML reads ``5e-4`` as text, ``lr: 5e-4`` is meant)."""
    kind = float if key == "lr" else str if key in ("scale", "model", "loss") else int
    try:
        if kind is int and (isinstance(value, bool) or float(value) != int(float(value))):
            raise ValueError
        return kind(int(float(value))) if kind is int else kind(value)
    except (TypeError, ValueError):
        what = {float: "a number", int: "an integer", str: "text"}[kind]
        raise UsageProblem(f"{where}: {key} must be {what}, got {value!r}") from None


def load_arms(path: str | Path) -> list[dict]:
    """The arms of an arms file (module docstring), each with ``generate`` / ``train`` as flag lists,
    ``series`` as a list and the ``defaults`` applied; :class:`UsageProblem` names what is wrong."""
    from uhrnet.workflows.stages import read_config_file

    p = Path(path)
    doc = read_config_file(p, "arms file", UsageProblem)
    if not isinstance(doc, dict) or not isinstance(doc.get("arms"), list) or not doc["arms"]:
        raise UsageProblem(f"{p}: expected a mapping with a non-empty list 'arms' (and optional 'defaults')")
    unknown = set(doc) - {"arms", "defaults"}
    defaults = doc.get("defaults") or {}
    if unknown or not isinstance(defaults, dict):
        raise UsageProblem(f"{p}: top-level keys are 'arms' and 'defaults' (a mapping), got {sorted(doc)}")
    arms, names = [], set()
    for i, item in enumerate(doc["arms"]):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise UsageProblem(f"{p}: arm {i} must be a mapping with a 'name'")
        item = {**defaults, **item}
        name = item["name"]
        bad = sorted(set(item) - ARM_KEYS)
        if bad:
            raise UsageProblem(f"{p}: arm {name!r} has unknown keys {bad} (known: {sorted(ARM_KEYS)})")
        if not name or name in names or any(c in name for c in "/\\ \t:|") or name.startswith("."):
            raise UsageProblem(f"{p}: arm name {name!r} must be a unique word without slashes, spaces, ':' or '|'")
        names.add(name)
        series = item.get("series") or []
        series = [series] if isinstance(series, str) else list(series)
        if any(s not in SERIES for s in series):
            raise UsageProblem(f"{p}: arm {name!r}: series must be of {sorted(SERIES)}, got {series}")
        arm = {"name": name, "description": str(item.get("description") or ""), "series": series,
               "generate": _resolve_paths(_flags(item.get("generate"), f"{p}: arm {name!r}: generate")),
               "train": _resolve_paths(_flags(item.get("train"), f"{p}: arm {name!r}: train"))}
        for key in CONFIG_FLAGS:
            if item.get(key) is not None:
                arm[key] = _typed(key, item[key], f"{p}: arm {name!r}")
        arms.append(arm)
    return arms


# ============================================================================================ one (arm, seed)
def phase_folders(dirs: list[str]) -> list[str]:
    """Real phase-shifting folders: each given folder, or the scan folders inside it (e.g. ../shared/real-phase
    -> ../shared/real-phase/FP1523)."""
    from fppsim.dataio.readers import is_psp_folder

    out = []
    for d in dirs:
        p = Path(d)
        inner = sorted(str(s) for s in p.iterdir() if s.is_dir() and is_psp_folder(s)) if p.is_dir() else []
        out += [str(d)] if is_psp_folder(p) or not inner else inner
    return out


def seed_folder(out: Path, arm: dict, seed: int) -> Path:
    return out / arm["name"] / f"s{seed}"


def arm_config(arm: dict, seed: int, args) -> tuple[object, list[str]]:
    """``(Sim2RealConfig, argv)``: the sim-to-real experiment of ``arm`` at training ``seed`` (its one variant
    ``s<seed>``, in ``OUT/<arm>``) and the ``uhrnet sim2real`` command line that runs exactly the same."""
    from uhrnet.cli import variant_commands
    from uhrnet.workflows.sim2real import Sim2RealConfig
    from uhrnet.workflows.sim2real.variants import VariantFlags, variant_from_flags

    out = Path(args.out) / arm["name"]
    given = {k: arm[k] for k in CONFIG_FLAGS if k in arm}
    if args.device:
        given["device"] = args.device
    if args.workers is not None:
        given["workers"] = args.workers
    cfg = Sim2RealConfig(out=str(out), real=list(args.real), meshes=list(args.meshes), real_phase=list(args.real_phase),
                         figures=not args.no_figures, **given)
    train = (list(arm["train"]) + (["--resize", args.resize] if args.resize else [])
             + (["--threads", str(args.threads)] if args.threads else []) + ["--seed", str(seed)])
    flags = VariantFlags(f"s{seed}", list(arm["generate"]), train)
    variant = variant_from_flags(cfg, flags, variant_commands())
    cfg = replace(cfg, variants=[variant])
    argv = ["uhrnet", "sim2real", "--real", *cfg.real, "--out", str(out), "--meshes", *cfg.meshes]
    for key, flag in CONFIG_FLAGS.items():
        if key in given:
            argv += [flag, str(given[key])]
    if "device" in given:
        argv += ["--device", given["device"]]
    if cfg.real_phase:
        argv += ["--real-phase", *cfg.real_phase]
    if args.no_figures:
        argv.append("--no-figures")
    argv += ["--variant", f"{flags.name}: {shlex.join(flags.generate)} | {shlex.join(flags.train)}"]
    return cfg, argv


def _variant(cfg, seed: int):
    return next(v for v in cfg.variants if v.name == f"s{seed}")


def steps_of(cfg, variant) -> int:
    """Optimizer steps of the variant's training run: epochs x ceil(draws per epoch / batch size), the draws
    being ``--samples-per-epoch`` or the reference split's training samples (80 % of the count)."""
    from uhrnet.data.splits import MIN_REFERENCE_SPLIT, split_indices

    tr = variant.train
    epochs, batch = int(tr.get("epochs") or cfg.epochs), int(tr.get("batch_size") or cfg.batch_size)
    draws = tr.get("samples_per_epoch")
    if not draws:
        draws = len(split_indices(cfg.count, "train")) if cfg.count >= MIN_REFERENCE_SPLIT else cfg.count
    return epochs * math.ceil(int(draws) / batch)


TABLE_MARK = "<!-- written by pipelines/scaling.py from scaling.json; do not edit -->"
RECORD = "study.json"  # OUT/<arm>/s<seed>/study.json: what the seed is and the command that ran it


def _same_folders(have, want) -> bool:
    """Whether two lists of folders name the same folders (resolved paths: ``../shared/x`` and its absolute
    path are one folder)."""
    def key(f):
        try:
            return str(Path(f).resolve())
        except OSError:
            return str(f)
    return {key(f) for f in have} == {key(f) for f in want}


COMMIT_RE = r"[0-9a-f]{40}"  # what $STUDY_COMMIT must be: a full commit


def code_version() -> dict:
    """``{"commit": HEAD of this checkout or None, "dirty": uncommitted changes to tracked files}``.

    ``$STUDY_COMMIT`` (40 hex digits), when set, is the commit whose tree this is, given by whoever copied the
    checkout elsewhere (a lent GPU machine gets the working tree, on top of the git folder of an older commit:
    its HEAD would be wrong). It is recorded as the commit (``"commit_from": "STUDY_COMMIT"``), beside what the
    copy's git says (``checkout_head``, ``checkout_dirty``)."""
    import os
    import re
    import subprocess

    def git(*a):
        return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True, timeout=30)
    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
        seen = {"commit": head.stdout.strip(), "dirty": bool(dirty.stdout.strip())} if not head.returncode else None
    except (OSError, subprocess.SubprocessError):
        seen = None
    given = os.environ.get("STUDY_COMMIT", "")
    if re.fullmatch(COMMIT_RE, given):
        return {"commit": given, "dirty": None, "commit_from": "STUDY_COMMIT",
                "checkout_head": seen and seen["commit"], "checkout_dirty": seen and seen["dirty"]}
    return seen or {"commit": None, "dirty": None}


def _rel(path: str) -> str:
    """A path as the recorded commands give it: relative to the repository root (they run from there)."""
    import os

    p = Path(path)
    return os.path.relpath(p.resolve(), ROOT) if p.exists() or p.is_absolute() else str(path)


def study_command(args, arm: dict, seed: int | list[int]) -> list[str]:
    """The ``python pipelines/scaling.py`` command, run from the repository root, that runs exactly this
    (arm, seed) (or these seeds): every input the study reads named explicitly (no default taken from the
    folder layout)."""
    seeds = [seed] if isinstance(seed, int) else list(seed)
    argv = ["python", "pipelines/scaling.py", "--arms-file", _rel(args.arms_file), "--arms", arm["name"],
            "--seeds", *map(str, seeds), "--out", _rel(args.out), "--real", *map(_rel, args.real),
            "--real-phase", *(map(_rel, args.real_phase) if args.real_phase else ["none"]),
            "--meshes", *map(_rel, args.meshes)]
    for flag, value in (("--resize", args.resize), ("--threads", args.threads), ("--device", args.device),
                        ("--workers", args.workers)):
        if value is not None:
            argv += [flag, str(value)]
    return argv + (["--no-figures"] if args.no_figures else [])


def seed_record(args, arm: dict, seed: int, cfg, argv: list[str]) -> dict:
    """What ``OUT/<arm>/s<seed>/study.json`` holds: the seed's identity (arm, seed, resize, device) and how it
    ran (the exact commands, the code's commit, torch and its CPU threads)."""
    import platform

    import torch

    gpu = torch.cuda.get_device_name(0) if cfg.device != "cpu" and torch.cuda.is_available() else None
    return {"arm": arm["name"], "seed": seed, "resize": args.resize, "device": cfg.device,
            "command": shlex.join(study_command(args, arm, seed)), "sim2real_command": shlex.join(argv),
            **code_version(), "torch": torch.__version__, "torch_threads": args.threads or torch.get_num_threads(),
            **({"gpu": gpu} if gpu else {}), "python": platform.python_version(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def seed_result(folder: Path, cfg, variant) -> dict | None:
    """The results of a finished (arm, seed) folder (``OUT/<arm>/s<seed>``), None when it is not a finished
    run OF THIS (arm, seed): found by what the folder holds, not by its path: a run with ``last.pt`` at the
    variant's epochs whose recorded training options and dataset are the variant's (resize, seed, samples per
    epoch, ...; :func:`~uhrnet.workflows.sim2real.run_differences`), an evaluation newer than it of the same
    real folders (resolved paths) with the level / relief split and, with ``cfg.real_phase``, the phase
    residuals of exactly those frames."""
    from uhrnet.workflows.sim2real import run_differences, train_config
    from uhrnet.workflows.sim2real.config import data_key
    from uhrnet.run_folder import CONFIG_JSON, LAST_PT, fresh, read_history, run_done

    run, ev = folder / "run", folder / "eval"
    epochs = int(variant.train.get("epochs") or cfg.epochs)
    if not run_done(run, epochs) or not fresh(ev / "real_metrics.json", run / LAST_PT):
        return None
    if run_differences(run, train_config(cfg, variant, "DATA", run), cfg.count, cfg.seed):
        return None
    try:
        recorded = json.loads((run / CONFIG_JSON).read_text())
        metrics = json.loads((ev / "real_metrics.json").read_text())
        frames = json.loads((ev / "real_phase.json").read_text())["frames"] if cfg.real_phase else []
        record = json.loads((folder / RECORD).read_text()) if (folder / RECORD).is_file() else {}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if [Path(f).name for f in recorded.get("synthetic") or []] != [data_key(variant.generate)]:
        return None
    if not _same_folders([r["folder"] for r in metrics.get("per_image", [])], cfg.real) \
            or "object_level_rmse_mm" not in metrics.get("mean", {}):
        return None
    if cfg.real_phase and not (fresh(ev / "real_phase.json", run / LAST_PT)
                               and _same_folders([f["folder"] for f in frames], cfg.real_phase)):
        return None
    rows = read_history(run)
    out = {"folder": str(folder)}
    out.update({k: metrics["mean"].get(src) for k, src in PAIR_KEYS.items()})
    out["pair_images"] = metrics["images"]
    out["pair_regions_per_image"] = [{"image": f"{Path(r['folder']).name}/{r['index']}",
                                      "regions": r.get("object_region_errors")} for r in metrics["per_image"]]
    out["phase_residual_rad"] = {f"{Path(f['folder']).name}/{f['id']}": f["rmse_rad"] for f in frames}
    out["phase_flat_rad"] = {f"{Path(f['folder']).name}/{f['id']}": f["flat_rmse_rad"] for f in frames}
    out["synthetic_val_rmse_mm"] = rows[-1].get("val_rmse_mm")
    out["epochs"] = int(rows[-1]["epoch"])
    timing = folder / "timing.json"
    out["minutes"] = (sum(v for v in json.loads(timing.read_text()).values() if isinstance(v, (int, float))) / 60.0
                      if timing.is_file() else None)
    for key in ("command", "sim2real_command", "commit", "dirty", "commit_from", "checkout_head", "checkout_dirty",
                "device", "torch", "torch_threads", "gpu", "started"):
        if key in record:
            out[key] = record[key]
    out.setdefault("device", cfg.device)
    return out


# ============================================================================================ summary, figures
def _mean_std(values: list) -> dict:
    import numpy as np

    v = np.array([x for x in values if x is not None and np.isfinite(x)], float)
    return {"mean": float(v.mean()) if v.size else None, "std": float(v.std(ddof=1)) if v.size > 1 else None,
            "n": int(v.size)}


def summarise(seeds: list[dict]) -> dict:
    """Per-arm mean and sample standard deviation (ddof 1; None with fewer than 2 seeds) of every result."""
    out = {k: _mean_std([s.get(k) for s in seeds]) for k in (*PAIR_KEYS, "synthetic_val_rmse_mm", "minutes")}
    frames = sorted({f for s in seeds for f in s.get("phase_residual_rad", {})})
    out["phase_residual_rad"] = {f: _mean_std([s["phase_residual_rad"].get(f) for s in seeds]) for f in frames}
    out["n_seeds"] = len(seeds)
    return out


def _cell(stat: dict, fmt: str = ".2f") -> str:
    if not stat or stat.get("mean") is None:
        return ""
    return format(stat["mean"], fmt) + (f" ± {format(stat['std'], fmt)}" if stat.get("std") is not None else "")


def markdown(doc: dict) -> str:
    """``scaling_table.md``: one line per arm, mean ± std over its finished seeds."""
    frames = sorted({f for a in doc["arms"] for f in a["summary"]["phase_residual_rad"]})
    lines = ["# Scaling study of the sim-to-real recipe", "",
             "Mean ± sample standard deviation over the finished training seeds (n). Pair: the labelled real "
             "pair(s); level / relief: the object RMSE split over connected object regions (median split); phase: "
             "calibration-free residual on held-out real frames (rad). Commands: scaling.json.", "",
             "| arm | samples | steps | n | pair object RMSE (mm) | level (mm) | relief (mm) |"
             + "".join(f" {f} (rad) |" for f in frames) + " minutes / seed |",
             "|---|---|---|---|---|---|---|" + "---|" * len(frames) + "---|"]
    for a in doc["arms"]:
        s = a["summary"]
        lines.append(f"| {arm_label(a)} | {a.get('count', '')} | {a.get('steps', '')} | {s['n_seeds']} | "
                     f"{_cell(s['pair_object_rmse_mm'])} | "
                     f"{_cell(s['pair_level_rmse_mm'])} | {_cell(s['pair_relief_rmse_mm'])} |"
                     + "".join(f" {_cell(s['phase_residual_rad'].get(f, {}), '.3f')} |" for f in frames)
                     + f" {_cell(s['minutes'], '.1f')} |")
    descriptions = {a["name"]: a.get("description") for a in doc["arms"]}
    lines += ["", "Arms marked @HxW trained at that size (uhrnet train --resize), [cuda] on a GPU; the rest at full "
              "size on the CPU.", "", *[f"- {n}: {d}" for n, d in descriptions.items() if d]]
    lines += _what_moves(doc, frames)
    return "\n".join(lines) + "\n"


REFERENCE_ARM = "n400"  # the judged recipe: every arm is compared with it on the same device and size


def compare(arm: dict, ref: dict, key: str, frame: str | None = None) -> dict | None:
    """``arm`` against ``ref`` on one result (``key``, or a phase ``frame``), both with at least 2 seeds:
    ``diff`` (difference of the means), ``spread`` (the larger of the two seed standard deviations),
    ``beyond`` (|diff| > spread: the project's rule, a difference inside the seed spread is no difference) and
    Welch's ``t`` (diff / sqrt(s1²/n1 + s2²/n2))."""
    import math

    def stat(a):
        return a["summary"]["phase_residual_rad"].get(frame, {}) if frame else a["summary"].get(key, {})
    x, r = stat(arm), stat(ref)
    if not x or not r or x.get("std") is None or r.get("std") is None:
        return None
    diff, spread = x["mean"] - r["mean"], max(x["std"], r["std"])
    se = math.sqrt(x["std"] ** 2 / x["n"] + r["std"] ** 2 / r["n"])
    t = diff / se if se > 0 else (math.copysign(math.inf, diff) if diff else math.nan)
    return {"diff": diff, "spread": spread, "beyond": abs(diff) > spread, "t": t}


def series_slope(arms: list[dict], key: str, frame: str | None = None, means: bool = False) -> dict | None:
    """Least-squares slope of the results against log2(samples) over ``arms`` (one device and size): ``slope``
    per doubling, its standard error and 95 % interval (Student t), ``n`` points. Every seed is a point, or
    with ``means`` every arm's mean: an arm's seeds share its synthetic data, so the per-seed interval counts
    them as independent (optimistic); the arm means' interval has only n - 2 degrees of freedom
    (conservative). None with fewer than 3 points or 2 sample counts."""
    import numpy as np
    from scipy import stats

    x, y = [], []
    for a in arms:
        vals = [s_.get("phase_residual_rad", {}).get(frame) if frame else s_.get(key) for s_ in a["seeds"]]
        vals = [v for v in vals if v is not None and np.isfinite(v)]
        if means and vals:
            vals = [float(np.mean(vals))]
        x += [np.log2(a["count"])] * len(vals)
        y += vals
    if len(x) < 3 or len(set(x)) < 2:
        return None
    fit = stats.linregress(x, y)
    half = stats.t.ppf(0.975, len(x) - 2) * fit.stderr
    return {"slope": fit.slope, "stderr": fit.stderr, "low": fit.slope - half, "high": fit.slope + half, "n": len(x)}


def _what_moves(doc: dict, frames: list[str]) -> list[str]:
    """The table's second part: each arm against n400 on the same device (beyond the seed spread or not) and
    the samples series' slope per doubling."""
    def cell(f):
        return "" if f is None else f"{f['slope']:+.3f} ± {f['stderr']:.3f} [{f['low']:+.3f}, {f['high']:+.3f}]"

    lines = []
    groups: dict = {}
    for a in doc["arms"]:
        groups.setdefault((a.get("device", "cpu"), a.get("resize")), []).append(a)
    for (device, resize), arms in groups.items():
        where = device + (f" @{resize}" if resize else "")
        ref = next((a for a in arms if a["name"] == REFERENCE_ARM), None)
        rows = []
        for a in arms:
            if ref is None or a is ref:
                continue
            cells = [compare(a, ref, "pair_object_rmse_mm"), *(compare(a, ref, "", f) for f in frames)]
            if not any(cells):
                continue
            rows.append(f"| {arm_label(a)} | " + " | ".join(
                "" if c is None else f"{c['diff']:+.2f} ({'beyond' if c['beyond'] else 'within'} ±{c['spread']:.2f}; "
                                     f"t {c['t']:+.1f})" for c in cells) + " |")
        if rows:
            lines += ["", f"## Against {REFERENCE_ARM} ({where})", "",
                      "Difference of the means (arm - n400); 'beyond' when it exceeds the larger seed standard "
                      "deviation of the two arms (a difference inside the seed spread is no difference); t: Welch's.",
                      "", "| arm | pair object RMSE (mm) |" + "".join(f" {f} (rad) |" for f in frames),
                      "|---|---|" + "---|" * len(frames), *rows]
        samples = [a for a in arms if "samples" in a.get("series", []) and a.get("count")]
        fits = [(label, series_slope(samples, key, frame), series_slope(samples, key, frame, means=True))
                for label, key, frame in [("pair object RMSE (mm)", "pair_object_rmse_mm", None),
                                          *((f"{f} (rad)", "", f) for f in frames)]]
        fits = [(label, f, m) for label, f, m in fits if f]
        if fits and len({a["count"] for a in samples}) > 2:
            lines += ["", f"## Samples series slope ({where}: {', '.join(arm_label(a) for a in samples)})", "",
                      "Least-squares slope against log2(samples), per doubling of the synthetic samples at the same "
                      "steps, ± its standard error [95 % interval]: every seed a point (an arm's seeds share its "
                      "data, so this interval is optimistic) and every arm's mean a point (conservative).", "",
                      "| result | every seed | seeds | arm means | arms |", "|---|---|---|---|---|",
                      *[f"| {label} | {cell(f)} | {f['n']} | {cell(m)} | {m['n'] if m else ''} |"
                        for label, f, m in fits]]
    return lines


GOALS = {"pair_object_rmse_mm": 4.5, "phase_residual_rad": 1.32}  # issue 35's targets (dashed in the figures)


def plot_series(doc: dict, series: str, path: Path) -> Path | None:
    """Pair object RMSE with its level and relief parts (left) and each phase frame's residual (right), mean
    ± std over seeds (single seeds as dots), against the arms' x of ``series``: one row per device (full-size
    arms only; a CPU and a GPU seed are different computations); the goals of :data:`GOALS` dashed. None when
    no arm has a result."""
    import numpy as np

    from fppsim.plots import pyplot, save_figure

    key, xlabel = SERIES[series]
    arms = [a for a in doc["arms"] if series in a.get("series", []) and a["seeds"] and not a.get("resize")]
    devices = sorted({a.get("device", "cpu") for a in arms}, key=lambda d: (d != "cpu", d))
    if not arms:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(len(devices), 2, figsize=(12, 4.2 * len(devices)), squeeze=False)
    parts = (("pair_object_rmse_mm", "object RMSE", "k", "o"),
             ("pair_level_rmse_mm", "level (region medians)", "C3", "s"),
             ("pair_relief_rmse_mm", "relief (rest)", "C0", "^"))
    for ax, device in zip(axes, devices):
        row = sorted((a for a in arms if a.get("device", "cpu") == device), key=lambda a: a[key])
        x = np.array([a[key] for a in row], float)
        for k, label, color, marker in parts:
            mean = np.array([a["summary"][k]["mean"] if a["summary"][k]["mean"] is not None else np.nan for a in row])
            std = np.array([a["summary"][k]["std"] or 0.0 for a in row])
            ax[0].errorbar(x, mean, yerr=std, color=color, marker=marker, capsize=4, label=label)
            for xi, a in zip(x, row):
                ys = [s_[k] for s_ in a["seeds"] if s_.get(k) is not None]
                ax[0].plot([xi] * len(ys), ys, ".", color=color, alpha=0.35)
        ax[0].axhline(GOALS["pair_object_rmse_mm"], color="k", ls="--", lw=1,
                      label=f"goal {GOALS['pair_object_rmse_mm']} mm")
        ax[0].set_ylabel("labelled real pair (mm)")
        ax[0].set_ylim(bottom=0)
        ax[0].set_title(f"{device}: real pair object RMSE, its level and relief parts", fontsize=10)
        frames = sorted({f for a in row for f in a["summary"]["phase_residual_rad"]})
        for j, f in enumerate(frames):
            mean = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("mean") or np.nan for a in row])
            std = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("std") or 0.0 for a in row])
            ax[1].errorbar(x, mean, yerr=std, color=f"C{j}", marker="o", capsize=4, label=f)
            for xi, a in zip(x, row):
                ys = [s_["phase_residual_rad"][f] for s_ in a["seeds"] if f in s_.get("phase_residual_rad", {})]
                ax[1].plot([xi] * len(ys), ys, ".", color=f"C{j}", alpha=0.35)
        if frames:
            ax[1].axhline(GOALS["phase_residual_rad"], color="k", ls="--", lw=1,
                          label=f"goal {GOALS['phase_residual_rad']} rad")
        ax[1].set_ylabel("phase residual (rad)")
        ax[1].set_ylim(bottom=0)
        ax[1].set_title(f"{device}: held-out real phase frames" if frames else "held-out real phase frames: none given",
                        fontsize=10)
        n = sorted({a["summary"]["n_seeds"] for a in row})
        ax[0].text(0.01, 0.02, f"{'/'.join(map(str, n))} seed(s): " + ", ".join(arm_label(a) for a in row),
                   transform=ax[0].transAxes, fontsize=7)
        for a_ in ax:
            a_.set_xscale("log", base=2)
            a_.set_xticks(x, [f"{int(v)}" for v in x])
            a_.set_xlabel(xlabel)
            a_.grid(alpha=0.3)
            if a_.get_legend_handles_labels()[0]:
                a_.legend(fontsize=7)
    fig.suptitle(f"sim-to-real scaling ({series}): mean ± std over training seeds (dots: each seed), full size",
                 fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)


def arm_label(entry: dict) -> str:
    """An arm's name in tables and figures: its name, the resize and a device other than the CPU."""
    return entry["name"] + (f" @{entry['resize']}" if entry.get("resize") else "") + \
        (f" [{entry['device']}]" if entry.get("device", "cpu") != "cpu" else "")


def _key(entry: dict) -> tuple:
    return entry["name"], entry.get("resize"), entry.get("device", "cpu")


def _strict_json(text: str):
    """``json.loads`` that refuses NaN and Infinity (not JSON; a record holding them is not strict JSON)."""
    def bad(name):
        raise ValueError(f"non-finite number {name}")
    return json.loads(text, parse_constant=bad)


def load_ledger(path: Path, role: str = "--ledger") -> dict:
    """The results recorded so far in ``path`` (a ``scaling.json``; ``{"arms": []}`` when there is none).
    Files of the first version (arm-level ``commands``, no resize or device) are read too: the resize comes
    from their commands, the device is the CPU. Anything else is refused (:class:`UsageProblem`, naming
    ``role``: ``--ledger`` for the record written, ``--merge`` for one read into it): the report replaces only
    a study record, and a record holds strict JSON (no NaN), each arm (name, resize, device) once."""
    import re

    hint = "name another --ledger" if role == "--ledger" else "nothing merged"
    if not path.exists():
        return {"arms": []}
    try:
        doc = _strict_json(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        why = str(exc) if str(exc).startswith("non-finite") else type(exc).__name__
        raise UsageProblem(f"{role} {path}: not a readable scaling.json ({why}); {hint}") from None
    if not (isinstance(doc, dict) and isinstance(doc.get("arms"), list)
            and all(isinstance(a, dict) and isinstance(a.get("name"), str) and isinstance(a.get("seeds"), list)
                    for a in doc["arms"])):
        raise UsageProblem(f"{role} {path}: not a scaling study record (no list of arms with seeds); {hint}")
    bad = next((a["name"] for a in doc["arms"] for s_ in a["seeds"]
                if not (isinstance(s_, dict) and isinstance(s_.get("seed"), int) and not isinstance(s_["seed"], bool))),
               None)
    if bad is not None:
        raise UsageProblem(f"{role} {path}: arm {bad!r} holds a seed entry without an integer 'seed'; "
                           f"not a study record; {hint}")
    for arm in doc["arms"]:
        commands = arm.pop("commands", None) or []
        if "resize" not in arm:
            sizes = {m for c in commands for m in re.findall(r"--resize[ =]([0-9]+x[0-9]+)", c)}
            arm["resize"] = sizes.pop() if len(sizes) == 1 else None
        arm.setdefault("device", "cpu")
        arm.pop("missing_seeds", None)
        for seed in arm["seeds"]:
            seed.setdefault("device", arm["device"])
            if "command" not in seed and "sim2real_command" not in seed:
                match = [c for c in commands if f"--seed {seed['seed']}'" in c]
                if match:
                    seed["sim2real_command"] = match[0]
    keys = [_key(a) for a in doc["arms"]]
    twice = next((k for k in keys if keys.count(k) > 1), None)
    if twice is not None:
        raise UsageProblem(f"{role} {path}: holds arm {arm_label(dict(zip(('name', 'resize', 'device'), twice)))} "
                           f"twice; not a study record; {hint}")
    for arm in doc["arms"]:
        seeds = [s_["seed"] for s_ in arm["seeds"]]
        if len(set(seeds)) != len(seeds):
            raise UsageProblem(f"{role} {path}: arm {arm_label(arm)} holds a seed twice; not a study record; {hint}")
    return doc


def _same_result(a: dict, b: dict) -> bool:
    keys = ("pair_object_rmse_mm", "phase_residual_rad", "commit", "synthetic_val_rmse_mm")
    return all(a.get(k) == b.get(k) for k in keys)


def write_report(args, arms: list[dict], configs: dict) -> dict:
    """Add the finished (arm, seed) folders under ``args.out`` to the study record ``args.ledger`` (default
    ``OUT/scaling.json``) and rewrite it, its table (``scaling_table.md``) and figures beside it.

    Nothing recorded is lost: a seed is keyed by (arm, resize, device, seed); results already in the record
    stay whether or not their folders are still here, and a folder whose result differs from the recorded one
    (another commit, or a re-run) keeps the earlier result in the seed's ``reruns``."""
    out, ledger = Path(args.out), Path(args.ledger)
    entries = {_key(a): a for a in load_ledger(ledger)["arms"]}
    found, pending = 0, []
    for arm in arms:
        for seed in args.seeds:
            cfg, argv = configs[arm["name"], seed]
            var = _variant(cfg, seed)
            res = seed_result(seed_folder(out, arm, seed), cfg, var)
            if res is None:
                pending.append(f"{arm['name']} s{seed}")
                continue
            found += 1
            res.setdefault("command", shlex.join(study_command(args, arm, seed)))
            res.setdefault("sim2real_command", shlex.join(argv))
            meta = {"name": arm["name"], "resize": args.resize, "device": res["device"],
                    "description": arm["description"], "series": arm["series"], "count": cfg.count,
                    "epochs": int(var.train.get("epochs") or cfg.epochs), "steps": steps_of(cfg, var),
                    **{k: getattr(cfg, k) for k in ("batch_size", "lr", "base_channels", "model", "loss", "scale")},
                    "generate": arm["generate"], "train": arm["train"]}
            _add_seed(entries, meta, _finite({"seed": seed, **res}),
                      f"arm {arm['name']!r} of {args.arms_file} against --ledger {ledger}")
    return _write_ledger(args, ledger, entries, found, pending)


# what defines an arm beside its key (name, resize, device): seeds of two definitions are never pooled
DEFINITION = ("count", "epochs", "steps", "batch_size", "lr", "base_channels", "model", "loss", "scale",
              "generate", "train")


def _flag_key(value):
    """An arm's flag list as compared between records: absolute paths by their name (another machine's
    checkout has another root)."""
    if isinstance(value, list):
        return [Path(v).name if isinstance(v, str) and v.startswith("/") else v for v in value]
    return value


def definition_conflict(have: dict, new: dict) -> str | None:
    """How ``new``'s arm definition differs from ``have``'s (``"count 50 vs 400, epochs 2 vs 10"``), over the
    :data:`DEFINITION` keys both give; None when they agree (a key only one gives is no conflict: records of
    the first version carry fewer)."""
    diffs = [f"{k} {new[k]} vs {have[k]}" for k in DEFINITION
             if have.get(k) is not None and new.get(k) is not None and _flag_key(have[k]) != _flag_key(new[k])]
    return ", ".join(diffs) or None


def _check_finite(value, where: str) -> None:
    """Refuse a non-finite number anywhere in ``value`` (:class:`UsageProblem` naming ``where``)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise UsageProblem(f"{where}: holds a non-finite number ({value}); a study record holds finite numbers")
    if isinstance(value, dict):
        for v in value.values():
            _check_finite(v, where)
    elif isinstance(value, list):
        for v in value:
            _check_finite(v, where)


def _finite(value):
    """``value`` with every non-finite number None (a finished folder's metric that could not be computed)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def _add_seed(entries: dict, meta: dict, new: dict, source: str = "the arms file") -> str:
    """Put one seed's result ``new`` into the arm entry of ``meta`` (its name, resize, device, definition and
    description) in ``entries`` (keyed by :func:`_key`): a seed recorded before with another result keeps
    that under ``reruns``. An arm recorded with another definition (:data:`DEFINITION`) is refused
    (:class:`UsageProblem` naming ``source``): its seeds are not the recorded arm's. Returns ``"added"``,
    ``"rerun"`` (another result for a recorded seed) or ``"same"`` (already recorded: nothing changed)."""
    entry = entries.get(_key(meta))
    if entry is not None:
        conflict = definition_conflict(entry, meta)
        if conflict:
            raise UsageProblem(f"{source}: arm {arm_label(meta)} is not the recorded {arm_label(entry)} ({conflict}): "
                               "its seeds would be pooled with another recipe's; rename the arm or use another "
                               "--ledger (nothing written)")
    entry = entries.setdefault(_key(meta), {"name": meta["name"], "resize": meta.get("resize"),
                                            "device": meta.get("device", "cpu"), "seeds": []})
    entry.update({k: v for k, v in meta.items() if k not in ("name", "resize", "device", "seeds", "summary")})
    old = next((s for s in entry["seeds"] if s["seed"] == new["seed"]), None)
    status = "added"
    if old is not None:
        if old == new:
            return "same"
        entry["seeds"].remove(old)
        earlier = old.pop("reruns", [])
        mine = [r for r in new.pop("reruns", []) if r not in earlier]
        status = "same" if _same_result(old, new) and not mine else "rerun"
        if not _same_result(old, new):
            earlier = [*earlier, old]
        if earlier or mine:
            new["reruns"] = [*earlier, *mine]
    entry["seeds"] = sorted([*entry["seeds"], new], key=lambda s: s["seed"])
    return status


def merge_records(args) -> dict:
    """``--merge FILE ...``: add every seed of the study records FILE (e.g. brought back from a GPU machine) to
    ``args.ledger``, with the same rules as a finished folder (nothing recorded is dropped; a differing
    result keeps the earlier one under ``reruns``; an arm of another definition under the same name, or a
    non-finite number, refuses the whole merge before anything is written), and rewrite its table and
    figures. The record returned counts ``found`` (seeds added or re-run) and ``merge_counts``."""
    ledger = Path(args.ledger)
    entries = {_key(a): a for a in load_ledger(ledger)["arms"]}
    counts = {"added": 0, "rerun": 0, "same": 0}
    for path in args.merge:
        if not Path(path).is_file():
            raise UsageProblem(f"--merge {path}: no such file")
        if Path(path).resolve() == ledger.resolve():
            raise UsageProblem(f"--merge {path}: is the --ledger itself")
        for arm in load_ledger(Path(path), "--merge")["arms"]:
            meta = {k: v for k, v in arm.items() if k not in ("seeds", "summary")}
            _check_finite(meta, f"--merge {path}: arm {arm_label(arm)}")
            for seed in arm["seeds"]:
                _check_finite(seed, f"--merge {path}: arm {arm_label(arm)} seed {seed['seed']}")
                counts[_add_seed(entries, meta, dict(seed), f"--merge {path}")] += 1
    doc = _write_ledger(args, ledger, entries, counts["added"] + counts["rerun"], [])
    doc["merge_counts"] = counts
    return doc


STUDY_TOOL = "pipelines/scaling.py"


def claim_beside(ledger: Path, files: list[Path]) -> None:
    """Claim the files written beside ``ledger`` (its table and figures) in the folder's ownership record
    (:mod:`fppsim.owned`) before anything is written: a file there that the study did not write (a user's
    ``study_samples.png``) is refused (:class:`UsageProblem`). A folder without a record adopts the table
    scaling.py wrote (its first line) and, with it, that ledger's figures."""
    from fppsim.errors import ForeignFiles
    from fppsim.owned import claim

    folder = ledger.parent
    table = files[0]

    def legacy():
        try:
            ours = table.is_file() and table.read_text(errors="replace").startswith(TABLE_MARK)
        except OSError:
            ours = False
        return [f.name for f in files] if ours else []
    try:
        claim(folder, STUDY_TOOL, [f.name for f in files], legacy=legacy,
              hint="move it away or name another --ledger (nothing written)")
    except ForeignFiles as exc:
        raise UsageProblem(str(exc)) from None


def _write_ledger(args, ledger: Path, entries: dict, found: int, pending: list[str]) -> dict:
    """Write the study record ``ledger`` from ``entries`` (arms in the arms file's order), its table and its
    figures; returns the record with ``found`` / ``pending`` added."""
    from fppsim.files import atomic_write_text

    order = {a["name"]: i for i, a in enumerate(load_arms(args.arms_file))}
    arm_list = sorted(entries.values(), key=lambda a: (order.get(a["name"], len(order)), a["name"],
                                                       a.get("resize") or "", a.get("device", "cpu")))
    for entry in arm_list:
        entry["summary"] = summarise(entry["seeds"])
    doc = {"study": "sim-to-real scaling (pipelines/scaling.py)", "arms_file": _rel(args.arms_file),
           "arms": arm_list}
    table = ledger.with_name(f"{ledger.stem}_table.md")
    if table.exists() and not (table.is_file() and table.read_text(errors="replace").startswith(TABLE_MARK)):
        raise UsageProblem(f"{table}: exists and was not written by scaling.py; move it away")
    try:
        text = json.dumps(doc, indent=2, allow_nan=False)
    except ValueError:
        raise UsageProblem(f"--ledger {ledger}: a result is not a finite number; nothing written") from None
    ledger.parent.mkdir(parents=True, exist_ok=True)
    figures = {series: ledger.with_name(f"{ledger.stem}_{series}.png") for series in SERIES}
    claim_beside(ledger, [table, *figures.values()])
    atomic_write_text(ledger, text)
    atomic_write_text(table, TABLE_MARK + "\n" + markdown(doc))
    for series, path in figures.items():
        fig = plot_series(doc, series, path)
        print(f"figure: {fig}" if fig else f"figure {path.name}: no finished full-size arm of series {series!r}")
    doc["found"], doc["pending"] = found, pending
    return doc


# ============================================================================================ main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="scaling.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="study folder (created; re-running the same command resumes it)")
    p.add_argument("--arms-file", default=str(DEFAULT_ARMS), help="YAML/JSON arms file [%(default)s]")
    p.add_argument("--arms", nargs="+", metavar="NAME", help="arms to run, in this order [every arm of the file]")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], metavar="N",
                   help="training seeds (uhrnet train --seed) of every arm [0 1 2]")
    real = SHARED / "real-sample"
    p.add_argument("--real", nargs="+", metavar="DIR", default=[str(real)] if real.is_dir() else None,
                   help="labelled real figshare-format folder(s), evaluation only [../shared/real-sample when present]")
    phase = SHARED / "real-phase"
    p.add_argument("--real-phase", nargs="+", metavar="DIR", default=[str(phase)] if phase.is_dir() else [],
                   help="held-out real phase-shifting folder(s), or a folder of them ('none': no phase residual) "
                        "[../shared/real-phase when present]")
    p.add_argument("--meshes", nargs="+", metavar="PATH", default=None,
                   help="meshes of the synthetic scenes [../shared/meshes (when present) and assets/meshes]")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="training device [the arm's scale: cpu]")
    p.add_argument("--workers", type=int, metavar="N", help="generator processes, 0: all cores [the scale's: 2]")
    p.add_argument("--resize", metavar="HxW", help="uhrnet train --resize HxW for every arm (e.g. quick looks)")
    p.add_argument("--threads", type=int, default=2, metavar="N",
                   help="uhrnet train --threads N for every arm: a seeded run repeats bit for bit only at the same "
                        "CPU thread count (0: torch's default, the cores) [2, the recipe's machine]")
    p.add_argument("--no-figures", action="store_true", help="no per-image figure of the real pairs (sim2real's)")
    p.add_argument("--ledger", metavar="FILE",
                   help="the study record the finished seeds are added to (never dropping one already recorded); "
                        "its table and figures are written beside it [OUT/scaling.json]")
    p.add_argument("--report-only", action="store_true",
                   help="add the finished folders to the record, rewrite its table and figures; run nothing")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="arms run at once, each in its own process (its seeds one after another: they share the "
                        "arm's folder), e.g. several arms on one GPU; output lines start with the arm [1]")
    p.add_argument("--deadline", type=float, metavar="SECONDS",
                   help="stop after this many seconds: the running seeds are interrupted (the same command "
                        "resumes them), no new one starts, and the finished ones are recorded [no limit]")
    p.add_argument("--merge", nargs="+", metavar="FILE",
                   help="add the seeds of these study records (e.g. a scaling.json brought back from a GPU "
                        "machine) to --ledger and rewrite its table and figures; runs nothing, needs no --out")
    p.add_argument("--no-report", action="store_true",
                   help="run only, write no record (what --jobs gives each arm's process; the parent reports)")
    p.add_argument("--list", action="store_true", help="print the arms and their commands; run nothing")
    return p.parse_args(argv)


def check_merge(args) -> None:
    """``--merge``'s own checks (:class:`UsageProblem`): a --ledger to merge into, nothing to run."""
    if not args.ledger:
        raise UsageProblem("--merge: give the study record to merge into as --ledger FILE")
    if Path(args.ledger).is_dir():
        raise UsageProblem(f"--ledger {args.ledger}: is a folder (give the scaling.json file)")
    if args.out or args.report_only or args.list or args.arms:
        raise UsageProblem("--merge runs nothing: give it no --out, --arms, --report-only or --list")
    load_arms(args.arms_file)  # the arms' order in the table


def check(args) -> tuple[list[dict], dict]:
    """Arms chosen and every (arm, seed)'s ``(Sim2RealConfig, argv)``; :class:`UsageProblem` before anything runs."""
    import os
    import re

    from uhrnet.errors import UhrnetError
    from uhrnet.run_folder import default_meshes
    from uhrnet.workflows.sim2real import (
        Sim2RealError, find_phase_frames, find_real_pairs, generate_config, train_config,
    )

    arms = load_arms(args.arms_file)
    by_name = {a["name"]: a for a in arms}
    if args.arms:
        unknown = [n for n in args.arms if n not in by_name]
        if unknown or len(set(args.arms)) != len(args.arms):
            raise UsageProblem(f"--arms: unknown or repeated arm(s) {', '.join(unknown) or 'repeated'} "
                               f"(arms of {args.arms_file}: {', '.join(by_name)})")
        arms = [by_name[n] for n in args.arms]
    if any(s < 0 for s in args.seeds) or len(set(args.seeds)) != len(args.seeds):
        raise UsageProblem(f"--seeds: distinct non-negative integers, got {args.seeds}")
    if not args.out and not args.list:
        raise UsageProblem("--out DIR is required")
    given = os.environ.get("STUDY_COMMIT")
    if given is not None and not re.fullmatch(COMMIT_RE, given):
        raise UsageProblem(f"STUDY_COMMIT={given!r}: give the full commit (40 lowercase hex digits, "
                           "git rev-parse HEAD) or unset it")
    if not 1 <= args.jobs <= 64:
        raise UsageProblem(f"--jobs: 1 to 64 arms at once, got {args.jobs}")
    if args.deadline is not None and not (math.isfinite(args.deadline) and 0 < args.deadline <= 30 * 86400):
        raise UsageProblem(f"--deadline: seconds, more than 0 and at most 30 days, got {args.deadline}")
    if not args.real:
        raise UsageProblem("--real DIR: no labelled real folder given (../shared/real-sample is absent)")
    args.meshes = args.meshes or default_meshes(SHARED)
    args.real_phase = [] if args.real_phase in (["none"], None) else phase_folders(args.real_phase)
    args.out = args.out or "OUT"
    args.ledger = args.ledger or str(Path(args.out) / "scaling.json")
    if Path(args.ledger).is_dir():
        raise UsageProblem(f"--ledger {args.ledger}: is a folder (give the scaling.json file)")
    if args.report_only or not args.list:
        load_ledger(Path(args.ledger))  # an unreadable record is refused before anything runs
    if args.report_only and not Path(args.out).is_dir():
        raise UsageProblem(f"--report-only: {args.out} " + ("is a file, not a study folder" if Path(args.out).exists()
                                                           else "does not exist (nothing to report)"))
    configs = {}
    try:
        if not args.list:
            find_real_pairs(args.real)
            find_phase_frames(args.real_phase)
        for arm in arms:
            for seed in args.seeds:
                cfg, argv = configs[arm["name"], seed] = arm_config(arm, seed, args)
                var = _variant(cfg, seed)  # the stage configs check themselves (e.g. a bad --resize)
                generate_config(cfg, var, "DATA")
                train_config(cfg, var, "DATA", "RUN")
    except (Sim2RealError, UhrnetError, ValueError) as exc:
        raise UsageProblem(str(exc).strip().splitlines()[0]) from None
    return arms, configs


def _cfg_var(configs: dict, arm: dict, seed: int):
    cfg = configs[arm["name"], seed][0]
    return cfg, _variant(cfg, seed)


def _write_record(folder: Path, record: dict) -> None:
    """Write the seed's ``study.json``; a seed resumed later keeps its first record (the commit it started
    at) and lists every later start under ``resumes``."""
    from fppsim.files import atomic_write_text

    path = folder / RECORD
    try:
        first = json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError):
        first = None
    if isinstance(first, dict) and first.get("arm") == record["arm"] and first.get("seed") == record["seed"]:
        first.setdefault("resumes", []).append({k: record[k] for k in ("commit", "dirty", "torch_threads", "started")})
        record = first
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(record, indent=2))


def run(args, arms: list[dict], configs: dict) -> int:
    """Every (arm, seed) not finished yet, in order; 1 if one failed (the others still run)."""
    from uhrnet.workflows.sim2real.variants import recipe_commands
    from uhrnet.errors import UhrnetError
    from fppsim.errors import FppsimError
    from uhrnet.workflows.sim2real import run_sim2real

    out, t_start, failed = Path(args.out), time.perf_counter(), []
    todo = [(arm, seed) for arm in arms for seed in args.seeds]
    for i, (arm, seed) in enumerate(todo, 1):
        cfg, argv = configs[arm["name"], seed]
        tag = f"[{i}/{len(todo)} {arm['name']} seed {seed}]"
        folder = seed_folder(out, arm, seed)
        if seed_result(folder, cfg, _variant(cfg, seed)) is not None:
            print(f"{tag} finished before: re-used", flush=True)
            continue
        # the arm's other finished seeds ride along (re-used, nothing re-run) so OUT/<arm>/report.md lists them all
        done = [_variant(configs[arm["name"], s][0], s) for s in args.seeds if s != seed
                and seed_result(seed_folder(out, arm, s), *_cfg_var(configs, arm, s)) is not None]
        if done:
            cfg = replace(cfg, variants=sorted([*done, _variant(cfg, seed)], key=lambda v: int(v.name[1:])))
        _write_record(folder, seed_record(args, arm, seed, cfg, argv))
        print(f"{tag} start ({(time.perf_counter() - t_start) / 60:.1f} min into the study): {shlex.join(argv)}",
              flush=True)
        t0 = time.perf_counter()

        def say(line, t0=t0, seed=seed):
            if line.startswith((f"[s{seed}]", f"[s{seed} ")):
                print(f"  {(time.perf_counter() - t0) / 60:5.1f} min  {line}", flush=True)

        try:
            run_sim2real(cfg, log=say, recipe=recipe_commands)
        except (UhrnetError, FppsimError, ValueError, OSError) as exc:
            failed.append(f"{arm['name']} seed {seed}")
            print(f"{tag} failed after {(time.perf_counter() - t0) / 60:.1f} min: {str(exc).strip().splitlines()[0]}",
                  file=sys.stderr, flush=True)
            continue
        res = seed_result(folder, cfg, _variant(cfg, seed)) or {}
        parts = ", ".join(f"{k} {res[v]:.2f} mm" for k, v in (("pair object RMSE", "pair_object_rmse_mm"),
                          ("level", "pair_level_rmse_mm"), ("relief", "pair_relief_rmse_mm")) if res.get(v) is not None)
        phase = ", ".join(f"{f} {v:.3f} rad" for f, v in res.get("phase_residual_rad", {}).items())
        print(f"{tag} done in {(time.perf_counter() - t0) / 60:.1f} min: {parts}{'; ' + phase if phase else ''}",
              flush=True)
    if failed:
        print(f"scaling.py: error: failed: {', '.join(failed)} (re-run the same command to retry; logs in "
              f"{out}/<arm>/s<seed>/train.log and {out}/<arm>/data/*.log)", file=sys.stderr)
    return 1 if failed else 0


GRACE_S = 8.0  # a stopped arm's time to exit after SIGINT before SIGKILL (gpu_check's guard allows 10 s)
PARENT_ENV = "SCALING_PARENT_PID"  # set for the arms' processes: they die with the process that started them


def run_jobs(args, arms: list[dict], started: float) -> int:
    """Run the arms in up to ``args.jobs`` processes at once (``scaling.py --arms ARM --no-report``: each arm's
    seeds one after another, since they share the arm's folder), their output echoed with the arm's name and
    kept in ``OUT/<arm>/scaling.log``. At ``args.deadline`` seconds after ``started`` (``time.monotonic()``; or on Ctrl-C /
    SIGTERM) the running ones are interrupted (SIGINT to each process group, SIGKILL :data:`GRACE_S` later): a
    seed cut off resumes with the same command. Returns 1 if an arm failed, 130 / 143 when interrupted
    (SIGINT / SIGTERM), else 0; arms left at the deadline are reported pending."""
    import os
    import signal
    import subprocess
    import threading

    out = Path(args.out)
    end = started + args.deadline if args.deadline else None
    queue, running, failed = list(arms), {}, []
    lock = threading.Lock()

    def echo(proc, name, log):
        # read to the end whatever happens, so that a child never blocks on a full pipe
        for line in proc.stdout:
            try:
                log.write(line)
                log.flush()
                with lock:
                    print(f"[{name}] {line}", end="", flush=True)
            except (OSError, ValueError):
                pass
        log.close()

    def start(arm):
        folder = out / arm["name"]
        folder.mkdir(parents=True, exist_ok=True)
        argv = [sys.executable, str(Path(__file__).resolve()), *study_command(args, arm, args.seeds)[2:],
                "--no-report"]
        log = open(folder / "scaling.log", "a", encoding="utf-8")
        log.write(f"# {shlex.join(argv)}\n")
        # its own process group (stopped as a whole); it dies with this process (PARENT_ENV, checked in main)
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                errors="replace", start_new_session=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())})
        thread = threading.Thread(target=echo, args=(proc, arm["name"], log), daemon=True)
        thread.start()
        running[proc] = (arm["name"], thread)

    def finished(proc, name, thread, stopped=False):
        thread.join(5)
        rc = proc.returncode
        if rc != 0 and not (stopped and rc in (130, -signal.SIGINT, -signal.SIGKILL)):
            failed.append(f"{name} (exit {rc}; {out / name / 'scaling.log'})")

    def stop_all():
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # stopping already: a second signal changes nothing
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        for proc in running:
            try:
                os.killpg(proc.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        limit = time.monotonic() + GRACE_S
        for proc, (name, thread) in running.items():
            try:
                proc.wait(max(0.1, limit - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait()
            finished(proc, name, thread, stopped=True)
        running.clear()

    caught = {}

    def on_term(signum, frame):
        caught["signal"] = signum
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, on_term), signal.getsignal(signal.SIGINT)
    rc = 0
    try:
        while queue or running:
            while queue and len(running) < args.jobs and (end is None or time.monotonic() < end):
                start(queue.pop(0))
            if end is not None and time.monotonic() >= end:
                print(f"scaling.py: deadline ({args.deadline:.0f} s) reached: stopping "
                      f"{', '.join(n for n, _ in running.values()) or 'nothing running'}"
                      + (f"; not started: {', '.join(a['name'] for a in queue)}" if queue else ""), flush=True)
                stop_all()
                break
            for proc in list(running):
                if proc.poll() is not None:
                    finished(proc, *running.pop(proc))
            time.sleep(0.5)
    except KeyboardInterrupt:
        stop_all()
        print("scaling.py: interrupted; the same command resumes (finished stages are re-used)", file=sys.stderr)
        rc = 143 if caught.get("signal") == signal.SIGTERM else 130
    finally:
        signal.signal(signal.SIGTERM, previous[0])
        signal.signal(signal.SIGINT, previous[1])
    if failed:
        print(f"scaling.py: error: failed: {', '.join(failed)}", file=sys.stderr)
    return rc or (1 if failed else 0)


def _die_with_starter() -> None:
    """An arm's process started by :func:`run_jobs` dies with it (kill -9 too): the parent-death signal,
    set here rather than between fork and exec (unsafe beside the parent's threads); exits at once when the
    parent is gone already."""
    import os
    import signal

    from fppsim.files import die_with_parent

    pid = os.environ.pop(PARENT_ENV, None)
    if pid:
        die_with_parent()
        if str(os.getppid()) != pid:
            sys.exit(130)
        # the parent stops an arm with SIGINT (--deadline, Ctrl-C): a study started from a non-interactive shell
        # with '&' hands its children SIGINT ignored, and the arm then ran on through the grace period and
        # recorded a seed after the deadline (seen in a whole-suite run started that way)
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv=None) -> int:
    started = time.monotonic()  # --deadline counts from here: the checks count too
    _die_with_starter()
    args = parse_args(sys.argv[1:] if argv is None else list(argv))
    if args.merge:
        try:
            check_merge(args)
            doc = merge_records(args)
        except UsageProblem as exc:
            print(f"scaling.py: error: {exc}", file=sys.stderr)
            return 2
        c = doc["merge_counts"]
        print(f"study: {doc['found']} seed result(s) merged ({c['added']} new, {c['rerun']} replacing another result, "
              f"kept under its reruns; {c['same']} already recorded, unchanged); {args.ledger} records "
              f"{sum(len(a['seeds']) for a in doc['arms'])} (arm, seed) in {len(doc['arms'])} arm(s)", flush=True)
        return 0
    try:
        arms, configs = check(args)
    except UsageProblem as exc:
        print(f"scaling.py: error: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for arm in arms:
            cfg, _ = configs[arm["name"], args.seeds[0]]
            var = _variant(cfg, args.seeds[0])
            print(f"{arm['name']}: {cfg.count} samples, {steps_of(cfg, var)} steps, series "
                  f"{', '.join(arm['series']) or '-'}; {arm['description']}")
            for seed in args.seeds:
                print("    " + shlex.join(configs[arm["name"], seed][1]))
        return 0
    try:
        if args.report_only:
            rc = 0
        elif args.jobs > 1 or args.deadline:
            rc = run_jobs(args, arms, started)  # stops its arms on a signal: what finished is still recorded
        else:
            rc = run(args, arms, configs)
    except KeyboardInterrupt:
        print("scaling.py: interrupted; the same command resumes (finished stages are re-used)", file=sys.stderr)
        return 130
    if args.no_report:
        return rc
    try:
        doc = write_report(args, arms, configs)
    except UsageProblem as exc:
        print(f"scaling.py: error: {exc}", file=sys.stderr)
        return 2
    recorded = sum(len(a["seeds"]) for a in doc["arms"])
    print(f"study: {doc['found']} of {len(arms) * len(args.seeds)} (arm, seed) asked for are finished in {args.out}"
          + (f" (pending: {', '.join(doc['pending'])})" if doc["pending"] else "")
          + f"; {args.ledger} records {recorded} (arm, seed) in {len(doc['arms'])} arm(s), with {Path(args.ledger).stem}_table.md",
          flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
