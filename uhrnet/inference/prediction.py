"""Prediction: running a trained model on images of any size (:func:`predict_labels`, which evaluation
and the sim-to-real experiment use too), and ``uhrnet.predict(PredictConfig(...))``, which turns fringe
image files into height maps (mm), colour previews and point clouds; ``uhrnet predict`` calls it.

Inputs (:func:`read_inputs`): 8-bit (or 16-bit) grey PNG/TIFF/BMP/JPEG images, or ``.npy`` arrays in the
dataset encoding (intensity / 127.5 - 1, shapes (H, W), (H, W, 1), (N, H, W) or (N, H, W, 1)), folders of
them, figshare folders (``f1_80.npy`` + ``Z.npy`` or ``fringe_pattern.npy`` + ``height_map.npy``: only the
fringes are read, named ``<folder>_<index>``) and phase-shifting folders (``PSin/ PCos/ Fringe/ iPattern/``:
the ``iPattern`` single-shot images, named ``<folder>_<id>``). For every image ``NAME`` it writes to ``out``:

* ``NAME_height.npy`` and ``NAME_height.tif``: float32 height above the reference plane in mm
  (label transform of the checkpoint: ``(label - plane_offset) / units_per_mm``), NaN where invalid;
* ``NAME_height.png``: colour-mapped preview (invalid pixels grey);
* ``NAME.ply``: binary point cloud of the valid pixels, grey from the fringe. With ``--rig`` the points
  are the camera rays of the calibrated rig (``fppsim.geometry.rig``) cut at the predicted height, in world
  millimetres; without it x, y are the pixel grid (times ``--pixel-size`` mm, y pointing up).

With a rig (``rig``, ``--rig``) the heights are then made to agree with the image's own fringe phase
(:func:`fppsim.phase.single_shot.single_shot_phase`) through it: ``refine="auto"`` (the default) does so when a rig
is given, ``"phase"`` always (the rig: ``rig``, else the checkpoint's own, else fppsim's default), ``None`` never.
``refine_method="orders"`` (default, :func:`order_choice`): every phase region at one whole fringe order chosen
for the image at once, its level and relief from the phase, and the rims between objects and the plane split by
the plane's own fringe (:mod:`uhrnet.physics.rims`); a region whose order the path cannot decide keeps the
network's own heights, as every pixel the path leaves alone does (a warning says how many); ``"relief"``
(:func:`uhrnet.physics.refine.refine_relief`): the relief from the phase, the level from the network.
The path starts from the mean of the network's heights on the image and on the image mirrored along its fringes
(:func:`path_estimate`; two passes of the network, each with a mirrored margin past the image's borders).
``NAME_height.*`` is then the refined map, ``NAME_height_network.npy`` the network's own (one pass), and
``refine.json`` lists per image the share of pixels moved and, for ``orders``, every region's order, confidence
and whether it was decided (:attr:`PredictResult.refine`; an earlier call's images into the same folder keep
their entries, an image predicted again without refinement loses its entry and network copy). Under ``auto`` an image without a readable fringe phase, or whose fringes are not the rig's
(:func:`fringe_phase`), keeps the network's heights with a warning; under ``"phase"`` it is an error naming it,
after the images before it were written whole. An image that reads turned against the rig (rotated 180 degrees or
mirrored across its fringes: its relief below the reference plane, :func:`uhrnet.physics.orientation.check_orientation`
from its phase and the rig alone) gets a one-line warning and its check in ``refine.json``; its heights are not
changed. The TIFF, preview and point cloud writers are :mod:`uhrnet.inference.outputs`.

A pixel is invalid when the predicted label is at or below the transform's invalid threshold or the
input is black (intensity 0, the dataset's marker of shadow); ``--keep-all`` keeps every pixel. A
prediction without any valid pixel is written and reported in :attr:`PredictResult.warnings`.

Inputs must be at least ``MIN_SIDE`` x ``MIN_SIDE`` pixels (the networks pool four times). Colour
images are accepted when they show a grey scene (channels equal within a few gray levels): they are
converted to their luminance, which for equal channels is exactly the grey image; other colour
images are refused (see :func:`fppsim.dataio.encoding.colour_to_grey`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from fppsim.dataio.encoding import as_image_stack, encode_fringe, json_default, load_npy
from fppsim.files import atomic_path, atomic_write_text, json_text
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.data.datasets import parse_size
from fppsim.dataio.readers import IMAGE_EXTS, PSPMatError, open_source, read_fringe_image, skipped_note, warn_skipped
from fppsim.geometry.rig import Rig, RigError, check_image_size, load_rig
from uhrnet.device import select_device
from uhrnet.inference.outputs import points_from_grid, points_from_rig, write_ply, write_preview, write_tiff
from uhrnet.errors import ConfigError, DataError, UsageError
from uhrnet.models import HEADS, prediction_of
from uhrnet.physics.orders import choose_orders
from uhrnet.physics.orientation import check_orientation, flipped_warning, lean_warning, plane_lean
from uhrnet.physics.refine import REFINE_METHODS, layer_for, refine_relief
from uhrnet.physics.rig_layer import RigLayer
from uhrnet.run_folder import refuse_own_source
from fppsim.owned import claim, output_folder, owners, remove_own, stamp
from fppsim.dataio.rig_choice import resolve_rig
from fppsim.phase.fringe_axis import fringe_axis, local_carrier, oriented_single_shot_phase, rig_phase_gradient

__all__ = ["PredictConfig", "PredictResult", "predict", "predict_labels", "network_heights", "label_heights",
           "labels_at_input_size", "pad_to_multiple", "collect_inputs", "load_inputs", "read_inputs", "refine_rig_for",
           "refine_with_phase", "fringe_phase", "fringe_mirror_axis", "path_estimate", "order_choice", "points_from_rig",
           "points_from_grid", "write_ply", "shape_note", "NO_RIG_HINT"]

INPUT_EXTS = IMAGE_EXTS + (".npy",)  # the image files fppsim reads, and dataset-encoded arrays
PREDICT_TOOL = "uhrnet predict"
PATH_MARGIN_PX = 16  # path_estimate's mirrored margin (network px); 8-32 score alike on the pair
MIN_SIDE = 16  # 2**4: the networks' four 2x2 poolings need at least one pixel at the bottom level


def pad_to_multiple(x: torch.Tensor, multiple: int = 16) -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad ``(N, C, H, W)`` at the bottom/right (edge replication) to multiples of ``multiple``;
    returns the padded tensor and the original ``(H, W)``."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (h, w)


@torch.no_grad()
def predict_labels(model: torch.nn.Module, fringe: torch.Tensor, size: tuple[int, int] | None = None,
                   amp: bool = False, margin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Labels ``(N, 1, H, W)`` float32 for fringes ``(N, 1, H, W)`` in [-1, 1], at the input's own size
    (:func:`labels_at_input_size`); ``model`` (a model in label units,
    :func:`uhrnet.checkpoint.model_from_checkpoint`) is put in eval mode."""
    model.eval()
    return labels_at_input_size(model, fringe, size, amp, margin)


