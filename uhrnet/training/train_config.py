"""The options of a training run: :class:`TrainConfig`, their defaults, checks and resolution on resume.

``None`` means "not given" for every option, so a resumed run can tell what the user set: options in
:data:`LOCKED` must then match the checkpoint's, the others may change (e.g. ``--epochs``, ``--lr``).
:class:`RunConfig`, the frozen result the trainer reads, declares each option's default and resume
behaviour once.
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

from fppsim.dataio.formats import LabelTransform, PRESETS
from uhrnet.data.datasets import parse_size
from uhrnet.errors import CheckpointError, ConfigError, DataError, UsageError
from fppsim.dataio.readers import LABEL_SOURCES, check_read_convention
from uhrnet.data.splits import SPLIT_MODES
from uhrnet.training.losses import LOSSES
from uhrnet.models import check_model_options, list_models
from uhrnet.training.tb_log import require_tensorboard
from fppsim.threads import check_cores
from uhrnet.models.init import INITS
from uhrnet.models.freeze import FREEZE_CHOICES
from uhrnet.models.heads import HEADS
from uhrnet.checkpoint import checkpoint_file
from uhrnet.data.augment import augment_config, augment_kind

__all__ = ["TrainConfig", "RunConfig", "option", "DEFAULTS", "LOCKED", "LEGACY", "LEGACY_LOCKED", "LR_SCHEDULES",
           "LR_FLOOR", "RESIZE_AUTO", "AMP_DTYPES", "SWITCHES", "HOST_SYNCS", "HALVE_FROM_PERIOD_PX", "HALVE_FROM_SIDE_PX", "VAL_PHASE_FRAMES",
           "check_options", "resolve_config", "auto_resize", "label_transform_from", "model_options_from", "parse_kv",
           "MAX_SEED"]

LR_SCHEDULES = ("cosine", "constant")  # flat-cosine removed 2026-11-26: no gain (docs/experiments/sim2real.md)
MAX_EPOCHS = 1_000_000
MAX_SEED = 2**32 - 1  # --seed: numpy's legacy generators take no more; torch's per-epoch seeds (seed * 100_003 + epoch) fit
MAX_LR = 10.0  # a learning rate above this is a typo (and above float32's range, a traceback)
LR_FLOOR = 0.05  # the cosine schedules end at this fraction of --lr
RESIZE_AUTO = "auto"  # --resize auto: the training size from the synthetic data's fringe period (auto_resize)
HALVE_FROM_PERIOD_PX = 10.0  # --resize auto halves the images when their fringes are at least this many px apart
HALVE_FROM_SIDE_PX = 256  # ... and their shorter side is at least this long (smaller ones the network sees whole)
AMP_DTYPES = ("auto", "fp16", "bf16")  # --amp-dtype (CUDA)
SWITCHES = ("auto", "on", "off")  # --channels-last, --device-data, --fused-adam
HOST_SYNCS = ("auto", "step", "epoch")  # --host-sync
VAL_PHASE_FRAMES = 8  # --val-phase scores at most this many frames per epoch (evenly spaced over its folders)


def option(default, *, locked: bool = False, legacy=MISSING, legacy_locked: bool = False):
    """A field of :class:`RunConfig`: its ``default`` for a fresh run; ``locked``: a resume must keep the
    checkpoint's value; ``legacy``: the value of a run made before the option existed (resuming it must not
    switch the option on); ``legacy_locked``: such a resume refuses another value too (its weights did not
    start from a checkpoint, nothing was frozen)."""
    meta = {"locked": locked, "legacy_locked": legacy_locked}
    if legacy is not MISSING:
        meta["legacy"] = legacy
    if isinstance(default, list):  # a fresh list per config (dataclasses refuse a shared mutable default)
        return field(default_factory=list, metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class RunConfig:
    """The resolved options of a run, what the trainer reads: the user's :class:`TrainConfig` after the
    defaults (fresh run) or the checkpoint's values (resume), by :func:`resolve_config`.

    Each option's default and resume behaviour is declared here, once (:func:`option`); :data:`DEFAULTS`,
    :data:`LOCKED` and :data:`LEGACY` are read off these fields. ``init_from_checkpoint``: the record of
    ``--init-from`` (:func:`uhrnet.checkpoint.init_from_checkpoint`), None for a run that did not start
    from a checkpoint. The field order is the order of ``config.json`` and the checkpoint's ``args``.
    """
    model: str = option("uhrnet", locked=True)
    loss: str = option("compound", locked=True)
    real: list = option([], locked=True)
    synthetic: list = option([], locked=True)
    synthetic_ratio: float | None = option(None, locked=True)
    real_split: str = option("reference", locked=True)
    synthetic_split: str = option("reference", locked=True)
    synthetic_label: str = option("true", locked=True)
    preset: str = option("figshare", locked=True)
    label_transform: list = option([], locked=True)
    epochs: int = option(200)
    batch_size: int = option(1, locked=True)
    lr: float = option(1e-4)
    weight_decay: float = option(0.0)
    device: str = option("auto")
    amp: bool = option(False)
    base_channels: int | None = option(None, locked=True)
    model_option: list = option([], locked=True)
    crop: str | None = option(None, locked=True)
    resize: str | None = option(None, locked=True)
    samples_per_epoch: int | None = option(None, locked=True)
    workers: int | None = option(None)
    threads: int | None = option(None)
    seed: int = option(0, locked=True)
    raw_output: bool = option(False, locked=True)
    grad_clip: float | None = option(None)
    augment: str | bool = option("shading", locked=True, legacy="off")
    lr_schedule: str = option("cosine", locked=True, legacy="constant")
    ema: float = option(0.0, locked=True)
    augment_probability: float = option(0.8, locked=True)
    init: str = option("auto", locked=True, legacy="torch")
    init_from: str | None = option(None, locked=True, legacy=None, legacy_locked=True)
    freeze: str = option("none", locked=True, legacy="none", legacy_locked=True)
    head: str = option("height", locked=True, legacy="height", legacy_locked=True)
    rig: str | None = option(None, locked=True, legacy=None, legacy_locked=True)
    val_phase: list = option([], locked=True, legacy=[], legacy_locked=True)
    val_phase_convention: str = option("auto", locked=True, legacy="benchmark", legacy_locked=True)
    val_phase_negate_sin: bool = option(False, locked=True, legacy=False, legacy_locked=True)
    # speed on CUDA (issue 49; :mod:`uhrnet.training.speed`): "auto" is each one's standard win on CUDA and
    # what every run did before on a CPU, where nothing changes; free to change on resume
    amp_dtype: str = option("auto")
    channels_last: str = option("auto")
    device_data: str = option("auto")
    host_sync: str = option("auto")
    fused_adam: str = option("auto")
    compile: bool = option(False)
    init_from_checkpoint: dict | None = None

    def to_dict(self) -> dict:
        """The options as ``config.json`` and the checkpoint's ``args`` hold them (no
        ``init_from_checkpoint`` key for a run that did not start from a checkpoint)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        if out["init_from_checkpoint"] is None:
            del out["init_from_checkpoint"]
        return out


