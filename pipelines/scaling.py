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
    OUT/scaling.md             the same as a table
    OUT/scaling_samples.png    pair object RMSE (with its level / relief parts) and held-out phase residual
    OUT/scaling_steps.png      against synthetic samples (arms of series "samples") and training steps ("steps")

A killed study resumes with the same command: sim2real re-uses finished datasets, runs and evaluations and
continues an interrupted training run; a finished (arm, seed) is not touched. ``--report-only`` rebuilds
the JSON, table and figures from the finished folders without running anything.

    python pipelines/scaling.py --arms n100 n400 n1600 n6400 --seeds 0 1 2 \\
        --real ../shared/real-sample --real-phase ../shared/real-phase --out runs/scaling
    python pipelines/scaling.py --list                          # the arms and their commands; runs nothing
    python pipelines/scaling.py --out runs/scaling --report-only

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
def default_meshes() -> list[str]:
    """../shared/meshes (when present) and the meshes fppsim ships, as pipelines/sim2real.py."""
    shared = SHARED / "meshes"
    return ([str(shared)] if shared.is_dir() else []) + [str(ROOT / "fppsim" / "data" / "meshes")]


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
    train = list(arm["train"]) + (["--resize", args.resize] if args.resize else []) + ["--seed", str(seed)]
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
    from uhrnet.training.splits import MIN_REFERENCE_SPLIT, split_indices

    tr = variant.train
    epochs, batch = int(tr.get("epochs") or cfg.epochs), int(tr.get("batch_size") or cfg.batch_size)
    draws = tr.get("samples_per_epoch")
    if not draws:
        draws = len(split_indices(cfg.count, "train")) if cfg.count >= MIN_REFERENCE_SPLIT else cfg.count
    return epochs * math.ceil(int(draws) / batch)


def _fresh(result: Path, source: Path) -> bool:
    return result.is_file() and source.is_file() and result.stat().st_mtime >= source.stat().st_mtime


def seed_result(folder: Path, epochs: int, real: list[str], phase: list[str]) -> dict | None:
    """The results of a finished (arm, seed) folder (``OUT/<arm>/s<seed>``), None when not finished: a run with
    ``last.pt`` at ``epochs`` and an evaluation newer than it, of exactly the ``real`` folders, with the level /
    relief split (and, with ``phase`` folders, the phase residuals of exactly those)."""
    import csv

    def covers(doc: dict, key: str, folders: list[str]) -> bool:
        return {r["folder"] for r in doc.get(key, [])} == {str(f) for f in folders}

    last, ev = folder / "run" / "last.pt", folder / "eval"
    hist = folder / "run" / "history.csv"
    if not (last.is_file() and hist.is_file() and _fresh(ev / "real_metrics.json", last)):
        return None
    rows = list(csv.DictReader(hist.open()))
    if not rows or int(float(rows[-1]["epoch"])) < epochs:
        return None
    if phase and not _fresh(ev / "real_phase.json", last):
        return None
    metrics = json.loads((ev / "real_metrics.json").read_text())
    if not covers(metrics, "per_image", real) or "object_level_rmse_mm" not in metrics["mean"]:
        return None
    frames = json.loads((ev / "real_phase.json").read_text())["frames"] if phase else []
    if phase and not covers({"frames": frames}, "frames", phase):
        return None
    out = {"folder": str(folder)}
    out.update({k: metrics["mean"].get(src) for k, src in PAIR_KEYS.items()})
    out["pair_images"] = metrics["images"]
    out["pair_regions_per_image"] = [{"image": f"{Path(r['folder']).name}/{r['index']}",
                                      "regions": r.get("object_region_errors")} for r in metrics["per_image"]]
    out["phase_residual_rad"], out["phase_flat_rad"] = {}, {}
    if phase:
        out["phase_residual_rad"] = {f"{Path(f['folder']).name}/{f['id']}": f["rmse_rad"] for f in frames}
        out["phase_flat_rad"] = {f"{Path(f['folder']).name}/{f['id']}": f["flat_rmse_rad"] for f in frames}
    val = rows[-1].get("val_rmse_mm")
    out["synthetic_val_rmse_mm"] = float(val) if val not in (None, "") else None
    out["epochs"] = int(float(rows[-1]["epoch"]))
    timing = folder / "timing.json"
    out["minutes"] = (sum(v for v in json.loads(timing.read_text()).values() if isinstance(v, (int, float))) / 60.0
                      if timing.is_file() else None)
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
    """``scaling.md``: one line per arm, mean ± std over its finished seeds."""
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
        lines.append(f"| {a['name']} | {a['count']} | {a['steps']} | {s['n_seeds']} | "
                     f"{_cell(s['pair_object_rmse_mm'])} | "
                     f"{_cell(s['pair_level_rmse_mm'])} | {_cell(s['pair_relief_rmse_mm'])} |"
                     + "".join(f" {_cell(s['phase_residual_rad'].get(f, {}), '.3f')} |" for f in frames)
                     + f" {_cell(s['minutes'], '.1f')} |")
    lines += ["", *[f"- {a['name']}: {a['description']}" for a in doc["arms"] if a["description"]]]
    return "\n".join(lines) + "\n"


