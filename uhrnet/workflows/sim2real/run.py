"""Running a sim-to-real experiment: generate -> train (synthetic only) -> [adapt] -> evaluate on REAL data -> report.

Every variant of :class:`~uhrnet.workflows.sim2real.config.Sim2RealConfig` runs these stages through the
libraries, in this process:

1. ``fppsim.generate(GenerateConfig)`` (:func:`generate_config`): the recipe's figshare-format dataset
   without phase-shifting images, plus the variant's ``generate`` overrides, in ``out/data/<key>``;
   variants with the same overrides share it. Log: ``out/data/<key>.log``.
2. ``uhrnet.train(TrainConfig)`` (:func:`train_config`) on that dataset alone, in ``out/<variant>/run``
   (``history.csv``, checkpoints). Log: ``out/<variant>/train.log``. A finished run given in
   ``cfg.reuse`` (or copied to ``out/<variant>/run``) replaces stages 1 and 2 when its training options are
   the variant's (:func:`run_differences`); its own dataset is then the variant's.
3. With ``variant.adapt``: ``uhrnet.training.adapt(AdaptConfig)`` (:func:`adapt_config`) of the run's ``last.pt`` on
   the UNLABELLED real images (``cfg.adapt_images``, default the ``real`` and ``real_phase`` folders; only
   fringe images are read), in ``out/<variant>/adapt``. Log: ``out/<variant>/adapt.log``.
4. Evaluation rows, each in its own folder: the network (``out/<variant>/eval``, with :func:`evaluate_level`
   on the synthetic validation split), each ``refine`` method (``eval-refine-<method>``), the adapted
   network (``eval-adapt``) and each method on it (``eval-adapt-refine-<method>``):
   :func:`evaluate_real` on every real pair and, with ``cfg.real_phase``, :func:`evaluate_real_phase`.

Every stage is resumable: a finished dataset (as many samples as asked), a finished run (``last.pt``
at the requested epochs), a finished adaptation and an evaluation newer than its checkpoint (of the same
real folders) are re-used; an interrupted run is resumed. ``out/report.json`` and ``out/report.md`` are
rewritten after every variant.
"""

from __future__ import annotations

import json
import time
from dataclasses import fields
from pathlib import Path
from typing import Callable, Sequence

from fppsim.errors import FppsimError, MeshError
from fppsim.errors import UsageError as FppsimUsageError
from fppsim.dataio.encoding import json_default
from fppsim.files import atomic_write_text, json_text
from fppsim.geometry.rig import load_rig
from uhrnet.checkpoint import find_checkpoint
from uhrnet.device import select_device
from uhrnet.errors import ConfigError, Sim2RealError, UhrnetError, UsageError
from uhrnet.scoring.chosen_frames import phase_frames
from uhrnet.run_folder import CONFIG_JSON, HISTORY_CSV, IMAGES_JSON, LAST_PT, fresh, read_history, run_done
from uhrnet.workflows.stages import dataset_count, run_stage
from uhrnet.workflows.sim2real.config import SCALES, Sim2RealConfig, Variant, data_key, generate_workers
from uhrnet.workflows.sim2real.score_real import (
    evaluate_level, evaluate_real, evaluate_real_phase, find_phase_frames, find_real_pairs,
)
from uhrnet.workflows.sim2real.report import markdown_report
from fppsim.dataio.formats import PRESETS, read_settings
from fppsim.generation import GenerateConfig, generate
from fppsim.rendering.scene import changed_meshes
from uhrnet.training.train_config import DEFAULTS, LEGACY, LOCKED, TrainConfig
from uhrnet.training.adapt import AdaptConfig, adapt
from fppsim.dataio.readers import open_source
from uhrnet.training.trainer import train
from fppsim.owned import claim

__all__ = ["generate_config", "train_config", "adapt_config", "run_differences", "find_real_pairs", "evaluate_real",
           "evaluate_real_phase", "evaluate_level", "run_sim2real"]

Recipe = Callable[[Sim2RealConfig, Variant, Path, Path], dict]


