"""Losses of the paper: chunked L2 with dynamic reordering, SSIM loss and their compound; the physics head's
loss; and their registries (:data:`LOSSES`, :data:`HEAD_LOSSES`: what each loss needs from the trainer).

Every loss is an ``nn.Module`` called as ``loss(pred, target, mask=None)`` with ``(N, C, H, W)`` tensors
and an optional valid-pixel ``mask`` (``(N, 1, H, W)`` or broadcastable; bool, or numeric with
nonzero = valid); only valid pixels count. A loss that needs more says so in its registry entry
(:class:`LossEntry`: batch fields after the mask, a head's intermediates instead of the prediction, the
rig), and the trainer gives it exactly that. Every loss has ``end_epoch()``, to be called once after each
training epoch (a no-op except for the chunked L2 loss), and a ``state_dict()`` that restores it
exactly, so training resumes with the same patch ranks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Callable

import torch
from torch import nn
import torch.nn.functional as F

from uhrnet.scoring.metrics import ssim, valid_mask
from uhrnet.errors import InputError


class Loss(nn.Module):
    """Base class: the ``loss(pred, target, mask=None)`` convention, ``end_epoch()`` and
    ``reduce_state()``."""

    def end_epoch(self) -> None:
        """Called after every training epoch; nothing to do by default."""

    def reduce_state(self, all_reduce_sum) -> None:
        """Combine the per-process state of a distributed run before :meth:`end_epoch`.

        ``all_reduce_sum(tensor)`` sums a tensor over all processes in place. Stateless losses have
        nothing to combine; composite losses pass the call on to the losses they contain.
        """
        for child in self.children():
            if isinstance(child, Loss):
                child.reduce_state(all_reduce_sum)


def _squared_error(pred: torch.Tensor, target: torch.Tensor, mask) -> tuple[torch.Tensor, torch.Tensor]:
    """``(pred - target)^2`` zeroed at invalid pixels, and the valid indicator as float (same shape)."""
    if pred.shape != target.shape:
        raise InputError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    valid = valid_mask(mask, pred)
    dtype = torch.promote_types(pred.dtype, torch.float32)  # sums of squares in at least float32
    diff = pred.to(dtype) - target.to(dtype)
    if valid is None:
        return diff * diff, torch.ones_like(diff)
    diff = torch.where(valid, diff, torch.zeros_like(diff))
    return diff * diff, valid.to(diff.dtype)


class L2Loss(Loss):
    """Masked mean squared error: ``sum_valid (pred - target)^2 / n_valid`` (0 without valid pixels)."""

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask=None) -> torch.Tensor:
        sq, valid = _squared_error(pred, target, mask)
        return sq.sum() / valid.sum().clamp(min=1)


def patch_sums(x: torch.Tensor, grid: Sequence[int]) -> torch.Tensor:
    """Sum of ``x (N, C, H, W)`` over batch, channels and each cell of a ``gh x gw`` grid -> ``(gh*gw,)``.

    Row ``h`` belongs to patch row ``floor(h * gh / H)`` (and likewise for columns), so patches are equal
    when ``gh`` divides ``H`` and differ by at most one pixel otherwise. Patches are numbered row-major.
    """
    gh, gw = grid
    h, w = x.shape[-2:]
    rows = F.one_hot(torch.arange(h, device=x.device) * gh // h, gh).to(x.dtype)  # (H, gh)
    cols = F.one_hot(torch.arange(w, device=x.device) * gw // w, gw).to(x.dtype)  # (W, gw)
    return (rows.T @ x.sum(dim=(0, 1)) @ cols).flatten()


def ranks_of(values: torch.Tensor) -> torch.Tensor:
    """Ascending ranks ``1..P`` of ``values (P,)`` (smallest value -> rank 1; ties by index)."""
    order = torch.argsort(values, stable=True)
    ranks = torch.empty_like(order)
    ranks[order] = torch.arange(1, len(values) + 1, device=values.device)
    return ranks


class ChunkedL2Loss(Loss):
    r"""Chunked L2 loss with dynamic reordering (UHRNet paper).

    Prediction and target are split into a ``gh x gw`` grid of ``P`` patches (4 x 4 = 16 by default;
    see :func:`patch_sums`). For patch ``p``, ``L2_p`` is the mean squared error over the valid pixels of
    that patch in the whole batch (all images and channels pooled; 0 if it has none):

    .. math::
        L2_p = \frac{\sum_{n,c,(h,w) \in p} m\,(\hat y - y)^2}{\sum_{n,c,(h,w) \in p} m}, \qquad
        \mathcal{L} = \frac{1}{P} \sum_p w_{r_p} L2_p

    where ``r_p`` in ``1..P`` is the patch's ascending rank and ``w_i = 0.2 i - 0.1`` by default
    (``weights`` overrides: ``P`` values, for ranks 1..P), so patches that are hard get larger weights.
    The ranks are *not* those of the current batch: they come from the previous epoch's per-patch L2
    (``sum`` of squared errors over ``sum`` of valid pixels, accumulated over every training call of the
    epoch), re-estimated when :meth:`end_epoch` is called. Until then (first epoch), the ranks of the
    first training batch are used. Only calls on a prediction that requires grad (training steps)
    accumulate or fix ranks, or any call with ``update=True``; validation under ``torch.no_grad()``
    leaves the state alone (before the first training batch it ranks its own batch).

    State (in ``state_dict()``): ``weights`` (P,), ``ranks`` (P,) (all 0 = not yet set), ``epoch_sse`` and
    ``epoch_count`` (P,) float64 accumulators.
    """

    def __init__(self, grid: Sequence[int] = (4, 4), weights: Sequence[float] | None = None) -> None:
        super().__init__()
        gh, gw = (int(g) for g in grid)
        if gh < 1 or gw < 1:
            raise InputError(f"grid must be two positive integers, got {grid}")
        self.grid = (gh, gw)
        n = gh * gw
        if weights is None:
            w = 0.2 * torch.arange(1, n + 1, dtype=torch.float64) - 0.1
        else:
            w = torch.as_tensor(weights, dtype=torch.float64).flatten()
            if len(w) != n:
                raise InputError(f"need {n} weights for a {gh}x{gw} grid, got {len(w)}")
        self.register_buffer("weights", w.float())
        self.register_buffer("ranks", torch.zeros(n, dtype=torch.long))
        self.register_buffer("epoch_sse", torch.zeros(n, dtype=torch.float64))
        self.register_buffer("epoch_count", torch.zeros(n, dtype=torch.float64))

    @property
    def num_patches(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def has_ranks(self) -> bool:
        return bool(self.ranks.min() > 0)

    def patch_weights(self) -> torch.Tensor:
        """Current weight of every patch as a ``(gh, gw)`` grid (zeros before ranks are set)."""
        w = torch.where(self.ranks > 0, self.weights[(self.ranks - 1).clamp(min=0)], torch.zeros_like(self.weights))
        return w.view(self.grid)

    def patch_losses(self, pred: torch.Tensor, target: torch.Tensor, mask=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L2_p, n_p)``: per-patch mean squared error over valid pixels and valid-pixel counts, ``(P,)``."""
        sq, valid = _squared_error(pred, target, mask)
        sse, count = patch_sums(sq, self.grid), patch_sums(valid, self.grid)
        return sse / count.clamp(min=1), count

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask=None, *, update: bool | None = None) -> torch.Tensor:
        """The weighted loss; ``update`` (default: ``pred.requires_grad``) accumulates the epoch state."""
        if self.ranks.device != pred.device:
            self.to(pred.device)  # the state follows the data, so the loss needs no explicit .to(device)
        l2, count = self.patch_losses(pred, target, mask)
        if update is None:
            update = pred.requires_grad
        ranks = self.ranks
        if pred.device.type != "cpu":  # the same ranks, chosen on the device: the host does not wait for it
            ranks = torch.where(self.ranks.min() > 0, self.ranks, ranks_of(l2.detach()))
            if update:
                self.ranks.copy_(ranks)
        elif not self.has_ranks:
            ranks = ranks_of(l2.detach())
            if update:
                self.ranks.copy_(ranks)
        if update:
            with torch.no_grad():
                self.epoch_sse += (l2 * count).double()
                self.epoch_count += count.double()
        return (self.weights.to(l2.dtype)[ranks - 1] * l2).sum() / self.num_patches

    def reduce_state(self, all_reduce_sum) -> None:
        """The epoch accumulators are sums over training calls: sum them over processes, so every
        process re-ranks the patches identically."""
        all_reduce_sum(self.epoch_sse)
        all_reduce_sum(self.epoch_count)

    def end_epoch(self) -> None:
        """Re-rank the patches by this epoch's accumulated per-patch L2 and reset the accumulators.

        Without accumulated data (no training call since the last ``end_epoch``), nothing changes.
        """
        if self.epoch_count.sum() > 0:
            self.ranks.copy_(ranks_of(self.epoch_sse / self.epoch_count.clamp(min=1)))
        self.epoch_sse.zero_()
        self.epoch_count.zero_()


