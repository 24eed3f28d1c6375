"""TensorBoard logs of a run (``train --tensorboard``, ``adapt --tensorboard``): ``RUN/tensorboard/``,
next to ``history.csv`` / ``history.png``; view them with ``tensorboard --logdir RUN/tensorboard``.

TensorBoard is an optional dependency (``pip install tensorboard``, or the package's ``tensorboard``
extra): :func:`require_tensorboard` turns its absence into one :class:`UsageError` line before anything
runs. :class:`RunLog` is the one writer both loops use; built without a folder (the option off, or a
process other than rank 0 under torchrun) every method does nothing.

One x-axis for every tag, the global optimizer step counted from 1, so a resumed run continues the
same curves: the writer opens with ``purge_step = start_step + 1``, which hides the events a killed run
wrote after its last checkpoint (TensorBoard's own readers drop them), and a fresh run (start step 0)
removes the event files an earlier run in the folder left. Tags:

* ``train/loss``, ``train/lr``: each step (rank 0's batch loss; adapt: the step's image);
  ``train/loss_terms/<name>``: each step, the unweighted terms of the loss where it has parts (the
  compound loss: ``chunked`` and ``ssim``, total = chunked + alpha * ssim; the phase head: ``base...``;
  adapt: ``grad``, ``drift``);
* ``epoch/<column>``: each of the epoch's ``history.csv`` numbers (``epoch/val_rmse_mm``,
  ``epoch/val_ssim``, ``epoch/train_loss``, ``epoch/lr`` ...; adapt: ``epoch/loss``, ``epoch/grad`` ...) and
  ``epoch`` itself, at the epoch's last step;
* ``<prefix>/prediction``, ``<prefix>/target`` (or ``/source``), ``<prefix>/error`` (or ``/change``):
  grey images of one sample each epoch (train: the first validation sample, prefix ``val_image``;
  adapt: the first image, prefix ``adapt_image``), scaled to [0, 1]; the millimetre ranges that black
  and white stand for are the text ``<prefix>/ranges`` of the same step.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uhrnet.errors import UsageError

__all__ = ["TB_FOLDER", "INSTALL_HINT", "require_tensorboard", "RunLog"]

TB_FOLDER = "tensorboard"  # inside the run folder
INSTALL_HINT = "pip install tensorboard (or pip install 'fppsim-uhrnet[tensorboard]')"


def require_tensorboard(flag: str = "--tensorboard") -> None:
    """Raise :class:`UsageError` (one line: the package and how to install it) unless PyTorch's
    TensorBoard writer imports."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError as exc:
        raise UsageError(f"{flag} needs the 'tensorboard' package, which cannot be imported ({exc}): "
                         f"{INSTALL_HINT}") from None