_OPTIONS = [f for f in fields(RunConfig) if "locked" in f.metadata]
# derived from RunConfig's fields for the code that reads them by name (resolve_config, the sim2real workflow)
DEFAULTS = {f.name: f.default_factory() if f.default is MISSING else f.default for f in _OPTIONS}
LOCKED = tuple(f.name for f in _OPTIONS if f.metadata["locked"])
LEGACY = {f.name: f.metadata["legacy"] for f in _OPTIONS if "legacy" in f.metadata}
LEGACY_LOCKED = tuple(f.name for f in _OPTIONS if f.metadata["legacy_locked"])


@dataclass
class TrainConfig:
    """Options of a training run as the user gives them; ``None`` means "not given": the default of
    :class:`RunConfig` for a fresh run, the checkpoint's value on ``resume`` (options
    :class:`RunConfig` declares locked must then match it).

    Field names are the ``uhrnet train`` flags (``--batch-size`` -> ``batch_size``); ``resume`` is
    ``"auto"`` (``out/last.pt``) or a checkpoint path; ``overwrite`` starts afresh in a folder that
    already holds a run (refused otherwise; with ``resume``, a usage error). ``augment``: augmentation of
    synthetic samples, a name of :data:`uhrnet.data.augment.AUGMENTS` (``shading``, ``photometric``, ``off``;
    True/False from older runs); ``augment_probability``: the chance that a synthetic training sample is augmented (the rest are shown
    as rendered).
    ``init``: weight initialisation of a fresh run, a name of :data:`uhrnet.models.init.INITS` (``auto``:
    ``he`` for models without batch norm, ``torch`` otherwise; ``he``: N(0, 2/fan_in) as the U-Net paper;
    ``torch``: PyTorch's default, what every run used before); on resume the checkpoint's weights are
    kept, and a different ``init`` is refused like every LOCKED option.
    ``init_from``: transfer learning: a fresh run starts from the weights of this checkpoint (a ``.pt``
    file or a run folder: its ``best.pt``, else ``last.pt``) instead of ``init``, with a fresh optimizer,
    schedule, loss state and epoch count; the architecture (``model``, ``base_channels``,
    ``model_option``) and what the network output means (``raw_output``, label scale) must match the
    checkpoint's; with an ``--ema`` checkpoint its averaged weights are taken
    (:func:`uhrnet.checkpoint.init_from_checkpoint`). The run records the resolved file as ``init_from``
    and ``init_from_checkpoint`` = ``{"path", "sha256", "epoch", "weights", ...}``; a resume continues
    the run (nothing is re-initialised) and refuses another ``init_from``.
    ``freeze``: ``none`` or a part of :data:`uhrnet.models.freeze.FREEZE_CHOICES` (``encoder``,
    ``decoder``) kept fixed at its initial weights (needs ``init_from``): left out of the optimizer, its
    batch norms in eval mode (:mod:`uhrnet.models.freeze`).
    ``head``: ``height`` (the network predicts height) or ``phase``: the physics head
    (:mod:`uhrnet.models.phase_head`): the network predicts the fringe phase (cosine, sine) and a coarse
    height, and the calibrated rig turns them into height; trained on synthetic native samples, whose
    ``phase_true`` supervises the phase (:class:`uhrnet.training.losses.PhaseHeadLoss`). ``rig``: the calibration
    file of the phase head (default: the rig recorded in the first synthetic sample's ``meta.json``, else
    fppsim's default rig); the checkpoint carries it. The phase head needs full camera-size images (no
    ``crop``/``resize``: each pixel is a camera ray).
    ``val_phase``: folders of REAL phase-shifting frames of the rig (the public layout: ``PSin/ PCos/
    Fringe/ iPattern/``; no labels, never trained on), scored after every epoch by the calibration-free
    phase residual as a fraction of the flat prediction's
    (:class:`uhrnet.scoring.phase_residual.PhaseValidation`: ``val_phase_ratio``, ``val_phase_rad`` in the
    history); ``best.pt`` is then the epoch with the lowest ratio, since the synthetic validation set cannot
    tell which epoch carries over to the real images. ``val_phase_convention`` / ``val_phase_negate_sin``: how
    those frames' PSin / PCos / Order make their phase (:func:`fppsim.dataio.readers.load_psp_folder_sample`;
    default ``auto``: the public data's ``benchmark`` unless a frame is clearly written another way).
    ``threads``: CPU threads torch computes with (``torch.set_num_threads`` for the run, restored after;
    None: torch's default, the cores). A seeded run repeats bit for bit at the same count, whatever else
    the machine is doing, but not across counts (the reductions split differently, and a long run
    amplifies the last bits); ``config.json`` records the count used as ``torch_threads``. Free to change
    on resume.
    Speed on CUDA (:mod:`uhrnet.training.speed`; each ``auto`` = its CUDA default below, and on a CPU what
    every run did before: a CPU run is unchanged bit for bit): ``amp_dtype`` (``auto``: bfloat16 where the
    GPU has it, no gradient scaler; ``fp16``: float16 with the scaler; a CPU's ``--amp`` is bfloat16
    whatever it says), ``channels_last`` (``auto``/``on``/``off``: the network and its input in NHWC),
    ``device_data`` (``auto``: on when the samples fit in a quarter of the free GPU memory: the training
    and validation sets decoded once onto the device, fringes as float16, augmented there with the same
    draws; no DataLoader in the loop), ``host_sync`` (``step``: the loss is checked and the metrics read
    on the host every step, as before; ``epoch``: summed on the device and read once per epoch, a
    non-finite loss still stops the run at the epoch's end naming its first step; ``auto``: ``epoch`` on
    CUDA), ``fused_adam`` (``auto``: PyTorch's fused Adam kernel on CUDA), ``compile`` (``torch.compile``
    the network: off unless given).
    ``ema``: decay per optimizer step of the exponential moving average of the weights that validation,
    ``best.pt`` and every later use of the checkpoint see (0: off). ``tensorboard``: also log to
    ``out/tensorboard/`` (:mod:`uhrnet.training.tb_log`; needs the optional ``tensorboard`` package; like
    ``progress``, free to change on resume). Checks itself on construction: :class:`UsageError` for a value that is wrong
    on its own (the command line exits 2), :class:`ConfigError` otherwise.
    """
    out: str | os.PathLike
    real: list | None = None
    synthetic: list | None = None
    synthetic_ratio: float | None = None
    real_split: str | None = None
    synthetic_split: str | None = None
    synthetic_label: str | None = None
    preset: str | None = None
    label_transform: list | None = None
    crop: str | None = None
    resize: str | None = None
    samples_per_epoch: int | None = None
    workers: int | None = None
    threads: int | None = None
    augment: str | bool | None = None
    augment_probability: float | None = None
    lr_schedule: str | None = None
    model: str | None = None
    base_channels: int | None = None
    model_option: list | None = None
    loss: str | None = None
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    weight_decay: float | None = None
    grad_clip: float | None = None
    ema: float | None = None
    init: str | None = None
    init_from: str | os.PathLike | None = None
    freeze: str | None = None
    head: str | None = None
    rig: str | os.PathLike | None = None
    val_phase: list | None = None
    val_phase_convention: str | None = None
    val_phase_negate_sin: bool | None = None
    amp: bool | None = None
    amp_dtype: str | None = None
    channels_last: str | None = None
    device_data: str | None = None
    host_sync: str | None = None
    fused_adam: str | None = None
    compile: bool | None = None
    raw_output: bool | None = None
    seed: int | None = None
    device: str | None = None
    resume: str | None = None
    overwrite: bool = False
    progress: bool = True
    tensorboard: bool = False

    def __post_init__(self):
        if self.tensorboard:  # a missing optional package stops the run before anything is read or written

            require_tensorboard()
        for key in ("real", "synthetic", "val_phase"):
            value = getattr(self, key)
            if isinstance(value, (str, os.PathLike)):
                setattr(self, key, [value])
        if self.resume and self.overwrite:
            raise UsageError("--resume continues the run in --out and --overwrite replaces it: give one of them")
        given = {k: v for k, v in asdict(self).items() if k in DEFAULTS and v is not None}
        check_options(given)
        if not self.resume:  # a fresh run's label transform and model options must be usable before anything is written
            fresh = RunConfig(**{**DEFAULTS, **given})
            label_transform_from(fresh)
            model_options_from(fresh)


