"""Running a sim-to-real experiment: generate -> train (synthetic only) -> evaluate on REAL data -> report.

Every variant of :class:`~uhrnet.sim2real.config.Sim2RealConfig` runs three stages through the
libraries, in this process:

1. ``fppsim.generate(GenerateConfig)`` (:func:`generate_config`): the recipe's figshare-format dataset
   without phase-shifting images, plus the variant's ``generate`` overrides, in ``out/data/<key>``;
   variants with the same overrides share it. Log: ``out/data/<key>.log``.
2. ``uhrnet.train(TrainConfig)`` (:func:`train_config`) on that dataset alone, in ``out/<variant>/run``
   (``history.csv``, checkpoints). Log: ``out/<variant>/train.log``.
3. :func:`evaluate_real` on every real folder and :func:`evaluate_level` on the synthetic validation
   split, in ``out/<variant>/eval``.

Every stage is resumable: a finished dataset (as many samples as asked), a finished run (``last.pt``
at the requested epochs) and an evaluation newer than ``last.pt`` are re-used; an interrupted run is
resumed. ``out/report.json`` and ``out/report.md`` are rewritten after every variant.
"""

from __future__ import annotations

import csv
import json
import time
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import fields
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fppsim.errors import FppsimError
from fppsim.encoding import json_default
from fppsim.files import atomic_write_text
from uhrnet.errors import Sim2RealError, UhrnetError
from uhrnet.sim2real.config import SCALES, Sim2RealConfig, Variant, data_key, generate_workers
from uhrnet.sim2real.metrics import level_response, real_metrics, twin_metrics
from uhrnet.sim2real.report import markdown_report, plot_real

__all__ = ["generate_config", "train_config", "find_real_pairs", "evaluate_real", "evaluate_level",
           "run_sim2real"]

Recipe = Callable[[Sim2RealConfig, Variant, Path, Path], dict]


def generate_config(cfg: Sim2RealConfig, variant: Variant, data: str | Path):
    """The :class:`fppsim.generation.GenerateConfig` of ``variant``'s dataset in folder ``data``: the
    recipe (``cfg``'s meshes, count, seed and workers; figshare format with the figshare label
    transform, no phase-shifting images, a preview, no progress bar) and the variant's overrides."""
    from fppsim.formats import PRESETS
    from fppsim.generation import GenerateConfig

    base = dict(meshes=list(cfg.meshes), out=str(data), count=cfg.count, seed=cfg.seed,
                workers=generate_workers(cfg), format="figshare", psp_freqs=(), label=PRESETS["figshare"],
                preview=True, progress=False)
    try:
        return GenerateConfig(**{**base, **variant.generate})
    except (FppsimError, ValueError) as exc:
        raise Sim2RealError(f"variant {variant.name!r}: generate: {exc}") from None


def train_config(cfg: Sim2RealConfig, variant: Variant, data: str | Path, run: str | Path, resume: bool = False):
    """The :class:`uhrnet.train_config.TrainConfig` of ``variant``'s run in folder ``run`` on the
    dataset ``data`` alone: ``cfg``'s model, width, loss, epochs, batch size, learning rate and device,
    the scale's own options (:data:`SCALES`), then the variant's overrides; ``resume`` continues an
    interrupted run."""
    from uhrnet.train_config import TrainConfig

    base = dict(out=str(run), synthetic=[str(data)], model=cfg.model, base_channels=cfg.base_channels,
                loss=cfg.loss, epochs=cfg.epochs, batch_size=cfg.batch_size, lr=cfg.lr, device=cfg.device,
                progress=False, **SCALES[cfg.scale]["train"])
    try:
        return TrainConfig(**{**base, **variant.train, **({"resume": "auto"} if resume else {})})
    except (UhrnetError, ValueError) as exc:
        raise Sim2RealError(f"variant {variant.name!r}: train: {exc}") from None


def find_real_pairs(folders: Sequence[str]) -> list[tuple[str, object]]:
    """Open each real folder (figshare layout) as a dataset; error names a folder that is not one."""
    from uhrnet.data import FigshareArrays, find_figshare_pair
    from uhrnet.errors import DataError

    out = []
    for f in folders:
        if find_figshare_pair(f) is None:
            raise Sim2RealError(f"{f}: no figshare-format pair (f1_80.npy + Z.npy, or fringe_pattern.npy + "
                                "height_map.npy)")
        try:
            out.append((str(f), FigshareArrays(f, source="real")))
        except DataError as exc:
            raise Sim2RealError(str(exc)) from None
    return out


