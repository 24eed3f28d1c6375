"""One (arm, seed) of the scaling study on disk (``OUT/<arm>/s<seed>``): its record ``study.json`` (what the
seed is and the command that ran it) and its results, read from a finished folder.

Results per seed: ``pair_object_rmse_mm`` (object RMSE on the labelled real pair(s), mean over images), its
split into ``pair_level_rmse_mm`` (each connected object region's median error) and ``pair_relief_rmse_mm``
(the rest), the exact mean split (``pair_level_rmse_mean_mm`` / ``pair_relief_rmse_mean_mm``: level^2 +
relief^2 = RMSE^2; :func:`uhrnet.workflows.sim2real.real_metrics.error_split`) and ``phase_residual_rad``
(``uhrnet evaluate-phase``'s calibration-free residual on each held-out real phase-shifting frame).
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import replace
from pathlib import Path

from fppsim.files import atomic_write_text, json_text
from uhrnet.run_folder import CONFIG_JSON, LAST_PT, fresh, read_history, run_done
from uhrnet.workflows.sim2real import run_differences, train_config
from uhrnet.workflows.sim2real.config import data_key
from uhrnet.workflows.scaling.arms import seed_folder, steps_of, variant_of

__all__ = ["PAIR_KEYS", "RECORD", "same_folders", "seed_result", "with_finished_seeds", "result_line", "seed_record",
           "write_seed_record", "arm_meta"]

# what a seed reports (scaling.json key <- real_metrics mean key)
PAIR_KEYS = {"pair_object_rmse_mm": "object_rmse_mm", "pair_level_rmse_mm": "object_level_rmse_mm",
             "pair_relief_rmse_mm": "object_relief_rmse_mm", "pair_level_rmse_mean_mm": "object_level_rmse_mean_mm",
             "pair_relief_rmse_mean_mm": "object_relief_rmse_mean_mm", "pair_regions": "object_regions",
             "pair_valid_rmse_mm": "valid_rmse_mm", "pair_median_abs_mm": "object_median_abs_mm",
             "pair_within_1mm": "object_within_1mm", "pair_relief_effect_mm": "relief_effect_mm"}
RECORD = "study.json"  # OUT/<arm>/s<seed>/study.json: what the seed is and the command that ran it
RECORD_KEYS = ("command", "sim2real_command", "commit", "dirty", "commit_from", "checkout_head", "checkout_dirty",
               "device", "torch", "torch_threads", "gpu", "started")
"""What a seed's result takes from its ``study.json``."""


def same_folders(have, want) -> bool:
    """Whether two lists of folders name the same folders (resolved paths: ``../shared/x`` and its absolute
    path are one folder)."""
    def key(f):
        try:
            return str(Path(f).resolve())
        except OSError:
            return str(f)
    return {key(f) for f in have} == {key(f) for f in want}


def seed_result(folder: Path, cfg, variant) -> dict | None:
    """The results of a finished (arm, seed) folder (``OUT/<arm>/s<seed>``), None when it is not a finished
    run OF THIS (arm, seed): found by what the folder holds, not by its path: a run with ``last.pt`` at the
    variant's epochs whose recorded training options and dataset are the variant's (resize, seed, samples per
    epoch, ...; :func:`~uhrnet.workflows.sim2real.run_differences`), an evaluation newer than it of the same
    real folders (resolved paths) with the level / relief split and, with ``cfg.real_phase``, the phase
    residuals of exactly those frames."""
    folder = Path(folder)
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
    if not same_folders([r["folder"] for r in metrics.get("per_image", [])], cfg.real) \
            or "object_level_rmse_mm" not in metrics.get("mean", {}):
        return None
    if cfg.real_phase and not (fresh(ev / "real_phase.json", run / LAST_PT)
                               and same_folders([f["folder"] for f in frames], cfg.real_phase)):
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
    for key in RECORD_KEYS:
        if key in record:
            out[key] = record[key]
    out.setdefault("device", cfg.device)
    return out


def with_finished_seeds(out: Path, arm: dict, seed: int, seeds: list[int], configs: dict):
    """The ``Sim2RealConfig`` that runs ``arm`` at ``seed`` (``configs[name, seed][0]``) with the arm's other
    finished seeds of ``seeds`` riding along (re-used, nothing re-run), so that ``OUT/<arm>/report.md`` lists
    them all; the variants in seed order."""
    cfg = configs[arm["name"], seed][0]
    done = [variant_of(configs[arm["name"], s][0], s) for s in seeds if s != seed
            and seed_result(seed_folder(out, arm, s), configs[arm["name"], s][0],
                            variant_of(configs[arm["name"], s][0], s)) is not None]
    if not done:
        return cfg
    return replace(cfg, variants=sorted([*done, variant_of(cfg, seed)], key=lambda v: int(v.name[1:])))


def result_line(res: dict) -> str:
    """A seed's results in one line: the pair's object RMSE, its level and relief parts (mm), and each phase
    frame's residual (rad)."""
    parts = ", ".join(f"{k} {res[v]:.2f} mm" for k, v in (("pair object RMSE", "pair_object_rmse_mm"),
                      ("level", "pair_level_rmse_mm"), ("relief", "pair_relief_rmse_mm")) if res.get(v) is not None)
    phase = ", ".join(f"{f} {v:.3f} rad" for f, v in res.get("phase_residual_rad", {}).items())
    return f"{parts}{'; ' + phase if phase else ''}"


def seed_record(arm: dict, seed: int, resize: str | None, device: str, commands: dict, version: dict,
                threads: int | None) -> dict:
    """What ``OUT/<arm>/s<seed>/study.json`` holds: the seed's identity (arm, seed, resize, device) and how it
    ran (``commands``: the study's and sim2real's command lines; ``version``: the code's commit; torch and
    its CPU threads: ``threads``, else torch's)."""
    import torch  # torch's version and threads: imported where they are read, the record's readers need no torch

    gpu = torch.cuda.get_device_name(0) if device != "cpu" and torch.cuda.is_available() else None
    return {"arm": arm["name"], "seed": seed, "resize": resize, "device": device,
            "command": commands["command"], "sim2real_command": commands["sim2real_command"],
            **version, "torch": torch.__version__, "torch_threads": threads or torch.get_num_threads(),
            **({"gpu": gpu} if gpu else {}), "python": platform.python_version(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def write_seed_record(folder: Path, record: dict) -> None:
    """Write the seed's ``study.json``; a seed resumed later keeps its first record (the commit it started
    at) and lists every later start under ``resumes``."""
    path = Path(folder) / RECORD
    try:
        first = json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError):
        first = None
    if isinstance(first, dict) and first.get("arm") == record["arm"] and first.get("seed") == record["seed"]:
        first.setdefault("resumes", []).append({k: record[k] for k in ("commit", "dirty", "torch_threads", "started")})
        record = first
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json_text(record, indent=2))


def arm_meta(arm: dict, cfg, variant, resize: str | None, device: str) -> dict:
    """What the study record holds of an arm beside its seeds: its key (name, resize, device), description,
    series and definition (sample count, epochs, steps, the sim2real options, its flags)."""
    return {"name": arm["name"], "resize": resize, "device": device,
            "description": arm["description"], "series": arm["series"], "count": cfg.count,
            "epochs": int(variant.train.get("epochs") or cfg.epochs), "steps": steps_of(cfg, variant),
            **{k: getattr(cfg, k) for k in ("batch_size", "lr", "base_channels", "model", "loss", "scale")},
            "generate": arm["generate"], "train": arm["train"]}
