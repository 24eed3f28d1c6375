"""Label-free adaptation to real fringe images: ``uhrnet.training.adapt(AdaptConfig(...))``; ``uhrnet adapt`` calls it.

A network trained on synthetic data meets real images whose fringes it reads imperfectly. Each real
fringe image carries its own phase (:func:`fppsim.phase.single_shot.single_shot_phase`: wrapped phase ``phi`` and
a reliability ``rho`` in [0, 1]), and the calibrated rig says which phase a height implies
(:class:`uhrnet.physics.rig_layer.RigLayer`: ``Phi(h)``, exact and differentiable). Fine-tuning minimises,
over the UNLABELLED images (no height label is ever read),

    L = w_grad L_grad + w_drift L_drift

* ``L_grad``, fringe-gradient consistency: the phase step between neighbouring pixels that the
  predicted height implies, ``Phi(h)[x+1] - Phi(h)[x]`` (rows and columns), against the image's own
  step ``wrap(phi[x+1] - phi[x])``, with a Charbonnier penalty, weighted by ``min(rho)`` of the pair and
  ignored where they differ by more than ``max_step`` rad (a wall whose fringes alias, a shadow edge).
  It fixes the relief's shape without the fringe-order ambiguity of the phase itself;
* ``L_drift``, anchor to the source model: mean ``|h - h_source| / 10 mm`` over the image's valid pixels,
  which keeps what the phase cannot tell (the level of an object behind walls, shadows) where it was.

A wrapped-phase term ``sum rho (1 - cos(phi - Phi(h) - o)) / sum rho`` (``--w-wrap``, off by default) was
removed on 2026-11-26: it pulls each pixel to the nearest height the rig calls phase-consistent, and the
default rig's depth scale is about 3.4 mm off at 40 mm on the real data, so it pulled raised objects the
wrong way (FP1523 residual 1.644 with it against 1.614 rad without, docs/experiments/physics.md).

Batch norm and dropout stay in evaluation mode (two or three images cannot re-estimate statistics).
The run folder holds ``last.pt`` (a checkpoint ``predict``/``evaluate`` accept, with the source's
training record and this adaptation's), ``history.csv`` (one row per epoch: the loss terms), ``images.json`` (each image's median
wrapped residual before and after, rad), ``config.json`` and ``figures/<image>_adapt.png`` (before /
after / difference and the phase residuals). Re-running the same command resumes (refused, naming the
option, when an option differs or the source checkpoint changed since); a folder holding another
adaptation is replaced only with ``overwrite``; files this command did not write (a training run's, a
person's) are never replaced (:mod:`uhrnet.run_folder`), ``out`` may not be the source's folder, nor hold a
``best.pt`` (an adaptation writes none, and a RUN folder stands for its ``best.pt`` first). Each epoch's image
order depends on ``seed`` and the epoch only, so a resumed run ends with the weights of an uninterrupted one.
The model sees each image as ``predict`` does (:func:`uhrnet.inference.prediction.labels_at_input_size`: the
source's ``--resize``, padding to multiples of 16).
With ``tensorboard`` the loss terms per step and epoch and the first image's height per epoch go to
``tensorboard/`` (:mod:`uhrnet.training.tb_log`: its event files are recorded as this command's; a fresh or
``overwrite`` adaptation removes only those, and refuses an event file there that is not, with ``tensorboard``).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from fppsim.phase import circular_mean, wrap
from fppsim.errors import check_seed
from fppsim.geometry.rig import RigError, check_image_size
from uhrnet.errors import ConfigError, UsageError
from uhrnet.training.train_config import MAX_LR
from uhrnet.physics.rig_layer import RigLayer, wrap as wrap_t
from uhrnet.run_folder import (BEST_PT, CONFIG_JSON, HISTORY_CSV, IMAGES_JSON, LAST_PT, claim_run_folder,
                               refuse_own_source, write_history, write_run_config)
from uhrnet.inference.prediction import fringe_phase, labels_at_input_size, read_inputs, refine_rig_for
from fppsim.owned import output_folder
from uhrnet.checkpoint import checkpoint_kind, load_checkpoint, model_from_checkpoint, rng_state, save_epoch
from fppsim.dataio.encoding import json_default
from fppsim.files import atomic_write_text, json_text
from uhrnet.data.datasets import parse_size
from uhrnet.device import keep_freed_memory, select_device
from uhrnet.training.tb_log import RunLog, TB_FOLDER, check_event_files, remove_own_event_files, require_tensorboard
from uhrnet.plots import plot_adaptation

__all__ = ["AdaptConfig", "AdaptResult", "adapt", "adapt_loss", "ImagePhase", "image_phase", "ADAPT_COLUMNS"]

ADAPT_COLUMNS = ("epoch", "loss", "grad", "drift", "lr", "seconds")
ADAPT_TOOL = "uhrnet adapt"
MAX_TORCH_SEED = 2**64 - 1  # --seed seeds a torch.Generator, which refuses more (a traceback mid-run before)


@dataclass
class AdaptConfig:
    """What to adapt and how (defaults chosen for 2 CPU cores; see the module docstring).

    checkpoint : a run folder (its ``last.pt``... as predict resolves it) or a ``.pt`` file.
    images : unlabelled fringe inputs: images / ``.npy`` (as ``uhrnet predict`` takes them), figshare
        folders (``f1_80.npy`` or ``fringe_pattern.npy``; labels are never read) and phase-shifting
        folders (their ``iPattern`` single-shot images).
    out : the adaptation's run folder.
    rig : calibration file; default the checkpoint's own rig (physics head), else fppsim's default rig.
    epochs : passes over the images (one image per step). lr : Adam learning rate.
    w_grad, w_drift : loss weights. Defaults chosen on a frame the adaptation did not see
        (adapting the recipe's U-Net on the real pair alone, scoring FP1523's calibration-free phase
        residual: 1.682 rad before; lr 1e-4 / 40 epochs: 1.614; lr 3e-4: 1.583; and 80 epochs: 1.573;
        w_drift 0.1 let objects sink, 1.733). max_step : largest phase-step disagreement (rad) that
        counts in ``L_grad`` (> 0). min_reliability : pixels below it count in no phase term (in [0, 1): the
        reliability of a pixel lies in [0, 1]).
    device : ``auto`` (cuda when available, as ``uhrnet train``), ``cpu`` or ``cuda``.
    """
    checkpoint: str | Path
    images: Sequence[str | Path]
    out: str | Path
    rig: str | Path | None = None
    epochs: int = 80
    lr: float = 3e-4
    w_grad: float = 1.0
    w_drift: float = 0.5
    max_step: float = 1.5
    min_reliability: float = 0.2
    device: str = "auto"
    seed: int = 0
    resume: bool = True
    overwrite: bool = False
    figures: bool = True
    progress: bool = True
    tensorboard: bool = False  # also log to out/tensorboard/ (uhrnet.training.tb_log; the optional tensorboard package)

    def __post_init__(self):
        if isinstance(self.images, (str, Path)):
            self.images = [self.images]
        if not self.images:
            raise UsageError("adapt: give at least one image (--images PATH ...)")
        if int(self.epochs) != self.epochs or self.epochs < 1:
            raise UsageError(f"--epochs must be an integer >= 1, got {self.epochs!r}")
        if not (self.lr > 0 and math.isfinite(self.lr) and self.lr <= MAX_LR):
            raise UsageError(f"--lr must be a finite rate > 0 and at most {MAX_LR:g}, got {self.lr!r}")
        for name in ("w_grad", "w_drift", "max_step", "min_reliability"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise UsageError(f"--{name.replace('_', '-')} must be a finite number >= 0, got {v!r}")
        if not self.max_step > 0:
            raise UsageError(f"--max-step must be > 0 rad (0 ignores every phase step), got {self.max_step!r}")
        if not self.min_reliability < 1:
            raise UsageError(f"--min-reliability must be in [0, 1) (reliabilities lie in [0, 1]), got "
                             f"{self.min_reliability!r}")
        check_seed(self.seed, error=UsageError, most=MAX_TORCH_SEED)
        if self.device not in ("auto", "cpu", "cuda"):
            raise UsageError(f"--device must be auto, cpu or cuda, got {self.device!r}")
        if self.w_grad == 0:
            raise UsageError("adapt needs its phase term: --w-grad must be > 0")
        if self.tensorboard:
            require_tensorboard()

    def record(self) -> dict:
        d = asdict(self)
        d["images"] = [str(Path(p).resolve()) for p in self.images]
        for k in ("checkpoint", "out", "rig"):
            d[k] = None if d[k] is None else str(Path(d[k]).resolve())
        return d


@dataclass
class AdaptResult:
    out: Path
    epochs: int
    history: list[dict]
    images: list[dict] = field(default_factory=list)  # name, before/after median wrapped residual (rad)
    figures: list[Path] = field(default_factory=list)


@dataclass
class ImagePhase:
    """One unlabelled image ready for adaptation (all (H, W) float32)."""
    name: str
    fringe: np.ndarray  # dataset encoding, [-1, 1]
    wrapped: np.ndarray  # rad, fppsim's phase_true convention up to a constant
    reliability: np.ndarray  # [0, 1]; 0 where invalid


def image_phase(name: str, fringe: np.ndarray, rig) -> ImagePhase:
    """The single-shot phase of ``fringe`` (dataset encoding) in ``rig``'s phase direction, with its
    reliability (0 on shadows: dark runs, the dataset's marker)."""

    ssp = fringe_phase(np.asarray(fringe, np.float64), rig, name)
    rel = np.where(ssp.valid, ssp.reliability, 0.0).astype(np.float32)
    return ImagePhase(name, np.asarray(fringe, np.float32), ssp.wrapped.astype(np.float32), rel)


def adapt_loss(height_mm: torch.Tensor, source_mm: torch.Tensor, wrapped: torch.Tensor, reliability: torch.Tensor,
               layer, w_grad: float = 1.0, w_drift: float = 0.5, max_step: float = 1.5,
               min_reliability: float = 0.2, eps: float = 0.05) -> tuple[torch.Tensor, dict]:
    """The adaptation loss (module docstring) for a batch ``(N, 1, H, W)``: heights in mm, the image's
    wrapped phase (rad) and reliability; ``layer`` maps height to absolute phase. Returns the total and
    its terms (floats)."""
    phi = layer.phase_from_height(height_mm)
    rho = torch.where(reliability >= min_reliability, reliability, torch.zeros_like(reliability))
    valid = (reliability > 0).to(height_mm.dtype)
    terms = {}
    # gradient consistency, rows and columns
    g_sum, g_w = height_mm.new_zeros(()), height_mm.new_zeros(())
    for dim in (-1, -2):
        n = phi.shape[dim]
        a, b = (lambda t: t.narrow(dim, 1, n - 1)), (lambda t: t.narrow(dim, 0, n - 1))
        r = (a(phi) - b(phi)) - wrap_t(a(wrapped) - b(wrapped))
        w = torch.minimum(a(rho), b(rho)) * (r.detach().abs() < max_step)
        g_sum = g_sum + (w * (torch.sqrt(r * r + eps * eps) - eps)).sum()
        g_w = g_w + w.sum()
    terms["grad"] = g_sum / g_w.clamp(min=1.0)
    terms["drift"] = (valid * (height_mm - source_mm).abs()).sum() / (10.0 * valid.sum().clamp(min=1.0))
    total = w_grad * terms["grad"] + w_drift * terms["drift"]
    return total, {k: float(v.detach()) for k, v in terms.items()}


def median_wrapped_residual(height_mm: np.ndarray, img: ImagePhase, layer, min_reliability: float = 0.5) -> float:
    """Median |wrap(phi - Phi(h) - o)| (rad) over the image's reliable pixels: 0 = the height explains
    the image's fringes exactly (up to the phase origin ``o``)."""
    with torch.no_grad():
        phi = layer.phase_from_height(torch.as_tensor(height_mm, dtype=torch.float32)[None, None])[0, 0].numpy()
    sel = (img.reliability >= min_reliability) & np.isfinite(height_mm)
    if not sel.any():
        return float("nan")
    d = (img.wrapped - phi)[sel]
    return float(np.median(np.abs(wrap(d - circular_mean(d)))))


def _rig_for(cfg: AdaptConfig, ckpt: dict):
    """The rig and its name: ``--rig``, else the checkpoint's own, else fppsim's default (as predict's refine)."""
    try:
        return refine_rig_for(ckpt, cfg.rig)
    except RigError as exc:
        raise ConfigError(f"--rig: {exc}") from None


def adapt(cfg: AdaptConfig, log: Callable[[str], None] = print) -> AdaptResult:
    """Fine-tune ``cfg.checkpoint`` on ``cfg.images`` without labels (module docstring); writes the
    run folder ``cfg.out`` (locked while it runs) and returns what happened."""

    refuse_own_source(Path(cfg.out), cfg.checkpoint, "RUN")
    _refuse_foreign_best(Path(cfg.out))
    with output_folder(cfg.out, ADAPT_TOOL, error=ConfigError):
        return _adapt(cfg, log)


def _refuse_foreign_best(out: Path) -> None:
    """:class:`ConfigError` when ``out`` holds a ``best.pt``: an adaptation writes only ``last.pt``, and a RUN
    folder stands for its ``best.pt`` first (:data:`uhrnet.run_folder.CHECKPOINTS`), so predict, evaluate and
    export of ``out`` would silently read that other model instead of the adaptation."""
    if (out / BEST_PT).exists() or (out / BEST_PT).is_symlink():
        raise ConfigError(f"--out {out} holds a {BEST_PT} that adapt did not write: predict and evaluate of that folder "
                          f"would read it, not the adaptation; choose another --out")


def _resume_from(cfg: AdaptConfig, out: Path, source: dict) -> dict | None:
    """The adaptation in ``out`` to continue, or None for a fresh one; refused (one line naming the
    option) when it was made with other options or from another state of the source checkpoint."""

    if not (out / LAST_PT).exists() or cfg.overwrite:
        return None
    prev = load_checkpoint(out / LAST_PT)
    if "adapt" not in prev:
        raise ConfigError(f"{out} holds a run that is not an adaptation: choose another --out")
    if not cfg.resume:
        raise ConfigError(f"{out} already holds an adaptation: pass --overwrite to replace it, or choose another --out")
    free = ("epochs", "progress", "figures", "overwrite", "resume", "device", "tensorboard")  # may change on resume
    recorded = prev["adapt"]["config"]
    for key, value in cfg.record().items():
        if key in free or key not in recorded or recorded[key] == value:
            continue
        flag = "RUN" if key == "checkpoint" else "--" + key.replace("_", "-")
        shown = lambda v: " ".join(map(str, v)) if isinstance(v, list) else v  # noqa: E731
        again = f"leave {flag} out" if recorded[key] is None else f"give {flag} {shown(recorded[key])}"
        raise ConfigError(f"{out} already holds an adaptation with other options: {flag} {shown(value)} differs from "
                          f"its {shown(recorded[key])}; {again} to resume, or choose another --out (or --overwrite)")
    was = prev["adapt"].get("source_sha256")
    if was is not None and was != source["sha256"]:
        raise ConfigError(f"{source['path']} changed since the adaptation in {out} started from it (sha256 "
                          f"{was[:12]} -> {source['sha256'][:12]}): choose another --out, or --overwrite to adapt "
                          "the new weights afresh")
    return prev


def _adapt(cfg: AdaptConfig, log: Callable[[str], None]) -> AdaptResult:

    out = Path(cfg.out)
    source = load_checkpoint(cfg.checkpoint, digest=True)
    rig, rig_name = _rig_for(cfg, source)
    device = select_device(cfg.device)
    if device.type == "cpu":
        keep_freed_memory()  # large maps re-used, not page-faulted in every step (same numbers)
    images = _read_images(cfg, rig, rig_name, log)
    names = [LAST_PT, HISTORY_CSV, CONFIG_JSON, IMAGES_JSON]
    names += [f"figures/{im.name}_adapt.png" for im in images] if cfg.figures else []
    claim_run_folder(out, ADAPT_TOOL, names, checkpoint_kind, kind="adapt")  # never replaces a file it did not write
    resume_from = _resume_from(cfg, out, source)
    if cfg.tensorboard:  # tensorboard/ not a folder, or (fresh) foreign event files in it: refused before any write
        check_event_files(out, ADAPT_TOOL, fresh=resume_from is None)
    model, transform = model_from_checkpoint(source, device)
    size = parse_size(source.get("args", {}).get("resize"))  # as predict and evaluate run it
    layer = RigLayer(rig).to(device)
    # times mm_per_unit, not LabelTransform.height_mm's division: the float bits of the recorded adaptations
    to_mm = lambda label: (label - transform.plane_offset) * transform.mm_per_unit  # noqa: E731

    def batch(im: ImagePhase):
        t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)[None, None]  # noqa: E731
        return t(im.fringe), t(im.wrapped), t(im.reliability)

    def heights(x):
        return to_mm(labels_at_input_size(model, x, size))

    model.eval()  # batch norm statistics and dropout as trained (module docstring)
    with torch.no_grad():  # the source model's heights: taken before any resumed or adapted weights load
        sources = [heights(batch(im)[0]) for im in images]
    params = [p for p in model.parameters() if p.requires_grad]
    optim = torch.optim.Adam(params, lr=cfg.lr)
    history, start = _resume_into(model, optim, resume_from)
    if start >= cfg.epochs and resume_from is not None:
        log(f"adapt: {out} already holds {start} epochs (--epochs {cfg.epochs}); nothing to do")
    elif start:
        log(f"adapt: resuming {out} at epoch {start + 1}")
    record = {**cfg.record(), "epochs": max(int(cfg.epochs), start)}  # what the weights in last.pt hold
    write_run_config(out, {**record, "rig_used": rig_name, "source": source["path"], "source_sha256": source["sha256"]})
    gen = torch.Generator().manual_seed(int(cfg.seed))
    for _ in range(min(start, int(cfg.epochs))):  # the image order of the epochs done: a resumed run shuffles as
        torch.randperm(len(images), generator=gen)  # an uninterrupted one (each epoch's order: seed and epoch only)
    before = [median_wrapped_residual(s[0, 0].cpu().numpy(), im, layer.cpu()) for s, im in zip(sources, images)]
    layer.to(device)
    bar = _progress_bar(cfg, start, len(images))
    if start == 0 and not cfg.tensorboard:  # a replaced adaptation's own curves go (with --tensorboard: RunLog)
        remove_own_event_files(out, ADAPT_TOOL)
    tb = RunLog(out / TB_FOLDER if cfg.tensorboard and start < cfg.epochs else None, start * len(images),
                tool=ADAPT_TOOL)
    for epoch in range(start, int(cfg.epochs)):
        t0 = time.perf_counter()
        sums = {"loss": 0.0, "grad": 0.0, "drift": 0.0}
        for k, i in enumerate(torch.randperm(len(images), generator=gen).tolist()):
            x, phi, rho = batch(images[i])
            h = heights(x)
            loss, terms = adapt_loss(h, sources[i], phi, rho, layer, cfg.w_grad, cfg.w_drift, cfg.max_step,
                                     cfg.min_reliability)
            if not torch.isfinite(loss):
                raise ConfigError(f"adapt: the loss became {float(loss):g} on {images[i].name} at epoch {epoch + 1}; "
                                  "lower --lr")
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            tb.step(epoch * len(images) + k + 1, loss.detach(), cfg.lr, terms)
            sums["loss"] += float(loss.detach()) / len(images)
            for name, v in terms.items():
                sums[name] += v / len(images)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{float(loss.detach()):.4g}", refresh=False)
        row = {"epoch": epoch + 1, **sums, "lr": cfg.lr, "seconds": time.perf_counter() - t0}
        history.append(row)
        if tb.enabled:  # the first image's height and its change from the source model's, flushed before last.pt
            with torch.no_grad():
                tb.height_images((epoch + 1) * len(images), "adapt_image", heights(batch(images[0])[0]),
                                 sources[0], images[0].reliability > 0, "change", images[0].name)
            tb.epoch((epoch + 1) * len(images), row)
        # an adaptation has no validation: last.pt only
        save_epoch(out, _adapted_checkpoint(source, model, optim, cfg, rig, history, epoch + 1), is_best=False)
        write_history(history, out, ADAPT_COLUMNS, extra=True, plot=False)
        if not cfg.progress:
            log(f"adapt epoch {epoch + 1}/{cfg.epochs}  loss {sums['loss']:.4g}  grad {sums['grad']:.4g}  "
                f"drift {sums['drift']:.4g}  {row['seconds']:.1f}s")
    if bar is not None:
        bar.close()
    tb.close()
    result = AdaptResult(out, max(int(cfg.epochs), start), history)
    with torch.no_grad():
        afters = [heights(batch(im)[0]) for im in images]
    _compare_images(result, images, sources, afters, before, layer.cpu(), cfg.figures)
    atomic_write_text(out / IMAGES_JSON, json_text(result.images, indent=2, default=json_default))
    return result