class SSIMLoss(Loss):
    """``1 - SSIM(pred, target)`` over valid pixels (see :func:`uhrnet.scoring.metrics.ssim`, which it calls).

    ``data_range`` is the dynamic range ``L`` of the labels, fixed per dataset (``C1 = (k1 L)^2``,
    ``C2 = (k2 L)^2``); Gaussian window ``window`` x ``window`` with standard deviation ``sigma``.
    """

    def __init__(
        self, data_range: float, window: int = 11, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03
    ) -> None:
        super().__init__()
        if data_range is None or not data_range > 0:
            raise InputError(f"SSIMLoss needs a positive data_range (fixed per dataset), got {data_range!r}")
        self.data_range = float(data_range)
        self.window, self.sigma, self.k1, self.k2 = window, sigma, k1, k2

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask=None) -> torch.Tensor:
        value = ssim(
            pred, target, self.data_range, mask, window=self.window, sigma=self.sigma, k1=self.k1, k2=self.k2
        )
        return 1 - value

    def extra_repr(self) -> str:
        return f"data_range={self.data_range}, window={self.window}, sigma={self.sigma}, k1={self.k1}, k2={self.k2}"


class CompoundLoss(Loss):
    """``ChunkedL2Loss(grid, weights) + alpha * SSIMLoss(data_range)``, alpha = 1000 as in the paper
    (Model D). ``end_epoch()`` and the state dict cover the chunked part (keys ``chunked.*``)."""

    def __init__(
        self,
        alpha: float = 1000.0,
        *,
        data_range: float,
        grid: Sequence[int] = (4, 4),
        weights: Sequence[float] | None = None,
        window: int = 11,
        sigma: float = 1.5,
    ) -> None:
        super().__init__()
        self.alpha = float(alpha)
        self.chunked = ChunkedL2Loss(grid, weights)
        self.ssim = SSIMLoss(data_range, window=window, sigma=sigma)

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask=None) -> torch.Tensor:
        return self.chunked(pred, target, mask) + self.alpha * self.ssim(pred, target, mask)

    def end_epoch(self) -> None:
        self.chunked.end_epoch()

    def extra_repr(self) -> str:
        return f"alpha={self.alpha}"