def network_heights(model: torch.nn.Module, transform, fringe: np.ndarray, size: tuple[int, int] | None = None,
                    keep_all: bool = False) -> np.ndarray:
    """The network's single pass in mm, as ``uhrnet predict`` writes it: (H, W) float64 of a dataset-encoded
    ``fringe`` (float, -1 = black), NaN where the label is invalid or the input black (``keep_all``: nowhere)."""
    x = torch.from_numpy(np.asarray(fringe, np.float32))[None, None]
    return label_heights(predict_labels(model, x, size)[0, 0].cpu().numpy(), transform, fringe, keep_all)


def label_heights(label: np.ndarray, transform, fringe: np.ndarray, keep_all: bool = False) -> np.ndarray:
    """Predicted ``label`` (H, W) in mm, float64: NaN where the label is invalid (``transform.valid``) or the
    dataset-encoded ``fringe`` black (-1) (``keep_all``: nowhere)."""
    height = transform.height_mm(np.asarray(label, np.float64))
    if keep_all:
        return height
    # validity on the label as given (a float32 label compares with the threshold in float32, as predict always did)
    return np.where(np.asarray(transform.valid(label)) & (np.asarray(fringe) > -1 + 1e-6), height, np.nan)


def labels_at_input_size(model: torch.nn.Module, fringe: torch.Tensor, size: tuple[int, int] | None = None,
                         amp: bool = False, margin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """THE image-size rule of every use of a model on whole images (predict, evaluate, adapt; differentiable):
    ``size``: run the network at this (H, W) (the ``--resize`` a model was trained with) and resample the
    prediction back; sides that are not multiples of 16 are padded (edge replication) and cropped back.
    ``margin``: (rows, columns) px mirrored out from each border at the network's size before that, and
    cropped back (:func:`path_estimate`: objects cut by the image's border continue past it).
    ``amp``: autocast (fp16 on CUDA, bf16 on CPU). Returns ``(N, 1, H, W)`` float32 at the input's size."""
    device = next(model.parameters()).device
    x = fringe.to(device, torch.float32)
    h, w = x.shape[-2:]
    if size is not None and tuple(size) != (h, w):
        x = F.interpolate(x, size=tuple(size), mode="area")
    my, mx = (min(int(m), n - 1) for m, n in zip(margin, x.shape[-2:]))  # reflection needs margin < side
    if my or mx:
        x = F.pad(x, (mx, mx, my, my), mode="reflect")
    x, (hh, ww) = pad_to_multiple(x)
    ctx = torch.autocast(device.type, dtype=torch.float16 if device.type == "cuda" else torch.bfloat16) \
        if amp else torch.autocast(device.type, enabled=False)
    with ctx:
        out = model(x)
    out = prediction_of(out).float()[..., my:hh - my, mx:ww - mx]
    if out.shape[-2:] != (h, w):
        out = F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False)
    return out