def _read_images(cfg: AdaptConfig, rig, rig_name: str, log: Callable[[str], None]) -> list[ImagePhase]:
    """The images and their single-shot phases, each checked against the rig's camera size; refused when no
    pixel is reliable enough to adapt to (before the run folder is claimed). What reading them noticed (a float
    frame with no value below 0, an input renamed) goes to ``log`` as a warning."""
    images, renamed, notes = [], {}, []
    inputs = read_inputs([str(p) for p in cfg.images], with_paths=True, renamed=renamed, notes=notes)
    for line in notes + [f"{path}: named {name} (another input is also named {given})"
                         for name, (given, path) in renamed.items()]:
        log(f"adapt: warning: {line}")
    for name, fr, path in inputs:
        check_image_size(rig, fr.shape, f"{path}: image {name}", who=f"the rig's camera ({rig_name}) is",
                         error=ConfigError, template="{what} is {got} but {who} {camera}{hint}")
        images.append(image_phase(name, fr, rig))
    if not any((im.reliability >= max(cfg.min_reliability, 1e-12)).any() for im in images):
        raise ConfigError(f"no pixel of the {len(images)} image(s) has a fringe phase reliability >= "
                          f"{cfg.min_reliability:g} (--min-reliability): nothing to adapt to")
    return images


