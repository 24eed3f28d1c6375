"""What a sim-to-real experiment runs: :class:`Sim2RealConfig`, its :data:`SCALES` and :class:`Variant`.

A variant changes the recipe through *overrides* of the library configs: ``generate`` maps
:class:`fppsim.generation.GenerateConfig` fields to values (e.g. ``{"pedestal": 0.0}``), ``train``
maps :class:`uhrnet.training.train_config.TrainConfig` fields (e.g. ``{"augment": "off"}``, ``{"head": "phase"}``).
Two optional post-steps add rows without training again: ``adapt`` (a dict of
:class:`uhrnet.training.adapt.AdaptConfig` overrides, ``{}`` for its defaults; None: no adaptation) fine-tunes the
trained model on the UNLABELLED real images, and ``refine`` (names of :data:`uhrnet.physics.refine.REFINE_METHODS`)
measures the predictions after ``--refine phase`` with each method. The ``uhrnet sim2real`` command turns
``--variant`` / ``--ablation`` flag text into such overrides with the commands' own parsers; this module
never reads flags.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field, fields

from fppsim.dataio.encoding import json_default
from uhrnet.errors import Sim2RealError, UsageError
from uhrnet.training.adapt import AdaptConfig
from uhrnet.training.train_config import MAX_EPOCHS, TrainConfig, check_options

MAX_COUNT = 10_000_000  # synthetic samples (fppsim.generation's bound)
from fppsim.geometry.rig import RigError, data_path, load_rig
from fppsim.errors import check_seed
from uhrnet.physics.refine import REFINE_METHODS
from uhrnet.data.splits import MIN_REFERENCE_SPLIT

__all__ = ["SCALES", "Variant", "Sim2RealConfig", "data_key", "generate_workers"]

# The two scales. "cpu" is the recipe the issue judges; "gpu" the full-size one. "train": TrainConfig
# overrides every run of the scale gets (before the variant's own).
SCALES: dict[str, dict] = {
    "cpu": {"count": 400, "seed": 100, "workers": 2, "model": "unet", "base_channels": 16, "loss": "compound",
            "epochs": 10, "batch_size": 2, "lr": 5e-4, "device": "cpu",
            # the recipe's machine has 2 cores; pinned so that its seeded runs repeat bit for bit on any machine
            "train": {"threads": 2}},
    # Sized for under 25 minutes on one H100-class GPU with 16 CPU cores (not yet run on one).
    "gpu": {"count": 2000, "seed": 100, "workers": 0, "model": "uhrnet", "base_channels": None,
            "loss": "compound", "epochs": 12, "batch_size": 4, "lr": 3e-4, "device": "cuda",
            "train": {"amp": True}},
}

# fields the experiment sets itself (folder layout, resuming, progress output, the images adapted on)
_OWN = {"generate": ("out", "progress"), "train": ("out", "resume", "overwrite", "progress"),
        "adapt": ("checkpoint", "images", "out", "resume", "overwrite", "progress", "device", "figures")}


def _packaged_meshes() -> str:
    """The meshes shipped with fppsim (``assets/meshes``), wherever the package is installed."""
    return str(data_path("meshes"))


def _field_names(kind: str) -> set[str]:
    if kind == "generate":
        from fppsim.generation import GenerateConfig as cls  # heavy: the renderer (pyrender, OpenGL) loads only here
    else:
        cls = AdaptConfig if kind == "adapt" else TrainConfig
    return {f.name for f in fields(cls)}


@dataclass
class Variant:
    """One row of an ablation: how its dataset and its training run differ from the recipe.

    generate : ``GenerateConfig`` field -> value; variants with equal ``generate`` share one dataset.
    train : ``TrainConfig`` field -> value.
    adapt : ``AdaptConfig`` field -> value of the adaptation post-step (``{}``: its defaults); None: none.
    refine : refinement methods (:data:`uhrnet.physics.refine.REFINE_METHODS`), one extra row each (and one per
        method on the adapted model).
    generate_flags, train_flags, adapt_flags : the same changes as the user wrote them (e.g.
        ``["--pedestal", "0"]``), shown in the report; None: shown as ``field=value``.
    """
    name: str
    generate: dict = field(default_factory=dict)
    train: dict = field(default_factory=dict)
    generate_flags: list[str] | None = None
    train_flags: list[str] | None = None
    adapt: dict | None = None
    refine: list[str] = field(default_factory=list)
    adapt_flags: list[str] | None = None

    def __post_init__(self):
        if not self.name or any(c in self.name for c in "/\\ \t") or self.name.startswith("."):
            raise Sim2RealError(f"variant name {self.name!r} must be a non-empty word without slashes or spaces")

        self.refine = [self.refine] if isinstance(self.refine, str) else list(self.refine or [])
        bad = [m for m in self.refine if m not in REFINE_METHODS]
        if bad or len(set(self.refine)) != len(self.refine):
            raise Sim2RealError(f"variant {self.name!r}: refine methods must be distinct names of "
                                f"{', '.join(REFINE_METHODS)}, got {', '.join(self.refine)}")
        for kind, config in (("generate", "GenerateConfig"), ("train", "TrainConfig"), ("adapt", "AdaptConfig")):
            if kind == "adapt" and self.adapt is None:
                continue
            given = dict(getattr(self, kind) or {})
            setattr(self, kind, given)
            unknown = sorted(set(given) - _field_names(kind)) if given else []
            if unknown:
                raise Sim2RealError(f"variant {self.name!r}: {config} has no field(s) {', '.join(unknown)}")
            own = sorted(set(given) & set(_OWN[kind]))
            if own:
                raise Sim2RealError(f"variant {self.name!r}: {kind} {', '.join(own)} is set by the experiment")

    def described(self, kind: str) -> list[str]:
        """The ``generate``, ``train`` or ``adapt`` changes as text: the flags given, else ``field=value`` items."""
        flags = {"generate": self.generate_flags, "train": self.train_flags, "adapt": self.adapt_flags}[kind]
        if flags is not None:
            return list(flags)
        return [f"{k}={json.dumps(v, default=json_default)}" for k, v in (getattr(self, kind) or {}).items()]


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
    real_phase : real phase-shifting folders (``PSin/ PCos/ Fringe/ iPattern/``, no labels): every row gets
        the calibration-free phase residual of each frame (evaluation only).
    rig : calibration file of the real data for ``refine`` and ``adapt`` (default: the checkpoint's own rig,
        else fppsim's default rig).
    adapt_images : what adaptation fine-tunes on (default: the ``real`` folders and the ``real_phase``
        folders; only their fringe images are read, never a label).
    reuse : variant name -> a finished training run folder used instead of training (``uhrnet train``'s
        folder: ``last.pt`` at the requested epochs, ``config.json`` with the variant's training options;
        its dataset must have ``count`` samples and, where recorded, ``seed``). A run folder copied to
        ``out/<variant>/run`` is taken the same way.
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
    real_phase: list[str] = field(default_factory=list)
    rig: str | None = None
    adapt_images: list[str] | None = None
    reuse: dict[str, str] = field(default_factory=dict)

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
        for key, most in (("count", MAX_COUNT), ("epochs", MAX_EPOCHS)):  # wrong on their own: exit 2, before anything runs
            if not 1 <= getattr(self, key) <= most:
                raise UsageError(f"--{key} must be from 1 to {most:,}, got {getattr(self, key)}")
        if self.workers < 0:
            raise UsageError(f"--workers must be >= 0 (0: all cores), got {self.workers}")
        check_seed(self.seed, error=UsageError)  # the generator's seed, as generate checks it
        # the recipe's training numbers, wrong on their own as uhrnet train refuses them (exit 2, before generating)
        check_options({k: getattr(self, k) for k in ("batch_size", "lr", "base_channels") if getattr(self, k) is not None})
        if not self.object_mm > 0:
            raise UsageError(f"--object-mm must be > 0 mm, got {self.object_mm}")

        for v in self.variants:  # the synthetic validation split is the reference one unless a variant says otherwise
            n = int(v.generate.get("count", self.count))
            if v.train.get("synthetic_split", "reference") == "reference" and n < MIN_REFERENCE_SPLIT:
                raise UsageError(f"--count {n}: the reference 80/10/10 split of the synthetic data needs at least "
                                 f"{MIN_REFERENCE_SPLIT} samples" + ("" if v.name == "default" else f" (variant {v.name!r})"))
        self.real_phase = [str(f) for f in (self.real_phase or [])]
        self.reuse = {str(k): str(v) for k, v in (self.reuse or {}).items()}
        unknown = sorted(set(self.reuse) - set(names))
        if unknown:
            raise Sim2RealError(f"reuse: no variant named {', '.join(unknown)} (variants: {', '.join(names)})")
        if self.adapt_images is not None and not self.adapt_images:
            raise Sim2RealError("adapt_images: give at least one image or folder (None: the real folders)")
        if self.rig is not None:  # a rig that cannot measure is refused now, not after generating and training

            try:
                load_rig(self.rig)
            except RigError as exc:
                raise Sim2RealError(f"--rig: {exc}") from None


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
