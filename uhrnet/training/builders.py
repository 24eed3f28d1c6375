"""What a training run is made of, built from its :class:`~uhrnet.training.train_config.RunConfig`: the run
folder's checkpoint, the data, the network, the loss, the optimizer and its schedule.

Plain functions apart from the loop (:mod:`uhrnet.training.trainer`), so each piece can be read and tested
alone. The order in which the trainer calls them is part of a seeded run's numbers (the seeded global
generator draws the weights after the data is built).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from fppsim.geometry.rig import RigError, check_image_size
from uhrnet.checkpoint import FORMAT, VERSION, LabelHead, checkpoint_kind, load_checkpoint, rng_state, set_rng_state
from uhrnet.data.augment import augment_config
from uhrnet.data.datasets import MixedSampler, Prepared, load_sources, parse_size
from uhrnet.data.device_data import DeviceLoader, DeviceSet, device_bytes
from uhrnet.device import keep_freed_memory, select_device
from uhrnet.errors import CheckpointError, ConfigError
from uhrnet.models import HEADS, build_model
from uhrnet.models.init import init_weights
from uhrnet.run_folder import LAST_PT, check_run_folder, package_version
from uhrnet.training.distributed import DistInfo
from uhrnet.training.ema import WeightEMA
from uhrnet.training.speed import Speed
from uhrnet.training.losses import HEAD_LOSSES, LOSSES, LossContext, build_head_loss, build_loss
from uhrnet.training.train_config import (LR_FLOOR, RESIZE_AUTO, VAL_PHASE_FRAMES, RunConfig, auto_resize,
                                          model_options_from)
from fppsim.dataio.rig_choice import dataset_rig, resolve_rig
from fppsim.phase.fringe_axis import rig_phase_gradient

__all__ = ["TrainingData", "Network", "open_run", "training_device", "loss_entry", "build_data", "auto_resize_of",
           "check_one_size", "head_rig", "build_network", "wrap_network", "build_loss_fn", "build_optimizer", "build_val_phase",
           "restore", "lr_at", "autocast", "first_best", "update_best", "gather_rng", "use_device_data", "match_layout",
           "checkpoint_payload"]

DEVICE_DATA_SHARE = 0.25  # --device-data auto: the samples may take this share of the GPU's free memory


# -- run folder and device ----------------------------------------------------------------------------
def open_run(out: Path, resume, overwrite: bool) -> tuple[dict | None, str]:
    """``(checkpoint or None, state)`` of the run folder ``out``: the training checkpoint to continue on
    ``resume``, else None; ``state`` as :func:`uhrnet.run_folder.check_run_folder` says."""
    state = check_run_folder(out, resume, overwrite)
    if state == "fresh":  # killed before its first checkpoint: nothing trained yet, so start the run afresh
        print(f"note: {out} has no {LAST_PT} yet; starting the run from epoch 1", file=sys.stderr)
    if state != "resume":
        return None, state
    path = out / LAST_PT if resume == "auto" else Path(resume)
    ckpt = load_checkpoint(path)
    if "args" not in ckpt:  # imported weights or an adaptation: no training state to continue
        made = {"import": "imported weights", "adapt": "an adaptation"}.get(checkpoint_kind(ckpt),
                                                                          "not a training checkpoint")
        raise ConfigError(f"--resume: {path} is {made}, not a training run to continue; start a new run "
                          "from it with --init-from (and another --out)")
    return ckpt, state


def training_device(name: str, info: DistInfo) -> torch.device:
    """The device of this process, with the settings that keep a run fast there."""
    device = select_device(name, info.local_rank if info.enabled else None)
    if device.type == "cpu":
        keep_freed_memory()  # large feature maps re-used, not page-faulted in every step (same numbers)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed input size; exact resume is promised on CPU
    return device


def loss_entry(cfg: RunConfig, head):
    """``(entry, needs_rig, phase)``: the registry entry the training loss is called as (the head's loss,
    which wraps the run's, or the run's own), whether a rig is needed, whether samples carry phase targets."""
    run_loss = LOSSES[cfg.loss.lower()]
    entry = HEAD_LOSSES[head.loss] if head.loss else run_loss
    if head.loss and not run_loss.plain:
        raise ConfigError(f"--loss {cfg.loss} needs more than (prediction, label, mask); the {head.name} "
                          "head's loss wraps only such a loss")
    needs_rig = head.needs_rig or run_loss.needs_rig or entry.needs_rig
    return entry, needs_rig, head.phase_targets or entry.phase_targets


# -- data ---------------------------------------------------------------------------------------------
@dataclass
class TrainingData:
    """The samples of a run and their loaders. ``resize``: the run's ``--resize`` with ``auto`` resolved
    (what config.json and the checkpoints record); ``native``: the data's own (H, W) before --crop /
    --resize, read only when something needs it, else None."""
    sources: object
    train_set: Prepared
    val_set: Prepared
    sampler: MixedSampler
    loader: DataLoader | DeviceLoader
    val_loader: DataLoader | DeviceLoader
    image_shape: tuple
    native: tuple | None
    resize: str | None


def build_data(cfg: RunConfig, transform, phase: bool, info: DistInfo, device: torch.device,
               speed: Speed | None = None) -> TrainingData:
    """The training and validation sets of ``cfg`` and their loaders (this rank's share of them): DataLoaders,
    or with ``--device-data`` (:func:`use_device_data`) the sets on the device and their :class:`DeviceLoader`."""
    sources = load_sources(cfg.real, cfg.synthetic, transform, cfg.real_split, cfg.synthetic_split,
                           cfg.synthetic_label, phase=phase)
    native = (tuple(Prepared(sources.train, None, None, random_crop=False)[0]["fringe"].shape[-2:])
              if len(sources.train) and (cfg.resize == RESIZE_AUTO or cfg.val_phase) else None)
    resize = auto_resize_of(cfg.synthetic, native, info.main) if cfg.resize == RESIZE_AUTO else cfg.resize
    crop, size = parse_size(cfg.crop), parse_size(resize)
    augment = augment_config(cfg.augment)
    if augment is not None:
        augment = dataclasses.replace(augment, probability=float(cfg.augment_probability))
    train_set = Prepared(sources.train, crop, size, random_crop=True, augment=augment, phase=phase)
    val_set = Prepared(sources.val, crop, size, random_crop=False, phase=phase)
    if len(train_set) == 0:
        raise ConfigError("no training samples: every sample is in the val/test split "
                          "(check --real-split/--synthetic-split)")
    # batches (and sets held on a GPU) stack their samples: one size, or a traceback in the first epoch; one
    # image per batch on a CPU trains as it always did (and such a run resumes)
    if size is None and crop is None and (cfg.batch_size > 1 or device.type == "cuda"):
        check_one_size([*sources.train.parts, *sources.val.parts], cfg.head if HEADS[cfg.head].whole_images else None)
    shape = tuple(train_set[0]["fringe"].shape[-2:])
    if min(shape) < 16:  # sides not multiples of 16 are padded inside the model (uhrnet.models.any_size)
        raise ConfigError(f"training images are {shape[0]}x{shape[1]}; the models need at least 16 x 16 pixels")
    sampler = MixedSampler(sources.train.n_real, sources.train.n_synthetic, cfg.synthetic_ratio,
                           cfg.samples_per_epoch, cfg.seed, info.rank, info.world)
    workers = cfg.workers if cfg.workers is not None else (4 if device.type == "cuda" else 0)
    pin = device.type == "cuda"
    val_idx = list(range(info.rank, len(val_set), info.world))
    if speed is not None and use_device_data(speed.device_data, device, train_set, val_set, phase):
        loader = DeviceLoader(DeviceSet(train_set, device, workers), sampler, cfg.batch_size, augment)
        val_loader = DeviceLoader(DeviceSet(val_set, device, workers, crop_later=False), val_idx, cfg.batch_size)
        return TrainingData(sources, train_set, val_set, sampler, loader, val_loader, shape, native, resize)
    loader = DataLoader(train_set, batch_size=cfg.batch_size, sampler=sampler, num_workers=workers,
                        pin_memory=pin, drop_last=False)
    val_loader = DataLoader(val_set, batch_size=cfg.batch_size, sampler=val_idx, num_workers=workers,
                            pin_memory=pin)
    return TrainingData(sources, train_set, val_set, sampler, loader, val_loader, shape, native, resize)


def check_one_size(parts, whole_head: str | None = None) -> None:
    """Refuse (:class:`ConfigError`) training on folders whose images differ in size without ``--resize`` or
    ``--crop``: ``parts`` are the folders' subsets (:class:`~uhrnet.data.datasets.DatasetSubset`); the first
    sample of each folder is read, and the message names two folders of different sizes and suggests
    ``--resize`` (unless ``whole_head`` names the run's head, one that needs whole camera images)."""
    seen = {}
    for part in parts:
        if id(part.dataset) in seen or not len(part):
            continue
        ds = part.dataset
        folder = getattr(ds, "root", None) or ds.fringe_path.parent
        seen[id(part.dataset)] = (folder, tuple(int(v) for v in part[0]["fringe"].shape[-2:]))
    sizes = list(seen.values())
    other = next(((f, s) for f, s in sizes[1:] if s != sizes[0][1]), None)
    if other is not None:
        (a, (ha, wa)), (b, (hb, wb)) = sizes[0], other
        fix = (f"--head {whole_head} needs whole images of one rig's camera: train on folders of one size" if whole_head
               else f"give --resize HxW (e.g. --resize {min(ha, hb)}x{min(wa, wb)}) to train on them together")
        raise ConfigError(f"training images differ in size: {a} holds {ha}x{wa} px, {b} {hb}x{wb} px; {fix}")


def use_device_data(choice: str, device: torch.device, train_set: Prepared, val_set: Prepared, phase: bool) -> bool:
    """``--device-data``: ``on`` (refused for samples with phase targets, which stay in the DataLoader), ``off``,
    or ``auto``: on CUDA when the sets take at most :data:`DEVICE_DATA_SHARE` of its free memory (never on a CPU)."""
    if choice == "off" or (choice == "auto" and device.type != "cuda"):
        return False
    if phase:
        if choice == "on":
            raise ConfigError("--device-data on: samples with phase targets (--head phase) are read by the DataLoader; "
                              "drop --device-data")
        return False
    if choice == "on":
        return True
    full = tuple(Prepared(train_set.dataset, None, train_set.resize, random_crop=False)[0]["fringe"].shape[-2:])
    need = device_bytes(train_set, full) + device_bytes(val_set, full)
    return need <= DEVICE_DATA_SHARE * torch.cuda.mem_get_info(device)[0]


def auto_resize_of(synthetic: list, shape, main: bool) -> str | None:
    """``--resize auto``: the training size from the fringe period of the synthetic data's rig
    (:func:`uhrnet.training.train_config.auto_resize`), as ``"HxW"``, or None for full size. ``shape``: the
    training data's own (H, W), None when there are no training samples (refused after)."""

    rig = None
    for folder in synthetic:
        try:
            rig = dataset_rig(folder)[0]
        except (RigError, OSError, KeyError, ValueError) as exc:
            raise ConfigError(f"--resize auto: {folder}: {exc}") from None
        if rig is not None:
            break
    if rig is None:
        raise ConfigError("--resize auto needs --synthetic data that records its rig (fppsim generate does): "
                          "the rig's fringe period sets the size; give --resize HxW instead")
    if shape is None:
        return None  # refused below: no training samples
    if shape != (rig.camera.height, rig.camera.width):
        raise ConfigError(f"--resize auto: the training images are {shape[0]}x{shape[1]} px but the synthetic "
                          f"data's rig camera is {rig.camera.height}x{rig.camera.width}; give --resize HxW")
    size, why = auto_resize(shape, 2.0 * math.pi / math.hypot(*rig_phase_gradient(rig)))
    if main:
        print(f"--resize auto: {why}", flush=True)
    return None if size is None else f"{size[0]}x{size[1]}"


# -- network ------------------------------------------------------------------------------------------
def head_rig(rig: str | None, synthetic) -> dict:
    """The rig of a head or loss that needs one, as a dictionary: ``rig`` (a calibration file) or the nominal rig of the first
    synthetic dataset (its ``dataset.json``, else its first sample's ``meta.json``; a figshare export's
    ``native/`` folder too), else fppsim's default rig. A dataset rendered with ``--rig-jitter`` has no
    single rig its phases fit: refused."""

    try:
        return resolve_rig(rig or None, datasets=synthetic or ())[0].to_dict()
    except (RigError, OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"--rig: {exc}") from None


def build_network(cfg: RunConfig, head, shape: tuple, needs_rig: bool):
    """``(net, rig)``: the run's network, its weights drawn from the global generator seeded with ``--seed``
    (a resume overwrites them), and the rig (a dictionary) of a head or loss that needs one, else None."""
    torch.manual_seed(cfg.seed)
    options = model_options_from(cfg)
    if cfg.base_channels is not None:
        options["base_channels"] = cfg.base_channels
    rig = head_rig(cfg.rig, cfg.synthetic) if needs_rig else None
    if rig is not None:
        check_image_size(rig, shape, f"--rig {cfg.rig}" if cfg.rig else "the synthetic data's rig",
                         who=f"the {head.name} head" if head.needs_rig else f"the {cfg.loss} loss",
                         error=ConfigError, template="{what}: its camera is {camera} but the training images are "
                                                     "{got}; {who} needs the rig of these images")
    options["head"] = head.name
    if head.needs_rig:
        options["rig"] = rig
    try:
        net = build_model(cfg.model, **options)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"--model {cfg.model}: {exc}") from None
    init_weights(net, cfg.init)
    return net, rig


@dataclass
class Network:
    """The network as the loop uses it: ``model`` (labels out, on the device), ``ddp`` (what trains: ``model``
    or its DistributedDataParallel wrapper), ``ema`` (the moving average, or None) and ``eval_model``
    (what validation and the checkpoints see: the average's labels, else ``model``)."""
    model: LabelHead
    ddp: torch.nn.Module
    ema: WeightEMA | None
    eval_model: LabelHead


def wrap_network(net, cfg: RunConfig, scale: float, shift: float, device: torch.device, info: DistInfo,
                 speed: Speed | None = None) -> Network:
    """``net`` with its label scale, its moving average (``--ema``) and, under torchrun, DDP; ``speed``: its
    memory layout (``--channels-last``, before the average copies it) and ``--compile`` (what trains)."""
    model = LabelHead(net, scale, shift).to(device)
    if speed is not None and speed.channels_last:
        model = model.to(memory_format=torch.channels_last)
    ema, eval_model = None, model
    if cfg.ema:
        ema = WeightEMA(net, cfg.ema)
        eval_model = LabelHead(ema.module, scale, shift)
    ddp = model
    if info.enabled:
        torch.manual_seed(cfg.seed + 1_000_003 * info.rank)  # distinct dropout streams per rank
        from torch.nn.parallel import DistributedDataParallel as DDP

        ddp = DDP(model, device_ids=[device.index] if device.type == "cuda" else None)
    if speed is not None and speed.compile:
        ddp = torch.compile(ddp)
    return Network(model, ddp, ema, eval_model)


def build_loss_fn(cfg: RunConfig, head, transform, scale: float, shift: float, rig, device: torch.device):
    """The training loss of ``cfg``, wrapped by the head's loss when the head learns more than the height."""
    context = LossContext(data_range=transform.data_range, scale=scale, shift=shift,
                          mm_per_unit=transform.mm_per_unit, rig=rig)
    try:
        loss_fn = build_loss(cfg.loss, data_range=transform.data_range, context=context).to(device)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"--loss {cfg.loss}: {exc}") from None
    if head.loss:
        loss_fn = build_head_loss(head.loss, loss_fn, context).to(device)
    return loss_fn