@dataclass
class PredictConfig:
    """What to predict. ``inputs``: image/.npy files or folders of them. ``rig``: calibration file for
    metric x, y in the point clouds (else the pixel grid times ``pixel_size`` mm). ``keep_all``: no
    invalid masking. ``range``: (lo, hi) colour range of the PNG in mm (default 1st-99th percentile).
    ``ply``: also write point clouds. Checks itself on construction (:class:`ConfigError`)."""

    checkpoint: str | Path
    inputs: Sequence[str | Path]
    out: str | Path
    rig: str | Path | None = None
    pixel_size: float = 1.0
    keep_all: bool = False
    range: tuple[float, float] | None = None
    colormap: str = "viridis"
    ply: bool = True
    device: str = "auto"
    progress: bool = True
    refine: str | None = None  # "phase", None, or "auto": "phase" when a rig is given
    refine_method: str = "orders"

    def __post_init__(self):
        if isinstance(self.inputs, (str, Path)):
            self.inputs = [self.inputs]
        if self.refine not in (None, "none", "phase", "auto"):
            raise UsageError(f"--refine must be auto, phase or none, got {self.refine!r}")

        if self.refine_method not in REFINE_METHODS:
            raise UsageError(f"--refine-method must be one of {', '.join(REFINE_METHODS)}, got {self.refine_method!r}")
        if not (self.pixel_size > 0 and np.isfinite(self.pixel_size)):
            raise UsageError(f"--pixel-size must be a finite spacing > 0 mm, got {self.pixel_size:g}")
        if self.range is not None and not (np.isfinite(self.range).all() and self.range[0] < self.range[1]):
            raise UsageError(f"--range: expected LO < HI (mm), got {self.range[0]:g} {self.range[1]:g}")
        if self.colormap not in __import__("matplotlib").colormaps:
            raise UsageError(f"--colormap: unknown matplotlib colour map {self.colormap!r}")


@dataclass
class PredictResult:
    """Input files read, the output name of every height map written (``<out>/<name>_height.npy``) and
    one line per suspicious result (e.g. no valid pixel at all)."""

    files: list[Path] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    refine: dict[str, dict] = field(default_factory=dict)  # name -> refine statistics (--refine phase)


def collect_inputs(items: list[str]) -> list[Path]:
    """The input files of ``items`` (files, and folders of them), each once; a folder's files that
    ``uhrnet predict`` wrote itself (its ownership record says so) are outputs, not inputs."""
    files: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            mine = {n for n, tool in (owners(p) or {}).items() if tool == PREDICT_TOOL}
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in INPUT_EXTS
                           and q.name not in mine)
            if not found:
                mat = open_source(p.parent).is_psp and any(q.suffix.lower() == ".mat" for q in p.iterdir())
                raise ConfigError(f"{p}: no images ({', '.join(INPUT_EXTS)}) in this folder" + (
                    f"; a phase-shifting folder is read from its root, the folder holding iPattern/ ({p.parent})"
                    if mat else "") + skipped_note(p, INPUT_EXTS))
            warn_skipped(p, INPUT_EXTS)
            files += found
        elif p.is_file():
            if p.suffix.lower() not in INPUT_EXTS:
                raise ConfigError(f"{p}: unsupported input type (use {', '.join(INPUT_EXTS)})")
            files.append(p)
        else:
            raise ConfigError(f"{p}: input not found")
    seen: set[Path] = set()
    files = [f for f in files if not (f.resolve() in seen or seen.add(f.resolve()))]  # a file named twice: once
    return files


def read_inputs(items: Sequence[str | Path], with_paths: bool = False, renamed: dict | None = None,
                notes: list | None = None) -> list[tuple]:
    """Every fringe image of ``items`` as ``[(name, fringe float32 (H, W) in [-1, 1]), ...]``: image and
    ``.npy`` files, folders of them, figshare folders (fringes only: labels are never read) and
    phase-shifting folders (their ``iPattern`` images); see the module docstring. Names are unique (a
    repeated name gets its folder's name in front, then a number). ``with_paths``: ``(name, fringe, path)``;
    ``renamed`` (a dict) gets ``{new name: (name it had, path)}`` for each of those; ``notes`` (a list), the
    lines of :func:`load_inputs`."""

    out: list[tuple[str, np.ndarray]] = []
    seen: set[Path] = set()
    for item in items:
        src = open_source(item)
        if src.plain_files:  # image and .npy files, folders of them: predict's own file rules
            for path in collect_inputs([str(item)]):
                if path.resolve() not in seen:  # a file named twice is read once
                    seen.add(path.resolve())
                    out += [(name, fringe, path) for name, fringe in load_inputs(path, notes)]
            continue
        try:
            for k, (name, fringe, path) in enumerate(src.inputs()):
                out.append((name, _checked(fringe, path, k), path))
        except PSPMatError as exc:
            raise DataError(str(exc)) from None
    names: set[str] = set()
    unique = []
    for name, fringe, path in out:
        given = name
        if name in names:  # same stem in two folders (e.g. <id>/fringe.png of a native dataset)
            name = f"{path.parent.name}_{name}"
        base, k = name, 1
        while name in names:
            k += 1
            name = f"{base}_{k}"
        names.add(name)
        if renamed is not None and name != given:
            renamed[name] = (given, path)
        unique.append((name, fringe, path) if with_paths else (name, fringe))
    return unique