def variant_error(exc: Exception, where: str) -> Exception:
    """``exc`` of a variant's step as one error naming ``where``: a :class:`UsageError` where the step's own command
    would exit 2 on it (a value wrong on its own), a :class:`Sim2RealError` otherwise."""
    usage = isinstance(exc, (UsageError, FppsimUsageError))
    return (UsageError if usage else Sim2RealError)(f"{where}: {exc}")


def generate_config(cfg: Sim2RealConfig, variant: Variant, data: str | Path):
    """The :class:`fppsim.generation.GenerateConfig` of ``variant``'s dataset in folder ``data``: the
    recipe (``cfg``'s meshes, count, seed and workers; figshare format with the figshare label
    transform, no phase-shifting images, a preview, no progress bar) and the variant's overrides."""

    base = dict(meshes=list(cfg.meshes), out=str(data), count=cfg.count, seed=cfg.seed,
                workers=generate_workers(cfg), format="figshare", psp_freqs=(), label=PRESETS["figshare"],
                preview=True, progress=False)
    try:
        return GenerateConfig(**{**base, **variant.generate})
    except (FppsimError, ValueError) as exc:
        raise variant_error(exc, f"variant {variant.name!r}: generate") from None


def train_config(cfg: Sim2RealConfig, variant: Variant, data: str | Path, run: str | Path, resume: bool = False):
    """The :class:`uhrnet.training.train_config.TrainConfig` of ``variant``'s run in folder ``run`` on the
    dataset ``data`` alone: ``cfg``'s model, width, loss, epochs, batch size, learning rate and device,
    the scale's own options (:data:`SCALES`), then the variant's overrides; ``resume`` continues an
    interrupted run."""

    base = dict(out=str(run), synthetic=[str(data)], model=cfg.model, base_channels=cfg.base_channels,
                loss=cfg.loss, epochs=cfg.epochs, batch_size=cfg.batch_size, lr=cfg.lr, device=cfg.device,
                progress=False, **SCALES[cfg.scale]["train"])
    try:
        return TrainConfig(**{**base, **variant.train, **({"resume": "auto"} if resume else {})})
    except (UhrnetError, ValueError) as exc:
        raise variant_error(exc, f"variant {variant.name!r}: train") from None


# --------------------------------------------------------------------------------------------------
# The experiment


def _as_dict(config) -> dict:
    """A config dataclass as JSON-ready values (a label transform as its dict)."""
    out = {}
    for f in fields(config):
        value = getattr(config, f.name)
        out[f.name] = value.to_dict() if hasattr(value, "to_dict") else value
    return out


def adapt_config(cfg: Sim2RealConfig, variant: Variant, checkpoint: str | Path, out: str | Path,
                 overwrite: bool = False):
    """The :class:`uhrnet.training.adapt.AdaptConfig` of ``variant``'s adaptation of ``checkpoint`` in folder ``out``:
    on ``cfg.adapt_images`` (default: the real and real phase-shifting folders; never their labels) through
    ``cfg.rig``, then the variant's ``adapt`` overrides."""

    images = list(cfg.adapt_images) if cfg.adapt_images else [*cfg.real, *cfg.real_phase]
    base = dict(checkpoint=str(checkpoint), images=images, out=str(out), rig=cfg.rig, progress=False,
                figures=cfg.figures, device="cuda" if cfg.device == "cuda" else "cpu", overwrite=overwrite)
    try:
        return AdaptConfig(**{**base, **(variant.adapt or {})})
    except (UhrnetError, ValueError) as exc:
        raise variant_error(exc, f"variant {variant.name!r}: adapt") from None


def _norm(value):
    return json.loads(json_text(value, default=json_default))  # as config.json holds it