def evaluate_real(checkpoint: str | Path, real: Sequence[str], out: str | Path, object_mm: float = 1.0,
                  device: str = "cpu", figures: bool = True, title: str = "") -> dict:
    """Predict every real image with ``checkpoint`` and measure it (:mod:`uhrnet.sim2real.metrics`).

    Writes ``out/real_metrics.json``, ``out/predictions.npz`` (float32 predicted labels, one array per
    image: ``<folder index>_<sample index>``) and, with ``figures``, ``out/real_<k>.png``.
    Returns the JSON document: per-image rows and their means.
    """
    import torch

    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.device import select_device
    from uhrnet.data import parse_size
    from uhrnet.prediction import predict_labels

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ck = load_checkpoint(checkpoint)
    dev = select_device(device)
    model, transform = model_from_checkpoint(ck, dev)
    size = parse_size(ck.get("args", {}).get("resize"))
    rows, preds = [], {}
    for fi, (folder, ds) in enumerate(find_real_pairs(real)):
        for i in range(len(ds)):
            s = ds[i]
            pred = predict_labels(model, s["fringe"][None], size)[0, 0].cpu().numpy()
            label = s["height"][0].numpy()
            valid = s["mask"][0].numpy() > 0.5
            m = real_metrics(pred, label, valid, transform.units_per_mm, object_mm)
            m.update(twin_metrics(model, s["fringe"][0].numpy(), pred, label, valid, transform.units_per_mm,
                                  object_mm, m["plane_label"], size))
            key = f"{fi}_{i:06d}"
            preds[key] = pred.astype(np.float32)
            rows.append({"folder": folder, "index": i, "key": key, **m})
            if figures:
                plot_real(s["fringe"][0].numpy(), label, valid, pred, transform.units_per_mm, m,
                          out / f"real_{key}.png", object_mm, title=title)
    np.savez_compressed(out / "predictions.npz", **preds)
    keys = [k for k in rows[0] if k not in ("folder", "index", "key")]
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    doc = {"checkpoint": str(checkpoint), "epoch": ck.get("epoch"), "object_mm": object_mm,
           "label_transform": transform.to_dict(), "images": len(rows), "mean": mean, "per_image": rows}
    del model
    torch.cuda.empty_cache() if torch.cuda.is_available() else None
    atomic_write_text(out / "real_metrics.json", json.dumps(doc, indent=2))
    return doc


def evaluate_level(checkpoint: str | Path, synthetic: Sequence[str], out: str | Path, object_mm: float = 5.0,
                   device: str = "cpu") -> dict:
    """:func:`level_response` of ``checkpoint`` on the validation split of the ``synthetic`` folders
    (split as the run split them); writes and returns ``out/synthetic_level.json``."""
    import torch

    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.data import load_sources, parse_size
    from uhrnet.device import select_device

    ck = load_checkpoint(checkpoint)
    model, transform = model_from_checkpoint(ck, select_device(device))
    args = ck.get("args", {})
    val = load_sources(synthetic=list(synthetic), transform=transform,
                       synthetic_split=args.get("synthetic_split") or "reference").val
    with torch.no_grad():
        doc = level_response(model, (val[i] for i in range(len(val))), transform.units_per_mm, object_mm,
                             size=parse_size(args.get("resize")))
    doc = {"checkpoint": str(checkpoint), "epoch": ck.get("epoch"), "object_mm": object_mm, **doc}
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(out) / "synthetic_level.json", json.dumps(doc, indent=1))
    return doc


# --------------------------------------------------------------------------------------------------
# The experiment


def _dataset_done(data: Path, count: int) -> bool:
    z = data / "Z.npy"
    if not z.is_file():
        return False
    try:
        return int(np.load(z, mmap_mode="r").shape[0]) == count
    except (ValueError, OSError):
        return False


def _run_done(run: Path, epochs: int) -> bool:
    hist = run / "history.csv"
    if not (run / "last.pt").is_file() or not hist.is_file():
        return False
    rows = list(csv.DictReader(hist.open()))
    return bool(rows) and int(rows[-1]["epoch"]) >= epochs


def _history(run: Path) -> list[dict]:
    hist = run / "history.csv"
    if not hist.is_file():
        return []
    return [{k: (float(v) if v not in ("", None) else None) for k, v in r.items()} for r in csv.DictReader(hist.open())]


