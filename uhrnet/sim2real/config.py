"""What a sim-to-real experiment runs: :class:`Sim2RealConfig`, its :data:`SCALES` and :class:`Variant`.

A variant changes the recipe through *overrides* of the two library configs: ``generate`` maps
:class:`fppsim.generation.GenerateConfig` fields to values (e.g. ``{"pedestal": 0.0}``), ``train``
maps :class:`uhrnet.train_config.TrainConfig` fields (e.g. ``{"augment": "off"}``). The ``uhrnet
sim2real`` command turns ``--variant`` / ``--ablation`` flag text into such overrides with the two
commands' own parsers; this module never reads flags.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field, fields

from fppsim.encoding import json_default
from uhrnet.errors import Sim2RealError

__all__ = ["SCALES", "Variant", "Sim2RealConfig", "data_key", "generate_workers"]

# The two scales. "cpu" is the recipe the issue judges; "gpu" the full-size one. "train": TrainConfig
# overrides every run of the scale gets (before the variant's own).
SCALES: dict[str, dict] = {
    "cpu": {"count": 400, "seed": 100, "workers": 2, "model": "unet", "base_channels": 16, "loss": "compound",
            "epochs": 10, "batch_size": 2, "lr": 5e-4, "device": "cpu", "train": {}},
    # Sized for under 25 minutes on one H100-class GPU with 16 CPU cores (not yet run on one).
    "gpu": {"count": 2000, "seed": 100, "workers": 0, "model": "uhrnet", "base_channels": None,
            "loss": "compound", "epochs": 12, "batch_size": 4, "lr": 3e-4, "device": "cuda",
            "train": {"amp": True}},
}

# fields the experiment sets itself (folder layout, resuming, progress output)
_OWN = {"generate": ("out", "progress"), "train": ("out", "resume", "overwrite", "progress")}


def _packaged_meshes() -> str:
    """The meshes shipped with fppsim (``assets/meshes``), wherever the package is installed."""
    from fppsim.rig import data_path

    return str(data_path("meshes"))


def _field_names(kind: str) -> set[str]:
    if kind == "generate":
        from fppsim.generation import GenerateConfig as cls
    else:
        from uhrnet.train_config import TrainConfig as cls
    return {f.name for f in fields(cls)}


@dataclass
class Variant:
    """One row of an ablation: how its dataset and its training run differ from the recipe.

    generate : ``GenerateConfig`` field -> value; variants with equal ``generate`` share one dataset.
    train : ``TrainConfig`` field -> value.
    generate_flags, train_flags : the same changes as the user wrote them (e.g. ``["--pedestal", "0"]``),
        shown in the report; None: shown as ``field=value``.
    """

    name: str
    generate: dict = field(default_factory=dict)
    train: dict = field(default_factory=dict)
    generate_flags: list[str] | None = None
    train_flags: list[str] | None = None

    def __post_init__(self):
        if not self.name or any(c in self.name for c in "/\\ \t") or self.name.startswith("."):
            raise Sim2RealError(f"variant name {self.name!r} must be a non-empty word without slashes or spaces")
        for kind, config in (("generate", "GenerateConfig"), ("train", "TrainConfig")):
            given = dict(getattr(self, kind) or {})
            setattr(self, kind, given)
            unknown = sorted(set(given) - _field_names(kind)) if given else []
            if unknown:
                raise Sim2RealError(f"variant {self.name!r}: {config} has no field(s) {', '.join(unknown)}")
            own = sorted(set(given) & set(_OWN[kind]))
            if own:
                raise Sim2RealError(f"variant {self.name!r}: {kind} {', '.join(own)} is set by the experiment")

    def described(self, kind: str) -> list[str]:
        """The ``generate`` or ``train`` changes as text: the flags given, else ``field=value`` items."""
        flags = self.generate_flags if kind == "generate" else self.train_flags
        if flags is not None:
            return list(flags)
        return [f"{k}={json.dumps(v, default=json_default)}" for k, v in getattr(self, kind).items()]


@dataclass
class Sim2RealConfig:
    """One experiment. ``None`` fields take the value of ``scale`` (see :data:`SCALES`).

    out : experiment folder; ``out/data/<key>`` synthetic sets (:func:`data_key`), ``out/<variant>/run``
        and ``out/<variant>/eval``.
    real : figshare-format folders of REAL data (evaluation only, never used for training).
    meshes : mesh files/folders of the synthetic scenes (default: the meshes fppsim ships).
    count, seed, workers : synthetic samples, generator seed, generator processes (0: all cores).
    model, base_channels, loss, epochs, batch_size, lr, device : the training run (``uhrnet train``).
    variants : the ablation rows (default: one row ``default``, the recipe itself).
    object_mm : object pixels are valid pixels more than this far (mm) above the plane.
    figures : write a figure per real image.
    """

    out: str
    real: list[str]
    meshes: list[str] = field(default_factory=lambda: [_packaged_meshes()])
    scale: str = "cpu"
    count: int | None = None
    seed: int | None = None
    workers: int | None = None
    model: str | None = None
    base_channels: int | None = None
    loss: str | None = None
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    device: str | None = None
    variants: list[Variant] = field(default_factory=lambda: [Variant("default")])
    object_mm: float = 1.0
    figures: bool = True

    def __post_init__(self):
        if self.scale not in SCALES:
            raise Sim2RealError(f"unknown scale {self.scale!r} (known: {', '.join(SCALES)})")
        for k, v in SCALES[self.scale].items():
            if k != "train" and getattr(self, k) is None:
                setattr(self, k, v)
        if not self.real:
            raise Sim2RealError("no real data: give at least one figshare-format folder")
        names = [v.name for v in self.variants]
        if len(set(names)) != len(names):
            raise Sim2RealError(f"variant names must be unique, got {names}")
        if self.count < 1 or self.epochs < 1:
            raise Sim2RealError("count and epochs must be >= 1")
        if self.workers < 0:
            raise Sim2RealError(f"workers must be >= 0 (0: all cores), got {self.workers}")
        if not self.object_mm > 0:
            raise Sim2RealError(f"object_mm must be > 0 mm, got {self.object_mm}")


def data_key(generate: dict) -> str:
    """Folder name of the dataset a variant's ``generate`` overrides make: ``defaults`` for none,
    else a hash of the overrides (equal overrides, one dataset)."""
    if not generate:
        return "defaults"
    text = json.dumps(generate, sort_keys=True, default=json_default)
    return "g" + hashlib.sha1(text.encode()).hexdigest()[:10]


def generate_workers(cfg: Sim2RealConfig) -> int:
    """Generator processes: ``cfg.workers``, 0 meaning every core this process may use."""
    if cfg.workers:
        return int(cfg.workers)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