def _checked(img, path: Path, k: int) -> np.ndarray:
    img = np.array(img, dtype=np.float32)
    if not np.isfinite(img).all():
        raise DataError(f"{path}: image {k} contains NaN/inf")
    lo, hi = float(img.min()), float(img.max())
    if lo < -1.001 or hi > 1.001:
        raise DataError(f"{path}: values span [{lo:g}, {hi:g}]; expected the dataset encoding "
                        "intensity / 127.5 - 1 in [-1, 1]")
    return img


def load_inputs(path: Path, notes: list | None = None) -> list[tuple[str, np.ndarray]]:
    """``[(name, fringe float32 (H, W) in [-1, 1]), ...]`` for one input file; ``notes`` (a list) gets a line for
    each float frame of a ``.npy`` with no value below 0 (likely scaled to [0, 1], not the encoding)."""
    if path.suffix.lower() != ".npy":
        return [(path.stem, read_fringe_image(path))]
    arr = as_image_stack(load_npy(path), path)
    floats = arr.dtype != np.uint8  # (a uint8 file cannot be a [0, 1] image)
    if not floats:
        arr = encode_fringe(arr)
    elif not np.issubdtype(arr.dtype, np.floating):
        raise DataError(f"{path}: dtype {arr.dtype}; expected float (intensity / 127.5 - 1) or uint8")
    frames = [(path.stem if arr.shape[0] == 1 else f"{path.stem}_{k:04d}", _checked(arr[k], path, k))
              for k in range(arr.shape[0])]
    if notes is not None and floats:  # fringes swing both ways: in the encoding their dark half is below 0
        for name, f in frames:
            lo, hi = float(f.min()), float(f.max())
            if 0.0 <= lo < hi <= 1.0:
                notes.append(f"{path} ({name}): values span [{lo:.3g}, {hi:.3g}], none below 0: if it was scaled to "
                             "[0, 1], it is read wrong (the encoding is intensity / 127.5 - 1 in [-1, 1]: 2 x - 1)")
    return frames


def predict(config: PredictConfig) -> PredictResult:
    """Predict every input of ``config`` and write its files (see the module docstring)."""
    from tqdm import tqdm

    # a run folder holds the run's files and record, not predictions (adapt refuses its source's folder too)
    refuse_own_source(Path(config.out), config.checkpoint, "CKPT", "predict's files would mix with the run's", True)
    renamed, notes = {}, []
    inputs = read_inputs(config.inputs, with_paths=True, renamed=renamed, notes=notes)
    ckpt = load_checkpoint(config.checkpoint)
    device = select_device(config.device)
    model, transform = model_from_checkpoint(ckpt, device)
    size = parse_size(ckpt.get("args", {}).get("resize"))
    rig = None
    if config.rig:
        try:
            rig = load_rig(config.rig)
        except RigError as exc:
            raise ConfigError(str(exc)) from None
    refine_rig, rig_name = None, ""
    auto = config.refine == "auto"
    if config.refine == "phase" or (auto and config.rig):
        refine_rig, rig_name = refine_rig_for(ckpt, rig, config.rig)
    head_rig = ckpt["model"]["config"].get("rig") if HEADS[ckpt["model"]["config"].get("head", "height")].needs_rig else None
    checks = [(head_rig, "the checkpoint's phase head sees", " (its rig's camera)"),
              (rig if config.ply else None, f"the rig camera ({config.rig}) is", ""),
              (refine_rig, f"the rig used by --refine ({rig_name}) sees",
               "" if config.rig else NO_RIG_HINT)]
    for name, fringe, path in inputs:  # every size is checked before anything is written
        if min(fringe.shape) < MIN_SIDE:
            raise ConfigError(f"{path}: image is {fringe.shape[1]}x{fringe.shape[0]}; the model needs at least "
                              f"{MIN_SIDE}x{MIN_SIDE} pixels")
        for seen_by, who, hint in checks:
            if seen_by is not None:
                check_image_size(seen_by, fringe.shape, str(path), who=who, hint=hint, error=ConfigError)
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a folder")
    names = [f"{name}{suffix}" for name, _, _ in inputs for suffix in
             ("_height.npy", "_height.tif", "_height.png")
             + ((".ply",) if config.ply else ()) + (("_height_network.npy",) if refine_rig is not None else ())]
    result = PredictResult(files=sorted({p for _, _, p in inputs}))
    result.warnings += notes + [f"{path}: written as {name}_* (another input is also named {given})"
                                for name, (given, path) in renamed.items()]
    for name, fringe, path in inputs:
        note = shape_note(ckpt, fringe.shape)
        if note:
            result.warnings.append(f"{path} ({name}): {note}")
    # locked for the run; a failed run drops its claims on what it never wrote, and a folder it made and left empty
    with output_folder(out, PREDICT_TOOL, error=ConfigError):
        claim(out, PREDICT_TOOL, names + (["refine.json"] if refine_rig is not None else []))  # never a foreign file
        try:
            for name, fringe, path in tqdm(inputs, desc="predict", unit="image",
                                           disable=not config.progress or len(inputs) < 2):
                _predict_one(config, model, transform, size, rig, refine_rig, rig_name, auto, out, result, name,
                             fringe, path)
        finally:  # what was done is described, also when a later image fails
            _write_refine_json(out, result.refine, [] if refine_rig is not None else result.names)
    return result