# -- optimizer, schedule, validation on real frames ---------------------------------------------------
def build_optimizer(net, cfg: RunConfig, speed: Speed | None = None) -> torch.optim.Adam:
    """Adam over the trainable weights (``--freeze``: frozen weights never move); ``--fused-adam``: its fused kernel."""
    trainable = [p for p in net.parameters() if p.requires_grad]
    fused = {"fused": True} if speed is not None and speed.fused_adam else {}
    return torch.optim.Adam(trainable, lr=cfg.lr, weight_decay=cfg.weight_decay, **fused)


def lr_at(cfg: RunConfig, steps_per_epoch: int, epoch: int, step: int) -> float:
    """Learning rate of ``step`` (0-based) of ``epoch`` (0-based): a function of the position in the
    run alone, so a resumed run follows the same curve.

    cosine: ``lr * (f + (1 - f) * (1 + cos(pi * t / (T - 1))) / 2)`` with ``t`` the global step,
    ``T`` the steps of all ``--epochs`` and ``f`` = ``LR_FLOOR``; constant: ``lr``.
    """
    if cfg.lr_schedule == "constant":
        return cfg.lr
    per = max(1, steps_per_epoch)
    total = max(2, per * cfg.epochs)
    t = min(epoch * per + step, total - 1)
    frac = t / (total - 1)
    return cfg.lr * (LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * frac)))


