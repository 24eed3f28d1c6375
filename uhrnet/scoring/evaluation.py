"""Evaluation: ``uhrnet.evaluate(checkpoints, EvalData(...), out=...) -> Report`` runs checkpoints on
the test split -> the paper's Table 3 and Figs. 7-9; ``uhrnet evaluate`` calls it.

Writes to ``out``: ``results.md``, ``results.csv``, ``results.json`` (per model: RMSE in mm, SSIM,
parameters, seconds per image), ``per_sample.csv`` (every model x image), and ``figures/*.png``
(fringe, ground truth, each model's prediction and height-error map, and a cross-section along a row).
Those names are claimed in ``out``'s ownership record (:mod:`fppsim.owned`) before anything is scored or
written: a file of them that evaluate did not write is refused in one line, its own report is replaced.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader

from fppsim.dataio.encoding import json_default, png_size
from fppsim.files import atomic_write_text, json_text
from fppsim.dataio.formats import LabelTransform
from fppsim.owned import claim, output_folder
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.data.datasets import Prepared, load_sources, parse_size
from uhrnet.device import select_device
from uhrnet.errors import ConfigError, UsageError
from uhrnet.inference.prediction import predict_labels
from uhrnet.models import count_parameters
from uhrnet.scoring.metrics import image_metrics
from uhrnet.scoring.timing import inference_seconds
from uhrnet.plots import plot_comparison

__all__ = ["EvalData", "Report", "evaluate", "markdown_table", "model_names", "check_name_count", "SPLITS",
           "EVALUATE_TOOL", "REPORT_FILES"]

SPLITS = ("test", "val", "train", "all")
#: the name evaluate's files carry in their folder's ownership record (:mod:`fppsim.owned`)
EVALUATE_TOOL = "uhrnet evaluate"
REPORT_FILES = ("results.md", "results.csv", "results.json", "per_sample.csv")  # what Report.write writes


@dataclass
class EvalData:
    """Which images to evaluate. ``None`` fields take the first checkpoint's training setting;
    ``real=[]`` / ``synthetic=[]`` means none of that kind. ``split``: one of :data:`SPLITS`
    (``all``: every image, no split). ``crop``: "HxW" centre crop; ``limit``: first N images only."""

    real: Sequence[str] | None = None
    synthetic: Sequence[str] | None = None
    split: str = "test"
    real_split: str | None = None
    synthetic_split: str | None = None
    synthetic_label: str | None = None
    crop: str | None = None
    limit: int | None = None

    def __post_init__(self):
        if self.limit is not None and self.limit < 1:
            raise UsageError(f"--limit must be >= 1, got {self.limit}")
        if self.split not in SPLITS:
            raise ConfigError(f"--split {self.split!r}: choose from {', '.join(SPLITS)}")
        try:
            parse_size(self.crop)
        except ValueError as exc:
            raise ConfigError(f"--crop: {exc}") from None


@dataclass
class Report:
    """What :func:`evaluate` measured: one summary row per model (``models``: RMSE mm, SSIM, parameters,
    seconds per image, per-source values), every model x image (``per_sample``), the markdown table
    (``table``, also ``results.md``) and the figure paths."""

    split: str
    images: int
    data: dict
    label_transform: dict
    models: list[dict]
    per_sample: list[dict]
    table: str
    header: str = ""
    figures: list = field(default_factory=list)

    def write(self, out: str | Path) -> None:
        """results.md, results.csv, results.json and per_sample.csv in ``out``, claimed first (never a file
        evaluate did not write: :class:`fppsim.errors.ForeignFiles`)."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        claim(out, EVALUATE_TOOL, REPORT_FILES, legacy=lambda: _own_report(out))  # (evaluate claimed them already)
        atomic_write_text(out / "results.md", self.header + self.table)
        _write_csv(out / "results.csv", self.models,
                   ["name", "rmse_mm", "rmse_mm_std", "ssim", "ssim_std", "parameters", "seconds_per_image", "images",
                    "rmse_mm_real", "ssim_real", "images_real", "rmse_mm_synthetic", "ssim_synthetic",
                    "images_synthetic", "model", "epoch", "checkpoint", "device"])
        _write_csv(out / "per_sample.csv", self.per_sample, ["model", "id", "source", "rmse_mm", "ssim"])
        atomic_write_text(out / "results.json", json_text(
            {"split": self.split, "images": self.images, "data": self.data, "label_transform": self.label_transform,
             "models": self.models}, indent=2, default=json_default))