NO_RIG_HINT = ": give --rig with your rig's file (e.g. fit-rig's rig.json)"
"""How a size refusal of ``--refine phase`` ends when no ``--rig`` was given (predict, evaluate-phase)."""


def shape_note(ckpt: dict, shape) -> str | None:
    """A warning when an image of ``shape`` (H, W) is not shaped like the images ``ckpt`` was trained on (aspect
    ratio more than 15 % off: another rig's, a rotated or a cropped image, which the network would read squashed;
    or, for a network trained without ``--resize``, a size more than 15 % off: the same view at another size brings
    its fringes to the network at another period in px; a crop would not), else None (also for an adapted network:
    its record is its source's)."""
    trained = ckpt.get("image_shape")
    if ckpt.get("adapt") or not trained or len(trained) != 2 or min(trained) <= 0 or min(shape) <= 0:
        return None
    a0, a = trained[1] / trained[0], shape[1] / shape[0]
    resized = bool(ckpt.get("args", {}).get("resize"))
    if abs(math.log(a / a0)) <= math.log(1.15):
        scale = math.sqrt(shape[0] * shape[1] / (trained[0] * trained[1]))
        if resized or abs(math.log(scale)) <= math.log(1.15):  # with --resize every image reaches it at one size
            return None
        return (f"{shape[1]}x{shape[0]} px but the network was trained on {trained[1]}x{trained[0]} px images at their "
                f"own size: if it shows the view they did, it sees the fringes {scale:.2f} x as far apart as it "
                "learned them (another rig's or a rescaled image?): its heights may mean little")
    how = " (after its --resize)" if resized else ""
    return (f"{shape[1]}x{shape[0]} px (aspect {a:.2f}) but the network was trained on {trained[1]}x{trained[0]} px "
            f"images{how} (aspect {a0:.2f}): another rig's, a rotated or a cropped image? its heights may mean little")