def build_val_phase(cfg: RunConfig, info: DistInfo, native):
    """``--val-phase``: the real frames scored after every epoch, on the writing rank (which picks
    ``best.pt``); None without them or on another rank."""
    if not (cfg.val_phase and info.main):
        return None
    from uhrnet.scoring.phase_residual import PhaseValidation  # matplotlib, scipy's .mat reader: only when asked

    return PhaseValidation(cfg.val_phase, max_frames=VAL_PHASE_FRAMES, shape=native,
                           convention=cfg.val_phase_convention, negate_sin=cfg.val_phase_negate_sin)


# -- resume -------------------------------------------------------------------------------------------
def restore(ckpt: dict, net, ema, optimizer, loss_fn, scaler, cfg: RunConfig, rank: int) -> None:
    """Load a training checkpoint's state into the run's pieces and this rank's RNG streams.

    ``--lr`` / ``--weight-decay`` may change on resume: ``cfg``'s replace the checkpoint's."""
    if ckpt["model"]["config"] != net.config:
        raise CheckpointError(f"{ckpt['path']}: model {ckpt['model']['config']} differs from {net.config}")
    # with --ema, "state_dict" holds the average (what every later use loads) and "train_state_dict"
    # the optimised weights
    net.load_state_dict(ckpt.get("train_state_dict", ckpt["state_dict"]))
    if ema is not None:
        ema.load_state_dict(ckpt["state_dict"], ckpt["ema"]["updates"])
    optimizer.load_state_dict(ckpt["optimizer"])
    match_layout(optimizer)
    for group in optimizer.param_groups:
        group["lr"], group["weight_decay"] = cfg.lr, cfg.weight_decay
    loss_fn.load_state_dict(ckpt["loss"])
    if ckpt.get("scaler"):
        scaler.load_state_dict(ckpt["scaler"])
    states = ckpt.get("rng", [])
    if rank < len(states):
        set_rng_state(states[rank])
    elif states:
        print(f"warning: {ckpt['path']} holds RNG state for {len(states)} process(es); rank "
              f"{rank} starts a fresh stream", file=sys.stderr)