def check_options(cfg: dict) -> None:
    """Raise :class:`ConfigError` (:class:`UsageError` for a value wrong on its own) naming the flag
    of the first invalid option in ``cfg``."""

    choices = {"model": list_models(), "loss": list(LOSSES), "real_split": SPLIT_MODES, "synthetic_split": SPLIT_MODES,
               "synthetic_label": LABEL_SOURCES, "preset": sorted(PRESETS), "device": ("auto", "cpu", "cuda"),
               "amp_dtype": AMP_DTYPES, "channels_last": SWITCHES, "device_data": SWITCHES, "host_sync": HOST_SYNCS,
               "fused_adam": SWITCHES}
    for key, allowed in choices.items():
        if key in cfg and cfg[key] not in allowed:
            raise ConfigError(f"--{key.replace('_', '-')} {cfg[key]!r}: choose from {', '.join(allowed)}")
    for key in ("crop", "resize"):
        if key == "resize" and cfg.get(key) == RESIZE_AUTO:
            continue
        try:
            parse_size(cfg.get(key))
        except ValueError as exc:
            raise UsageError(f"--{key}: {exc}") from None
    _check_counts(cfg)
    if cfg.get("synthetic_ratio") is not None and not 0 <= cfg["synthetic_ratio"] <= 1:
        raise UsageError(f"--synthetic-ratio must be in [0, 1], got {cfg['synthetic_ratio']}")
    if cfg.get("threads") is not None:
        check_cores(cfg["threads"], "--threads", "threads", UsageError)
    if "lr" in cfg and not cfg["lr"] > 0:
        raise UsageError(f"--lr must be positive, got {cfg['lr']}")
    if "lr" in cfg and not (math.isfinite(cfg["lr"]) and cfg["lr"] <= MAX_LR):
        raise UsageError(f"--lr must be a finite rate up to {MAX_LR:g}, got {cfg['lr']}")
    if cfg.get("grad_clip") is not None and not (cfg["grad_clip"] > 0 and math.isfinite(cfg["grad_clip"])):
        raise UsageError(f"--grad-clip must be a finite gradient norm > 0, got {cfg['grad_clip']}")
    if "augment" in cfg:
        try:
            augment_config(cfg["augment"])
        except ValueError as exc:
            raise UsageError(f"--augment: {exc}") from None
    if "augment_probability" in cfg:
        p = cfg["augment_probability"]
        if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
            raise UsageError(f"--augment-probability must be in [0, 1], got {p}")
    if "val_phase_convention" in cfg:
        check_read_convention(cfg["val_phase_convention"], "--val-phase-convention", UsageError)
    if "lr_schedule" in cfg and cfg["lr_schedule"] not in LR_SCHEDULES:
        raise UsageError(f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got {cfg['lr_schedule']!r}")
    if "ema" in cfg and not (isinstance(cfg["ema"], (int, float)) and 0.0 <= cfg["ema"] < 1.0):
        raise UsageError(f"--ema must be a decay in [0, 1) (0: off), got {cfg['ema']}")
    if "init" in cfg:
        if cfg["init"] not in INITS:
            raise UsageError(f"--init must be one of {', '.join(INITS)}, got {cfg['init']!r}")
    if "freeze" in cfg:
        if cfg["freeze"] not in FREEZE_CHOICES:
            raise UsageError(f"--freeze must be one of {', '.join(FREEZE_CHOICES)}, got {cfg['freeze']!r}")
        if cfg["freeze"] != "none" and "init_from" in cfg and not cfg["init_from"]:
            raise ConfigError(f"--freeze {cfg['freeze']} needs --init-from CKPT (frozen random weights never learn)")

    if "head" in cfg:
        if cfg["head"] not in HEADS:
            raise UsageError(f"--head must be one of {', '.join(HEADS)}, got {cfg['head']!r}")
        head, name = HEADS[cfg["head"]], cfg["head"]
        if head.whole_images and (cfg.get("crop") or cfg.get("resize")):
            raise UsageError(f"--head {name} needs whole camera images (each pixel is a ray of the rig): drop --crop/--resize")
        if head.phase_targets and "synthetic" in cfg and not cfg["synthetic"]:
            raise ConfigError(f"--head {name} learns the phase from synthetic samples (phase_true): give --synthetic DIR")
        if head.needs_rig and cfg.get("raw_output"):
            raise ConfigError(f"--head {name} predicts heights through the rig: --raw-output does not apply")
    if cfg.get("rig"):
        head, loss = HEADS[cfg.get("head", DEFAULTS["head"])], LOSSES.get(str(cfg.get("loss", DEFAULTS["loss"])).lower())
        if not (head.needs_rig or (loss is not None and loss.needs_rig)):
            users = [f"--head {n}" for n, h in HEADS.items() if h.needs_rig] + \
                    [f"--loss {n}" for n, e in LOSSES.items() if e.needs_rig]
            raise ConfigError(f"--rig belongs to {' or '.join(users)} (the rig that turns phase into height)")
    if "weight_decay" in cfg and not (cfg["weight_decay"] >= 0 and math.isfinite(cfg["weight_decay"])):
        raise UsageError(f"--weight-decay must be finite and >= 0, got {cfg['weight_decay']}")


def _whole(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_counts(cfg: dict) -> None:
    """The whole-number options, each wrong on its own (:class:`UsageError`) outside its range; None is
    "not given" (workers, threads, width and draws per epoch have no default)."""
    ranges = {"epochs": (1, None, ""), "batch_size": (1, None, ""),
              "threads": (1, 1024, "a number of CPU threads "), "workers": (0, None, "a number of loader processes "),
              "base_channels": (1, None, "a number of channels "),
              "samples_per_epoch": (1, None, "a number of draws (leave it out for all training samples) "),
              "seed": (0, MAX_SEED, "a whole number ")}
    for key, (low, high, what) in ranges.items():
        value = cfg.get(key)
        if value is not None and not (_whole(value) and value >= low and (high is None or value <= high)):
            bound = f"from {low} to {high}" if high is not None else f">= {low}"
            raise UsageError(f"--{key.replace('_', '-')} must be {what}{bound}, got {value!r}")
    if cfg.get("epochs") is not None and cfg["epochs"] > MAX_EPOCHS:
        raise UsageError(f"--epochs must be at most {MAX_EPOCHS:,}, got {cfg['epochs']}")


def parse_kv(items, what: str) -> dict:
    out = {}
    if not items:
        return out  # (without importing yaml: a bare GPU machine may lack it)
    import yaml

    for item in items:
        if "=" not in item:
            raise UsageError(f"{what}: expected KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip().replace("-", "_")] = yaml.safe_load(v)
    return out


def _normalise(key: str, value):
    if key in ("real", "synthetic", "val_phase"):
        return [str(Path(v).resolve()) for v in (value or [])]
    if key == "rig" and value:
        return str(Path(value).resolve())
    if key in ("label_transform", "model_option"):
        return sorted(value or [])
    if key == "init_from":  # the checkpoint file itself, however it was named (file or run folder)
        if not value:
            return None

        try:
            return str(checkpoint_file(Path(value).resolve()))
        except CheckpointError:  # a folder that no longer holds a checkpoint: compare the names
            return str(Path(value).resolve())
    if key == "augment":  # runs saved before the augmentation kinds hold a boolean

        return augment_kind(value)
    return value


def _refuse_change(key: str, given, recorded) -> None:
    if given is not None and key in LOCKED and _normalise(key, given) != _normalise(key, recorded):
        flag = "--" + key.replace("_", "-")
        raise ConfigError(
            f"{flag} {given} differs from the checkpoint's {recorded!r}; drop {flag} to resume, "
            "or start a new --out"
        )


def resolve_config(args: TrainConfig, previous: dict | None = None) -> dict:
    """Options after defaults (fresh run) or the checkpoint's options (resume).

    On resume ``init_from_checkpoint`` (what a run started with ``--init-from`` recorded) is carried over.
    """
    cfg = {}
    if previous is not None and previous.get("samples_per_epoch") == 0:  # runs before stop 67 recorded 0 for all
        previous = {**previous, "samples_per_epoch": None}
    for key, default in DEFAULTS.items():
        given = getattr(args, key, None)
        if key == "resize" and given == RESIZE_AUTO and previous is not None:
            given = None  # a resumed run keeps the size its auto chose
        if previous is not None and key in previous:
            _refuse_change(key, given, previous[key])
            cfg[key] = previous[key] if given is None else given
        elif previous is not None and key in LEGACY and (given is None or key in LEGACY_LOCKED):
            _refuse_change(key, given, LEGACY[key])
            cfg[key] = LEGACY[key]
        else:
            cfg[key] = default if given is None else given
    cfg["real"] = _normalise("real", cfg["real"])
    cfg["synthetic"] = _normalise("synthetic", cfg["synthetic"])
    cfg["val_phase"] = _normalise("val_phase", cfg["val_phase"])
    if not cfg["val_phase"]:
        given = [f"--{k.replace('_', '-')}" for k in ("val_phase_convention", "val_phase_negate_sin")
                 if getattr(args, k, None) not in (None, DEFAULTS[k])]
        if given:
            raise ConfigError(f"{', '.join(given)}: how the --val-phase frames are read; give --val-phase DIR")
    cfg["init_from"] = _normalise("init_from", cfg["init_from"])
    if previous is not None and previous.get("init_from_checkpoint"):
        cfg["init_from_checkpoint"] = previous["init_from_checkpoint"]
    check_options(cfg)
    return cfg


def auto_resize(shape: tuple[int, int], period_px: float) -> tuple[tuple[int, int] | None, str]:
    """``--resize auto``: ``(size, why)``, the training size of images ``shape`` (H, W) whose fringes are
    ``period_px`` camera pixels apart at the image centre, and a phrase saying why.

    Half the size (each side halved, rounded up) when the fringes are at least :data:`HALVE_FROM_PERIOD_PX`
    px apart (so at least 5 px at half size) and the shorter side is at least :data:`HALVE_FROM_SIDE_PX` px;
    else ``None`` (full size). At half size each pixel of the network's receptive field covers twice the
    scene, so deep inside a large object it still sees the plane around it, which tells the object's
    height; and training takes a quarter of the time. An image much smaller than that the network
    already sees whole, and halving only loses detail. Measured in docs/own_rig.md.
    """
    h, w = (int(v) for v in shape)
    if not (math.isfinite(period_px) and period_px > 0):
        raise ConfigError(f"--resize auto: the fringe period must be > 0 px, got {period_px:g}")
    if period_px < HALVE_FROM_PERIOD_PX:
        return None, f"full size: the fringes are {period_px:.1f} px apart (halved from {HALVE_FROM_PERIOD_PX:g} px on)"
    if min(h, w) < HALVE_FROM_SIDE_PX:
        return None, f"full size: {h}x{w} px (halved from a shorter side of {HALVE_FROM_SIDE_PX} px on)"
    size = ((h + 1) // 2, (w + 1) // 2)
    return size, f"half size: the fringes are {period_px:.1f} px apart, {period_px / 2:.1f} px at {size[0]}x{size[1]}"


def label_transform_from(cfg: RunConfig) -> LabelTransform:
    """The run's label transform: ``--preset`` with the ``--label-transform`` overrides, checked as a writer of
    labels checks it (:meth:`fppsim.dataio.formats.LabelTransform.check`, what ``fppsim generate`` refuses): the
    reference plane must count as valid, or every plane pixel would be masked out of the loss."""
    overrides = parse_kv(cfg.label_transform, "--label-transform")
    try:
        return LabelTransform.from_dict({"preset": cfg.preset, "name": cfg.preset, **overrides}).check()
    except DataError as exc:
        raise UsageError(f"--label-transform: {exc}") from None


def model_options_from(cfg: RunConfig) -> dict:
    """``--model-option`` as constructor options of ``--model``; :class:`UsageError` for an item that is not
    KEY=VALUE or names an option that neither the model nor ``--head`` takes
    (:func:`uhrnet.models.check_model_options`; the values are the constructor's to check)."""
    options = parse_kv(cfg.model_option, "--model-option")
    try:
        check_model_options(cfg.model, options, cfg.head)
    except ValueError as exc:
        raise UsageError(f"--model-option: {exc}") from None
    return options