def _predict_one(config, model, transform, size, rig, refine_rig, rig_name, auto, out, result, name, fringe, path):
    """One image of :func:`predict`: its heights, refined through ``refine_rig`` (if any), and its files; every file
    of the image is written after its refinement succeeded (an error leaves none of them)."""
    height = network_heights(model, transform, fringe, size, config.keep_all).astype(np.float32)
    if not np.isfinite(height).any():
        result.warnings.append(
            f"{path} ({name}): no valid pixel in the prediction (every label at or below "
            f"{transform.invalid_threshold:g}, or a black input); is this a fringe image like the training data?")
    elif config.keep_all and not (np.asarray(fringe) > -1.0).any():  # kept, but nothing in it was seen
        result.warnings.append(f"{path} ({name}): the input is black everywhere; --keep-all kept the network's "
                               "heights, which no fringe informs")
    network = height
    if refine_rig is not None:
        try:
            estimate = path_estimate(model, transform, fringe, size, refine_rig, height)
            height, stats = refine_with_phase(estimate, fringe, refine_rig, config.refine_method, network_mm=height,
                                              name=str(path))
        except DataError as exc:
            if not auto:
                raise
            # the default path: an image whose phase cannot be read keeps the network's heights, and says so
            reason = str(exc).removeprefix(f"{path}: ")
            stats = {"method": "none", "moved_fraction": 0.0, "mean_abs_move_mm": 0.0, "offset_rad": 0.0,
                     "undecided_regions": 0, "error": reason}
            result.warnings.append(f"{path} ({name}): no fringe phase to refine with ({reason}): the network's heights")
        if stats.get("regions", 1) == 0:
            result.warnings.append(f"{path} ({name}): no phase region of reliable fringes: the network's heights")
        flipped = flipped_warning(stats.get("orientation"), rig_name)
        for said in (flipped, lean_warning(stats, rig_name)):  # said, never acted on: the heights stay the path's
            if said:
                result.warnings.append(f"{path} ({name}): {said}")
        undecided = stats.get("undecided_regions", 0)
        if undecided:
            result.warnings.append(
                f"{path} ({name}): {undecided} phase region(s), {stats['undecided_fraction']:.1%} of the pixels, "
                "have no fringe order the path can decide: the network's heights stay there")
        with atomic_path(out / f"{name}_height_network.npy") as tmp, open(tmp, "wb") as fh:
            np.save(fh, network)
        stamp(out, [f"{name}_height_network.npy"])  # remove_own spares it once someone else replaces it
        result.refine[name] = {**stats, "rig": rig_name}
    with atomic_path(out / f"{name}_height.npy") as tmp, open(tmp, "wb") as fh:
        np.save(fh, height)
    write_tiff(out / f"{name}_height.tif", height)
    write_preview(out / f"{name}_height.png", height, config.colormap, config.range)
    if config.ply:
        pts = points_from_rig(rig, height) if rig is not None else points_from_grid(height, config.pixel_size)
        grey = np.clip((fringe + 1) * 127.5, 0, 255).round()
        write_ply(out / f"{name}.ply", pts, grey)
    result.names.append(name)


def _write_refine_json(out: Path, refine: dict, unrefined: list[str]) -> None:
    """``refine`` merged into ``out/refine.json`` (predict claims it when it refines): the images of an earlier call
    into the same folder keep their entries, an image predicted again gets its new one, or none when it was
    predicted again without refinement (``unrefined``: its entry and its ``NAME_height_network.npy`` of then
    described a map no longer there; that file goes only if predict wrote it)."""
    remove_own(out, PREDICT_TOOL, [f"{name}_height_network.npy" for name in unrefined])
    path = out / "refine.json"
    if (owners(out) or {}).get("refine.json") != PREDICT_TOOL:
        return  # none, or someone else's: left alone
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        old = {}
    old = old if isinstance(old, dict) else {}
    merged = {k: v for k, v in {**old, **refine}.items() if k not in unrefined}
    if not merged:
        remove_own(out, PREDICT_TOOL, ["refine.json"])  # as a folder predicted without refinement: no refine.json
    elif refine or len(merged) < len(old):
        atomic_write_text(path, json_text(merged, indent=2, default=json_default))
        stamp(out, ["refine.json"])


def refine_rig_for(ckpt: dict, rig=None, rig_path=None):
    """The rig ``--refine`` uses and its name: ``rig`` (``--rig``: a loaded rig named ``rig_path``, or a
    file), else the checkpoint's own (physics head or an adaptation's), else fppsim's default rig
    (:func:`fppsim.dataio.rig_choice.resolve_rig`)."""

    own = ckpt["model"]["config"].get("rig") or ckpt.get("adapt", {}).get("rig")
    return resolve_rig(rig, name=None if rig_path is None else str(rig_path), checkpoint_rig=own,
                       checkpoint=ckpt.get("path", "the checkpoint"))


def fringe_phase(fringe: np.ndarray, rig, name: str = "image"):
    """The single-shot phase of ``fringe`` (dataset encoding) in the rig's direction: the phase must grow
    along the camera rows (vertical fringes) or down the columns (horizontal fringes: a projector above or
    below the camera) as the rig's reference-plane phase does (:func:`fppsim.phase.single_shot.single_shot_phase`
    cannot tell the two directions apart from one image). :class:`DataError` for a frame without fringes, or
    whose fringes are not the rig's (period or direction at the image centre: :data:`CARRIER_PERIOD_RATIO`,
    :data:`CARRIER_ANGLE_DEG`, in an image of at least :data:`CARRIER_MIN_PERIODS` periods both ways, half of it
    with fringes, through a rig with the plane in view; otherwise the direction alone, from the phase's own steps:
    :data:`CARRIER_MIN_VOTES`)."""

    r = rig if isinstance(rig, Rig) else Rig.from_dict(rig)
    gradient = rig_phase_gradient(r)
    orientation, direction = _fringes_along(gradient)
    try:
        ssp = oriented_single_shot_phase(fringe, orientation, direction=direction)
    except ValueError as exc:
        raise DataError(f"{name}: {exc}") from None
    if r.plane_in_view and ssp.valid.mean() >= 0.5:
        _check_carrier(ssp, gradient, name)
    else:  # objects on black, or mostly dark: the spectrum's peak is the envelope's, the phase's own steps are not
        _check_carrier(ssp, gradient, name, local=True)
    return ssp