def match_layout(optimizer) -> None:
    """Optimizer state loaded from a checkpoint in the memory layout of its weights (``--channels-last``: the
    fused and foreach kernels expect each weight's moments strided as the weight); a no-op where they match."""
    for p, state in optimizer.state.items():
        for k, v in state.items():
            if torch.is_tensor(v) and v.shape == p.shape and v.stride() != p.stride():
                state[k] = torch.empty_like(p, dtype=v.dtype).copy_(v)


def gather_rng(info: DistInfo) -> list:
    """The RNG streams of every rank, what a checkpoint carries so that a resume draws the same numbers."""
    state = rng_state()
    if not info.enabled:
        return [state]
    states = [None] * info.world
    dist.all_gather_object(states, state)
    return states


# -- steps and epochs ---------------------------------------------------------------------------------
def autocast(amp: bool, device: torch.device, dtype: torch.dtype | None = None):
    """``--amp``: ``dtype`` (:func:`uhrnet.training.speed.resolve_speed`: ``--amp-dtype`` on CUDA, bfloat16 on a
    CPU; None: float16 on CUDA, bfloat16 on CPU); else no autocast."""
    if not amp:
        return nullcontext()
    if dtype is None:
        dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    return torch.autocast(device.type, dtype=dtype)


def first_best(cfg: RunConfig) -> dict:
    """The best-epoch record before any epoch: ``--val-phase`` runs are judged by the real frames, since the
    synthetic validation set cannot tell which epoch carries over to them."""
    return {"metric": "val_phase_ratio" if cfg.val_phase else "val_rmse_mm", "value": float("inf"), "epoch": 0}