def plot_series(doc: dict, series: str, path: Path) -> Path | None:
    """Pair object RMSE with its level and relief parts (left) and each phase frame's residual (right), mean
    ± std over seeds (single seeds as dots), against the arms' x of ``series``; None when no arm has a result."""
    import numpy as np

    from fppsim.plots import pyplot, save_figure

    key, xlabel = SERIES[series]
    arms = sorted((a for a in doc["arms"] if series in a["series"] and a["seeds"]), key=lambda a: a[key])
    if not arms:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2))
    x = np.array([a[key] for a in arms], float)
    parts = (("pair_object_rmse_mm", "object RMSE", "k", "o"),
             ("pair_level_rmse_mm", "level (region medians)", "C3", "s"),
             ("pair_relief_rmse_mm", "relief (rest)", "C0", "^"))
    for k, label, color, marker in parts:
        mean = np.array([a["summary"][k]["mean"] if a["summary"][k]["mean"] is not None else np.nan for a in arms])
        std = np.array([a["summary"][k]["std"] or 0.0 for a in arms])
        ax[0].errorbar(x, mean, yerr=std, color=color, marker=marker, capsize=4, label=label)
        for xi, a in zip(x, arms):
            ys = [s[k] for s in a["seeds"] if s.get(k) is not None]
            ax[0].plot([xi] * len(ys), ys, ".", color=color, alpha=0.35)
    ax[0].set_ylabel("labelled real pair (mm)")
    ax[0].set_ylim(bottom=0)
    ax[0].set_title("real pair: object RMSE, its level and relief parts (median split)", fontsize=10)
    frames = sorted({f for a in arms for f in a["summary"]["phase_residual_rad"]})
    for j, f in enumerate(frames):
        mean = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("mean") or np.nan for a in arms])
        std = np.array([a["summary"]["phase_residual_rad"].get(f, {}).get("std") or 0.0 for a in arms])
        ax[1].errorbar(x, mean, yerr=std, color=f"C{j}", marker="o", capsize=4, label=f)
        flat = next((s["phase_flat_rad"][f] for a in arms for s in a["seeds"]
                     if f in s.get("phase_flat_rad", {})), None)
        if flat is not None:
            ax[1].axhline(flat, color=f"C{j}", ls=":", lw=1, label=f"{f}: flat plane")
    ax[1].set_ylabel("phase residual (rad)")
    ax[1].set_title("held-out real phase frames" if frames else "held-out real phase frames: none given")
    for a_ in ax:
        a_.set_xscale("log", base=2)
        a_.set_xticks(x, [f"{int(v)}" for v in x])
        a_.set_xlabel(xlabel)
        a_.grid(alpha=0.3)
        if a_.get_legend_handles_labels()[0]:
            a_.legend(fontsize=7)
    n = sorted({a["summary"]["n_seeds"] for a in arms})
    fig.suptitle(f"sim-to-real scaling ({series}): mean ± std over {'/'.join(map(str, n))} training seed(s); "
                 + ", ".join(a["name"] for a in arms), fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)