def run_differences(run: str | Path, tr, count: int | None = None, seed: int | None = None) -> list[str]:
    """How the finished run in folder ``run`` differs from the training run ``tr`` (a ``TrainConfig``) would
    make: its recorded training options (``config.json``: every option a resume locks, and epochs, lr,
    weight decay, gradient clipping, AMP; not the dataset's path, device or workers) and its dataset (sample
    count ``count`` and, where the dataset records it, generator ``seed``). Empty: the same run."""

    run = Path(run)
    try:
        recorded = json.loads((run / CONFIG_JSON).read_text())
    except (OSError, ValueError) as exc:
        return [f"no readable config.json ({exc})"]
    wanted = {**DEFAULTS, **{f.name: getattr(tr, f.name) for f in fields(tr) if getattr(tr, f.name) is not None}}
    diffs = []
    for key in [k for k in LOCKED if k != "synthetic"] + ["epochs", "lr", "weight_decay", "grad_clip", "amp"]:
        have = _norm(recorded.get(key, LEGACY.get(key, DEFAULTS.get(key))))
        want = _norm(wanted.get(key))
        if have != want:
            diffs.append(f"{key} {have!r} (wanted {want!r})")
    folders = recorded.get("synthetic") or []
    if count is not None:
        n = sum(int(d.get("n", 0)) for d in (recorded.get("data") or {}).get("synthetic") or [])
        if n != count:
            diffs.append(f"{n} synthetic samples (wanted {count})")
    for folder in folders:
        samples = open_source(folder).fppsim_samples()
        settings = read_settings(samples.path) if samples is not None else None
        if settings is not None and seed is not None and settings.get("seed") not in (None, seed):
            diffs.append(f"dataset {folder} seed {settings.get('seed')} (wanted {seed})")
    return diffs


def _finished_run(cfg: Sim2RealConfig, var: Variant, run: Path, tr, gen) -> list[str] | None:
    """The dataset folders of ``run`` when it is a finished run of ``var`` (None: not finished; a reused run
    must be); a finished run of other options is refused."""
    reused = var.name in cfg.reuse
    what = f"--reuse-run {var.name}={run}" if reused else str(run)
    if not run_done(run, tr.epochs):
        if reused:
            hist = read_history(run)
            at = f"epoch {int(hist[-1]['epoch'])} of {tr.epochs}" if hist else "no finished epoch"
            raise Sim2RealError(f"{what}: not a finished run ({at}; last.pt and history.csv needed)")
        return None
    diffs = run_differences(run, tr, gen.count, gen.seed)
    if diffs:
        raise Sim2RealError(f"{what}: a finished run of other training options than variant {var.name!r}: "
                            + "; ".join(diffs[:4]) + ("" if reused else " (move it away to train afresh)"))
    return [str(f) for f in json.loads((run / CONFIG_JSON).read_text()).get("synthetic") or []]


def _check_training_inputs(var: Variant, tr) -> None:
    """What the training run ``tr`` of ``var`` reads besides its dataset (its device, ``--init-from``
    checkpoint, ``--val-phase`` folders, ``--rig``), refused in one line before the first stage runs, not
    after its dataset is generated."""
    try:
        select_device(tr.device or "auto")
        if tr.init_from:
            find_checkpoint(tr.init_from)
        if tr.val_phase:
            phase_frames(tr.val_phase)
        if tr.rig:
            load_rig(tr.rig)
    except (UhrnetError, FppsimError) as exc:
        raise Sim2RealError(f"variant {var.name!r}: train: {exc}") from None


def _check_dataset(var: Variant, data: Path, gen, run: Path) -> None:
    """A complete dataset in ``data`` generated with another seed or from other meshes than ``gen``'s is refused
    before the first stage: left by a run stopped while training and started again with another ``--seed`` or
    ``--meshes``, it was re-used as it was (its sample count matched, so generate, which compares both, never ran),
    and the run trained on the old samples while the report named the new options."""
    if dataset_count(data) != gen.count:
        return  # the generate stage makes or completes it, and refuses a dataset of other settings itself
    samples = open_source(data).fppsim_samples()
    settings = (read_settings(samples.path) or {}) if samples is not None else {}
    seed = settings.get("seed")
    if seed not in (None, gen.seed):
        raise Sim2RealError(f"variant {var.name!r}: {data} holds {gen.count} samples generated with seed {seed}, "
                            f"not {gen.seed}: give --seed {seed} to continue, or move {data} and {run} away")
    other = _mesh_difference(settings, gen)
    if other:
        raise Sim2RealError(f"variant {var.name!r}: {data} holds {gen.count} samples generated from {other}: give "
                            f"the --meshes it was made from to continue, or move {data} and {run} away")