def update_best(best: dict, row: dict) -> bool:
    """Whether the epoch of history ``row`` is the best so far (``best`` updated if so). Without a validation
    split the training RMSE judges; with ``--val-phase`` an epoch the real frames cannot score is not the best."""
    metric = row.get(best["metric"], float("nan"))
    if not np.isfinite(metric) and best["metric"] == "val_rmse_mm":
        best["metric"], metric = "train_rmse_mm", row["train_rmse_mm"]
    is_best = bool(np.isfinite(metric) and metric < best["value"])
    if is_best:
        best.update(value=float(metric), epoch=row["epoch"])
    return is_best


def checkpoint_payload(t, epoch: int, rng: list) -> dict:
    """What a checkpoint of the :class:`~uhrnet.training.trainer.Trainer` ``t`` after ``epoch`` epochs holds."""
    ema = t.network.ema
    return {
        "format": FORMAT, "version": VERSION,
        "model": {"name": t.net.config["name"], "config": dict(t.net.config)},
        "state_dict": (ema.state_dict() if ema is not None else t.net.state_dict()),
        **({"train_state_dict": t.net.state_dict(),
            "ema": {"decay": ema.decay, "updates": ema.updates}} if ema is not None else {}),
        "output": {"scale": t.network.model.scale, "shift": t.network.model.shift},
        "label_transform": t.transform.to_dict(),
        "epoch": epoch,
        "optimizer": t.optimizer.state_dict(),
        "scaler": t.scaler.state_dict() if t.scaler.is_enabled() else None,
        "loss": {k: v for k, v in t.loss_fn.state_dict().items()},
        "loss_name": t.cfg.loss,
        "rng": rng,
        "best": dict(t.best),
        "history": [dict(r) for r in t.history],
        "args": t.cfg.to_dict(),
        "data": t.data.sources.description,
        "image_shape": list(t.data.image_shape),
        "val_phase_frames": t.val_phase.record() if t.val_phase is not None else None,
        "n_parameters": int(t.n_params),
        "world_size": t.info.world,
        "uhrnet_version": package_version(),
    }
