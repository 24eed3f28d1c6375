"""Training at the GPU's speed (issue 49): the speed options of a run resolved for its device, and the pieces
that keep the host out of the training step on CUDA.

Each option's ``auto`` is its standard win on CUDA and, on a CPU, exactly what every run did before (a seeded
CPU run repeats bit for bit; none of the CUDA-only code below runs there unless an option asks for it):

- ``amp_dtype``: bfloat16 autocast where the GPU has it (no gradient scaler needed), float16 with the scaler
  otherwise; a CPU's ``--amp`` is bfloat16 as before;
- ``channels_last``: the network and its input in NHWC (cuDNN's fast convolution layout);
- ``device_data``: the samples decoded once onto the device (:mod:`uhrnet.data.device_data`);
- ``host_sync``: ``epoch``: the loss check and the metrics summed on the device, read once per epoch
  (:class:`DeviceSums`, :class:`LossWatch`); ``step``: read every step, as before;
- ``fused_adam``: Adam's fused kernel;
- ``compile``: ``torch.compile`` of the network (off unless given: its warm-up pays off only on long runs).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from uhrnet.scoring.metrics import ssim, valid_mask
from uhrnet.training.distributed import DistInfo, MetricSums, all_reduce

__all__ = ["Speed", "resolve_speed", "DeviceSums", "metric_sums", "LossWatch", "device_metrics", "to_layout", "only"]


@dataclass(frozen=True)
class Speed:
    """The speed settings of a run on its device (``device_data``: as asked, ``auto`` decided by the data)."""
    amp_dtype: torch.dtype
    scaler: bool
    channels_last: bool
    device_data: str
    epoch_sync: bool
    fused_adam: bool
    compile: bool

    def describe(self, on_device: bool) -> str:
        """One line for the run's opening lines; ``on_device``: whether the samples live on the device."""
        on = [n for n, v in (("samples on the device", on_device), ("channels_last", self.channels_last),
                             ("host sync per epoch", self.epoch_sync), ("fused Adam", self.fused_adam),
                             ("torch.compile", self.compile)) if v]
        return f"amp dtype {str(self.amp_dtype).replace('torch.', '')}; " + (", ".join(on) or "no speed options")


def resolve_speed(cfg, device: torch.device) -> Speed:
    """The :class:`Speed` of the run options ``cfg`` (a :class:`~uhrnet.training.train_config.RunConfig`) on
    ``device``: each ``auto`` on for CUDA, off on a CPU (what runs did before the options existed)."""
    cuda = device.type == "cuda"

    def switch(value: str) -> bool:
        return value == "on" or (value == "auto" and cuda)

    if not cuda:
        dtype = torch.bfloat16  # as before: a CPU's autocast is bfloat16
    elif cfg.amp_dtype == "bf16" or (cfg.amp_dtype == "auto" and torch.cuda.is_bf16_supported()):
        dtype = torch.bfloat16
    else:
        dtype = torch.float16
    return Speed(amp_dtype=dtype, scaler=bool(cfg.amp) and cuda and dtype == torch.float16,
                 channels_last=switch(cfg.channels_last), device_data=cfg.device_data,
                 epoch_sync=cfg.host_sync == "epoch" or (cfg.host_sync == "auto" and cuda),
                 fused_adam=switch(cfg.fused_adam), compile=bool(cfg.compile))


def to_layout(x: torch.Tensor, speed: Speed) -> torch.Tensor:
    """An input batch in the network's memory layout."""
    return x.contiguous(memory_format=torch.channels_last) if speed.channels_last and x.dim() == 4 else x


class DeviceSums:
    """:class:`uhrnet.training.distributed.MetricSums` kept on the device: NaN skipped without boolean
    indexing (which waits for the device), read once by :meth:`reduce`."""

    def __init__(self, keys, device: torch.device):
        self.keys = list(keys)
        self.v = torch.zeros(2 * len(self.keys), dtype=torch.float64, device=device)

    def add(self, key: str, values: torch.Tensor) -> None:
        values = values.detach().to(self.v.device, torch.float64).flatten()
        ok = torch.isfinite(values)
        i = self.keys.index(key)
        self.v[2 * i] += torch.where(ok, values, torch.zeros_like(values)).sum()
        self.v[2 * i + 1] += ok.sum()

    def reduce(self, info: DistInfo, device) -> dict:
        v = all_reduce(self.v.clone(), info, device).cpu()  # the one read of the epoch
        return {k: (float(v[2 * i] / v[2 * i + 1]) if v[2 * i + 1] > 0 else float("nan"))
                for i, k in enumerate(self.keys)}


def metric_sums(keys, speed: Speed, device: torch.device):
    """The epoch's metric sums: on the device with ``host_sync epoch``, else on the host as before."""
    return DeviceSums(keys, device) if speed.epoch_sync else MetricSums(keys)


class LossWatch:
    """``host_sync epoch``: the first step of the epoch whose loss is not finite, kept on the device and read
    once at the epoch's end (:meth:`first_bad`)."""

    def __init__(self, device: torch.device):
        self.step = torch.full((), -1, dtype=torch.long, device=device)
        self.loss = torch.zeros((), dtype=torch.float32, device=device)

    def note(self, loss: torch.Tensor, step: int) -> None:
        loss = loss.detach().float()
        bad = ~torch.isfinite(loss) & (self.step < 0)
        self.step = torch.where(bad, torch.full_like(self.step, step), self.step)
        self.loss = torch.where(bad, loss, self.loss)

    def first_bad(self, info: DistInfo, device) -> tuple[int, float, bool] | None:
        """``(step, loss, on_this_rank)`` of the first non-finite loss of any rank, or None."""
        mine = self.step.to(torch.float64).reshape(1)
        worst = all_reduce(mine.clone(), info, device, torch.distributed.ReduceOp.MAX if info.enabled else None)
        here = int(mine.cpu())
        if float(worst) < 0:
            return None
        return (here if here >= 0 else int(float(worst))), float(self.loss.cpu()), here >= 0


def device_metrics(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, transform):
    """:func:`uhrnet.scoring.metrics.image_metrics` left on the device: per-image RMSE (mm) and SSIM, float64,
    NaN where an image has no valid pixel."""
    with torch.no_grad():
        pred, target = pred.detach().to(torch.float64), target.to(torch.float64)
        valid = valid_mask(mask, pred)
        sq = (pred - target) ** 2
        if valid is None:
            r = sq.flatten(1).mean(dim=1).sqrt()
        else:
            sq = torch.where(valid, sq, torch.zeros_like(sq))
            r = (sq.flatten(1).sum(dim=1) / valid.flatten(1).sum(dim=1)).sqrt()
        s = ssim(pred.float(), target.float(), transform.data_range, mask, reduction="none").double()
    return r * transform.mm_per_unit, s


def only(values: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    """The per-image ``values`` of the images ``sel`` (a host boolean tensor) for a metric sum: indexed on the
    host as before; on a device the others NaN (skipped by the sums), so the host need not wait for it."""
    if values.device.type == "cpu":
        return values[sel]
    sel = sel.pin_memory().to(values.device, non_blocking=True) if values.device.type == "cuda" else sel.to(values.device)
    return torch.where(sel, values, torch.full_like(values, float("nan")))