def _mesh_difference(settings: dict, gen) -> str | None:
    """Where the meshes a dataset's ``settings`` record (``dataset.json``'s ``meshes``; none recorded: no check)
    differ from ``gen``'s ``--meshes`` (:func:`fppsim.rendering.scene.changed_meshes`), in words; None: the same."""
    recorded = settings.get("meshes")
    if not isinstance(recorded, list):
        return None
    try:
        gone, new = changed_meshes(recorded, gen.mesh_paths)
    except MeshError as exc:
        raise Sim2RealError(f"--meshes: {exc}") from None
    if not gone and not new:
        return None
    given = " ".join(gen.mesh_paths) or "none (procedural)"
    return (f"{len(recorded)} mesh file(s) (listed in its dataset.json"
            + (f"; {len(gone)} not among --meshes, e.g. {gone[0]}" if gone else "")
            + (f"; not {new[0]}, which --meshes gives" if new else "") + f"), not from --meshes {given}")


def _row_line(row: dict) -> str:
    """A row's real-pair result in one log line (a metric read back as null from its file: n/a)."""
    obj, val = (row["real"][k] for k in ("object_rmse_mm", "valid_rmse_mm"))
    return (f"[{row['row']}] object RMSE {'n/a' if obj is None else format(obj, '.2f')} mm, valid RMSE "
            f"{'n/a' if val is None else format(val, '.2f')} mm")


def _adapt_done(acfg, source: Path) -> bool:
    out = Path(acfg.out)
    if not all((out / name).is_file() for name in (LAST_PT, IMAGES_JSON, HISTORY_CSV)):
        return False
    try:
        done = json.loads((out / CONFIG_JSON).read_text())
    except (OSError, ValueError):
        return False
    skip = ("epochs", "progress", "figures", "overwrite", "resume")
    same = all(_norm(done.get(k)) == _norm(v) for k, v in acfg.record().items() if k not in skip)
    return same and len(read_history(out)) >= acfg.epochs and fresh(out / LAST_PT, source)


def _rows(var: Variant, out: Path, last: Path, adapted: Path | None) -> list[dict]:
    """The evaluation rows of a variant: name, kind, checkpoint, refine method, folder."""
    base = out / var.name
    rows = [{"row": var.name, "kind": "network", "checkpoint": last, "refine": None, "eval": base / "eval"}]
    rows += [{"row": f"{var.name} +refine {m}", "kind": "refine", "checkpoint": last, "refine": m,
              "eval": base / f"eval-refine-{m}"} for m in var.refine]
    if adapted is not None:
        rows.append({"row": f"{var.name} +adapt", "kind": "adapt", "checkpoint": adapted, "refine": None,
                     "eval": base / "eval-adapt"})
        rows += [{"row": f"{var.name} +adapt +refine {m}", "kind": "adapt+refine", "checkpoint": adapted,
                  "refine": m, "eval": base / f"eval-adapt-refine-{m}"} for m in var.refine]
    return rows


def _done_json(path: Path, source: Path, folders: Sequence[str], key: str) -> dict | None:
    """A result file newer than ``source`` that covers exactly ``folders`` (its rows' ``folder``), else None."""
    if not fresh(path, source):
        return None
    doc = json.loads(path.read_text())
    return doc if {r["folder"] for r in doc.get(key, [])} == {str(f) for f in folders} else None


# what a report row keeps of each labelled real image (the level / relief split of its object error)
_PER_IMAGE = ("folder", "index", "object_rmse_mm", "object_level_rmse_mm", "object_relief_rmse_mm",
              "object_level_rmse_mean_mm", "object_relief_rmse_mean_mm", "object_regions", "object_region_errors")


