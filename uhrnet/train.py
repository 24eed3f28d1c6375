"""`uhrnet train`: train UHRNet or a baseline on real (figshare) and/or synthetic (fppsim) data.

Per epoch: training loss, train/validation RMSE (mm) and SSIM go to ``RUN/history.csv`` and
``RUN/history.png`` (the paper's Fig. 6); ``RUN/last.pt`` is written atomically after every epoch and
``RUN/best.pt`` whenever the validation RMSE improves. ``--resume`` continues a run exactly (model,
optimizer, loss ranks, RNG streams, data order). Under ``torchrun --nproc_per_node N -m uhrnet train``
it runs DistributedDataParallel (gloo on CPU, nccl on GPU); only rank 0 writes.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import shutil
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from fppsim._fs import check_writable_dir, clean_stale_tmp, folder_lock, tmp_path
from uhrnet.checkpoint import (
    FORMAT, VERSION, CheckpointError, LabelHead, atomic_save, atomic_write_text, load_checkpoint, rng_state,
    select_device, set_rng_state,
)
from uhrnet.cli import CLIError, UsageError
from uhrnet.data import (
    PRESETS, SPLIT_MODES, DataError, LabelTransform, MixedSampler, Prepared, load_sources, parse_size,
)

LOSS_NAMES = ("compound", "l2", "chunked", "ssim")
RUN_FILES = ("best.pt", "last.pt", "history.csv", "config.json")  # a folder holding any of them is a run

# Defaults are applied after parsing (argparse defaults are None) so --resume can tell which options
# the user set; LOCKED options must match the checkpoint's, the others may change on resume.
DEFAULTS = {
    "model": "uhrnet", "loss": "compound", "real": [], "synthetic": [], "synthetic_ratio": None,
    "real_split": "reference", "synthetic_split": "reference", "synthetic_label": "true",
    "preset": "figshare", "label_transform": [], "epochs": 200, "batch_size": 1, "lr": 1e-4,
    "weight_decay": 0.0, "device": "auto", "amp": False, "base_channels": None, "model_option": [],
    "crop": None, "resize": None, "samples_per_epoch": None, "workers": None, "seed": 0,
    "raw_output": False, "grad_clip": None, "augment": True, "lr_schedule": "constant",
}
# what a run made before an option existed used: resuming it must not switch the option on
LEGACY = {"augment": False, "lr_schedule": "constant"}
LR_SCHEDULES = ("cosine", "constant")
LR_FLOOR = 0.05  # the cosine schedule ends at this fraction of --lr
LOCKED = ("model", "loss", "real", "synthetic", "synthetic_ratio", "real_split", "synthetic_split",
          "synthetic_label", "preset", "label_transform", "batch_size", "base_channels", "model_option",
          "crop", "resize", "samples_per_epoch", "seed", "raw_output", "augment", "lr_schedule")

HISTORY_COLUMNS = ("epoch", "train_loss", "train_rmse_mm", "train_ssim", "val_rmse_mm", "val_ssim",
                   "val_rmse_mm_real", "val_ssim_real", "val_rmse_mm_synthetic", "val_ssim_synthetic",
                   "lr", "seconds", "best")


def _model_names() -> list[str]:
    try:
        from uhrnet.models import list_models

        return list_models()
    except ImportError:  # pragma: no cover
        return ["uhrnet", "unet", "hnet", "model_a", "model_b", "model_c", "model_d"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = p.add_argument_group("data (at least one of --real / --synthetic)")
    d.add_argument("--real", nargs="+", metavar="DIR", help="figshare-layout folder(s) (f1_80.npy + Z.npy)")
    d.add_argument("--synthetic", nargs="+", metavar="DIR",
                   help="fppsim folder(s): native (manifest.jsonl) or figshare-format exports")
    d.add_argument("--synthetic-ratio", type=float, metavar="R",
                   help="share of synthetic samples per batch in expectation when both kinds are given "
                        "(default: proportional to the dataset sizes)")
    d.add_argument("--real-split", choices=SPLIT_MODES,
                   help="reference = the paper's 80/10/10 split; train/val/test = every real sample in that "
                        "split (e.g. a single sample) [reference]")
    d.add_argument("--synthetic-split", choices=SPLIT_MODES, help="same for synthetic folders [reference]")
    d.add_argument("--synthetic-label", choices=("true", "psp"),
                   help="train on the exact rendered height or the phase-shifting height [true]")
    d.add_argument("--preset", choices=sorted(PRESETS), help="label transform preset [figshare]")
    d.add_argument("--label-transform", nargs="+", metavar="KEY=VALUE",
                   help="override preset fields: units_per_mm, invalid_value, invalid_threshold, plane_offset, "
                        "data_range")
    d.add_argument("--crop", metavar="HxW", help="random HxW crop per training sample (centre crop for validation)")
    d.add_argument("--resize", metavar="HxW", help="resize every sample to HxW first (area averaging)")
    d.add_argument("--samples-per-epoch", type=int, metavar="N", help="draws per epoch [all training samples]")
    d.add_argument("--workers", type=int, metavar="N", help="data-loader processes [0 on CPU, 4 on GPU]")
    d.add_argument("--augment", dest="augment", action="store_const", const=True,
                   help="photometric augmentation of synthetic samples (gain, gamma, contrast, blur, noise; "
                        "uhrnet.augment; real samples are never augmented) [on]")
    d.add_argument("--no-augment", dest="augment", action="store_const", const=False,
                   help="no photometric augmentation")
    m = p.add_argument_group("model and optimisation")
    m.add_argument("--model", choices=_model_names(), help="architecture [uhrnet]")
    m.add_argument("--base-channels", type=int, metavar="N", help="width of the first level [model default]")
    m.add_argument("--model-option", nargs="+", metavar="KEY=VALUE", help="extra model constructor options")
    m.add_argument("--loss", choices=LOSS_NAMES, help="training loss [compound]")
    m.add_argument("--epochs", type=int, help="total epochs (the paper: 200) [200]")
    m.add_argument("--batch-size", type=int, help="images per step (per process under torchrun) [1]")
    m.add_argument("--lr", type=float, help="Adam learning rate [1e-4]")
    m.add_argument("--lr-schedule", choices=LR_SCHEDULES,
                   help="learning rate over the run: cosine decays it per step from --lr to "
                        f"{LR_FLOOR:g} x --lr at the last step of --epochs; constant keeps --lr [constant]")
    m.add_argument("--weight-decay", type=float, help="Adam weight decay [0]")
    m.add_argument("--grad-clip", type=float, metavar="NORM", help="clip the gradient norm [off]")
    m.add_argument("--amp", action="store_const", const=True, help="mixed precision (fp16 on CUDA, bf16 on CPU)")
    m.add_argument("--raw-output", action="store_const", const=True,
                   help="the network outputs raw labels (as the reference code) instead of height/10 mm "
                        "above the plane")
    m.add_argument("--seed", type=int, help="seed of weights, data order, crops and dropout [0]")
    r = p.add_argument_group("run")
    r.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder (history, checkpoints, plots)")
    r.add_argument("--resume", nargs="?", const="auto", metavar="CKPT",
                   help="continue from RUN_DIR/last.pt (or CKPT) with the same settings")
    r.add_argument("--overwrite", action="store_true",
                   help="start afresh in a RUN_DIR that already holds a run (its best.pt, last.pt, history and "
                        "config are replaced); without it such a folder is refused")
    r.add_argument("--device", choices=("auto", "cpu", "cuda"), help="[auto: cuda when available]")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")


# --------------------------------------------------------------------------------------------------
# Options


def _parse_kv(items, what: str) -> dict:
    import yaml

    out = {}
    for item in items or []:
        if "=" not in item:
            raise CLIError(f"{what}: expected KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip().replace("-", "_")] = yaml.safe_load(v)
    return out


def _normalise(key: str, value):
    if key in ("real", "synthetic"):
        return [str(Path(v).resolve()) for v in (value or [])]
    if key in ("label_transform", "model_option"):
        return sorted(value or [])
    return value


def resolve_config(args: argparse.Namespace, previous: dict | None = None) -> dict:
    """Options after defaults (fresh run) or the checkpoint's options (resume)."""
    cfg = {}
    for key, default in DEFAULTS.items():
        given = getattr(args, key, None)
        if previous is not None and key in previous:
            if given is not None and key in LOCKED and _normalise(key, given) != _normalise(key, previous[key]):
                flag = "--" + key.replace("_", "-")
                raise CLIError(
                    f"{flag} {given} differs from the checkpoint's {previous[key]!r}; drop {flag} to resume, "
                    "or start a new --out"
                )
            cfg[key] = previous[key] if given is None else given
        elif previous is not None and key in LEGACY and given is None:
            cfg[key] = LEGACY[key]
        else:
            cfg[key] = default if given is None else given
    cfg["real"] = _normalise("real", cfg["real"])
    cfg["synthetic"] = _normalise("synthetic", cfg["synthetic"])
    for key in ("crop", "resize"):
        try:
            parse_size(cfg[key])
        except ValueError as exc:
            raise CLIError(f"--{key}: {exc}") from None
    if cfg["synthetic_ratio"] is not None and not 0 <= cfg["synthetic_ratio"] <= 1:
        raise CLIError(f"--synthetic-ratio must be in [0, 1], got {cfg['synthetic_ratio']}")
    for key in ("epochs", "batch_size"):
        if cfg[key] < 1:
            raise CLIError(f"--{key.replace('_', '-')} must be >= 1, got {cfg[key]}")
    if not cfg["lr"] > 0:
        raise CLIError(f"--lr must be positive, got {cfg['lr']}")
    if not math.isfinite(cfg["lr"]):
        raise UsageError(f"--lr must be finite, got {cfg['lr']}")
    if cfg["grad_clip"] is not None and not (cfg["grad_clip"] > 0 and math.isfinite(cfg["grad_clip"])):
        raise UsageError(f"--grad-clip must be a finite gradient norm > 0, got {cfg['grad_clip']}")
    if not (cfg["weight_decay"] >= 0 and math.isfinite(cfg["weight_decay"])):
        raise UsageError(f"--weight-decay must be finite and >= 0, got {cfg['weight_decay']}")
    return cfg