def _stage(name: str, fn: Callable[[], object], log: Path, header: str) -> float:
    """Run ``fn()`` with its printed output appended to ``log``; seconds taken. A failure is raised as
    :class:`Sim2RealError` naming the stage, its first line and the log."""
    t0 = time.perf_counter()
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write(header.rstrip("\n") + "\n")
        fh.flush()
        try:
            with redirect_stdout(fh), redirect_stderr(fh):
                fn()
        except (UhrnetError, FppsimError, ValueError, OSError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            fh.write(f"error: {first}\n")
            raise Sim2RealError(f"{name} failed: {first} (log {log})") from exc
    return time.perf_counter() - t0


def _as_dict(config) -> dict:
    """A config dataclass as JSON-ready values (a label transform as its dict)."""
    out = {}
    for f in fields(config):
        value = getattr(config, f.name)
        out[f.name] = value.to_dict() if hasattr(value, "to_dict") else value
    return out


def _fresh(result: Path, source: Path) -> bool:
    return result.is_file() and result.stat().st_mtime >= source.stat().st_mtime


def run_sim2real(cfg: Sim2RealConfig, log: Callable[[str], None] | None = print, recipe: Recipe | None = None) -> dict:
    """Run every variant of ``cfg`` (generate -> train -> evaluate on real), write ``report.json`` and
    ``report.md`` in ``cfg.out``; returns the report document. Stages already done are re-used.

    ``log`` gets one line per stage (None: silent). ``recipe(cfg, variant, data, run)`` returns the
    ``{"generate": ..., "train": ...}`` text stored as ``report["recipe"][variant]`` and at the top of
    the stage logs (the ``uhrnet sim2real`` command passes the equivalent command lines); without it
    the stages' configs are stored.
    """
    from fppsim.generation import generate
    from uhrnet.trainer import train

    say = log or (lambda line: None)
    out = Path(cfg.out)
    find_real_pairs(cfg.real)  # fail early on bad real folders, before anything is written
    plans = []
    for var in cfg.variants:  # every variant's configs are checked before the first stage runs
        data = out / "data" / data_key(var.generate)
        run = out / var.name / "run"
        plans.append((var, data, run, generate_config(cfg, var, data), train_config(cfg, var, data, run)))
    out.mkdir(parents=True, exist_ok=True)
    report = {"config": {f.name: getattr(cfg, f.name) for f in fields(cfg) if f.name != "variants"},
              "recipe": {}, "variants": []}
    device = "cuda" if cfg.device == "cuda" else "cpu"
    for var, data, run, gen, tr in plans:
        ev = out / var.name / "eval"
        timing = {}
        text = recipe(cfg, var, data, run) if recipe is not None else None
        described = text or {"generate": _as_dict(gen), "train": _as_dict(tr)}
        if not _dataset_done(data, gen.count):
            say(f"[{var.name}] generate -> {data}")

            def run_generate(gen=gen):
                for line in generate(gen).lines():
                    print(line)

            timing["generate_s"] = _stage("generate", run_generate, data.parent / f"{data.name}.log",
                                          _header("generate", described))
        if not _run_done(run, tr.epochs):
            say(f"[{var.name}] train -> {run}")
            if run.is_dir() and any(run.iterdir()):  # an interrupted run: continue it (or restart it)
                tr = train_config(cfg, var, data, run, resume=True)
            timing["train_s"] = _stage("train", lambda tr=tr: train(tr), out / var.name / "train.log",
                                       _header("train", described))
        last = run / "last.pt"
        done = ev / "real_metrics.json"
        if _fresh(done, last):
            metrics = json.loads(done.read_text())
        else:
            say(f"[{var.name}] evaluate on {len(cfg.real)} real folder(s)")
            t0 = time.perf_counter()
            metrics = evaluate_real(last, cfg.real, ev, cfg.object_mm, device=device, figures=cfg.figures,
                                    title=f"sim2real {var.name} ({cfg.scale})")
            timing["evaluate_s"] = time.perf_counter() - t0
        lvl = ev / "synthetic_level.json"
        level = json.loads(lvl.read_text()) if _fresh(lvl, last) else evaluate_level(last, [str(data)], ev, device=device)
        hist = _history(run)
        entry = {"name": var.name, "generate": var.described("generate"), "train": var.described("train"),
                 "data": str(data), "run": str(run), "timing": timing, "real": metrics["mean"],
                 "images": metrics["images"],
                 "synthetic_level": {k: level[k] for k in ("slope", "intercept_mm", "prior_level_mm",
                                                           "shape_rmse_mm", "n_objects")},
                 "synthetic_val_rmse_mm": hist[-1].get("val_rmse_mm") if hist else None,
                 "history": hist}
        timing_file = out / var.name / "timing.json"
        if timing:
            old = json.loads(timing_file.read_text()) if timing_file.is_file() else {}
            old.update(timing)
            atomic_write_text(timing_file, json.dumps(old, indent=1))
        entry["timing"] = json.loads(timing_file.read_text()) if timing_file.is_file() else timing
        report["variants"].append(entry)
        say(f"[{var.name}] object RMSE {metrics['mean']['object_rmse_mm']:.2f} mm, valid RMSE "
            f"{metrics['mean']['valid_rmse_mm']:.2f} mm")
        report["recipe"][var.name] = described
        atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=json_default))
        atomic_write_text(out / "report.md", markdown_report(report))
    return report


def _header(stage: str, described: dict) -> str:
    """First line(s) a stage writes to its log: what runs (command line or config)."""
    what = described[stage]
    return f"$ {what}" if isinstance(what, str) else f"# {stage}: {json.dumps(what, default=json_default)}"
