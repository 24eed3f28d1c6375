"""Training: ``uhrnet.train(TrainConfig(...))`` trains UHRNet or a baseline on real (figshare) and/or
synthetic (fppsim) data; ``uhrnet train`` calls it.

The run's options live in :mod:`uhrnet.training.train_config`, its files in :mod:`uhrnet.run_folder`, the
process layout under torchrun in :mod:`uhrnet.training.distributed`; this module is the loop.

Per epoch: training loss, train/validation RMSE (mm) and SSIM go to ``RUN/history.csv`` and
``RUN/history.png`` (the paper's Fig. 6); ``RUN/last.pt`` is written atomically after every epoch and
``RUN/best.pt`` whenever the validation RMSE improves; ``--tensorboard`` logs the same numbers, the
loss per step and a prediction image per epoch to ``RUN/tensorboard/`` (:mod:`uhrnet.training.tb_log`).
``--resume`` continues a run exactly (model, optimizer, loss ranks, RNG streams, data order). ``--init-from CKPT`` starts a fresh run from a
checkpoint's weights (transfer learning; :func:`uhrnet.checkpoint.init_from_checkpoint`), ``--freeze
PART`` keeps a part of them fixed (:mod:`uhrnet.models.freeze`). Under ``torchrun --nproc_per_node N -m uhrnet train``
it runs DistributedDataParallel (gloo on CPU, nccl on GPU); only rank 0 writes.
"""

from __future__ import annotations

import math
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from fppsim.geometry.rig import RigError, check_image_size
from fppsim.owned import output_folder
from uhrnet.checkpoint import (FORMAT, LabelHead, VERSION, checkpoint_kind, init_from_checkpoint, load_checkpoint,
                               output_mm, rng_state, save_epoch, set_rng_state)
from uhrnet.data.datasets import MixedSampler, Prepared, load_sources, parse_size
from uhrnet.device import keep_freed_memory, select_device
from uhrnet.training.losses import HEAD_LOSSES, LOSSES, STEP_FIELDS, LossContext, build_head_loss, build_loss
from uhrnet.training.distributed import DistInfo, MetricSums, all_reduce, init_distributed
from uhrnet.errors import CheckpointError, ConfigError, TrainingDiverged
from uhrnet.scoring.metrics import image_metrics
from uhrnet.models import HEADS, build_model, count_parameters, outputs_of
from uhrnet.models.freeze import freeze, keep_frozen_eval
from uhrnet.run_folder import (BEST_PT, HISTORY_CSV, LAST_PT, RUN_FILES, TRAIN_TOOL, check_run_folder, claim_run_folder,
                               package_version, refuse_own_source, write_history, write_run_config)
from uhrnet.training.tb_log import TB_FOLDER, RunLog, check_event_files, remove_own_event_files
from uhrnet.training.train_config import (LR_FLOOR, RESIZE_AUTO, VAL_PHASE_FRAMES, TrainConfig, auto_resize,
                                          label_transform_from, parse_kv, resolve_config)
from uhrnet.data.augment import augment_config
from uhrnet.models.init import init_weights
from uhrnet.models.any_size import any_size
from uhrnet.training.ema import WeightEMA

__all__ = ["TrainConfig", "Trainer", "train"]


