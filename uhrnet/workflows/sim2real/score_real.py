"""Measuring one checkpoint of a sim-to-real experiment on real data (and its synthetic validation split).

* :func:`evaluate_real`: every image of the real figshare-format folders (labelled pairs) ->
  :func:`~uhrnet.workflows.sim2real.real_metrics.real_metrics` (object RMSE, median |error|, share within 1 mm, coverage, ...)
  and, for the network's own prediction, the fringe twins (:func:`~uhrnet.workflows.sim2real.real_metrics.twin_metrics`);
* :func:`evaluate_real_phase`: every frame of real phase-shifting folders (``PSin/ PCos/ Fringe/ iPattern/``,
  no labels) -> the calibration-free phase residual of the prediction, the metric ``uhrnet evaluate-phase``
  reports with its defaults (:func:`uhrnet.scoring.phase_residual.evaluate_phase`: degree-3 plane, least squares,
  pixels with real phase and a lit input, predicted-invalid pixels kept);
* :func:`evaluate_level`: the level response on the synthetic validation split.

``refine`` (a name of :data:`uhrnet.physics.refine.REFINE_METHODS`) measures the prediction after ``uhrnet predict
--refine phase --refine-method METHOD`` (:func:`uhrnet.inference.prediction.refine_with_phase`) through ``rig`` (a
calibration file; default the checkpoint's own rig, else fppsim's default, :func:`uhrnet.inference.prediction.refine_rig_for`).
Pixels the network marks invalid stay as predicted, so the coverage of a refined row is the network's.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from fppsim.dataio.encoding import encode_fringe
from fppsim.files import atomic_write_text, json_text
from fppsim.geometry.rig import RigError, check_image_size
from uhrnet.errors import DataError, Sim2RealError
from fppsim.dataio.readers import open_source
from uhrnet.data.datasets import load_sources, open_dataset, parse_size
from fppsim.errors import PSPMatError
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.device import select_device
from uhrnet.inference.prediction import (label_heights, path_estimate, predict_labels, refine_rig_for,
                                         refine_with_phase)
from uhrnet.physics.refine import REFINE_METHODS
from uhrnet.workflows.sim2real.real_metrics import error_split, level_response, object_mask, real_metrics, twin_metrics
from uhrnet.workflows.sim2real.report import plot_real
from uhrnet.scoring.phase_residual import evaluate_phase

__all__ = ["find_real_pairs", "find_phase_frames", "refine_labels", "evaluate_real", "evaluate_real_phase",
           "evaluate_level"]


def find_real_pairs(folders: Sequence[str]) -> list[tuple[str, object]]:
    """Open each labelled real folder (any labelled layout) as a dataset; error names a folder that is not one."""
    out = []
    for f in folders:
        if not open_source(f).labelled:
            raise Sim2RealError(f"{f}: no labelled real samples (a figshare-format pair f1_80.npy + Z.npy, or "
                                "fringe_pattern.npy + height_map.npy, or another labelled layout)")
        try:
            out.append((str(f), open_dataset(f, source="real")))
        except DataError as exc:
            raise Sim2RealError(str(exc)) from None
    return out


def find_phase_frames(folders: Sequence[str]) -> list[tuple[str, str]]:
    """``[(folder, id), ...]`` of every frame of the real phase-shifting folders; error names a folder that is
    not one (``PSin/ PCos/ Fringe/ iPattern/`` with one ``<id>.mat`` each)."""

    out = []
    for f in folders:
        try:
            ids = open_source(f).phase_ids()
        except PSPMatError as exc:
            raise Sim2RealError(str(exc)) from None
        if not ids:
            raise Sim2RealError(f"{f}: not a phase-shifting folder (PSin/, PCos/, Fringe/, iPattern/ of <id>.mat)")
        out += [(str(f), sid) for sid in ids]
    return out


def _model(checkpoint, device: str):

    ck = load_checkpoint(checkpoint)
    model, transform = model_from_checkpoint(ck, select_device(device))
    return ck, model, transform, parse_size(ck.get("args", {}).get("resize"))


def _refine_rig(ck: dict, refine: str | None, rig: str | Path | None):
    """The rig ``refine`` uses (None without ``refine``) and its name."""
    if refine is None:
        return None, None

    if refine not in REFINE_METHODS:
        raise Sim2RealError(f"refine method {refine!r} unknown (known: {', '.join(REFINE_METHODS)})")
    try:
        return refine_rig_for(ck, rig or None)
    except RigError as exc:
        raise Sim2RealError(f"rig: {exc}") from None


def refine_labels(label: np.ndarray, fringe: np.ndarray, transform, rig, method: str, rig_name: str = "the rig",
                  model=None, size=None):
    """``(labels, stats)``: predicted labels (H, W) after ``--refine phase --refine-method method`` on the
    image ``fringe`` (dataset encoding) through ``rig``; pixels the prediction marks invalid (or a black input)
    keep their label. With ``model`` (and its ``size``) the path starts where ``uhrnet predict``'s does, from
    the network's mean over the image and its mirror along the fringes
    (:func:`uhrnet.inference.prediction.path_estimate`); without it, from ``label``."""

    check_image_size(rig, fringe.shape, "refine", who=f"{rig_name} sees", hint=" (give the real data's rig: --rig FILE)",
                     error=Sim2RealError)
    lab = np.asarray(label, np.float64)
    h = network = label_heights(lab, transform, fringe)
    if model is not None:
        h = path_estimate(model, transform, fringe, size, rig, h)
    refined, stats = refine_with_phase(h, np.asarray(fringe, np.float32), rig, method, network_mm=network)
    out = np.where(np.isfinite(refined), refined * transform.units_per_mm + transform.plane_offset, lab)
    return out.astype(np.float32), stats


def evaluate_real(checkpoint: str | Path, real: Sequence[str], out: str | Path, object_mm: float = 1.0,
                  device: str = "cpu", figures: bool = True, title: str = "", refine: str | None = None,
                  rig: str | Path | None = None) -> dict:
    """Predict every real image with ``checkpoint`` (then ``refine`` it, module docstring) and measure it
    (:mod:`uhrnet.workflows.sim2real.real_metrics`; the fringe twins for the network's own prediction only).

    Each per-image row also lists its object regions' errors (``object_region_errors``: area in px, median
    and mean error in mm, largest first; :func:`~uhrnet.workflows.sim2real.real_metrics.error_split`).
    Writes ``out/real_metrics.json``, ``out/predictions.npz`` (float32 predicted labels, one array per
    image: ``<folder index>_<sample index>``) and, with ``figures``, ``out/real_<k>.png``.
    Returns the JSON document: per-image rows and their means.
    """
    import torch


    out = Path(out)
    pairs = find_real_pairs(real)
    ck, model, transform, size = _model(checkpoint, device)
    refine_rig, rig_name = _refine_rig(ck, refine, rig)
    out.mkdir(parents=True, exist_ok=True)
    rows, preds = [], {}
    for fi, (folder, ds) in enumerate(pairs):
        for i in range(len(ds)):
            s = ds[i]
            fringe = s["fringe"][0].numpy()
            pred = predict_labels(model, s["fringe"][None], size)[0, 0].cpu().numpy()
            extra = {}
            if refine_rig is not None:
                pred, stats = refine_labels(pred, fringe, transform, refine_rig, refine, rig_name, model, size)
                extra = {"refine_moved_fraction": float(stats["moved_fraction"])}
            label = s["height"][0].numpy()
            valid = s["mask"][0].numpy() > 0.5
            m = real_metrics(pred, label, valid, transform.units_per_mm, object_mm, transform.invalid_threshold)
            obj, _ = object_mask(label, valid, transform.units_per_mm, object_mm, m["plane_label"])
            regions = error_split((pred.astype(np.float64) - label) / transform.units_per_mm, obj)["per_region"]
            if refine_rig is None:
                m.update(twin_metrics(model, fringe, pred, label, valid, transform.units_per_mm, object_mm,
                                      m["plane_label"], size))
            m.update(extra)
            key = f"{fi}_{i:06d}"
            preds[key] = pred.astype(np.float32)
            rows.append({"folder": folder, "index": i, "key": key, **m, "object_region_errors": regions})
            if figures:
                plot_real(fringe, label, valid, pred, transform.units_per_mm, m, out / f"real_{key}.png", object_mm,
                          title=title)
    np.savez_compressed(out / "predictions.npz", **preds)
    keys = [k for k in rows[0] if k not in ("folder", "index", "key", "object_region_errors")]
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    doc = {"checkpoint": str(checkpoint), "epoch": ck.get("epoch"), "object_mm": object_mm, "refine": refine,
           "rig": rig_name, "label_transform": transform.to_dict(), "images": len(rows), "mean": mean,
           "per_image": rows}
    del model
    torch.cuda.empty_cache() if torch.cuda.is_available() else None
    atomic_write_text(out / "real_metrics.json", json_text(doc, indent=2))
    return doc


def evaluate_real_phase(checkpoint: str | Path, folders: Sequence[str], out: str | Path, device: str = "cpu",
                        refine: str | None = None, rig: str | Path | None = None, degree: int = 3) -> dict:
    """The calibration-free phase residual (module docstring) of ``checkpoint``'s prediction (then ``refine``d)
    on every frame of the real phase-shifting ``folders``; writes and returns ``out/real_phase.json``:
    ``{"checkpoint", "refine", "frames": [{"folder", "id", "rmse_rad", "explained", "flat_rmse_rad",
    "pixel_fraction", ...}], "mean_rmse_rad"}``."""
    import torch


    frames = find_phase_frames(folders)
    ck, model, transform, size = _model(checkpoint, device)
    refine_rig, rig_name = _refine_rig(ck, refine, rig)
    rows = []
    for folder, sid in frames:
        try:
            s = open_source(folder).scan(sid)
        except PSPMatError as exc:
            raise Sim2RealError(str(exc)) from None
        fringe = encode_fringe(s.image)
        label = predict_labels(model, torch.from_numpy(fringe)[None, None], size)[0, 0].cpu().numpy()
        row = {"folder": folder, "id": sid}
        if refine_rig is not None:
            label, stats = refine_labels(label, fringe, transform, refine_rig, refine, rig_name, model, size)
            row["refine_moved_fraction"] = float(stats["moved_fraction"])
        h = transform.height_mm(label.astype(np.float64))
        ok = s.valid & (s.image > 0)
        try:
            res = evaluate_phase(s.phase, h, ok, degree=degree)
        except ValueError as exc:
            raise Sim2RealError(f"{folder}/{sid}: {exc}") from None
        p, f = res["prediction"], res["flat"]
        rows.append({**row, "rmse_rad": p["rmse_rad"], "explained": p["explained"], "flat_rmse_rad": f["rmse_rad"],
                     "a_rad_per_mm": p["a_rad_per_mm"], "pixel_fraction": float(ok.mean()),
                     "predicted_invalid_fraction": float((s.valid & ~np.asarray(transform.valid(label))).mean())})
    doc = {"checkpoint": str(checkpoint), "epoch": ck.get("epoch"), "refine": refine, "rig": rig_name,
           "degree": degree, "frames": rows,
           "mean_rmse_rad": float(np.mean([r["rmse_rad"] for r in rows])) if rows else float("nan")}
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(out) / "real_phase.json", json_text(doc, indent=2))
    return doc


def evaluate_level(checkpoint: str | Path, synthetic: Sequence[str], out: str | Path, object_mm: float = 5.0,
                   device: str = "cpu") -> dict:
    """:func:`~uhrnet.workflows.sim2real.real_metrics.level_response` of ``checkpoint`` on the validation split of the
    ``synthetic`` folders (split as the run split them); writes and returns ``out/synthetic_level.json``."""
    import torch


    ck, model, transform, size = _model(checkpoint, device)
    args = ck.get("args", {})
    val = load_sources(synthetic=list(synthetic), transform=transform,
                       synthetic_split=args.get("synthetic_split") or "reference").val
    with torch.no_grad():
        doc = level_response(model, (val[i] for i in range(len(val))), transform.units_per_mm, object_mm, size=size)
    doc = {"checkpoint": str(checkpoint), "epoch": ck.get("epoch"), "object_mm": object_mm, **doc}
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(out) / "synthetic_level.json", json_text(doc, indent=1))
    return doc