def check_name_count(given: Sequence[str] | None, count: int) -> None:
    """:class:`UsageError` unless ``--names`` (``given``, None or empty: none) names each of ``count`` checkpoints."""
    if given and len(given) != count:
        raise UsageError(f"--names: {len(given)} names for {count} checkpoints")


def model_names(ckpts: list[dict], given: list[str] | None) -> list[str]:
    if given:
        check_name_count(given, len(ckpts))
        return list(given)
    base = [c["model"]["name"] for c in ckpts]
    names = []
    for c, b in zip(ckpts, base):
        names.append(f"{b} ({Path(c['path']).parent.name})" if base.count(b) > 1 else b)
    seen: dict[str, int] = {}
    for i, n in enumerate(names):
        if n in seen:
            seen[n] += 1
            names[i] = f"{n} #{seen[n]}"
        else:
            seen[n] = 1
    return names


def _nanmean(values) -> float:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def _nanstd(values) -> float:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v.std()) if v.size else float("nan")


def _cross_row(height_mm: np.ndarray, valid: np.ndarray) -> int:
    """The row crossing the most valid object pixels (more than 1 mm above the plane)."""
    score = ((height_mm > 1.0) & valid).sum(axis=1)
    return int(np.argmax(score)) if score.max() > 0 else height_mm.shape[0] // 2


