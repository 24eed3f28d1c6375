"""Training: ``uhrnet.train(TrainConfig(...))`` trains UHRNet or a baseline on real (figshare) and/or
synthetic (fppsim) data; ``uhrnet train`` calls it.

The run's options live in :mod:`uhrnet.training.train_config`, its files in :mod:`uhrnet.run_folder`, the
process layout under torchrun in :mod:`uhrnet.training.distributed`, the pieces it is built of (data,
network, loss, optimizer, schedule) in :mod:`uhrnet.training.builders` and its console lines in
:mod:`uhrnet.training.run_messages`; this module is the loop.

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

import dataclasses
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist

from fppsim.owned import output_folder
from uhrnet.checkpoint import checkpoint_kind, init_from_checkpoint, output_mm, save_epoch
from uhrnet.data.datasets import parse_size
from uhrnet.data.device_data import DeviceLoader
from uhrnet.errors import ConfigError, TrainingDiverged
from uhrnet.models import HEADS, count_parameters, outputs_of
from uhrnet.models.any_size import any_size
from uhrnet.models.freeze import freeze, keep_frozen_eval
from uhrnet.run_folder import (LAST_PT, RUN_FILES, TRAIN_TOOL, claim_run_folder, refuse_own_source, write_history,
                               write_run_config)
from uhrnet.scoring.metrics import image_metrics
from uhrnet.training import builders
from uhrnet.training.distributed import DistInfo, all_reduce, init_distributed
from uhrnet.training.speed import LossWatch, device_metrics, metric_sums, only, resolve_speed, to_layout
from uhrnet.training.losses import STEP_FIELDS
from uhrnet.training.run_messages import closing_line, epoch_line, opening_lines
from uhrnet.training.tb_log import TB_FOLDER, RunLog, check_event_files, remove_own_event_files
from uhrnet.training.train_config import RunConfig, TrainConfig, label_transform_from, resolve_config

__all__ = ["TrainConfig", "Trainer", "train"]


class Trainer:
    """One training run of a :class:`TrainConfig` in this process (one rank under torchrun).

    ``cfg``: the resolved options (:class:`RunConfig`); the pieces come from :mod:`uhrnet.training.builders`,
    in an order that is part of a seeded run's numbers.
    """

    def __init__(self, args: TrainConfig, info: DistInfo):
        self.args, self.info = args, info
        self.out = Path(args.out)
        self.ckpt, state = builders.open_run(self.out, args.resume, args.overwrite)
        cfg = RunConfig(**resolve_config(args, self.ckpt["args"] if self.ckpt else None))
        if not cfg.real and not cfg.synthetic:
            raise ConfigError("no data: give --real DIR and/or --synthetic DIR")
        self.device = builders.training_device(cfg.device, info)
        self.speed = resolve_speed(cfg, self.device)  # --amp-dtype, --channels-last, ... (uhrnet.training.speed)
        self.transform = label_transform_from(cfg)
        self.tb = RunLog()  # --tensorboard: fit() opens it on rank 0
        if info.main and args.tensorboard:  # foreign event files: refused before any write
            check_event_files(self.out, TRAIN_TOOL, fresh=state != "resume")
        self._build(cfg)

    def _build(self, cfg: RunConfig) -> None:
        head = HEADS[cfg.head]
        self.loss_entry, needs_rig, phase = builders.loss_entry(cfg, head)
        self.data = builders.build_data(cfg, self.transform, phase, self.info, self.device, self.speed)
        cfg = dataclasses.replace(cfg, resize=self.data.resize)  # config.json and checkpoints: the size chosen
        net, rig = builders.build_network(cfg, head, self.data.image_shape, needs_rig)
        self.net = any_size(net)  # as inference: padded by replication to multiples of 16, cropped back
        self.n_params = count_parameters(net)
        scale, shift = (1.0, 0.0) if cfg.raw_output else (10.0 * self.transform.units_per_mm,
                                                          self.transform.plane_offset)
        if cfg.init_from and self.ckpt is None:  # a fresh run from a checkpoint's weights (a resume keeps its own)
            record = init_from_checkpoint(net, cfg.init_from, output_mm(scale, shift, self.transform))
            cfg = dataclasses.replace(cfg, init_from=record["path"], init_from_checkpoint=record)
        self.cfg = cfg
        self.frozen = freeze(net, cfg.freeze)  # before the average copies the network and DDP wraps it
        self.n_trainable = sum(p.numel() for p in net.parameters() if p.requires_grad)
        self.network = builders.wrap_network(net, cfg, scale, shift, self.device, self.info, self.speed)
        self.loss_fn = builders.build_loss_fn(cfg, head, self.transform, scale, shift, rig, self.device)
        self.optimizer = builders.build_optimizer(net, cfg, self.speed)
        self.amp = bool(cfg.amp)
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.speed.scaler)  # float16 on CUDA only
        self.val_phase = builders.build_val_phase(cfg, self.info, self.data.native)
        self.history: list[dict] = []
        self.best = builders.first_best(cfg)
        self.start_epoch = 0
        if self.ckpt is not None:
            builders.restore(self.ckpt, self.net, self.network.ema, self.optimizer, self.loss_fn, self.scaler, cfg,
                             self.info.rank)
            self.history = list(self.ckpt.get("history", []))
            self.best = dict(self.ckpt.get("best", self.best))
            self.start_epoch = int(self.ckpt["epoch"])

    # -- one epoch ------------------------------------------------------------------------------------
    def _to_device(self, batch, names) -> list:
        """The batch fields ``names`` on the device (None for a field the batch lacks)."""
        nb = self.device.type == "cuda"
        out = [batch[f].to(self.device, non_blocking=nb) if f in batch else None for f in names]
        return [to_layout(out[0], self.speed), *out[1:]] if names and names[0] == "fringe" else out

    def lr_at(self, epoch: int, step: int) -> float:
        """Learning rate of ``step`` of ``epoch`` (both 0-based): :func:`uhrnet.training.builders.lr_at`."""
        return builders.lr_at(self.cfg, len(self.data.loader), epoch, step)

    def train_epoch(self, epoch: int) -> dict:
        data, ddp, loader = self.data, self.network.ddp, self.data.loader
        data.sampler.set_epoch(epoch)
        loader.generator = torch.Generator().manual_seed(self.cfg.seed * 100_003 + epoch)
        ddp.train()
        keep_frozen_eval(self.frozen)  # --freeze: the frozen part's batch norms keep their statistics
        sums = metric_sums(["loss", "rmse", "ssim"], self.speed, self.device)
        metrics, watch = (device_metrics, LossWatch(self.device)) if self.speed.epoch_sync else (image_metrics, None)
        bar = None
        if self.info.main and self.args.progress:  # tqdm only when it shows (a bare GPU machine may lack it)
            from tqdm import tqdm

            bar = tqdm(loader, desc=f"epoch {epoch + 1}/{self.cfg.epochs}", unit="step", leave=False,
                       dynamic_ncols=True)
        for step, batch in enumerate(bar if bar is not None else loader):
            x, y, m = self._to_device(batch, STEP_FIELDS)
            with builders.autocast(self.amp, self.device, self.speed.amp_dtype):
                out = ddp(x)
            outs = outputs_of(out)  # hNet: the fused and the side outputs, all supervised
            extra = self._to_device(batch, self.loss_entry.batch)  # what the loss takes after the mask
            if self.loss_entry.parts:  # a head's loss: its intermediates (e.g. coarse height, phase, height via the rig)
                loss = self.loss_fn(self.net.last_parts, y, m, *extra)
            else:
                loss = sum(self.loss_fn(o.float(), y, m, *extra) for o in outs)
            if watch is None:
                self._stop_if_diverged(loss, epoch, step)
            else:  # --host-sync epoch: read once, after the epoch
                watch.note(loss, step)
            self._step(loss, epoch, step)
            self.tb.step(epoch * len(loader) + step + 1, loss.detach(), self.optimizer.param_groups[0]["lr"])
            sums.add("loss", loss.detach().double().reshape(1) if watch else loss.detach().double().cpu().reshape(1))
            r, s = metrics(outs[0], y, m, self.transform)
            sums.add("rmse", r)
            sums.add("ssim", s)
            if bar is not None and (watch is None or step % 50 == 0):
                bar.set_postfix(loss=f"{loss.item():.4g}", rmse_mm=f"{float(r.nanmean()):.3f}", refresh=False)
        if bar is not None:
            bar.close()
        bad = watch.first_bad(self.info, self.device) if watch is not None else None
        if bad is not None:
            raise TrainingDiverged(f"loss became {bad[1]:g} at epoch {epoch + 1}, step {bad[0] + 1}"
                                   + ("" if bad[2] else " (on another process)"))
        res = sums.reduce(self.info, self.device)
        return {"train_loss": res["loss"], "train_rmse_mm": res["rmse"], "train_ssim": res["ssim"]}

    def _stop_if_diverged(self, loss, epoch: int, step: int) -> None:
        """Every rank stops together when any rank's loss is not finite."""
        finite = torch.isfinite(loss.detach()).to(torch.float64).reshape(1).cpu()
        if float(all_reduce(finite, self.info, self.device, dist.ReduceOp.MIN if self.info.enabled else None)) < 1:
            raise TrainingDiverged(f"loss became {float(loss.detach()):g} at epoch {epoch + 1}, step {step + 1}"
                                   + (" (on another process)" if torch.isfinite(loss) else ""))

    def _step(self, loss, epoch: int, step: int) -> None:
        lr = self.lr_at(epoch, step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        if self.cfg.grad_clip:
            self.scaler.unscale_(self.optimizer)
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg.grad_clip)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        if self.network.ema is not None:
            self.network.ema.update()

    @torch.no_grad()
    def validate(self) -> dict:
        if len(self.data.val_set) == 0:
            return {}
        model = self.network.eval_model
        model.eval()
        sums = metric_sums(["rmse", "ssim", "rmse_real", "ssim_real", "rmse_synthetic", "ssim_synthetic"], self.speed,
                           self.device)
        for batch in self.data.val_loader:
            x, y, m = self._to_device(batch, STEP_FIELDS)
            with builders.autocast(self.amp, self.device, self.speed.amp_dtype):
                pred = model(x)
            r, s = (device_metrics if self.speed.epoch_sync else image_metrics)(pred, y, m, self.transform)
            sums.add("rmse", r)
            sums.add("ssim", s)
            for src in ("real", "synthetic"):
                sel = torch.tensor([v == src for v in batch["source"]])
                if sel.any():
                    sums.add(f"rmse_{src}", only(r, sel))
                    sums.add(f"ssim_{src}", only(s, sel))
        res = sums.reduce(self.info, self.device)
        row = {"val_rmse_mm": res["rmse"], "val_ssim": res["ssim"]}
        if self.data.sources.val.n_real and self.data.sources.val.n_synthetic:
            for src in ("real", "synthetic"):
                row[f"val_rmse_mm_{src}"], row[f"val_ssim_{src}"] = res[f"rmse_{src}"], res[f"ssim_{src}"]
        return row

    # -- checkpoints ----------------------------------------------------------------------------------
    def _payload(self, epoch: int, rng: list) -> dict:
        return builders.checkpoint_payload(self, epoch, rng)

    # -- main loop ------------------------------------------------------------------------------------
    def _open(self) -> None:
        """Rank 0: write config.json and say what the run is."""
        cfg, info = self.cfg, self.info
        self.out.mkdir(parents=True, exist_ok=True)
        # the epochs the weights hold: a resume with fewer --epochs trains nothing and must not say otherwise
        write_run_config(self.out, {**cfg.to_dict(), "epochs": max(int(cfg.epochs), self.start_epoch),
                                    "torch_threads": torch.get_num_threads(),
                                    "label_transform_resolved": self.transform.to_dict(),
                                    "data": self.data.sources.description, "n_parameters": self.n_params,
                                    "world_size": info.world})
        lines = opening_lines(cfg, n_params=self.n_params, n_trainable=self.n_trainable, sources=self.data.sources,
                              image_shape=self.data.image_shape, device=self.device, world=info.world,
                              distributed=info.enabled, out=self.out, start_epoch=self.start_epoch,
                              val_phase_notes=self.val_phase.notes if self.val_phase is not None else [])
        if self.device.type == "cuda":  # (a CPU run says what it always said)
            lines.append(f"speed: {self.speed.describe(isinstance(self.data.loader, DeviceLoader))}")
        for line in lines:
            print(line, flush=True)

    def fit(self) -> int:
        cfg, info, steps = self.cfg, self.info, len(self.data.loader)
        if info.main:
            self._open()
        if self.start_epoch >= cfg.epochs:
            if info.main:
                print(f"already trained {self.start_epoch} epochs (--epochs {cfg.epochs}); nothing to do")
            return 0
        if info.main and self.args.tensorboard:
            self.tb = RunLog(self.out / TB_FOLDER, self.start_epoch * steps, self.loss_fn, TRAIN_TOOL)
            print(f"tensorboard: tensorboard --logdir {self.out / TB_FOLDER}", flush=True)
        elif info.main and self.start_epoch == 0:  # a replaced run's own curves go without --tensorboard too
            remove_own_event_files(self.out, TRAIN_TOOL)
        for epoch in range(self.start_epoch, cfg.epochs):
            row, is_best = self._epoch(epoch)
            rng = builders.gather_rng(self.info)
            if info.main:
                self.tb.validation_images((epoch + 1) * steps, self.network.eval_model, self.data.val_set,
                                          self.transform, self.device)
                self.tb.epoch((epoch + 1) * steps, row)  # flushed before the checkpoint
                save_epoch(self.out, self._payload(epoch + 1, rng), is_best)
                write_history(self.history, self.out)
                print(epoch_line(row, cfg.epochs, is_best), flush=True)
        self.tb.close()
        if info.enabled:
            dist.barrier()
        if info.main:
            print(closing_line(self.out, self.best), flush=True)
        return 0

    def _epoch(self, epoch: int) -> tuple[dict, bool]:
        """Train and score one epoch; ``(its history row, whether it is the best so far)``."""
        t0 = time.perf_counter()
        try:
            row = self.train_epoch(epoch)
        except TrainingDiverged as exc:
            last = self.out / LAST_PT
            hint = f"; the last good checkpoint is {last}" if last.exists() else ""
            raise TrainingDiverged(f"training diverged: {exc}{hint}; try a lower --lr (now {self.cfg.lr:g})"
                                   + (" or drop --amp" if self.amp else "")) from None
        if self.info.enabled:  # the loss's per-epoch accumulators summed over ranks: every rank re-ranks alike
            self.loss_fn.reduce_state(dist.all_reduce)
        self.loss_fn.end_epoch()
        row.update(self.validate())
        if self.val_phase is not None:
            row.update(self.val_phase.score(self.network.eval_model, self.transform, parse_size(self.cfg.resize)))
        row["epoch"] = epoch + 1
        row["lr"] = self.optimizer.param_groups[0]["lr"]
        is_best = builders.update_best(self.best, row)
        row["best"] = int(is_best)
        row["seconds"] = time.perf_counter() - t0
        self.history.append(row)
        return row, is_best


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