def label_transform_from(cfg: dict) -> LabelTransform:
    overrides = _parse_kv(cfg["label_transform"], "--label-transform")
    try:
        return LabelTransform.from_dict({"preset": cfg["preset"], "name": cfg["preset"], **overrides})
    except DataError as exc:
        raise UsageError(f"--label-transform: {exc}") from None


# --------------------------------------------------------------------------------------------------
# Distributed


@dataclass
class DistInfo:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device_name: str) -> DistInfo:
    """torchrun sets WORLD_SIZE/RANK/LOCAL_RANK; without them this is a single process."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = device_name != "cpu" and torch.cuda.is_available()
    if use_cuda:
        torch.cuda.set_device(local)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo", timeout=timedelta(minutes=30))
    return DistInfo(rank, world, local)


def _all_reduce(values: torch.Tensor, info: DistInfo, device, op=None) -> torch.Tensor:
    if not info.enabled:
        return values
    t = values.to(device)
    dist.all_reduce(t, op=op or dist.ReduceOp.SUM)
    return t.cpu()


# --------------------------------------------------------------------------------------------------
# Metrics helpers (shared with evaluate)


def image_metrics(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, transform: LabelTransform):
    """Per-image RMSE (mm) and SSIM (float64 CPU tensors, NaN where an image has no valid pixel)."""
    from uhrnet.metrics import rmse_mm, ssim

    pred, target, mask = pred.detach().float(), target.float(), mask
    r = rmse_mm(pred, target, mask, transform.mm_per_unit, reduction="none").double().cpu()
    s = ssim(pred, target, transform.data_range, mask, reduction="none").detach().double().cpu()
    return r, s


class _Sums:
    """Sums and counts of per-image values (NaN skipped), reducible across ranks."""

    def __init__(self, keys):
        self.keys = list(keys)
        self.v = torch.zeros(2 * len(self.keys), dtype=torch.float64)

    def add(self, key: str, values: torch.Tensor) -> None:
        values = values.double().flatten()
        ok = torch.isfinite(values)
        i = self.keys.index(key)
        self.v[2 * i] += values[ok].sum()
        self.v[2 * i + 1] += ok.sum()

    def reduce(self, info: DistInfo, device) -> dict:
        v = _all_reduce(self.v.clone(), info, device)
        return {k: (float(v[2 * i] / v[2 * i + 1]) if v[2 * i + 1] > 0 else float("nan"))
                for i, k in enumerate(self.keys)}


# --------------------------------------------------------------------------------------------------
# Trainer


class Diverged(RuntimeError):
    pass


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def write_history(rows: list[dict], out: Path) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=HISTORY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow({k: _fmt(row.get(k)) for k in HISTORY_COLUMNS})
    atomic_write_text(out / "history.csv", buf.getvalue())
    try:
        from uhrnet.plots import plot_history

        plot_history(rows, out / "history.png")
    except Exception as exc:  # a plotting problem must not stop training
        print(f"warning: could not draw history.png ({exc})", file=sys.stderr)


class Trainer:
    def __init__(self, args: argparse.Namespace, info: DistInfo):
        self.args, self.info = args, info
        self.out = Path(args.out)
        self.ckpt = None
        fresh = (args.resume == "auto" and not (self.out / "last.pt").exists()
                 and not any((self.out / n).exists() for n in ("best.pt", "history.csv")))
        if fresh:  # killed before its first checkpoint: nothing trained yet, so start the run afresh
            print(f"note: {self.out} has no last.pt yet; starting the run from epoch 1", file=sys.stderr)
        elif args.resume:
            path = self.out / "last.pt" if args.resume == "auto" else Path(args.resume)
            self.ckpt = load_checkpoint(path)
        elif not getattr(args, "overwrite", False):
            existing = [n for n in RUN_FILES if (self.out / n).exists()]
            if existing:
                raise CLIError(f"{self.out} already holds a run ({', '.join(existing)}): pass --resume to continue "
                               "it, --overwrite to replace it, or choose another --out")
        self.cfg = resolve_config(args, self.ckpt["args"] if self.ckpt else None)
        if not self.cfg["real"] and not self.cfg["synthetic"]:
            raise CLIError("no data: give --real DIR and/or --synthetic DIR")
        try:
            self.device = select_device(self.cfg["device"], info.local_rank if info.enabled else None)
        except ValueError as exc:
            raise CLIError(str(exc)) from None
        if self.device.type == "cuda":
            torch.backends.cudnn.benchmark = True  # fixed input size; exact resume is promised on CPU
        self.transform = label_transform_from(self.cfg)
        self._build()

    # -- construction -------------------------------------------------------------------------------
    def _build(self) -> None:
        cfg, info = self.cfg, self.info
        sources = load_sources(cfg["real"], cfg["synthetic"], self.transform, cfg["real_split"],
                               cfg["synthetic_split"], cfg["synthetic_label"])
        self.sources = sources
        crop, resize = parse_size(cfg["crop"]), parse_size(cfg["resize"])
        from uhrnet.augment import AugmentConfig

        self.train_set = Prepared(sources.train, crop, resize, random_crop=True,
                                  augment=AugmentConfig() if cfg["augment"] else None)
        self.val_set = Prepared(sources.val, crop, resize, random_crop=False)
        if len(self.train_set) == 0:
            raise CLIError("no training samples: every sample is in the val/test split "
                           "(check --real-split/--synthetic-split)")
        shape = tuple(self.train_set[0]["fringe"].shape[-2:])
        if shape[0] % 16 or shape[1] % 16:
            raise CLIError(f"training images are {shape[0]}x{shape[1]}; the models need multiples of 16: "
                           "use --crop HxW or --resize HxW")
        self.image_shape = shape
        self.sampler = MixedSampler(sources.train.n_real, sources.train.n_synthetic, cfg["synthetic_ratio"],
                                    cfg["samples_per_epoch"], cfg["seed"], info.rank, info.world)
        workers = cfg["workers"] if cfg["workers"] is not None else (4 if self.device.type == "cuda" else 0)
        pin = self.device.type == "cuda"
        self.loader = DataLoader(self.train_set, batch_size=cfg["batch_size"], sampler=self.sampler,
                                 num_workers=workers, pin_memory=pin, drop_last=False)
        val_idx = list(range(info.rank, len(self.val_set), info.world))
        self.val_loader = DataLoader(self.val_set, batch_size=cfg["batch_size"], sampler=val_idx,
                                     num_workers=workers, pin_memory=pin)

        from uhrnet.losses import build_loss
        from uhrnet.metrics import count_parameters
        from uhrnet.models import build_model

        torch.manual_seed(cfg["seed"])
        options = _parse_kv(cfg["model_option"], "--model-option")
        if cfg["base_channels"] is not None:
            options["base_channels"] = cfg["base_channels"]
        try:
            net = build_model(cfg["model"], **options)
        except (TypeError, ValueError) as exc:
            raise CLIError(f"--model {cfg['model']}: {exc}") from None
        self.net = net
        self.n_params = count_parameters(net)
        scale, shift = (1.0, 0.0) if cfg["raw_output"] else (10.0 * self.transform.units_per_mm,
                                                             self.transform.plane_offset)
        self.model = LabelHead(net, scale, shift).to(self.device)
        if info.enabled:
            torch.manual_seed(cfg["seed"] + 1_000_003 * info.rank)  # distinct dropout streams per rank
            from torch.nn.parallel import DistributedDataParallel as DDP

            ids = [self.device.index] if self.device.type == "cuda" else None
            self.ddp = DDP(self.model, device_ids=ids)
        else:
            self.ddp = self.model
        try:
            self.loss_fn = build_loss(cfg["loss"], data_range=self.transform.data_range).to(self.device)
        except (TypeError, ValueError) as exc:
            raise CLIError(f"--loss {cfg['loss']}: {exc}") from None
        self.optimizer = torch.optim.Adam(net.parameters(), lr=cfg["lr"], weight_decay=cfg["weight_decay"])
        self.amp = bool(cfg["amp"])
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp and self.device.type == "cuda")
        self.history: list[dict] = []
        self.best = {"metric": "val_rmse_mm", "value": float("inf"), "epoch": 0}
        self.start_epoch = 0
        if self.ckpt is not None:
            self._restore(self.ckpt)

    def _restore(self, ckpt: dict) -> None:
        if ckpt["model"]["config"] != self.net.config:
            raise CheckpointError(f"{ckpt['path']}: model {ckpt['model']['config']} differs from {self.net.config}")
        self.net.load_state_dict(ckpt["state_dict"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        for group in self.optimizer.param_groups:  # --lr / --weight-decay may change on resume
            group["lr"], group["weight_decay"] = self.cfg["lr"], self.cfg["weight_decay"]
        self.loss_fn.load_state_dict(ckpt["loss"])
        if ckpt.get("scaler"):
            self.scaler.load_state_dict(ckpt["scaler"])
        self.history = list(ckpt.get("history", []))
        self.best = dict(ckpt.get("best", self.best))
        self.start_epoch = int(ckpt["epoch"])
        states = ckpt.get("rng", [])
        if self.info.rank < len(states):
            set_rng_state(states[self.info.rank])
        elif states:
            print(f"warning: {ckpt['path']} holds RNG state for {len(states)} process(es); rank "
                  f"{self.info.rank} starts a fresh stream", file=sys.stderr)

    # -- one epoch ------------------------------------------------------------------------------------
    def _autocast(self):
        if not self.amp:
            return nullcontext()
        dtype = torch.float16 if self.device.type == "cuda" else torch.bfloat16
        return torch.autocast(self.device.type, dtype=dtype)

    def _batch(self, batch):
        nb = self.device.type == "cuda"
        return (batch["fringe"].to(self.device, non_blocking=nb), batch["height"].to(self.device, non_blocking=nb),
                batch["mask"].to(self.device, non_blocking=nb))

    def lr_at(self, epoch: int, step: int) -> float:
        """Learning rate of ``step`` (0-based) of ``epoch`` (0-based): a function of the position in the
        run alone, so a resumed run follows the same curve.

        cosine: ``lr * (f + (1 - f) * (1 + cos(pi * t / (T - 1))) / 2)`` with ``t`` the global step,
        ``T`` the steps of all ``--epochs`` and ``f`` = ``LR_FLOOR``; constant: ``lr``.
        """
        base = self.cfg["lr"]
        if self.cfg["lr_schedule"] == "constant":
            return base
        per = max(1, len(self.loader))
        total = max(2, per * self.cfg["epochs"])
        t = min(epoch * per + step, total - 1)
        return base * (LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * t / (total - 1))))

    def _set_lr(self, epoch: int, step: int) -> None:
        lr = self.lr_at(epoch, step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def train_epoch(self, epoch: int) -> dict:
        from tqdm import tqdm

        self.sampler.set_epoch(epoch)
        self.loader.generator = torch.Generator().manual_seed(self.cfg["seed"] * 100_003 + epoch)
        self.ddp.train()
        sums = _Sums(["loss", "rmse", "ssim"])
        bar = tqdm(self.loader, desc=f"epoch {epoch + 1}/{self.cfg['epochs']}", unit="step", leave=False,
                   disable=not self.info.main or self.args.no_progress, dynamic_ncols=True)
        for step, batch in enumerate(bar):
            x, y, m = self._batch(batch)
            with self._autocast():
                out = self.ddp(x)
            outs = out if isinstance(out, (tuple, list)) else (out,)
            loss = sum(self.loss_fn(o.float(), y, m) for o in outs)
            finite = torch.isfinite(loss.detach()).to(torch.float64).reshape(1).cpu()
            if float(_all_reduce(finite, self.info, self.device, dist.ReduceOp.MIN if self.info.enabled else None)) < 1:
                raise Diverged(f"loss became {float(loss.detach()):g} at epoch {epoch + 1}, step {step + 1}"
                               + (" (on another process)" if torch.isfinite(loss) else ""))
            self._set_lr(epoch, step)
            self.optimizer.zero_grad(set_to_none=True)
            self.scaler.scale(loss).backward()
            if self.cfg["grad_clip"]:
                self.scaler.unscale_(self.optimizer)
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg["grad_clip"])
            self.scaler.step(self.optimizer)
            self.scaler.update()
            sums.add("loss", loss.detach().double().cpu().reshape(1))
            r, s = image_metrics(outs[0], y, m, self.transform)
            sums.add("rmse", r)
            sums.add("ssim", s)
            if self.info.main and not self.args.no_progress:
                bar.set_postfix(loss=f"{loss.item():.4g}", rmse_mm=f"{float(r.nanmean()):.3f}", refresh=False)
        bar.close()
        res = sums.reduce(self.info, self.device)
        return {"train_loss": res["loss"], "train_rmse_mm": res["rmse"], "train_ssim": res["ssim"]}

    @torch.no_grad()
    def validate(self) -> dict:
        if len(self.val_set) == 0:
            return {}
        self.model.eval()
        sums = _Sums(["rmse", "ssim", "rmse_real", "ssim_real", "rmse_synthetic", "ssim_synthetic"])
        for batch in self.val_loader:
            x, y, m = self._batch(batch)
            with self._autocast():
                pred = self.model(x)
            r, s = image_metrics(pred, y, m, self.transform)
            sums.add("rmse", r)
            sums.add("ssim", s)
            for src in ("real", "synthetic"):
                sel = torch.tensor([v == src for v in batch["source"]])
                if sel.any():
                    sums.add(f"rmse_{src}", r[sel])
                    sums.add(f"ssim_{src}", s[sel])
        res = sums.reduce(self.info, self.device)
        row = {"val_rmse_mm": res["rmse"], "val_ssim": res["ssim"]}
        if self.sources.val.n_real and self.sources.val.n_synthetic:
            for src in ("real", "synthetic"):
                row[f"val_rmse_mm_{src}"], row[f"val_ssim_{src}"] = res[f"rmse_{src}"], res[f"ssim_{src}"]
        return row

    def _end_epoch_loss(self) -> None:
        """Sum the loss's per-epoch accumulators over ranks, so every rank re-ranks identically."""
        if self.info.enabled:
            for name, buf in self.loss_fn.named_buffers():
                if name.split(".")[-1].startswith("epoch_"):
                    dist.all_reduce(buf)
        self.loss_fn.end_epoch()

    # -- checkpoints ----------------------------------------------------------------------------------
    def _payload(self, epoch: int, rng: list) -> dict:
        return {
            "format": FORMAT, "version": VERSION,
            "model": {"name": self.net.config["name"], "config": dict(self.net.config)},
            "state_dict": self.net.state_dict(),
            "output": {"scale": self.model.scale, "shift": self.model.shift},
            "label_transform": self.transform.to_dict(),
            "epoch": epoch,
            "optimizer": self.optimizer.state_dict(),
            "scaler": self.scaler.state_dict() if self.scaler.is_enabled() else None,
            "loss": {k: v for k, v in self.loss_fn.state_dict().items()},
            "loss_name": self.cfg["loss"],
            "rng": rng,
            "best": dict(self.best),
            "history": [dict(r) for r in self.history],
            "args": dict(self.cfg),
            "data": self.sources.description,
            "image_shape": list(self.image_shape),
            "n_parameters": int(self.n_params),
            "world_size": self.info.world,
            "uhrnet_version": _version(),
        }

    def _gather_rng(self) -> list:
        state = rng_state()
        if not self.info.enabled:
            return [state]
        states = [None] * self.info.world
        dist.all_gather_object(states, state)
        return states

    # -- main loop ------------------------------------------------------------------------------------
    def fit(self) -> int:
        cfg, info = self.cfg, self.info
        if info.main:
            self.out.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.out / "config.json", json.dumps(
                {**cfg, "label_transform_resolved": self.transform.to_dict(), "data": self.sources.description,
                 "n_parameters": self.n_params, "world_size": info.world}, indent=2, default=str))
            src = self.sources
            print(f"uhrnet train: {cfg['model']} ({self.n_params:,} parameters), loss {cfg['loss']}, "
                  f"{src.train.n_real} real + {src.train.n_synthetic} synthetic training / {len(src.val)} validation "
                  f"images at {self.image_shape[0]}x{self.image_shape[1]}, device {self.device}"
                  + (f" x {info.world} processes" if info.enabled else "") + f", run folder {self.out}", flush=True)
            if self.start_epoch:
                print(f"resuming after epoch {self.start_epoch}", flush=True)
            if cfg["synthetic_ratio"] is not None and not (src.train.n_real and src.train.n_synthetic):
                print("note: --synthetic-ratio has no effect with only one kind of training data", flush=True)
        if self.start_epoch >= cfg["epochs"]:
            if info.main:
                print(f"already trained {self.start_epoch} epochs (--epochs {cfg['epochs']}); nothing to do")
            return 0
        for epoch in range(self.start_epoch, cfg["epochs"]):
            t0 = time.perf_counter()
            try:
                row = self.train_epoch(epoch)
            except Diverged as exc:
                last = self.out / "last.pt"
                hint = f"; the last good checkpoint is {last}" if last.exists() else ""
                raise CLIError(f"training diverged: {exc}{hint}; try a lower --lr (now {cfg['lr']:g})"
                               + (" or drop --amp" if self.amp else "")) from None
            self._end_epoch_loss()
            row.update(self.validate())
            row["epoch"] = epoch + 1
            row["lr"] = self.optimizer.param_groups[0]["lr"]
            metric = row.get("val_rmse_mm", float("nan"))
            if not np.isfinite(metric):  # no validation split: fall back to the training RMSE
                self.best["metric"], metric = "train_rmse_mm", row["train_rmse_mm"]
            is_best = bool(np.isfinite(metric) and metric < self.best["value"])
            if is_best:
                self.best.update(value=float(metric), epoch=epoch + 1)
            row["best"] = int(is_best)
            row["seconds"] = time.perf_counter() - t0
            self.history.append(row)
            rng = self._gather_rng()
            if info.main:
                payload = self._payload(epoch + 1, rng)
                atomic_save(payload, self.out / "last.pt")
                if is_best:
                    _atomic_copy(self.out / "last.pt", self.out / "best.pt")
                write_history(self.history, self.out)
                val = (f"  val RMSE {row['val_rmse_mm']:.3f} mm  val SSIM {row['val_ssim']:.4f}"
                       if "val_rmse_mm" in row else "")
                print(f"epoch {epoch + 1}/{cfg['epochs']}  loss {row['train_loss']:.4g}  train RMSE "
                      f"{row['train_rmse_mm']:.3f} mm{val}  {row['seconds']:.1f}s" + ("  *best" if is_best else ""),
                      flush=True)
        if info.enabled:
            dist.barrier()
        if info.main:
            if (self.out / "best.pt").is_file() and self.best["epoch"]:
                print(f"done: {self.out / 'best.pt'} (epoch {self.best['epoch']}, {self.best['metric']} "
                      f"{self.best['value']:.4f}), history {self.out / 'history.csv'}", flush=True)
            else:  # every epoch's metric was NaN (e.g. no valid pixel): no best model to point to
                print(f"done: no best.pt written (no epoch had a finite {self.best['metric']}); last epoch in "
                      f"{self.out / 'last.pt'}, history {self.out / 'history.csv'}", flush=True)
        return 0


def _atomic_copy(src: Path, dst: Path) -> None:
    tmp = tmp_path(dst)
    try:
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _version() -> str:
    from uhrnet import __version__

    return __version__


def run(args: argparse.Namespace) -> int:
    info = init_distributed(args.device or "auto")
    try:
        if not info.main:
            return Trainer(args, info).fit()
        if not args.resume:  # refuse bad options before the run folder is created
            label_transform_from(resolve_config(args))
        try:
            check_writable_dir(args.out)
        except ValueError as exc:
            raise CLIError(str(exc)) from None
        with folder_lock(args.out, "uhrnet train"):  # two trainings in one folder would overwrite each other
            clean_stale_tmp(args.out)  # checkpoint temp files of a killed run
            return Trainer(args, info).fit()
    finally:
        if info.enabled and dist.is_initialized():
            dist.destroy_process_group()