def markdown_table(rows: list[dict], per_source: bool) -> str:
    head = ["Model", "RMSE (mm)", "SSIM", "Parameters", "Time (s/image)", "Images"]
    if per_source:
        head[3:3] = ["RMSE real (mm)", "RMSE synthetic (mm)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
    for r in rows:
        cells = [r["name"], f"{r['rmse_mm']:.4f}", f"{r['ssim']:.4f}"]
        if per_source:
            cells += [f"{r['rmse_mm_real']:.4f}", f"{r['rmse_mm_synthetic']:.4f}"]
        t = r["seconds_per_image"]
        cells += [f"{r['parameters'] / 1e6:.2f}M", "n/a" if t is None else f"{t:.4f}", str(r["images"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def evaluate(checkpoints: Sequence, data: EvalData | None = None, *, out: str | Path | None = None,
             names: Sequence[str] | None = None, figures: int = 3, samples: Sequence[str] | None = None,
             row: int | None = None, batch_size: int = 1, device: str = "auto", timing_repeats: int = 5,
             progress: bool = True) -> Report:
    """Evaluate checkpoints (files or run folders) on ``data``; with ``out``, write the report files and
    comparison figures (``figures`` evenly spaced images, or the ids in ``samples``; cross-section
    ``row``) there. ``timing_repeats`` timed forward passes at batch 1 per model (0: no timing)."""
    data = data or EvalData()
    for flag, value, lowest in (("--batch-size", batch_size, 1), ("--figures", figures, 0),
                                ("--timing-repeats", timing_repeats, 0)):
        if value is not None and value < lowest:
            raise UsageError(f"{flag} must be >= {lowest}, got {value}")
    check_name_count(names, len(checkpoints))  # before any checkpoint is read
    ckpts = [load_checkpoint(p) for p in checkpoints]
    names = model_names(ckpts, names)
    transform = _shared_transform(ckpts)
    sources, subset, ds, n = _open_split(data, ckpts, transform)
    figure_idx = _figure_indices(subset.ids, n, samples, figures) if out is not None else []
    device = select_device(device)
    image_shape = tuple(ds[0]["fringe"].shape[-2:])
    if row is not None and not 0 <= row < image_shape[0]:
        raise ConfigError(f"--row {row}: the evaluated images have {image_shape[0]} rows (0..{image_shape[0] - 1})")
    scoring = dict(ckpts=ckpts, names=names, transform=transform, sources=sources, ds=ds, n=n, split=data.split,
                   figure_idx=figure_idx, device=device, image_shape=image_shape, timing_repeats=timing_repeats,
                   progress=progress, batch_size=batch_size)
    if out is None:
        return _scored_report(**scoring)[0]
    out = Path(out)
    figure_names = [f"figures/{_figure_name(ds[i])}" for i in figure_idx]
    figures_dir = out / "figures"
    if figure_names and (figures_dir.exists() or figures_dir.is_symlink()) and not figures_dir.is_dir():
        raise ConfigError(f"{figures_dir}: a file where evaluate writes its figures folder; move it away or "
                          "choose another --out")
    # locked for the run; every name claimed before anything is scored or written (a user's results.md once was
    # replaced); a failed run drops its claims on what it never wrote, and a folder it made and left empty
    with output_folder(out, EVALUATE_TOOL, error=ConfigError):
        claim(out, EVALUATE_TOOL, [*REPORT_FILES, *figure_names], legacy=lambda: _own_report(out))
        report, preds = _scored_report(**scoring)
        report.write(out)
        if preds:
            _write_figures(report, ds, figure_idx, preds, transform, row, out)
    return report


def _scored_report(ckpts, names, transform, sources, ds, n, split, figure_idx, device, image_shape, timing_repeats,
                   progress, batch_size) -> tuple[Report, dict]:
    """Every checkpoint scored on the first ``n`` images of ``ds``: the :class:`Report` and the heights of the
    figure images (``{index: {model name: mm}}``)."""
    per_sample: list[dict] = []
    summary: list[dict] = []
    preds: dict[int, dict[str, np.ndarray]] = {i: {} for i in figure_idx}
    loader = DataLoader(torch.utils.data.Subset(ds, list(range(n))), batch_size=batch_size, shuffle=False)
    for ck, name in zip(ckpts, names):
        rows, entry = _score_model(ck, name, loader, transform, device, preds, image_shape, timing_repeats,
                                   progress, batch_size)
        per_sample += rows
        summary.append(entry)

    per_source = any(r["images_real"] for r in summary) and any(r["images_synthetic"] for r in summary)
    report = Report(split=split, images=n, data=sources.description, label_transform=transform.to_dict(),
                    models=summary, per_sample=per_sample, table=markdown_table(summary, per_source),
                    header=_report_header(split, n, per_sample, transform, device))
    return report, preds


def _own_report(out: Path) -> list[str]:
    """The files of an ``--out`` evaluate wrote before it recorded its files: its ``results.json`` (with the keys
    :meth:`Report.write` gives it) and, beside it, the report files that begin as evaluate writes them and the
    PNG figures named as it names them (everything else stays someone else's)."""
    try:
        doc = json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        return []
    if not (isinstance(doc, dict) and {"split", "images", "data", "label_transform", "models"} <= doc.keys()):
        return []
    starts = {"results.md": (b"# Evaluation:",), "results.csv": (b"name,rmse_mm,",),
              "per_sample.csv": (b"model,id,source,rmse_mm,ssim",)}
    mine = ["results.json"] + [name for name, heads in starts.items() if _begins(out / name, heads)]
    if (out / "figures").is_dir():
        mine += [f"figures/{p.name}" for p in sorted((out / "figures").glob("*.png"))
                 if p.name.startswith(("real_", "synthetic_")) and png_size(p) is not None]
    return mine


def _begins(path: Path, heads: tuple[bytes, ...]) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(64).startswith(heads)
    except OSError:
        return False


def _shared_transform(ckpts: list[dict]) -> LabelTransform:
    """The label transform of the checkpoints, which must all share it: one table compares their heights."""
    transform = LabelTransform.from_dict(ckpts[0]["label_transform"])
    for c in ckpts[1:]:
        if LabelTransform.from_dict(c["label_transform"]) != transform:
            raise ConfigError(f"{c['path']}: label transform {c['label_transform']} differs from "
                           f"{ckpts[0]['path']}'s {transform.to_dict()}")
    return transform


def _open_split(data: EvalData, ckpts: list[dict], transform: LabelTransform):
    """(sources, the split's subset, its prepared dataset, the number of images evaluated): ``data``'s
    folders and splits, each unset one as the first checkpoint was trained; refused when empty."""
    first = ckpts[0].get("args", {})
    real = data.real if data.real is not None else (first.get("real") or [])
    synthetic = data.synthetic if data.synthetic is not None else (first.get("synthetic") or [])
    if not real and not synthetic:
        raise ConfigError("no data: give --real DIR and/or --synthetic DIR")
    real_split = data.real_split or first.get("real_split", "reference")
    syn_split = data.synthetic_split or first.get("synthetic_split", "reference")
    if data.split == "all":
        real_split = syn_split = "test"
    sources = load_sources(real, synthetic, transform, real_split, syn_split,
                           data.synthetic_label or first.get("synthetic_label", "true"))
    split = data.split
    subset = {"test": sources.test, "val": sources.val, "train": sources.train, "all": sources.test}[split]
    _warn_split_drift(ckpts, sources.description)
    ds = Prepared(subset, crop=parse_size(data.crop), random_crop=False)
    n = len(ds) if data.limit is None else min(len(ds), max(0, data.limit))
    if n == 0:
        raise ConfigError(f"the {split} split is empty ({len(sources.train)} train / {len(sources.val)} val / "
                       f"{len(sources.test)} test images); try --split all or --real-split test")
    return sources, subset, ds, n


def _score_model(ck: dict, name: str, loader, transform: LabelTransform, device, preds: dict, image_shape: tuple,
                 timing_repeats: int, progress: bool, batch_size: int) -> tuple[list[dict], dict]:
    """One checkpoint on every image: its per-image rows and its summary entry; the heights of the figure
    images go into ``preds`` (only those, so the figures never hold every prediction in memory)."""
    from tqdm import tqdm

    model, _ = model_from_checkpoint(ck, device)
    size = parse_size(ck.get("args", {}).get("resize"))
    rows = []
    pos = 0
    bar = tqdm(loader, desc=f"evaluate {name}", unit="img", unit_scale=batch_size, leave=False,
               disable=not progress)
    for batch in bar:
        y, m = batch["height"].to(device), batch["mask"].to(device)
        pred = predict_labels(model, batch["fringe"], size)
        r, s = image_metrics(pred, y, m, transform)
        for k in range(len(r)):
            i = pos + k
            rows.append({"model": name, "id": batch["id"][k], "source": batch["source"][k],
                         "rmse_mm": float(r[k]), "ssim": float(s[k])})
            if i in preds:
                preds[i][name] = transform.height_mm(pred[k, 0].cpu().numpy().astype(np.float64))
        pos += len(r)
    bar.close()
    seconds = None
    if timing_repeats > 0:
        seconds = inference_seconds(model, (1, 1, *(_mult16(size or image_shape))), device,
                                    warmup=1, repeats=timing_repeats)
    entry = {
        "name": name, "checkpoint": ck["path"], "model": ck["model"]["name"], "config": ck["model"]["config"],
        "epoch": ck.get("epoch"), "images": len(rows),
        "rmse_mm": _nanmean([r["rmse_mm"] for r in rows]), "rmse_mm_std": _nanstd([r["rmse_mm"] for r in rows]),
        "ssim": _nanmean([r["ssim"] for r in rows]), "ssim_std": _nanstd([r["ssim"] for r in rows]),
        "parameters": int(count_parameters(model.net)), "seconds_per_image": seconds,
        "timing_shape": list(_mult16(size or image_shape)), "device": str(device),
    }
    for src in ("real", "synthetic"):
        sel = [r for r in rows if r["source"] == src]
        entry[f"rmse_mm_{src}"] = _nanmean([r["rmse_mm"] for r in sel])
        entry[f"ssim_{src}"] = _nanmean([r["ssim"] for r in sel])
        entry[f"images_{src}"] = len(sel)
    return rows, entry


def _report_header(split: str, n: int, per_sample: list[dict], transform: LabelTransform, device) -> str:
    """results.md's heading: what was evaluated and how each column was measured."""
    return (f"# Evaluation: {split} split, {n} images ({sum(1 for r in per_sample[:n] if r['source'] == 'real')} "
            f"real, {sum(1 for r in per_sample[:n] if r['source'] == 'synthetic')} synthetic)\n\n"
            f"RMSE over valid pixels in mm (label transform {transform.name}: {transform.units_per_mm:g} units/mm, "
            f"invalid <= {transform.invalid_threshold:g}), SSIM with L = {transform.data_range:g}, "
            f"time = one forward pass at batch 1 on {device}.\n\n")


def _write_figures(report: Report, ds, figure_idx: list[int], preds: dict, transform: LabelTransform,
                   row: int | None, out: Path) -> None:
    """The comparison figure of each figure image (fringe, truth, every model's height and error, a cross
    section along ``row`` or the row crossing the most object pixels), into ``out/figures`` and ``report``."""
    (out / "figures").mkdir(exist_ok=True)
    for i in figure_idx:
        sample = ds[i]
        fringe = sample["fringe"][0].numpy()
        label = sample["height"][0].numpy().astype(np.float64)
        valid = sample["mask"][0].numpy() > 0.5
        truth = transform.height_mm(label)
        r = row if row is not None else _cross_row(truth, valid)
        path = out / "figures" / _figure_name(sample)
        report.figures.append(plot_comparison(fringe, truth, valid, preds[i], path, row=r,
                                              title=f"{sample['source']} sample {sample['id']} ({report.split} split)"))


def _figure_name(sample: dict) -> str:
    return f"{sample['source']}_{sample['id']}.png"


def _mult16(shape) -> tuple[int, int]:
    h, w = shape
    return (h + (-h) % 16, w + (-w) % 16)


def _figure_indices(ids: list[str], n: int, samples: list[str] | None, count: int) -> list[int]:
    if samples:
        out = []
        for s in samples:
            if s.startswith("#") and s[1:].isdigit() and int(s[1:]) < n:
                out.append(int(s[1:]))
            elif s in ids[:n]:
                out.append(ids.index(s))
            else:
                raise ConfigError(f"--samples: {s!r} is not a sample id of the evaluated split (e.g. {ids[0]!r}, or #0)")
        return sorted(set(out))
    if count <= 0:
        return []
    return sorted(set(np.linspace(0, n - 1, min(count, n)).round().astype(int).tolist()))


def _warn_split_drift(ckpts: list[dict], description: dict) -> None:
    """Warn when a dataset changed size since training: its reference split (and test set) changed too."""
    now = {d["path"]: d["n"] for kind in ("real", "synthetic") for d in description[kind]}
    for c in ckpts:
        for kind in ("real", "synthetic"):
            for d in c.get("data", {}).get(kind, []):
                if d["path"] in now and now[d["path"]] != d["n"]:
                    print(f"warning: {d['path']} had {d['n']} samples when {c['path']} was trained and has "
                          f"{now[d['path']]} now: its split differs, test images may have been trained on",
                          file=sys.stderr)


def _write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if (v is None or (isinstance(v, float) and math.isnan(v))) else
                        (f"{v:.6g}" if isinstance(v, float) else v)) for k, v in r.items() if k in columns})
    atomic_write_text(path, buf.getvalue())