class PhaseHeadLoss(Loss):
    """Training loss of the physics head (:class:`uhrnet.models.phase_head.PhaseHead`), per backbone output::

        L = base(coarse label) + phase_weight * mean_valid[(c - cos Phi)^2 + (s - sin Phi)^2]
            + invalid_weight * mean_invalid[c^2 + s^2] + height_weight * L2(final label, right order)

    ``base`` is the run's height loss (e.g. compound) on the coarse height; ``(c, s)`` the predicted cosine
    and sine, ``Phi`` the exact projector phase (``phase_true``, rad) of synthetic samples (pixels without
    it, e.g. real ones, count in no phase term); on invalid (shadow) pixels ``(c, s)`` is pulled to 0, so
    its length is the head's confidence. The final height (through the rig) is supervised with L2 where
    its fringe order is right (within ``right_mm`` of the label): a wrong order is the coarse height's
    fault, which ``base`` already penalises. ``phase_weight`` 100 makes a phase error cost about what its
    height error would in label units (6 units/mm, ~0.9 rad/mm: ``(6/0.9)^2 / 2`` ~ 22 per rad^2 in the
    small-error limit, times the chunked L2's patch weights and the SSIM term's scale).
    """

    def __init__(self, base: Loss, scale: float, shift: float, mm_per_unit: float, phase_weight: float = 100.0,
                 invalid_weight: float = 10.0, height_weight: float = 1.0, right_mm: float = 1.5) -> None:
        super().__init__()
        self.base = base
        self.scale, self.shift, self.mm_per_unit = float(scale), float(shift), float(mm_per_unit)
        self.phase_weight, self.invalid_weight = float(phase_weight), float(invalid_weight)
        self.height_weight, self.right_mm = float(height_weight), float(right_mm)

    def forward(self, parts: Sequence[dict], target: torch.Tensor, mask, phase: torch.Tensor | None) -> torch.Tensor:
        m = torch.ones_like(target) if mask is None else mask.to(target.dtype)
        total = target.new_zeros(())
        for p in parts:
            coarse = p["coarse"] * self.scale + self.shift
            total = total + self.base(coarse, target, m)
            final = p["height"] * self.scale + self.shift
            right = m * ((final.detach() - target).abs() * self.mm_per_unit < self.right_mm)
            total = total + self.height_weight * ((final - target) ** 2 * right).sum() / right.sum().clamp(min=1)
            c, s = p["cos_sin"]
            if phase is not None:
                has = m * torch.isfinite(phase)
                ph = torch.nan_to_num(phase)
                err = (c - torch.cos(ph)) ** 2 + (s - torch.sin(ph)) ** 2
                total = total + self.phase_weight * (err * has).sum() / has.sum().clamp(min=1)
            off = 1 - m
            total = total + self.invalid_weight * ((c * c + s * s) * off).sum() / off.sum().clamp(min=1)
        return total

    def end_epoch(self) -> None:
        self.base.end_epoch()