#: The image's fringes must match the rig's at the image centre: period within this ratio either way, direction
#: within this angle, checked where the image spans at least :data:`CARRIER_MIN_PERIODS` of the rig's periods both
#: ways (a smaller one's spectrum is too coarse, and its relief can move the peak) and at least half of it carries
#: fringes, through a rig with a plane in view (objects on black move the peak: FP672 on black, 40 px against the
#: plane's 10.5). The rigs here match their frames within 0.97-1.08 and 0.3 deg (the pair, FP1523, FP672, FP147,
#: FP1523 without its plane, rendered samples); an image of another rig, rotated or rescaled, gave heights
#: thousands of mm off without a word.
CARRIER_PERIOD_RATIO = 1.5
CARRIER_ANGLE_DEG = 20.0
CARRIER_MIN_PERIODS = 16
#: Through a rig without a plane in view, or in an image less than half lit, the DIRECTION alone is checked, from the
#: wrapped phase's own steps (:func:`~fppsim.phase.fringe_axis.local_carrier`), where at least this share of the
#: pixels votes. The period is not: the phase is demodulated around the spectrum's peak, and where that is the
#: objects' envelope the steps read its period too (FP672 on black 35-37 px against 10.5, its axis 8-12 deg off).
#: The frames without a plane here (11-41 % voting) read within 3 deg of their rigs; an image with fringes across
#: the rig's (79-90 deg off) once gave heights hundreds of mm off there without a word. One zoomed 2x is not caught,
#: nor one where fewer vote (FP672 on black under most masks: 0.2-1 %); the :data:`CARRIER_MIN_PERIODS` gate holds.
CARRIER_MIN_VOTES = 0.01


def _check_carrier(ssp, gradient: tuple[float, float], name: str, local: bool = False) -> None:
    """:class:`DataError` naming both when the fringes the image shows (``ssp.period``, ``ssp.carrier``; with
    ``local``, :func:`~fppsim.phase.fringe_axis.local_carrier` of its reliable phase, skipped below a share
    :data:`CARRIER_MIN_VOTES` of the pixels) are not the rig's (``gradient``: its reference-plane phase gradient
    at the image centre, rad/px)."""
    gu, gv = gradient
    g = float(np.hypot(gu, gv))
    fx, fy = ssp.carrier
    shown, tilt = ssp.period, math.degrees(math.atan(-fy / fx)) if fx else 90.0  # lines from the image's vertical
    if local:
        shown, axis, votes = local_carrier(ssp.wrapped, ssp.reliability)
        if votes < CARRIER_MIN_VOTES * ssp.wrapped.size or not np.isfinite(axis):
            return
        fx, fy, tilt = math.cos(axis), math.sin(axis), 0.0 - math.degrees(axis)  # tilt: the lines from vertical
    f = float(np.hypot(fx, fy))
    period = 2 * np.pi / g
    if min(ssp.wrapped.shape) < CARRIER_MIN_PERIODS * period:
        return
    angle = float(np.degrees(np.arccos(min(1.0, abs(fx * gu + fy * gv) / (f * g)))))
    ratio = 1.0 if local else shown / period  # (the local period is the demodulation's: not checked)
    if angle > CARRIER_ANGLE_DEG or not 1 / CARRIER_PERIOD_RATIO <= ratio <= CARRIER_PERIOD_RATIO:
        raise DataError(f"{name}: its fringes run every {shown:.1f} px at {tilt:+.0f} deg, the rig's every "
                        f"{period:.1f} px {fringe_axis((gu, gv))} ({angle:.0f} deg apart): not an image of this rig "
                        "(another rig, a rotated or rescaled image, or no fringes)")


def _rig_fringes(rig) -> tuple[str, int]:
    """(``"vertical"`` or ``"horizontal"``, +1 / -1: the phase grows along +columns / +rows or against them)
    from the plane phase's gradient at the image centre: a few points of the forward model, no layer."""
    return _fringes_along(rig_phase_gradient(rig if isinstance(rig, Rig) else Rig.from_dict(rig)))


def _fringes_along(gradient) -> tuple[str, int]:
    """:func:`_rig_fringes` of the plane phase's gradient ``(g_u, g_v)`` (rad/px)."""
    gu, gv = gradient
    orientation = fringe_axis((gu, gv))
    return orientation, 1 if (gu if orientation == "vertical" else gv) >= 0 else -1