class Trainer:
    """One training run of a :class:`TrainConfig` in this process (one rank under torchrun)."""

    def __init__(self, args: TrainConfig, info: DistInfo):
        self.args, self.info = args, info
        self.out = Path(args.out)
        self.ckpt = None
        state = check_run_folder(self.out, args.resume, args.overwrite)
        if state == "fresh":  # killed before its first checkpoint: nothing trained yet, so start the run afresh
            print(f"note: {self.out} has no {LAST_PT} yet; starting the run from epoch 1", file=sys.stderr)
        elif state == "resume":
            path = self.out / LAST_PT if args.resume == "auto" else Path(args.resume)
            self.ckpt = load_checkpoint(path)
            if "args" not in self.ckpt:  # imported weights or an adaptation: no training state to continue
                made = {"import": "imported weights", "adapt": "an adaptation"}.get(checkpoint_kind(self.ckpt),
                                                                                  "not a training checkpoint")
                raise ConfigError(f"--resume: {path} is {made}, not a training run to continue; start a new run "
                                  "from it with --init-from (and another --out)")
        self.cfg = resolve_config(args, self.ckpt["args"] if self.ckpt else None)
        if not self.cfg["real"] and not self.cfg["synthetic"]:
            raise ConfigError("no data: give --real DIR and/or --synthetic DIR")
        self.device = select_device(self.cfg["device"], info.local_rank if info.enabled else None)
        if self.device.type == "cpu":
            keep_freed_memory()  # large feature maps re-used, not page-faulted in every step (same numbers)
        if self.device.type == "cuda":
            torch.backends.cudnn.benchmark = True  # fixed input size; exact resume is promised on CPU
        self.transform = label_transform_from(self.cfg)
        self.tb = RunLog()  # --tensorboard: fit() opens it on rank 0
        if info.main and args.tensorboard:  # foreign event files: refused before any write
            check_event_files(self.out, TRAIN_TOOL, fresh=state != "resume")
        self._build()

    # -- construction -------------------------------------------------------------------------------
    def _build(self) -> None:
        cfg, info = self.cfg, self.info
        self.head = HEADS[cfg["head"]]
        # what the training loss is called with: the head's loss (wrapping the run's) or the run's own
        run_loss = LOSSES[cfg["loss"].lower()]
        self.loss_entry = HEAD_LOSSES[self.head.loss] if self.head.loss else run_loss
        if self.head.loss and not run_loss.plain:
            raise ConfigError(f"--loss {cfg['loss']} needs more than (prediction, label, mask); the {self.head.name} "
                              "head's loss wraps only such a loss")
        needs_rig = self.head.needs_rig or run_loss.needs_rig or self.loss_entry.needs_rig
        phase = self.head.phase_targets or self.loss_entry.phase_targets
        sources = load_sources(cfg["real"], cfg["synthetic"], self.transform, cfg["real_split"],
                               cfg["synthetic_split"], cfg["synthetic_label"], phase=phase)
        self.sources = sources
        # the data's own size (before --crop / --resize), read once for what needs it
        native = (tuple(Prepared(sources.train, None, None, random_crop=False)[0]["fringe"].shape[-2:])
                  if len(sources.train) and (cfg["resize"] == RESIZE_AUTO or cfg["val_phase"]) else None)
        if cfg["resize"] == RESIZE_AUTO:
            cfg["resize"] = self._auto_resize(native)  # config.json and the checkpoints record the size chosen
        crop, resize = parse_size(cfg["crop"]), parse_size(cfg["resize"])
        import dataclasses


        augment = augment_config(cfg["augment"])
        if augment is not None:
            augment = dataclasses.replace(augment, probability=float(cfg["augment_probability"]))
        self.train_set = Prepared(sources.train, crop, resize, random_crop=True, augment=augment, phase=phase)
        self.val_set = Prepared(sources.val, crop, resize, random_crop=False, phase=phase)
        if len(self.train_set) == 0:
            raise ConfigError("no training samples: every sample is in the val/test split "
                           "(check --real-split/--synthetic-split)")
        shape = tuple(self.train_set[0]["fringe"].shape[-2:])
        if min(shape) < 16:
            raise ConfigError(f"training images are {shape[0]}x{shape[1]}; the models need at least 16 x 16 pixels")
        self.image_shape = shape  # sides not multiples of 16: padded inside the model (uhrnet.models.any_size)
        self.sampler = MixedSampler(sources.train.n_real, sources.train.n_synthetic, cfg["synthetic_ratio"],
                                    cfg["samples_per_epoch"], cfg["seed"], info.rank, info.world)
        workers = cfg["workers"] if cfg["workers"] is not None else (4 if self.device.type == "cuda" else 0)
        pin = self.device.type == "cuda"
        self.loader = DataLoader(self.train_set, batch_size=cfg["batch_size"], sampler=self.sampler,
                                 num_workers=workers, pin_memory=pin, drop_last=False)
        val_idx = list(range(info.rank, len(self.val_set), info.world))
        self.val_loader = DataLoader(self.val_set, batch_size=cfg["batch_size"], sampler=val_idx,
                                     num_workers=workers, pin_memory=pin)

        torch.manual_seed(cfg["seed"])
        options = parse_kv(cfg["model_option"], "--model-option")
        if cfg["base_channels"] is not None:
            options["base_channels"] = cfg["base_channels"]
        rig = head_rig(cfg["rig"], cfg["synthetic"]) if needs_rig else None
        if rig is not None:
            check_image_size(rig, shape, f"--rig {cfg['rig']}" if cfg["rig"] else "the synthetic data's rig",
                             who=f"the {self.head.name} head" if self.head.needs_rig else f"the {cfg['loss']} loss",
                             error=ConfigError, template="{what}: its camera is {camera} but the training images are "
                                                         "{got}; {who} needs the rig of these images")
        options["head"] = self.head.name
        if self.head.needs_rig:
            options["rig"] = rig
        try:
            net = build_model(cfg["model"], **options)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"--model {cfg['model']}: {exc}") from None

        init_weights(net, cfg["init"])  # drawn from the seeded global generator, so --seed fixes it; resume overwrites it

        self.net = any_size(net)  # as inference: padded by replication to multiples of 16, cropped back
        self.n_params = count_parameters(net)
        scale, shift = (1.0, 0.0) if cfg["raw_output"] else (10.0 * self.transform.units_per_mm,
                                                             self.transform.plane_offset)
        if cfg["init_from"] and self.ckpt is None:  # a fresh run from a checkpoint's weights (a resume keeps its own)

            record = init_from_checkpoint(net, cfg["init_from"], output_mm(scale, shift, self.transform))
            cfg["init_from"] = record["path"]
            cfg["init_from_checkpoint"] = record

        self.frozen = freeze(net, cfg["freeze"])  # before the average copies the network and DDP wraps it
        self.n_trainable = sum(p.numel() for p in net.parameters() if p.requires_grad)
        self.model = LabelHead(net, scale, shift).to(self.device)
        self.ema = None
        self.eval_model = self.model
        if cfg["ema"]:
            self.ema = WeightEMA(net, cfg["ema"])
            self.eval_model = LabelHead(self.ema.module, scale, shift)
        if info.enabled:
            torch.manual_seed(cfg["seed"] + 1_000_003 * info.rank)  # distinct dropout streams per rank
            from torch.nn.parallel import DistributedDataParallel as DDP

            ids = [self.device.index] if self.device.type == "cuda" else None
            self.ddp = DDP(self.model, device_ids=ids)
        else:
            self.ddp = self.model
        context = LossContext(data_range=self.transform.data_range, scale=scale, shift=shift,
                              mm_per_unit=self.transform.mm_per_unit, rig=rig)
        try:
            self.loss_fn = build_loss(cfg["loss"], data_range=self.transform.data_range, context=context).to(self.device)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"--loss {cfg['loss']}: {exc}") from None
        if self.head.loss:  # a head that learns more than the height wraps the run's loss
            self.loss_fn = build_head_loss(self.head.loss, self.loss_fn, context).to(self.device)
        trainable = [p for p in net.parameters() if p.requires_grad]  # --freeze: frozen weights never move
        self.optimizer = torch.optim.Adam(trainable, lr=cfg["lr"], weight_decay=cfg["weight_decay"])
        self.amp = bool(cfg["amp"])
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp and self.device.type == "cuda")
        self.val_phase = None  # --val-phase: real frames scored on the writing rank, which picks best.pt
        if cfg["val_phase"] and info.main:
            from uhrnet.scoring.phase_residual import PhaseValidation  # matplotlib, scipy's .mat reader: only when asked

            self.val_phase = PhaseValidation(cfg["val_phase"], max_frames=VAL_PHASE_FRAMES, shape=native,
                                             convention=cfg["val_phase_convention"],
                                             negate_sin=cfg["val_phase_negate_sin"])
        self.history: list[dict] = []
        self.best = {"metric": "val_phase_ratio" if cfg["val_phase"] else "val_rmse_mm", "value": float("inf"),
                     "epoch": 0}
        self.start_epoch = 0
        if self.ckpt is not None:
            self._restore(self.ckpt)

    def _auto_resize(self, shape) -> str | None:
        """``--resize auto``: the training size from the fringe period of the synthetic data's rig
        (:func:`uhrnet.training.train_config.auto_resize`), as ``"HxW"``, or None for full size. ``shape``: the
        training data's own (H, W), None when there are no training samples (refused after)."""
        from fppsim.dataio.rig_choice import dataset_rig  # only --resize auto reads a dataset's rig
        from fppsim.phase.fringe_axis import rig_phase_gradient  # (scipy: not needed on a bare GPU machine otherwise)

        rig = None
        for folder in self.cfg["synthetic"]:
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
        if self.info.main:
            print(f"--resize auto: {why}", flush=True)
        return None if size is None else f"{size[0]}x{size[1]}"

    def _restore(self, ckpt: dict) -> None:
        if ckpt["model"]["config"] != self.net.config:
            raise CheckpointError(f"{ckpt['path']}: model {ckpt['model']['config']} differs from {self.net.config}")
        # with --ema, "state_dict" holds the average (what every later use loads) and "train_state_dict"
        # the optimised weights
        self.net.load_state_dict(ckpt.get("train_state_dict", ckpt["state_dict"]))
        if self.ema is not None:
            self.ema.load_state_dict(ckpt["state_dict"], ckpt["ema"]["updates"])
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
        return tuple(batch[f].to(self.device, non_blocking=nb) for f in STEP_FIELDS)

    def _fields(self, batch) -> list:
        """The batch fields the training loss takes after the mask (its registry entry's ``batch``)."""
        nb = self.device.type == "cuda"
        return [batch[f].to(self.device, non_blocking=nb) if f in batch else None for f in self.loss_entry.batch]

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
        frac = t / (total - 1)
        return base * (LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * frac)))

    def _set_lr(self, epoch: int, step: int) -> None:
        lr = self.lr_at(epoch, step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def train_epoch(self, epoch: int) -> dict:
        self.sampler.set_epoch(epoch)
        self.loader.generator = torch.Generator().manual_seed(self.cfg["seed"] * 100_003 + epoch)
        self.ddp.train()
        keep_frozen_eval(self.frozen)  # --freeze: the frozen part's batch norms keep their statistics
        sums = MetricSums(["loss", "rmse", "ssim"])
        bar = None
        if self.info.main and self.args.progress:  # tqdm only when it shows (a bare GPU machine may lack it)
            from tqdm import tqdm

            bar = tqdm(self.loader, desc=f"epoch {epoch + 1}/{self.cfg['epochs']}", unit="step", leave=False,
                       dynamic_ncols=True)
        for step, batch in enumerate(bar if bar is not None else self.loader):
            x, y, m = self._batch(batch)
            with self._autocast():
                out = self.ddp(x)
            outs = outputs_of(out)  # hNet: the fused and the side outputs, all supervised
            extra = self._fields(batch)
            if self.loss_entry.parts:  # a head's loss: its intermediates (e.g. coarse height, phase, height via the rig)
                loss = self.loss_fn(self.net.last_parts, y, m, *extra)
            else:
                loss = sum(self.loss_fn(o.float(), y, m, *extra) for o in outs)
            finite = torch.isfinite(loss.detach()).to(torch.float64).reshape(1).cpu()
            if float(all_reduce(finite, self.info, self.device, dist.ReduceOp.MIN if self.info.enabled else None)) < 1:
                raise TrainingDiverged(f"loss became {float(loss.detach()):g} at epoch {epoch + 1}, step {step + 1}"
                               + (" (on another process)" if torch.isfinite(loss) else ""))
            self._set_lr(epoch, step)
            self.optimizer.zero_grad(set_to_none=True)
            self.scaler.scale(loss).backward()
            if self.cfg["grad_clip"]:
                self.scaler.unscale_(self.optimizer)
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg["grad_clip"])
            self.scaler.step(self.optimizer)
            self.scaler.update()
            if self.ema is not None:
                self.ema.update()
            self.tb.step(epoch * len(self.loader) + step + 1, loss.detach(), self.optimizer.param_groups[0]["lr"])
            sums.add("loss", loss.detach().double().cpu().reshape(1))
            r, s = image_metrics(outs[0], y, m, self.transform)
            sums.add("rmse", r)
            sums.add("ssim", s)
            if bar is not None:
                bar.set_postfix(loss=f"{loss.item():.4g}", rmse_mm=f"{float(r.nanmean()):.3f}", refresh=False)
        if bar is not None:
            bar.close()
        res = sums.reduce(self.info, self.device)
        return {"train_loss": res["loss"], "train_rmse_mm": res["rmse"], "train_ssim": res["ssim"]}

    @torch.no_grad()
    def validate(self) -> dict:
        if len(self.val_set) == 0:
            return {}
        self.eval_model.eval()
        sums = MetricSums(["rmse", "ssim", "rmse_real", "ssim_real", "rmse_synthetic", "ssim_synthetic"])
        for batch in self.val_loader:
            x, y, m = self._batch(batch)
            with self._autocast():
                pred = self.eval_model(x)
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
            self.loss_fn.reduce_state(dist.all_reduce)
        self.loss_fn.end_epoch()

    # -- checkpoints ----------------------------------------------------------------------------------
    def _payload(self, epoch: int, rng: list) -> dict:
        return {
            "format": FORMAT, "version": VERSION,
            "model": {"name": self.net.config["name"], "config": dict(self.net.config)},
            "state_dict": (self.ema.state_dict() if self.ema is not None else self.net.state_dict()),
            **({"train_state_dict": self.net.state_dict(),
                "ema": {"decay": self.ema.decay, "updates": self.ema.updates}} if self.ema is not None else {}),
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
            "uhrnet_version": package_version(),
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
            # the epochs the weights hold: a resume with fewer --epochs trains nothing and must not say otherwise
            write_run_config(self.out, {**cfg, "epochs": max(int(cfg["epochs"]), self.start_epoch),
                                        "torch_threads": torch.get_num_threads(),
                                        "label_transform_resolved": self.transform.to_dict(),
                                        "data": self.sources.description, "n_parameters": self.n_params,
                                        "world_size": info.world})
            src = self.sources
            frozen = (f", {self.n_trainable:,} trainable (--freeze {cfg['freeze']})"
                      if cfg["freeze"] != "none" else "")
            print(f"uhrnet train: {cfg['model']} ({self.n_params:,} parameters{frozen}), loss {cfg['loss']}, "
                  f"{src.train.n_real} real + {src.train.n_synthetic} synthetic training / {len(src.val)} validation "
                  f"images at {self.image_shape[0]}x{self.image_shape[1]}, device {self.device}"
                  + (f" x {info.world} processes" if info.enabled else "") + f", run folder {self.out}", flush=True)
            if self.start_epoch:
                print(f"resuming after epoch {self.start_epoch}", flush=True)
            elif cfg.get("init_from_checkpoint"):
                rec = cfg["init_from_checkpoint"]
                kind = "moving-average (--ema)" if rec["weights"] == "ema" else "trained"
                other = rec.get("other_options") or {}
                other = f"; this run keeps its own {', '.join(other)} (no weight depends on it)" if other else ""
                print(f"init-from {rec['path']}: the {kind} weights of its epoch {rec['epoch']} "
                      f"(sha256 {rec['sha256'][:12]}){other}; fresh optimizer and schedule", flush=True)
            if cfg["synthetic_ratio"] is not None and not (src.train.n_real and src.train.n_synthetic):
                print("note: --synthetic-ratio has no effect with only one kind of training data", flush=True)
            for note in (self.val_phase.notes if self.val_phase is not None else []):
                print(f"--val-phase: {note}", flush=True)
        if self.start_epoch >= cfg["epochs"]:
            if info.main:
                print(f"already trained {self.start_epoch} epochs (--epochs {cfg['epochs']}); nothing to do")
            return 0
        if info.main and self.args.tensorboard:
            self.tb = RunLog(self.out / TB_FOLDER, self.start_epoch * len(self.loader), self.loss_fn, TRAIN_TOOL)
            print(f"tensorboard: tensorboard --logdir {self.out / TB_FOLDER}", flush=True)
        elif info.main and self.start_epoch == 0:  # a replaced run's own curves go without --tensorboard too
            remove_own_event_files(self.out, TRAIN_TOOL)
        for epoch in range(self.start_epoch, cfg["epochs"]):
            t0 = time.perf_counter()
            try:
                row = self.train_epoch(epoch)
            except TrainingDiverged as exc:
                last = self.out / LAST_PT
                hint = f"; the last good checkpoint is {last}" if last.exists() else ""
                raise TrainingDiverged(f"training diverged: {exc}{hint}; try a lower --lr (now {cfg['lr']:g})"
                               + (" or drop --amp" if self.amp else "")) from None
            self._end_epoch_loss()
            row.update(self.validate())
            if self.val_phase is not None:
                row.update(self.val_phase.score(self.eval_model, self.transform, parse_size(cfg["resize"])))
            row["epoch"] = epoch + 1
            row["lr"] = self.optimizer.param_groups[0]["lr"]
            metric = row.get(self.best["metric"], float("nan"))
            # no validation split: the training RMSE (--val-phase: the real frames choose, and an epoch
            # they cannot score is not the best)
            if not np.isfinite(metric) and self.best["metric"] == "val_rmse_mm":
                self.best["metric"], metric = "train_rmse_mm", row["train_rmse_mm"]
            is_best = bool(np.isfinite(metric) and metric < self.best["value"])
            if is_best:
                self.best.update(value=float(metric), epoch=epoch + 1)
            row["best"] = int(is_best)
            row["seconds"] = time.perf_counter() - t0
            self.history.append(row)
            rng = self._gather_rng()
            if info.main:
                self.tb.validation_images((epoch + 1) * len(self.loader), self.eval_model, self.val_set,
                                          self.transform, self.device)
                self.tb.epoch((epoch + 1) * len(self.loader), row)  # flushed before the checkpoint
                save_epoch(self.out, self._payload(epoch + 1, rng), is_best)
                write_history(self.history, self.out)
                val = (f"  val RMSE {row['val_rmse_mm']:.3f} mm  val SSIM {row['val_ssim']:.4f}"
                       if "val_rmse_mm" in row else "")
                if "val_phase_ratio" in row:
                    val += f"  real phase residual {row['val_phase_ratio']:.3f} of flat"
                print(f"epoch {epoch + 1}/{cfg['epochs']}  loss {row['train_loss']:.4g}  train RMSE "
                      f"{row['train_rmse_mm']:.3f} mm{val}  {row['seconds']:.1f}s" + ("  *best" if is_best else ""),
                      flush=True)
        self.tb.close()
        if info.enabled:
            dist.barrier()
        if info.main:
            if (self.out / BEST_PT).is_file() and self.best["epoch"]:
                print(f"done: {self.out / BEST_PT} (epoch {self.best['epoch']}, {self.best['metric']} "
                      f"{self.best['value']:.4f}), history {self.out / HISTORY_CSV}", flush=True)
            else:  # every epoch's metric was NaN (e.g. no valid pixel): no best model to point to
                print(f"done: no {BEST_PT} written (no epoch had a finite {self.best['metric']}); last epoch in "
                      f"{self.out / LAST_PT}, history {self.out / HISTORY_CSV}", flush=True)
        return 0


def head_rig(rig: str | None, synthetic) -> dict:
    """The rig of a head or loss that needs one, as a dictionary: ``rig`` (a calibration file) or the nominal rig of the first
    synthetic dataset (its ``dataset.json``, else its first sample's ``meta.json``; a figshare export's
    ``native/`` folder too), else fppsim's default rig. A dataset rendered with ``--rig-jitter`` has no
    single rig its phases fit: refused."""
    from fppsim.dataio.rig_choice import resolve_rig  # a dataset's unreadable dataset.json: DatasetError, a ValueError

    try:
        return resolve_rig(rig or None, datasets=synthetic or ())[0].to_dict()
    except (RigError, OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"--rig: {exc}") from None


def train(config: TrainConfig) -> dict:
    """Train (or resume) the run ``config`` describes; returns ``{"out", "best", "history"}``.

    Under ``torchrun`` every process calls this; it runs DistributedDataParallel and only rank 0 writes.
    """
    info = init_distributed(config.device or "auto")
    threads = torch.get_num_threads()
    if config.threads:
        torch.set_num_threads(int(config.threads))
    try:
        if not info.main:
            trainer = Trainer(config, info)
            trainer.fit()
        else:
            if config.init_from:
                refuse_own_source(Path(config.out), config.init_from, "--init-from")
            # created, locked (two trainings in one folder would overwrite each other), temp files of a killed
            # run removed; the run's file names claimed before anything is written (run_folder)
            with output_folder(config.out, "uhrnet train", error=ConfigError):
                claim_run_folder(Path(config.out), TRAIN_TOOL, RUN_FILES, checkpoint_kind)
                trainer = Trainer(config, info)
                trainer.fit()
        return {"out": trainer.out, "best": dict(trainer.best), "history": [dict(r) for r in trainer.history]}
    finally:
        torch.set_num_threads(threads)
        if info.enabled and dist.is_initialized():
            dist.destroy_process_group()