# ---------------------------------------------------------------------------------------------- the registry
STEP_FIELDS = ("fringe", "height", "mask")
"""The batch fields of every training step (:class:`uhrnet.data.datasets.Prepared`): input, label, valid mask;
a loss is called with the model's output, the label and the mask, then its entry's ``batch`` fields."""
PHASE_FIELD = "phase"  # the batch field of the true projector phase (rad; the datasets' phase=True, NaN where unknown)


@dataclass(frozen=True)
class LossContext:
    """What a loss may be built from, beyond its own options: the label range ``data_range`` (SSIM's ``L``),
    the run's output mapping (label = output * ``scale`` + ``shift``), ``mm_per_unit`` of the labels, the
    calibrated ``rig`` (fppsim's rig dictionary; only for a loss that asks for it) and, for a head's loss,
    ``base``: the run's loss it wraps."""

    data_range: float | None = None
    scale: float = 1.0
    shift: float = 0.0
    mm_per_unit: float = 1.0
    rig: dict | None = None
    base: Loss | None = None


@dataclass(frozen=True)
class LossEntry:
    """One registered loss: how to build it and what the trainer must give it.

    build : ``(context: LossContext, **options) -> Loss``. help : one line (docs, ``--help``).
    batch : batch fields the loss takes after ``(pred, target, mask)``, in this order (None for a batch
    without one); :data:`PHASE_FIELD` makes the datasets load the true phase. parts : the loss takes the
    model's intermediates (``model.last_parts``: a head's, e.g. :class:`~uhrnet.models.phase_head.PhaseHead`)
    instead of each output; otherwise the trainer calls it on every output of the model (hNet's side outputs
    too) and sums. needs_rig : it is built with the run's rig (``context.rig``: ``--rig``, else the synthetic
    data's rig).

    State across steps (the chunked L2's patch ranks) needs no entry field: the loss keeps it in buffers (its
    ``state_dict`` is checkpointed and restored on ``--resume``), and the trainer calls every loss's
    :meth:`Loss.end_epoch` after each epoch, after :meth:`Loss.reduce_state` under DDP.
    """

    build: Callable[..., Loss]
    help: str
    batch: tuple[str, ...] = ()
    parts: bool = False
    needs_rig: bool = False

    @property
    def plain(self) -> bool:
        """Called as ``loss(pred, target, mask)`` alone (what a head's loss can wrap)."""
        return not self.batch and not self.parts

    @property
    def phase_targets(self) -> bool:
        """Training batches must carry the true phase (synthetic samples only)."""
        return PHASE_FIELD in self.batch