def _evaluate_row(cfg: Sim2RealConfig, row: dict, device: str, say, timing: dict) -> dict:
    """Real-pair metrics (and phase residuals) of one row, re-used when fresh; the report's row entry."""
    ck, ev, method = row["checkpoint"], row["eval"], row["refine"]
    metrics = _done_json(ev / "real_metrics.json", ck, cfg.real, "per_image")
    if metrics is not None and "object_level_rmse_mm" not in metrics["mean"]:
        metrics = None  # measured before the level / relief split: measured again (seconds)
    if metrics is None:
        say(f"[{row['row']}] evaluate on {len(cfg.real)} real folder(s)")
        t0 = time.perf_counter()
        metrics = evaluate_real(ck, cfg.real, ev, cfg.object_mm, device=device, figures=cfg.figures,
                                title=f"sim2real {row['row']} ({cfg.scale})", refine=method, rig=cfg.rig)
        timing["evaluate_s" if ev.name == "eval" else f"evaluate_{ev.name}_s"] = time.perf_counter() - t0
    phase = None
    if cfg.real_phase:
        phase = _done_json(ev / "real_phase.json", ck, cfg.real_phase, "frames")
        if phase is None:
            say(f"[{row['row']}] phase residual on {len(cfg.real_phase)} real phase-shifting folder(s)")
            phase = evaluate_real_phase(ck, cfg.real_phase, ev, device=device, refine=method, rig=cfg.rig)
    return {"row": row["row"], "kind": row["kind"], "refine": method, "checkpoint": str(ck), "eval": str(ev),
            "real": metrics["mean"], "images": metrics["images"],
            "real_per_image": [{k: r.get(k) for k in _PER_IMAGE} for r in metrics["per_image"]],
            "real_phase": None if phase is None else [
                {k: f[k] for k in ("folder", "id", "rmse_rad", "flat_rmse_rad", "explained")} for f in phase["frames"]]}