def fringe_mirror_axis(rig) -> int:
    """The image axis that runs along the rig's fringes: -2 (rows are mirrored) for vertical fringes, -1 for
    horizontal ones. An image mirrored along it keeps every fringe's phase and the direction the phase grows
    in, i.e. it is the image of a mirrored scene through the same kind of rig, so the network may be asked
    about it too. Averaging both answers (:func:`path_estimate`) is the estimate the phase path starts from:
    on the labelled pair 4.17 -> 3.99 mm object RMSE and on FP1523/1201 0.86 -> 0.83 of the network's residual
    (3 seeds, every seed lower; docs/experiments/orders.md)."""
    return -2 if _rig_fringes(rig)[0] == "vertical" else -1


def path_estimate(model: torch.nn.Module, transform, fringe: np.ndarray, size, rig, network_mm: np.ndarray,
                  amp: bool = False) -> np.ndarray:
    """Heights (mm, float64 (H, W)) the phase path starts from: the mean of the network's heights on ``fringe``
    (dataset encoding, at ``size``) and on ``fringe`` mirrored along the rig's fringes
    (:func:`fringe_mirror_axis`), mirrored back. Both passes see the image continued by
    :data:`PATH_MARGIN_PX` mirrored pixels past the two borders the fringes run into (there the mirror image
    continues every fringe), so that an object the border cuts is not read as ending there: on the labelled
    pair, whose bust is cut by the bottom border, the network alone was up to 21 mm low in the last rows. A
    model holding a rig layer (the phase head) sees its camera's grid only and gets no margin.
    NaN where ``network_mm`` (the network's own map) is."""
    axis = fringe_mirror_axis(rig)
    margin = (PATH_MARGIN_PX, 0) if axis == -2 else (0, PATH_MARGIN_PX)
    if any(isinstance(m, RigLayer) for m in model.modules()):  # a head with a rig layer sees its camera's grid only
        margin = (0, 0)
    x = torch.from_numpy(np.ascontiguousarray(fringe, np.float32))[None, None]
    passes = (predict_labels(model, x, size, amp, margin),
              torch.flip(predict_labels(model, torch.flip(x, [axis]), size, amp, margin), [axis]))
    h = sum(transform.height_mm(p[0, 0].cpu().numpy().astype(np.float64)) for p in passes) / 2.0
    return np.where(np.isfinite(network_mm), h, np.nan)


def order_choice(height_mm: np.ndarray, fringe: np.ndarray, rig, network_mm: np.ndarray | None = None,
                 name: str = "image", phase=None):
    """THE orders path on one image (:func:`uhrnet.physics.orders.choose_orders` with the rim split): every phase
    region of ``fringe`` (dataset encoding) at one order, from the estimate ``height_mm`` (mm, NaN = none)
    through ``rig``; the pixels it leaves alone keep ``network_mm`` (the network's own map; default the
    estimate); ``phase``: the image's :func:`fringe_phase` when already read. Returns the
    :class:`~uhrnet.physics.orders.OrderChoice`."""
    ssp = fringe_phase(fringe, rig, name) if phase is None else phase
    return choose_orders(height_mm, ssp.wrapped, ssp.reliability, layer_for(rig, np.shape(height_mm)),
                         valid=np.isfinite(height_mm) & ssp.valid, shadow=~ssp.valid,
                         fringe=(np.asarray(fringe, np.float64), ssp.background, ssp.modulation), keep=network_mm)


def refine_with_phase(height_mm: np.ndarray, fringe: np.ndarray, rig, method: str = "relief",
                      network_mm: np.ndarray | None = None, name: str = "image") -> tuple[np.ndarray, dict]:
    """``height_mm`` (H, W) moved to agree with the single-shot phase of ``fringe`` (dataset encoding)
    through ``rig`` (module docstring); returns the refined map (NaN kept) and the statistics. With ``orders``
    the pixels the path leaves alone keep ``network_mm`` (default ``height_mm``); ``name`` heads its errors. The
    statistics also say whether the image reads flipped through the rig (``orientation``:
    :func:`uhrnet.physics.orientation.check_orientation`, from the image's phase and the rig alone) and, with
    ``orders``, how far the plane it reads leans against the estimate's (``plane_lean``:
    :func:`uhrnet.physics.orientation.plane_lean`); neither changes a height."""

    ssp = fringe_phase(fringe, rig, name)
    r = rig if isinstance(rig, Rig) else Rig.from_dict(rig)
    if method == "orders":
        choice = order_choice(height_mm, fringe, rig, network_mm, name, phase=ssp)
        refined, stats = choice.height, {**choice.stats, "per_region": [asdict(reg) for reg in choice.regions]}
        stats["plane_lean"] = plane_lean(choice.height, choice.moved, height_mm, r)
    else:
        refined, _, stats = refine_relief(height_mm, ssp.wrapped, ssp.reliability, rig,
                                          valid=np.isfinite(height_mm) & ssp.valid)
    stats["orientation"] = check_orientation(ssp.wrapped, ssp.reliability, ssp.valid, r).to_dict()
    refined = np.where(np.isfinite(height_mm), refined, np.nan).astype(np.float32)
    return refined, stats
