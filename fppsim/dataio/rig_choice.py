"""Which rig a command uses: :func:`resolve_rig`, the one resolver of every command that measures or
predicts through a rig (train's phase head, predict / adapt / sim2real's ``--refine``, label-real), and
:func:`dataset_rig`, the nominal rig a synthetic dataset records. Each rig it returns passed
:func:`fppsim.geometry.rig.usable_rig`; whether images fit it is :func:`fppsim.geometry.rig.check_image_size`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from fppsim.errors import RigError
from fppsim.dataio.formats import read_settings
from fppsim.dataio.readers import open_source
from fppsim.geometry.rig import Rig, load_rig, usable_rig

__all__ = ["DEFAULT_REASON", "PER_SAMPLE_REASON", "dataset_rig", "resolve_rig"]

DEFAULT_REASON = "fppsim's default rig"
PER_SAMPLE_REASON = "each sample's meta.json"


def dataset_rig(folder: str | os.PathLike) -> tuple[Rig | None, str]:
    """``(rig, reason)``: the nominal rig of the synthetic dataset ``folder`` (its ``dataset.json``, else
    its first sample's ``meta.json``; a figshare export's ``native/`` folder too), ``(None, "")`` when it
    records none. A dataset rendered with ``--rig-jitter`` has no single rig: :class:`RigError`."""
    samples = open_source(folder).fppsim_samples()
    root = samples.path if samples is not None else Path(folder)
    d = read_settings(root)
    if d is not None:
        jitter = (d.get("config") or {}).get("rig_jitter")
        values = jitter.values() if isinstance(jitter, dict) else jitter if isinstance(jitter, (list, tuple)) else [jitter or 0]
        if any(float(v) for v in values):
            raise RigError(f"{root}: rendered with --rig-jitter {jitter}: its phases fit no single rig, "
                           "so the phase head cannot be trained on it (regenerate without jitter)")
        if d.get("rig"):
            return (usable_rig(Rig.from_dict(d["rig"]), f"{root}/dataset.json: its rig"),
                    f"the dataset's rig ({root}/dataset.json)")
    meta = next(iter(sorted(root.glob("*/meta.json"))), None)  # samples written without dataset.json
    if meta is not None:
        return usable_rig(Rig.from_dict(json.loads(meta.read_text())["rig"]), f"{meta}: its rig"), f"the dataset's rig ({meta})"
    return None, ""


def resolve_rig(flag=None, *, name: str | None = None, checkpoint_rig: dict | None = None,
                checkpoint: str = "the checkpoint", datasets=(), per_sample: bool = False) -> tuple[Rig | None, str]:
    """``(rig, reason)``: the rig a command uses and a short phrase saying where it came from, first of

    1. ``flag`` (``--rig``): a calibration file (:func:`fppsim.geometry.rig.load_rig`; reason: the path, or
       ``name``) or a :class:`Rig` (reason ``name``, else ``"the given rig"``);
    2. ``checkpoint_rig``: a checkpoint's own rig document (reason ``"the checkpoint's rig"``; errors
       name ``checkpoint``);
    3. the first of ``datasets`` that records a rig (:func:`dataset_rig`);
    4. with ``per_sample``, ``(None, PER_SAMPLE_REASON)``: each sample brings its own (label-real's native
       scans);
    5. fppsim's default rig (``DEFAULT_REASON``).

    Every rig passed :func:`fppsim.geometry.rig.usable_rig`; :class:`RigError` (or the file's ``OSError``)
    otherwise; a dataset's unreadable record raises ``KeyError`` / ``ValueError``."""
    if isinstance(flag, Rig):
        return usable_rig(flag, "rig"), name or "the given rig"
    if flag is not None:
        return load_rig(flag), name or str(flag)
    if checkpoint_rig is not None:
        return usable_rig(Rig.from_dict(checkpoint_rig), f"{checkpoint}: its rig"), "the checkpoint's rig"
    for folder in datasets or ():
        rig, reason = dataset_rig(folder)
        if rig is not None:
            return rig, reason
    if per_sample:
        return None, PER_SAMPLE_REASON
    return load_rig(None), DEFAULT_REASON
