"""TensorBoard logs of a run (``train --tensorboard``, ``adapt --tensorboard``): ``RUN/tensorboard/``,
next to ``history.csv`` / ``history.png``; view them with ``tensorboard --logdir RUN/tensorboard``.

TensorBoard is an optional dependency (``pip install tensorboard``, or the package's ``tensorboard``
extra): :func:`require_tensorboard` turns its absence into one :class:`UsageError` line before anything
runs. :class:`RunLog` is the one writer both loops use; built without a folder (the option off, or a
process other than rank 0 under torchrun) every method does nothing.

One x-axis for every tag, the global optimizer step counted from 1, so a resumed run continues the
same curves: the writer opens with ``purge_step = start_step + 1``, which hides the events a killed run
wrote after its last checkpoint (TensorBoard's own readers drop them). Tags are listed below.

Which event files are the run's own: the folder's ownership record (:mod:`fppsim.owned`,
``RUN/.fppsim-owned.json``). The writer's event file gets a new name each session (time, host, process,
counter), so it cannot replace anything; as soon as it exists it is recorded there as
``tensorboard/<event file>`` of the tool (``uhrnet train`` or ``uhrnet adapt``), and only recorded files
are ever removed:

* a run that starts from step 0 (a new run, ``--overwrite``, a ``--resume`` killed before its first
  checkpoint) removes the event files the record says the same tool wrote (the replaced run's curves),
  with ``--tensorboard`` or without (:func:`remove_own_event_files`), when its first epoch starts;
* a run that starts from step 0 with ``--tensorboard`` is refused before it writes anything
  (:class:`fppsim.errors.ForeignFiles`, one line naming the file; :func:`check_event_files`) when
  ``tensorboard/`` holds an event file (a name containing ``tfevents``, which TensorBoard reads) that the
  record does not give to the tool: TensorBoard would show it as this run's curves, and it is not ours
  to delete. Other files there (and subfolders, which TensorBoard shows as runs of their own) are left
  as they are;
* a resumed run removes nothing and refuses nothing: it adds its own event file, and files it did not
  record (e.g. the curves of a run made before event files were recorded) stay untouched.

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
from uhrnet.training.losses import Loss
from fppsim.owned import ForeignFiles, forget, owners, record_created

__all__ = ["TB_FOLDER", "INSTALL_HINT", "require_tensorboard", "check_event_files", "remove_own_event_files",
           "RunLog"]

TB_FOLDER = "tensorboard"  # inside the run folder
INSTALL_HINT = "pip install tensorboard (or, from the repository root of the checkout, pip install -e '.[tensorboard]')"


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
    unchanged). ``tool``: the command writing the run (``folder`` is ``RUN/tensorboard``): its event file
    is recorded as its own in the run's ownership record, and at step 0 the event files it recorded earlier
    are removed and foreign ones refused (module docstring); None: no record, nothing removed.
    """
    def __init__(self, folder: str | Path | None = None, start_step: int = 0, loss=None, tool: str | None = None):
        self.writer = None
        self._terms: dict = {}
        self._hooks: list = []
        if folder is None:
            return
        from torch.utils.tensorboard import SummaryWriter

        folder = Path(folder)
        if tool is not None and start_step == 0:  # a fresh run: the curves of the run it replaces go
            check_event_files(folder.parent, tool, folder.name)
            remove_own_event_files(folder.parent, tool, folder.name)
        before = set(_event_files(folder))
        self.writer = SummaryWriter(str(folder), purge_step=int(start_step) + 1)  # creates its event file
        if tool is not None:
            for path in sorted(set(_event_files(folder)) - before):
                _record(folder.parent, tool, f"{folder.name}/{path.name}")
        if loss is not None:
            self._watch(loss)

    @property
    def enabled(self) -> bool:
        return self.writer is not None

    def _watch(self, loss) -> None:
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


def _event_files(folder: Path) -> list[Path]:
    """The files directly in ``folder`` that TensorBoard reads as event files (a name containing
    ``tfevents``), symlinks included."""
    try:
        return sorted(p for p in folder.iterdir() if "tfevents" in p.name and (p.is_symlink() or not p.is_dir()))
    except (FileNotFoundError, NotADirectoryError):
        return []


def check_event_files(run: str | Path, tool: str, sub: str = TB_FOLDER, fresh: bool = True) -> None:
    """Refuse (:class:`fppsim.errors.ForeignFiles`, one line naming the file) a ``--tensorboard`` run of
    ``tool`` in ``run`` whose ``run/sub`` is not a folder, or, for a ``fresh`` run, holds an event file the
    ownership record does not give to ``tool``: it would show as this run's curves, and only its writer may
    delete it."""

    run = Path(run)
    if (run / sub).exists() and not (run / sub).is_dir():
        raise ForeignFiles(f"{run / sub} exists and is not a folder: --tensorboard writes its logs there; "
                           "move it away or choose another --out")
    if not fresh:
        return
    record = owners(run) or {}
    for path in _event_files(run / sub):
        owner = record.get(f"{sub}/{path.name}")
        if owner == tool:
            continue
        who = "was not written by" if owner is None else f"was written by {owner}, not"
        raise ForeignFiles(f"{path} exists and {who} {tool} (TensorBoard would show it as this run's curves): "
                           "move it away or choose another --out")


def remove_own_event_files(run: str | Path, tool: str, sub: str = TB_FOLDER) -> list[Path]:
    """Delete the event files in ``run/sub`` that ``run``'s ownership record says ``tool`` wrote (the
    curves of the run a fresh one replaces) and drop them from the record; files it does not give to
    ``tool`` stay. Returns the removed paths."""

    run = Path(run)
    record = owners(run)
    if not record:
        return []
    prefix = f"{sub}/"
    mine = [n for n, t in record.items() if t == tool and n.startswith(prefix) and "/" not in n[len(prefix):]
            and "tfevents" in n[len(prefix):]]
    removed = []
    for name in mine:
        path = run / name
        if path.is_symlink() or path.is_file():
            path.unlink()
            removed.append(path)
    forget(run, mine)
    return removed


def _record(run: Path, tool: str, name: str) -> None:
    """Record ``name`` (the event file the writer has just created under a new name) as ``tool``'s in
    ``run``'s ownership record (the run's claims came first, under the run folder's lock)."""

    record_created(run, tool, name)


def _plane(a) -> np.ndarray:
    """An (H, W) float64 array of a tensor or array with leading size-1 dimensions."""
    if hasattr(a, "detach"):
        a = a.detach().float().cpu().numpy()
    a = np.asarray(a, dtype=np.float64)
    while a.ndim > 2:
        a = a[0]
    return a