def _data_range(context: LossContext, name: str) -> float:
    if context.data_range is None:
        raise InputError(f"the {name} loss needs data_range (the label range L of the dataset)")
    return context.data_range


LOSSES: dict[str, LossEntry] = {
    "compound": LossEntry(lambda c, **o: CompoundLoss(data_range=_data_range(c, "compound"), **o),
                          "chunked L2 + alpha * SSIM (the paper's Model D, alpha 1000)"),
    "l2": LossEntry(lambda c, **o: L2Loss(**o), "masked mean squared error"),
    "chunked": LossEntry(lambda c, **o: ChunkedL2Loss(**o), "chunked L2 with dynamic reordering (4 x 4 patches)"),
    "ssim": LossEntry(lambda c, **o: SSIMLoss(_data_range(c, "ssim"), **o), "1 - SSIM"),
}
"""The run losses, ``--loss`` NAME -> :class:`LossEntry` (``--loss`` choices, ``TrainConfig`` checks and the
trainer read it). Adding a loss: a :class:`Loss` subclass and one entry here."""

HEAD_LOSSES: dict[str, LossEntry] = {
    "phase_head": LossEntry(lambda c, **o: PhaseHeadLoss(c.base, c.scale, c.shift, c.mm_per_unit, **o),
                            "the physics head: the run's loss on the coarse height + phase + height through the rig",
                            batch=(PHASE_FIELD,), parts=True),
}
"""Training losses of the heads that learn more than the height (:data:`uhrnet.models.heads.HEADS`' ``loss``):
each wraps the run's loss (``context.base``, a plain one)."""


def build_loss(name: str, data_range: float | None = None, *, context: LossContext | None = None,
               **options) -> Loss:
    """Run loss by (case-insensitive) name of :data:`LOSSES` (:func:`loss_help` says what each is).
    ``data_range`` (or ``context.data_range``) is required by the SSIM-based ones and ignored by the others;
    ``context`` gives what else a loss may need (:class:`LossContext`); ``options`` go to the constructor."""
    key = name.lower()
    if key not in LOSSES:
        raise InputError(f"unknown loss {name!r}; known losses: {', '.join(LOSSES)}")
    context = context or LossContext()
    if data_range is not None:
        context = replace(context, data_range=data_range)
    return LOSSES[key].build(context, **options)


def loss_help(default: str | None = None) -> str:
    """``--loss``'s help, from :data:`LOSSES`: each name with its entry's ``help``, then ``[default]``."""
    text = "training loss: " + "; ".join(f"{name} = {entry.help}" for name, entry in LOSSES.items())
    return text + (f" [{default}]" if default else "")


def build_head_loss(name: str, base: Loss, context: LossContext, **options) -> Loss:
    """The head loss ``name`` of :data:`HEAD_LOSSES` around the run's loss ``base``."""
    return HEAD_LOSSES[name].build(replace(context, base=base), **options)