def run_sim2real(cfg: Sim2RealConfig, log: Callable[[str], None] | None = print, recipe: Recipe | None = None) -> dict:
    """Run every variant of ``cfg`` (generate -> train -> [adapt] -> evaluate on real), write ``report.json``
    and ``report.md`` in ``cfg.out``; returns the report document. Stages already done are re-used.

    ``log`` gets one line per stage (None: silent). ``recipe(cfg, variant, data, run)`` returns the
    ``{"generate": ..., "train": ...[, "adapt": ...]}`` text stored as ``report["recipe"][variant]`` and at
    the top of the stage logs (the ``uhrnet sim2real`` command passes the equivalent command lines); without
    it the stages' configs are stored.
    """
    say = log or (lambda line: None)
    out = Path(cfg.out)
    find_real_pairs(cfg.real)  # fail early on bad real folders, before anything is written
    find_phase_frames(cfg.real_phase)
    try:  # training and evaluation run there
        select_device(cfg.device)
    except ConfigError:
        raise Sim2RealError(f"--device {cfg.device}: no CUDA device is available" + (
            f" (the --scale {cfg.scale} recipe's device; --device cpu runs it here)"
            if SCALES[cfg.scale]["device"] == cfg.device else "")) from None
    plans = []
    for var in cfg.variants:  # every variant's configs are checked before the first stage runs
        data = out / "data" / data_key(var.generate)
        run = Path(cfg.reuse[var.name]) if var.name in cfg.reuse else out / var.name / "run"
        gen, tr = generate_config(cfg, var, data), train_config(cfg, var, data, run)
        if var.adapt is not None:
            adapt_config(cfg, var, run / LAST_PT, out / var.name / "adapt")
        trained_on = _finished_run(cfg, var, run, tr, gen)
        if trained_on is None:
            _check_training_inputs(var, tr)
            _check_dataset(var, data, gen, run)
        plans.append((var, data, run, gen, tr, trained_on))
    out.mkdir(parents=True, exist_ok=True)

    # the experiment's own files (its stages claim theirs): never one it did not write
    claim(out, "uhrnet sim2real", ["report.json", "report.md"] + [f"{v.name}/timing.json" for v in cfg.variants])
    report = {"config": {f.name: getattr(cfg, f.name) for f in fields(cfg) if f.name != "variants"},
              "recipe": {}, "variants": []}
    device = "cuda" if cfg.device == "cuda" else "cpu"
    for var, data, run, gen, tr, trained_on in plans:
        timing = {}
        text = recipe(cfg, var, data, run) if recipe is not None else None
        described = text or {"generate": _as_dict(gen), "train": _as_dict(tr)}
        if trained_on is None:
            if not dataset_count(data) == gen.count:
                say(f"[{var.name}] generate -> {data}")

                def run_generate(gen=gen):
                    for line in generate(gen).lines():
                        print(line)

                timing["generate_s"] = run_stage("generate", run_generate, data.parent / f"{data.name}.log",
                                              _header("generate", described))
            say(f"[{var.name}] train -> {run}")
            if run.is_dir() and any(run.iterdir()):  # an interrupted run: continue it (or restart it)
                tr = train_config(cfg, var, data, run, resume=True)
            timing["train_s"] = run_stage("train", lambda tr=tr: train(tr), out / var.name / "train.log",
                                       _header("train", described))
            trained_on = [str(data)]
        last = run / LAST_PT
        adapted, adapt_entry = None, None
        if var.adapt is not None:
            acfg = adapt_config(cfg, var, last, out / var.name / "adapt")
            if not _adapt_done(acfg, last):
                if (Path(acfg.out) / LAST_PT).is_file() and not fresh(Path(acfg.out) / LAST_PT, last):
                    acfg = adapt_config(cfg, var, last, acfg.out, overwrite=True)  # the run was trained again
                say(f"[{var.name}] adapt on {len(acfg.images)} unlabelled real input(s) -> {acfg.out}")
                timing["adapt_s"] = run_stage("adapt", lambda a=acfg: adapt(a, log=print), out / var.name / "adapt.log",
                                           _header("adapt", described) if "adapt" in described else
                                           f"# adapt: {json_text(acfg.record(), default=json_default)}")
            adapted = Path(acfg.out) / LAST_PT
            hist = read_history(acfg.out)
            adapt_entry = {"run": str(acfg.out), "images": [str(i) for i in acfg.images], "labels_read": False,
                           "flags": var.described("adapt"), "epochs": len(hist),
                           "per_image": json.loads((Path(acfg.out) / IMAGES_JSON).read_text())}
        rows = [_evaluate_row(cfg, row, device, say, timing) for row in _rows(var, out, last, adapted)]
        ev = out / var.name / "eval"
        lvl = ev / "synthetic_level.json"
        level = json.loads(lvl.read_text()) if fresh(lvl, last) else evaluate_level(last, trained_on, ev, device=device)
        hist = read_history(run)
        entry = {"name": var.name, "generate": var.described("generate"), "train": var.described("train"),
                 "data": trained_on[0] if len(trained_on) == 1 else trained_on, "run": str(run),
                 "reused": var.name in cfg.reuse, "timing": timing, "real": rows[0]["real"],
                 "images": rows[0]["images"], "real_phase": rows[0]["real_phase"],
                 "synthetic_level": {k: level[k] for k in ("slope", "intercept_mm", "prior_level_mm",
                                                           "shape_rmse_mm", "n_objects")},
                 "synthetic_val_rmse_mm": hist[-1].get("val_rmse_mm") if hist else None,
                 "history": hist, "adapt": adapt_entry, "refine": list(var.refine), "rows": rows}
        timing_file = out / var.name / "timing.json"
        if timing:
            old = json.loads(timing_file.read_text()) if timing_file.is_file() else {}
            old.update(timing)
            atomic_write_text(timing_file, json_text(old, indent=1))
        entry["timing"] = json.loads(timing_file.read_text()) if timing_file.is_file() else timing
        report["variants"].append(entry)
        for r in rows:
            say(_row_line(r))
        report["recipe"][var.name] = described
        atomic_write_text(out / "report.json", json_text(report, indent=2, default=json_default))
        atomic_write_text(out / "report.md", markdown_report(report))
    return report


def _header(stage: str, described: dict) -> str:
    """First line(s) a stage writes to its log: what runs (command line or config)."""
    what = described[stage]
    return f"$ {what}" if isinstance(what, str) else f"# {stage}: {json_text(what, default=json_default)}"