def write_report(args, arms: list[dict], configs: dict) -> dict:
    """``scaling.json``, ``scaling.md`` and the figures from the finished (arm, seed) folders."""
    from fppsim.dataio.files import atomic_write_text

    out = Path(args.out)
    doc = {"arms_file": str(args.arms_file), "seeds": list(args.seeds), "real": list(args.real),
           "real_phase": list(args.real_phase), "arms": []}
    for arm in arms:
        seeds, commands, missing = [], [], []
        cfg0 = None
        for seed in args.seeds:
            cfg, argv = configs[arm["name"], seed]
            cfg0 = cfg0 or (cfg, _variant(cfg, seed))
            commands.append(shlex.join(argv))
            res = seed_result(seed_folder(out, arm, seed), int(_variant(cfg, seed).train.get("epochs") or cfg.epochs),
                              cfg.real, cfg.real_phase)
            if res is None:
                missing.append(seed)
            else:
                seeds.append({"seed": seed, **res})
        cfg, var = cfg0
        doc["arms"].append({"name": arm["name"], "description": arm["description"], "series": arm["series"],
                            "count": cfg.count, "epochs": int(var.train.get("epochs") or cfg.epochs),
                            "steps": steps_of(cfg, var), "generate": arm["generate"], "train": arm["train"],
                            "commands": commands, "seeds": seeds, "missing_seeds": missing,
                            "summary": summarise(seeds)})
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "scaling.json", json.dumps(doc, indent=2))
    atomic_write_text(out / "scaling.md", markdown(doc))
    for series in SERIES:
        fig = plot_series(doc, series, out / f"scaling_{series}.png")
        print(f"figure: {fig}" if fig else f"figure scaling_{series}.png: no finished arm of series {series!r}")
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
    p.add_argument("--no-figures", action="store_true", help="no per-image figure of the real pairs (sim2real's)")
    p.add_argument("--report-only", action="store_true",
                   help="rebuild scaling.json / .md / figures from the finished folders; run nothing")
    p.add_argument("--list", action="store_true", help="print the arms and their commands; run nothing")
    return p.parse_args(argv)


def check(args) -> tuple[list[dict], dict]:
    """Arms chosen and every (arm, seed)'s ``(Sim2RealConfig, argv)``; :class:`UsageProblem` before anything runs."""
    from uhrnet.errors import UhrnetError
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
    if not args.real:
        raise UsageProblem("--real DIR: no labelled real folder given (../shared/real-sample is absent)")
    args.meshes = args.meshes or default_meshes()
    args.real_phase = [] if args.real_phase in (["none"], None) else phase_folders(args.real_phase)
    args.out = args.out or "OUT"
    if args.report_only and not Path(args.out).is_dir():
        raise UsageProblem(f"--report-only: {args.out} does not exist (nothing to report)")
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
        epochs = int(_variant(cfg, seed).train.get("epochs") or cfg.epochs)
        if seed_result(seed_folder(out, arm, seed), epochs, cfg.real, cfg.real_phase) is not None:
            print(f"{tag} finished before: re-used", flush=True)
            continue
        # the arm's other finished seeds ride along (re-used, nothing re-run) so OUT/<arm>/report.md lists them all
        done = [_variant(configs[arm["name"], s][0], s) for s in args.seeds if s != seed
                and seed_result(seed_folder(out, arm, s), epochs, cfg.real, cfg.real_phase) is not None]
        if done:
            cfg = replace(cfg, variants=sorted([*done, _variant(cfg, seed)], key=lambda v: int(v.name[1:])))
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
        res = seed_result(seed_folder(out, arm, seed), epochs, cfg.real, cfg.real_phase) or {}
        parts = ", ".join(f"{k} {res[v]:.2f} mm" for k, v in (("pair object RMSE", "pair_object_rmse_mm"),
                          ("level", "pair_level_rmse_mm"), ("relief", "pair_relief_rmse_mm")) if res.get(v) is not None)
        phase = ", ".join(f"{f} {v:.3f} rad" for f, v in res.get("phase_residual_rad", {}).items())
        print(f"{tag} done in {(time.perf_counter() - t0) / 60:.1f} min: {parts}{'; ' + phase if phase else ''}",
              flush=True)
    if failed:
        print(f"scaling.py: error: failed: {', '.join(failed)} (re-run the same command to retry; logs in "
              f"{out}/<arm>/s<seed>/train.log and {out}/<arm>/data/*.log)", file=sys.stderr)
    return 1 if failed else 0


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else list(argv))
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
        rc = 0 if args.report_only else run(args, arms, configs)
    except KeyboardInterrupt:
        print("scaling.py: interrupted; the same command resumes (finished stages are re-used)", file=sys.stderr)
        return 130
    doc = write_report(args, arms, configs)
    done = sum(len(a["seeds"]) for a in doc["arms"])
    print(f"study: {done} of {len(arms) * len(args.seeds)} (arm, seed) finished; {Path(args.out) / 'scaling.json'}, "
          f"scaling.md", flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