class RunLog:
    """Scalars and images of one run in ``folder`` (None: disabled, every method a no-op).

    ``start_step``: optimizer steps already taken (a resumed run: its epochs times the steps per epoch).
    ``loss``: a loss module whose sub-losses are recorded each step (forward hooks, so the loss code is
    unchanged).
    """

    def __init__(self, folder: str | Path | None = None, start_step: int = 0, loss=None):
        self.writer = None
        self._terms: dict = {}
        self._hooks: list = []
        if folder is None:
            return
        from torch.utils.tensorboard import SummaryWriter

        folder = Path(folder)
        if start_step == 0 and folder.is_dir():  # a fresh run: the curves of an overwritten one go
            for old in folder.glob("events.out.tfevents.*"):
                old.unlink()
        self.writer = SummaryWriter(str(folder), purge_step=int(start_step) + 1)
        if loss is not None:
            self._watch(loss)

    @property
    def enabled(self) -> bool:
        return self.writer is not None

    def _watch(self, loss) -> None:
        from uhrnet.training.losses import Loss

        for name, module in loss.named_modules():
            if name and isinstance(module, Loss):
                self._hooks.append(module.register_forward_hook(
                    lambda _m, _i, out, name=name: self._add_term(name, out)))

    def _add_term(self, name: str, value) -> None:
        if getattr(value, "ndim", None) == 0:  # summed over the calls of one step (hNet's side outputs)
            self._terms[name] = self._terms.get(name, 0.0) + value.detach().float()

    def step(self, step: int, loss, lr: float, terms: dict | None = None) -> None:
        """One optimizer step: its loss, learning rate and loss terms (``terms`` and the watched ones)."""
        if self.writer is None:
            return
        w = self.writer
        w.add_scalar("train/loss", float(loss), step)
        w.add_scalar("train/lr", float(lr), step)
        for name, value in {**self._terms, **(terms or {})}.items():
            w.add_scalar(f"train/loss_terms/{name}", float(value), step)
        self._terms = {}

    def epoch(self, step: int, row: dict) -> None:
        """An epoch's history row at its last step, then everything written so far is flushed (before
        the checkpoint that a resume starts from, so no finished epoch is missing from the log)."""
        if self.writer is None:
            return
        for key, value in row.items():
            if key == "best" or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            self.writer.add_scalar("epoch" if key == "epoch" else f"epoch/{key}", float(value), step)
        self.writer.flush()

    def height_images(self, step: int, prefix: str, prediction, other, valid=None, kind: str = "error",
                      name: str = "") -> None:
        """``prediction`` and ``other`` (heights, mm, (H, W) arrays or tensors of any leading size-1
        dims) as images ``prefix/prediction``, ``prefix/<target|source>`` on one scale (``other``'s valid
        range) and their difference ``prefix/<kind>`` on a symmetric one (mid grey = 0); invalid pixels
        (``valid`` False) black. ``kind``: ``"error"`` (other is the target) or ``"change"`` (the source)."""
        if self.writer is None:
            return
        p, o = _plane(prediction), _plane(other)
        ok = np.isfinite(p) & np.isfinite(o) & (np.ones_like(p, bool) if valid is None else _plane(valid) > 0)
        ref = o[ok] if ok.any() else np.zeros(1)
        lo, hi = float(ref.min()), float(ref.max())
        d = p - o
        m = float(np.abs(d[ok]).max()) if ok.any() else 0.0
        span, m = max(hi - lo, 1e-6), max(m, 1e-6)  # a flat map or a perfect fit still gives an image
        other_name = "target" if kind == "error" else "source"
        for tag, img in (("prediction", (p - lo) / span), (other_name, (o - lo) / span), (kind, (d + m) / (2 * m))):
            img = np.where(ok, np.clip(img, 0.0, 1.0), 0.0).astype(np.float32)
            self.writer.add_image(f"{prefix}/{tag}", img[None], step)
        sample = f"{name}: " if name else ""
        self.writer.add_text(f"{prefix}/ranges", f"{sample}prediction, {other_name}: black {lo:.4g} mm .. white "
                             f"{hi:.4g} mm; {kind}: black {-m:.4g} mm .. white {m:.4g} mm (mid grey 0); "
                             "invalid pixels black", step)

    def validation_images(self, step: int, model, dataset, transform, device) -> None:
        """:meth:`height_images` of ``model`` (labels out) on ``dataset[0]`` (prefix ``val_image``);
        nothing without a validation sample."""
        if self.writer is None or len(dataset) == 0:
            return
        import torch

        sample = dataset[0]
        was_training = model.training
        model.eval()
        with torch.no_grad():
            label = model(sample["fringe"][None].to(device)).float().cpu()
        model.train(was_training)
        self.height_images(step, "val_image", transform.height_mm(label), transform.height_mm(sample["height"]),
                           sample["mask"], "error", str(sample.get("id", "")))

    def flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        for hook in self._hooks:
            hook.remove()
        self._hooks, self._terms = [], {}
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def _plane(a) -> np.ndarray:
    """An (H, W) float64 array of a tensor or array with leading size-1 dimensions."""
    if hasattr(a, "detach"):
        a = a.detach().float().cpu().numpy()
    a = np.asarray(a, dtype=np.float64)
    while a.ndim > 2:
        a = a[0]
    return a