def _resume_into(model, optim, resume_from: dict | None) -> tuple[list, int]:
    """Load a resumed adaptation's weights and optimizer state; its history and the epochs done (a fresh
    one: none)."""
    if resume_from is None:
        return [], 0
    model.net.load_state_dict(resume_from["state_dict"])
    optim.load_state_dict(resume_from["adapt"]["optimizer"])
    history = list(resume_from["adapt"]["history"])
    start = int(resume_from["adapt"]["epoch"])
    return history, start


def _progress_bar(cfg: AdaptConfig, start: int, n_images: int):
    """A step progress bar over the epochs still to run, or None (--no-progress, or nothing to run)."""
    if not (cfg.progress and start < cfg.epochs):
        return None
    from tqdm import tqdm  # only a run with a progress bar needs it

    return tqdm(total=(cfg.epochs - start) * n_images, desc="adapt", unit="step", dynamic_ncols=True)


def _adapted_checkpoint(source: dict, model, optim, cfg: AdaptConfig, rig, history: list, epochs: int) -> dict:
    """last.pt of an adaptation: the source checkpoint with the adapted weights, less its training state,
    plus what resuming needs (options, history, source digest, rig, optimizer, RNG)."""
    payload = {k: v for k, v in source.items() if k not in ("path", "sha256", "optimizer", "scaler", "loss", "rng")}
    payload.update({
        "state_dict": model.net.state_dict(), "epoch": int(source.get("epoch", 0)),
        "adapt": {"config": cfg.record(), "epoch": epochs, "history": history, "source": source["path"],
                  "source_sha256": source["sha256"],
                  "rig": rig.to_dict(), "optimizer": optim.state_dict(), "rng": rng_state()},
    })
    payload.pop("train_state_dict", None)
    payload.pop("ema", None)
    return payload


def _compare_images(result: AdaptResult, images: list[ImagePhase], sources: list, afters: list, before: list,
                    layer, figures: bool) -> None:
    """Per image, the median wrapped residual before and after and the mean height change on reliable
    pixels, into ``result`` (and its figure with ``figures``)."""
    for im, s, a, b in zip(images, sources, afters, before):
        h0, h1 = s[0, 0].cpu().numpy(), a[0, 0].cpu().numpy()
        after = median_wrapped_residual(h1, im, layer)
        result.images.append({"name": im.name, "before_rad": b, "after_rad": after,
                              "mean_change_mm": float(np.mean(np.abs(h1 - h0)[im.reliability > 0]))})
        if figures:
            result.figures.append(plot_adaptation(im, h0, h1, layer, result.out / "figures" / f"{im.name}_adapt.png"))
