"""Checkpoints: atomic writes (``save_epoch``: a run's ``last.pt`` and its ``best.pt`` copy), safe loading (a RUN
folder stands for its checkpoint), what made one (``checkpoint_kind``), RNG state capture, and rebuilding a model
for inference. The file names are :mod:`uhrnet.run_folder`'s.

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
    val_phase_frames [{"root", "id", "held_out", "digest"}]       (with --val-phase: the frames that choose best.pt
                                                                   and those held out; evaluate-phase warns on the first,
                                                                   copies too: digest = PspMat.digest())
"""

from __future__ import annotations

import hashlib
import os
import pickle
import random
import shutil
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fppsim.files import atomic_path
from fppsim.dataio.formats import LabelTransform
from uhrnet.errors import CheckpointError
from uhrnet.models import ALIASES, build_model, outputs_of
from uhrnet.run_folder import BEST_PT, CHECKPOINTS, LAST_PT

FORMAT = "uhrnet-checkpoint"
VERSION = 1


def atomic_save(obj, path: str | os.PathLike) -> Path:
    """``torch.save`` through :func:`fppsim.files.atomic_path` (temporary file, fsync, rename).

    A crash or kill at any moment leaves either the previous file or the new one, never a torn file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            torch.save(obj, f)
    except RuntimeError as exc:  # torch's writer reports a full disk as "unexpected pos ..."
        cause = exc.__cause__ or exc.__context__
        while cause is not None and not isinstance(cause, OSError):
            cause = cause.__cause__ or cause.__context__
        if cause is not None and cause.errno:
            raise OSError(cause.errno, cause.strerror or os.strerror(cause.errno), str(path)) from None
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointError(f"{path}: cannot write the checkpoint ({first})") from None
    return path


def save_epoch(out: Path, payload: dict, is_best: bool) -> None:
    """A run's epoch checkpoint: ``out/last.pt`` (atomically); a copy as ``out/best.pt`` when this epoch is the
    best so far (the names: :mod:`uhrnet.run_folder`)."""
    atomic_save(payload, out / LAST_PT)
    if is_best:
        with atomic_path(out / BEST_PT) as tmp:
            shutil.copyfile(out / LAST_PT, tmp)


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint file a RUN argument names: ``path`` itself, or a run folder's ``best.pt`` (else
    ``last.pt``: :data:`uhrnet.run_folder.CHECKPOINTS`); how ``predict``, ``evaluate`` and ``train --init-from``
    read it."""
    path = Path(path)
    if path.is_dir():
        for name in CHECKPOINTS:
            if (path / name).is_file():
                return path / name
        raise CheckpointError(f"{path}: folder holds no {' or '.join(CHECKPOINTS)}")
    return path


