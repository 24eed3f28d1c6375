"""Checkpoints: atomic writes, safe loading, RNG state capture, and rebuilding a model for inference.

A checkpoint (``last.pt`` / ``best.pt`` in a run folder) is a plain dict saved with ``torch.save`` that
loads with ``weights_only=True``::

    format "uhrnet-checkpoint", version 1
    model            {"name", "config"}   build_model(**config) rebuilds the architecture
    state_dict       the model's weights (the bare model, not a DDP/affine wrapper); with ``--ema``
                     their moving average, the weights every use of the checkpoint should see
    output           {"scale", "shift"}   label = network output * scale + shift
    label_transform  LabelTransform.to_dict()
    epoch            number of finished epochs
    optimizer, scaler, loss, rng, best, history, args, data   (for --resume)
    train_state_dict, ema {"decay", "updates"}                  (with --ema, for --resume)
"""

from __future__ import annotations

import os
import pickle
import random
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fppsim.formats import LabelTransform, atomic_path
from uhrnet.errors import CheckpointError

FORMAT = "uhrnet-checkpoint"
VERSION = 1


def atomic_save(obj, path: str | os.PathLike) -> Path:
    """``torch.save`` through :func:`fppsim.formats.atomic_path` (temporary file, fsync, rename).

    A crash or kill at any moment leaves either the previous file or the new one, never a torn file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)
    return path


def load_checkpoint(path: str | os.PathLike, map_location="cpu") -> dict:
    """Load and validate a uhrnet checkpoint (``weights_only=True``: no code runs while loading)."""
    path = Path(path)
    if path.is_dir():
        for name in ("best.pt", "last.pt"):
            if (path / name).is_file():
                path = path / name
                break
        else:
            raise CheckpointError(f"{path}: folder holds no best.pt or last.pt")
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: empty file (0 bytes), not a checkpoint")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError:  # torch's message advises weights_only=False: wrong for a garbage file
        raise CheckpointError(
            f"{path}: cannot load checkpoint: not a PyTorch checkpoint (truncated or another format)"
        ) from None
    except Exception as exc:  # truncated file, not a torch file ...
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else "no details"
        raise CheckpointError(f"{path}: cannot load checkpoint ({type(exc).__name__}: {first})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a uhrnet checkpoint (no format={FORMAT!r} entry)")
    if int(ckpt.get("version", 0)) > VERSION:
        raise CheckpointError(f"{path}: checkpoint version {ckpt['version']} is newer than this uhrnet ({VERSION})")
    for key in ("model", "state_dict", "label_transform"):
        if key not in ckpt:
            raise CheckpointError(f"{path}: checkpoint lacks {key!r}")
    ckpt["path"] = str(path)
    return ckpt


# --------------------------------------------------------------------------------------------------
# RNG state (only types that load under weights_only=True)


def rng_state() -> dict:
    np_state = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), int(np_state[2]),
                  int(np_state[3]), float(np_state[4])],
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"].cpu() if hasattr(state["torch"], "cpu") else state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


# --------------------------------------------------------------------------------------------------
# Models from checkpoints


class LabelHead(nn.Module):
    """Wraps a model so it outputs label units: ``label = output * scale + shift``.

    Training the network on ``(label - plane) / (10 mm in label units)`` instead of raw labels (-105 ..
    +180) spares it learning a large constant offset; ``scale=1, shift=0`` reproduces raw-label training.
    hNet's tuple of outputs (training mode) is mapped element by element.
    """

    def __init__(self, net: nn.Module, scale: float = 1.0, shift: float = 0.0):
        super().__init__()
        self.net, self.scale, self.shift = net, float(scale), float(shift)

    def forward(self, x):
        out = self.net(x)
        if isinstance(out, (tuple, list)):
            return tuple(o.float() * self.scale + self.shift for o in out)
        return out.float() * self.scale + self.shift


def model_from_checkpoint(ckpt: dict, device="cpu") -> tuple[LabelHead, LabelTransform]:
    """The checkpoint's network in eval mode, wrapped to output labels, and its label transform
    (checkpoints of any version: old label field names are read too)."""
    from uhrnet.models import build_model

    config = dict(ckpt["model"]["config"])
    try:
        net = build_model(**config)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{ckpt.get('path', 'checkpoint')}: cannot rebuild model {config}: {exc}") from None
    try:
        net.load_state_dict(ckpt["state_dict"])
    except RuntimeError as exc:
        raise CheckpointError(f"{ckpt.get('path', 'checkpoint')}: weights do not fit {config['name']}: "
                              f"{str(exc).splitlines()[0]}") from None
    out = ckpt.get("output", {"scale": 1.0, "shift": 0.0})
    model = LabelHead(net, out["scale"], out["shift"]).to(device).eval()
    return model, LabelTransform.from_dict(ckpt["label_transform"])
