"""`uhrnet evaluate`: checkpoints on the test split -> the paper's Table 3 and Figs. 7-9.

Writes to ``--out``: ``results.md``, ``results.csv``, ``results.json`` (per model: RMSE in mm, SSIM,
parameters, seconds per image), ``per_sample.csv`` (every model x image), and ``figures/*.png``
(fringe, ground truth, each model's prediction and height-error map, and a cross-section along a row).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from fppsim.formats import LabelTransform, atomic_write_text
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint, select_device
from uhrnet.data import SPLIT_MODES, Prepared, load_sources, parse_size
from uhrnet.errors import ConfigError as CLIError, UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoints", nargs="+", metavar="CKPT", help="checkpoint files or run folders (best.pt)")
    p.add_argument("--real", nargs="*", metavar="DIR",
                   help="real figshare-layout folder(s); bare --real: none [the first checkpoint's]")
    p.add_argument("--synthetic", nargs="*", metavar="DIR",
                   help="fppsim folder(s); bare --synthetic: none [the first checkpoint's]")
    p.add_argument("--out", required=True, metavar="DIR", help="report folder")
    p.add_argument("--split", choices=("test", "val", "train", "all"), default="test", help="which split to evaluate [test]")
    p.add_argument("--real-split", choices=SPLIT_MODES, help="how real folders are split [the checkpoint's]")
    p.add_argument("--synthetic-split", choices=SPLIT_MODES, help="how synthetic folders are split [the checkpoint's]")
    p.add_argument("--synthetic-label", choices=("true", "psp"), help="ground truth of native folders [the checkpoint's]")
    p.add_argument("--names", nargs="+", metavar="NAME", help="model names in the table (one per checkpoint)")
    p.add_argument("--crop", metavar="HxW", help="evaluate a centre crop of every image")
    p.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N images of the split")
    p.add_argument("--figures", type=int, default=3, metavar="N", help="comparison figures for N evenly spaced images [3]")
    p.add_argument("--samples", nargs="+", metavar="ID", help="figures for these sample ids (or split positions #K)")
    p.add_argument("--row", type=int, help="cross-section row [the row crossing most object pixels]")
    p.add_argument("--batch-size", type=int, default=1)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--timing-repeats", type=int, default=5, metavar="N",
                   help="timed forward passes per model at batch 1 (0: skip timing) [5]")
    p.add_argument("--no-progress", action="store_true")


def _names(ckpts: list[dict], given: list[str] | None) -> list[str]:
    if given:
        if len(given) != len(ckpts):
            raise CLIError(f"--names: {len(given)} names for {len(ckpts)} checkpoints")
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


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from uhrnet.inference import predict_labels
    from uhrnet.metrics import count_parameters, inference_seconds
    from uhrnet.plots import plot_comparison
    from uhrnet.train import image_metrics

    for flag, value, lowest in (("--limit", args.limit, 1), ("--batch-size", args.batch_size, 1),
                                ("--figures", args.figures, 0), ("--timing-repeats", args.timing_repeats, 0)):
        if value is not None and value < lowest:
            raise UsageError(f"{flag} must be >= {lowest}, got {value}")
    ckpts = [load_checkpoint(p) for p in args.checkpoints]
    names = _names(ckpts, args.names)
    transform = LabelTransform.from_dict(ckpts[0]["label_transform"])
    for c in ckpts[1:]:
        if LabelTransform.from_dict(c["label_transform"]) != transform:
            raise CLIError(f"{c['path']}: label transform {c['label_transform']} differs from "
                           f"{ckpts[0]['path']}'s {transform.to_dict()}")
    first = ckpts[0].get("args", {})
    real = args.real if args.real is not None else (first.get("real") or [])
    synthetic = args.synthetic if args.synthetic is not None else (first.get("synthetic") or [])
    if not real and not synthetic:
        raise CLIError("no data: give --real DIR and/or --synthetic DIR")
    real_split = args.real_split or first.get("real_split", "reference")
    syn_split = args.synthetic_split or first.get("synthetic_split", "reference")
    if args.split == "all":
        real_split = syn_split = "test"
    sources = load_sources(real, synthetic, transform, real_split, syn_split,
                           args.synthetic_label or first.get("synthetic_label", "true"))
    data = {"test": sources.test, "val": sources.val, "train": sources.train, "all": sources.test}[args.split]
    _warn_split_drift(ckpts, sources.description)
    try:
        crop = parse_size(args.crop)
    except ValueError as exc:
        raise CLIError(f"--crop: {exc}") from None
    ds = Prepared(data, crop=crop, random_crop=False)
    n = len(ds) if args.limit is None else min(len(ds), max(0, args.limit))
    if n == 0:
        raise CLIError(f"the {args.split} split is empty ({len(sources.train)} train / {len(sources.val)} val / "
                       f"{len(sources.test)} test images); try --split all or --real-split test")
    indices = list(range(n))
    figure_idx = _figure_indices(data.ids, n, args.samples, args.figures)
    try:
        device = select_device(args.device)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    image_shape = tuple(ds[0]["fringe"].shape[-2:])
    if args.row is not None and not 0 <= args.row < image_shape[0]:
        raise CLIError(f"--row {args.row}: the evaluated images have {image_shape[0]} rows (0..{image_shape[0] - 1})")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    per_sample: list[dict] = []
    summary: list[dict] = []
    preds: dict[int, dict[str, np.ndarray]] = {i: {} for i in figure_idx}
    loader = DataLoader(torch.utils.data.Subset(ds, indices), batch_size=args.batch_size, shuffle=False)
    for ck, name in zip(ckpts, names):
        model, _ = model_from_checkpoint(ck, device)
        size = parse_size(ck.get("args", {}).get("resize"))
        rows = []
        pos = 0
        bar = tqdm(loader, desc=f"evaluate {name}", unit="img", unit_scale=args.batch_size, leave=False,
                   disable=args.no_progress)
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
        per_sample += rows
        seconds = None
        if args.timing_repeats > 0:
            seconds = inference_seconds(model, (1, 1, *(_mult16(size or image_shape))), device,
                                        warmup=1, repeats=args.timing_repeats)
        row = {
            "name": name, "checkpoint": ck["path"], "model": ck["model"]["name"], "config": ck["model"]["config"],
            "epoch": ck.get("epoch"), "images": len(rows),
            "rmse_mm": _nanmean([r["rmse_mm"] for r in rows]), "rmse_mm_std": _nanstd([r["rmse_mm"] for r in rows]),
            "ssim": _nanmean([r["ssim"] for r in rows]), "ssim_std": _nanstd([r["ssim"] for r in rows]),
            "parameters": int(count_parameters(model.net)), "seconds_per_image": seconds,
            "timing_shape": list(_mult16(size or image_shape)), "device": str(device),
        }
        for src in ("real", "synthetic"):
            sel = [r for r in rows if r["source"] == src]
            row[f"rmse_mm_{src}"] = _nanmean([r["rmse_mm"] for r in sel])
            row[f"ssim_{src}"] = _nanmean([r["ssim"] for r in sel])
            row[f"images_{src}"] = len(sel)
        summary.append(row)
        del model

    per_source = any(r["images_real"] for r in summary) and any(r["images_synthetic"] for r in summary)
    md = markdown_table(summary, per_source)
    header = (f"# Evaluation: {args.split} split, {n} images ({sum(1 for r in per_sample[:n] if r['source'] == 'real')} "
              f"real, {sum(1 for r in per_sample[:n] if r['source'] == 'synthetic')} synthetic)\n\n"
              f"RMSE over valid pixels in mm (label transform {transform.name}: {transform.units_per_mm:g} units/mm, "
              f"invalid <= {transform.invalid_threshold:g}), SSIM with L = {transform.data_range:g}, "
              f"time = one forward pass at batch 1 on {device}.\n\n")
    atomic_write_text(out / "results.md", header + md)
    _write_csv(out / "results.csv", summary, ["name", "rmse_mm", "rmse_mm_std", "ssim", "ssim_std", "parameters",
                                              "seconds_per_image", "images", "rmse_mm_real", "ssim_real",
                                              "images_real", "rmse_mm_synthetic", "ssim_synthetic",
                                              "images_synthetic", "model", "epoch", "checkpoint", "device"])
    _write_csv(out / "per_sample.csv", per_sample, ["model", "id", "source", "rmse_mm", "ssim"])
    atomic_write_text(out / "results.json", json.dumps(
        {"split": args.split, "images": n, "data": sources.description, "label_transform": transform.to_dict(),
         "models": summary}, indent=2, default=_json_default, allow_nan=True))

    figures = []
    if preds:
        (out / "figures").mkdir(exist_ok=True)
        for i in figure_idx:
            sample = ds[i]
            fringe = sample["fringe"][0].numpy()
            label = sample["height"][0].numpy().astype(np.float64)
            valid = sample["mask"][0].numpy() > 0.5
            truth = transform.height_mm(label)
            row = args.row if args.row is not None else _cross_row(truth, valid)
            path = out / "figures" / f"{sample['source']}_{sample['id']}.png"
            figures.append(plot_comparison(fringe, truth, valid, preds[i], path, row=row,
                                           title=f"{sample['source']} sample {sample['id']} ({args.split} split)"))
    print(md, end="")
    print(f"report: {out / 'results.md'} (also results.csv, results.json, per_sample.csv)")
    if figures:
        print(f"figures: {out / 'figures'} ({len(figures)} image{'s' if len(figures) > 1 else ''})")
    return 0


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
                raise CLIError(f"--samples: {s!r} is not a sample id of the evaluated split (e.g. {ids[0]!r}, or #0)")
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


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    return str(o)


def _write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if (v is None or (isinstance(v, float) and math.isnan(v))) else
                        (f"{v:.6g}" if isinstance(v, float) else v)) for k, v in r.items() if k in columns})
    atomic_write_text(path, buf.getvalue())