def find_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint file ``path`` names (:func:`checkpoint_file`), refused (:class:`CheckpointError`) when it
    is missing or empty; nothing is loaded (:func:`load_checkpoint` reads it)."""
    path = checkpoint_file(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: empty file (0 bytes), not a checkpoint")
    return path


def load_checkpoint(path: str | os.PathLike, map_location="cpu", *, digest: bool = False) -> dict:
    """Load and validate a uhrnet checkpoint (``weights_only=True``: no code runs while loading).

    ``path``: a checkpoint file or a run folder (:func:`checkpoint_file`); the result's ``"path"`` is the
    file read. ``digest``: also put the SHA-256 of the file's bytes in ``"sha256"`` (hashed from the same
    open file that is loaded, so a checkpoint replaced meanwhile cannot mismatch its hash).
    """
    path = find_checkpoint(path)
    sha256 = None
    try:
        with open(path, "rb") as f:
            if digest:
                h = hashlib.sha256()
                for chunk in iter(lambda: f.read(1 << 22), b""):
                    h.update(chunk)
                sha256 = h.hexdigest()
                f.seek(0)
            ckpt = torch.load(f, map_location=map_location, weights_only=True)
    except (pickle.UnpicklingError, KeyError, EOFError):
        # torch's message advises weights_only=False (wrong for a garbage file), or names a byte of it (a text
        # file: "KeyError: 105"), or is empty (a 0-byte file)
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
    if sha256 is not None:
        ckpt["sha256"] = sha256
    return ckpt


def checkpoint_kind(ckpt: dict | str | os.PathLike) -> str | None:
    """What made a uhrnet checkpoint (loaded, or a file / run folder that :func:`load_checkpoint` reads):
    ``"adapt"`` (``uhrnet adapt``), ``"import"`` (``uhrnet import-weights``) or None (a training run)."""
    if not isinstance(ckpt, dict):
        ckpt = load_checkpoint(ckpt)
    return "adapt" if "adapt" in ckpt else "import" if "imported" in ckpt else None


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
        labels = tuple(o.float() * self.scale + self.shift for o in outputs_of(out))
        return labels if len(labels) > 1 else labels[0]  # hNet's tuple stays a tuple (side outputs)


def model_from_checkpoint(ckpt: dict, device="cpu") -> tuple[LabelHead, LabelTransform]:
    """The checkpoint's network in eval mode, wrapped to output labels, and its label transform
    (checkpoints of any version: old label field names are read too)."""

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


# --------------------------------------------------------------------------------------------------
# Transfer learning: a fresh run that starts from a checkpoint's weights


def output_mm(scale: float, shift: float, transform: LabelTransform) -> tuple[float, float]:
    """``(a, b)`` such that a network output ``o`` means a height of ``a * o + b`` mm above the plane,
    for a :class:`LabelHead` with ``scale``/``shift`` and the label transform ``transform``."""
    return scale / transform.units_per_mm, (shift - transform.plane_offset) / transform.units_per_mm


def _architecture(name: str) -> str:

    return ALIASES[name][0] if name in ALIASES else name


def _describe(config: dict, keys) -> str:
    def short(v):
        text = repr(v)
        return text if len(text) <= 40 else "<" + type(v).__name__ + ">"

    opts = ", ".join(f"{k}={short(config.get(k))}" for k in keys)
    return _architecture(config.get("name", "?")) + (f" ({opts})" if opts else "")


def init_from_checkpoint(net: nn.Module, path: str | os.PathLike, output: tuple[float, float] | None = None) -> dict:
    """Copy the weights of the checkpoint ``path`` (a ``.pt`` file or a run folder, read as
    :func:`checkpoint_file` says) into ``net``: ``uhrnet train --init-from``.

    The checkpoint must hold the same architecture: the same model (an ablation alias counts as its
    architecture) with weights of the same names and shapes; options that shape no weight (dropout) may
    differ and are listed in the result. ``output``: ``(a, b)`` of :func:`output_mm` for this run; the
    checkpoint's network output must mean the same height (else ``--raw-output`` or the label scale
    differs and the weights would predict other units).

    The weights copied are the checkpoint's ``state_dict``: for a run trained with ``--ema`` that is
    the moving average, the weights ``predict`` and ``evaluate`` use and ``best.pt`` was chosen on (the
    optimised ``train_state_dict`` is not used). Batch-norm running statistics come along.

    Returns the record a run keeps of it: ``{"path", "sha256", "epoch", "weights" ("ema" or
    "trained"), "model", "other_options"}``. Raises :class:`CheckpointError` (one line, naming the file
    and the mismatch).
    """
    ckpt = load_checkpoint(path, digest=True)
    where = f"init-from {ckpt['path']}"
    theirs, ours = dict(ckpt["model"]["config"]), dict(net.config)
    keys = sorted((set(theirs) | set(ours)) - {"name"})
    differ = [k for k in keys if theirs.get(k) != ours.get(k)]
    if _architecture(theirs.get("name", "?")) != _architecture(ours["name"]):
        raise CheckpointError(f"{where}: model {_describe(theirs, [])} does not match this run's "
                              f"{_describe(ours, [])}")
    state, own = ckpt["state_dict"], net.state_dict()
    bad = sorted(set(state) ^ set(own)) or [k for k in own if tuple(state[k].shape) != tuple(own[k].shape)]
    if bad:
        if differ:
            raise CheckpointError(f"{where}: model {_describe(theirs, differ)} does not match this run's "
                                  f"{_describe(ours, differ)}")
        k = bad[0]
        detail = (f"{k} has shape {tuple(state[k].shape)}, this run's {tuple(own[k].shape)}"
                  if k in state and k in own else f"{k} is only in {'the checkpoint' if k in state else 'this run'}")
        raise CheckpointError(f"{where}: weights do not fit this run's {_describe(ours, [])}: {detail}")
    if output is not None:
        out = ckpt.get("output", {"scale": 1.0, "shift": 0.0})
        a, b = output_mm(out["scale"], out["shift"], LabelTransform.from_dict(ckpt["label_transform"]))
        if not (np.isclose(a, output[0], rtol=1e-6, atol=0) and np.isclose(b, output[1], rtol=1e-6, atol=1e-9)):
            raise CheckpointError(f"{where}: its network output means {a:g} * output + {b:g} mm, this run's "
                                  f"{output[0]:g} * output + {output[1]:g} mm (--raw-output or the label "
                                  "transform differs)")
    with torch.no_grad():
        net.load_state_dict(state)
    return {"path": str(Path(ckpt["path"]).resolve()), "sha256": ckpt["sha256"], "epoch": int(ckpt.get("epoch", 0)),
            "weights": "ema" if "ema" in ckpt else "trained", "model": theirs.get("name"),
            "other_options": {k: theirs.get(k) for k in differ}}
