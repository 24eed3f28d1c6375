"""Prediction: ``uhrnet.predict(PredictConfig(...))`` turns fringe images into height maps (mm), colour
previews and point clouds; ``uhrnet predict`` calls it.

Inputs: 8-bit (or 16-bit) grey PNG/TIFF/BMP/JPEG images, or ``.npy`` arrays in the dataset encoding
(intensity / 127.5 - 1, shapes (H, W), (H, W, 1), (N, H, W) or (N, H, W, 1)), or folders of them.
For every image ``NAME`` it writes to ``out``:

* ``NAME_height.npy`` and ``NAME_height.tif``: float32 height above the reference plane in mm
  (label transform of the checkpoint: ``(label - plane_offset) / units_per_mm``), NaN where invalid;
* ``NAME_height.png``: colour-mapped preview (invalid pixels grey);
* ``NAME.ply``: binary point cloud of the valid pixels, grey from the fringe. With ``--rig`` the points
  are the camera rays of the calibrated rig (``fppsim.rig``) cut at the predicted height, in world
  millimetres; without it x, y are the pixel grid (times ``--pixel-size`` mm, y pointing up).

A pixel is invalid when the predicted label is at or below the transform's invalid threshold or the
input is black (intensity 0, the dataset's marker of shadow); ``--keep-all`` keeps every pixel. A
prediction without any valid pixel is written and reported in :attr:`PredictResult.warnings`.

Inputs must be at least ``MIN_SIDE`` x ``MIN_SIDE`` pixels (the networks pool four times). Colour
images are accepted when they show a grey scene (channels equal within a few gray levels): they are
converted to their luminance, which for equal channels is exactly the grey image; other colour
images are refused (see :func:`fppsim.formats.colour_to_grey`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from fppsim.formats import as_image_stack, atomic_path, encode_fringe
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.data import parse_size
from uhrnet.reading import read_fringe_image
from uhrnet.device import select_device
from uhrnet.errors import ConfigError, DataError, UsageError

__all__ = ["PredictConfig", "PredictResult", "predict", "collect_inputs", "load_inputs", "points_from_rig",
           "points_from_grid", "write_ply"]

IMAGE_EXTS = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
INPUT_EXTS = IMAGE_EXTS + (".npy",)
MIN_SIDE = 16  # 2**4: the networks' four 2x2 poolings need at least one pixel at the bottom level


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

    def __post_init__(self):
        if isinstance(self.inputs, (str, Path)):
            self.inputs = [self.inputs]
        if not (self.pixel_size > 0 and np.isfinite(self.pixel_size)):
            raise UsageError(f"--pixel-size must be a finite spacing > 0 mm, got {self.pixel_size:g}")
        if self.range is not None and not (np.isfinite(self.range).all() and self.range[0] < self.range[1]):
            raise ConfigError(f"--range: expected LO < HI (mm), got {self.range[0]:g} {self.range[1]:g}")
        if self.colormap not in __import__("matplotlib").colormaps:
            raise ConfigError(f"--colormap: unknown matplotlib colour map {self.colormap!r}")


@dataclass
class PredictResult:
    """Input files read, the output name of every height map written (``<out>/<name>_height.npy``) and
    one line per suspicious result (e.g. no valid pixel at all)."""

    files: list[Path] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def collect_inputs(items: list[str]) -> list[Path]:
    files: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in INPUT_EXTS)
            if not found:
                raise ConfigError(f"{p}: no images ({', '.join(INPUT_EXTS)}) in this folder")
            files += found
        elif p.is_file():
            if p.suffix.lower() not in INPUT_EXTS:
                raise ConfigError(f"{p}: unsupported input type (use {', '.join(INPUT_EXTS)})")
            files.append(p)
        else:
            raise ConfigError(f"{p}: input not found")
    return files


def load_inputs(path: Path) -> list[tuple[str, np.ndarray]]:
    """``[(name, fringe float32 (H, W) in [-1, 1]), ...]`` for one input file."""
    if path.suffix.lower() != ".npy":
        return [(path.stem, read_fringe_image(path))]
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DataError(f"{path}: cannot read as a .npy array ({exc})") from None
    arr = as_image_stack(arr, path)
    if arr.dtype == np.uint8:
        arr = encode_fringe(arr)
    elif not np.issubdtype(arr.dtype, np.floating):
        raise DataError(f"{path}: dtype {arr.dtype}; expected float (intensity / 127.5 - 1) or uint8")
    out = []
    for k in range(arr.shape[0]):
        img = np.array(arr[k], dtype=np.float32)
        if not np.isfinite(img).all():
            raise DataError(f"{path}: image {k} contains NaN/inf")
        lo, hi = float(img.min()), float(img.max())
        if lo < -1.001 or hi > 1.001:
            raise DataError(f"{path}: values span [{lo:g}, {hi:g}]; expected the dataset encoding "
                            "intensity / 127.5 - 1 in [-1, 1]")
        out.append((path.stem if arr.shape[0] == 1 else f"{path.stem}_{k:04d}", img))
    return out


def points_from_rig(rig, height_mm: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) where each camera pixel's ray reaches world z = height (mm)."""
    cam = rig.camera
    h, w = height_mm.shape
    if (cam.width, cam.height) != (w, h):
        raise ConfigError(f"the rig camera is {cam.width}x{cam.height} but the image is {w}x{h}")
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    origin, d = cam.pixel_rays(np.stack([uu, vv], axis=-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (height_mm.astype(np.float64) - origin[2]) / d[..., 2]
    return origin + s[..., None] * d


def points_from_grid(height_mm: np.ndarray, pixel_size: float) -> np.ndarray:
    h, w = height_mm.shape
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([uu * pixel_size, (h - 1 - vv) * pixel_size, height_mm.astype(np.float64)], axis=-1)


def write_ply(path: Path, points: np.ndarray, grey: np.ndarray) -> int:
    """Binary little-endian PLY with float x, y, z and uchar red, green, blue; returns the point count."""
    ok = np.isfinite(points).all(axis=-1)
    pts, g = points[ok].astype(np.float32), grey[ok].astype(np.uint8)
    rec = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"] = rec["green"] = rec["blue"] = g
    header = ("ply\nformat binary_little_endian 1.0\ncomment uhrnet predicted height, millimetres\n"
              f"element vertex {len(rec)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())
    return len(rec)


def write_tiff(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array, dtype=np.float32)).save(tmp, format="TIFF")


def write_preview(path: Path, height_mm: np.ndarray, cmap: str, vrange) -> None:
    import matplotlib

    matplotlib.use("Agg", force=True)
    from matplotlib import colormaps

    finite = height_mm[np.isfinite(height_mm)]
    if vrange is None:
        vrange = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
    lo, hi = float(vrange[0]), float(vrange[1])
    scaled = np.clip((height_mm - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    rgb = (colormaps[cmap](np.nan_to_num(scaled))[..., :3] * 255).round().astype(np.uint8)
    rgb[~np.isfinite(height_mm)] = 128
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), rgb[..., ::-1]):
            raise OSError(f"cannot write {path}")


def predict(config: PredictConfig) -> PredictResult:
    """Predict every input of ``config`` and write its files (see the module docstring)."""
    from tqdm import tqdm

    from uhrnet.inference import predict_labels

    files = collect_inputs(config.inputs)
    ckpt = load_checkpoint(config.checkpoint)
    device = select_device(config.device)
    model, transform = model_from_checkpoint(ckpt, device)
    size = parse_size(ckpt.get("args", {}).get("resize"))
    rig = None
    if config.rig:
        from fppsim.rig import Rig, RigError

        try:
            rig = Rig.load(config.rig)
        except RigError as exc:
            raise ConfigError(str(exc)) from None
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    result = PredictResult(files=files)
    used: set[str] = set()
    for path in tqdm(files, desc="predict", unit="file", disable=not config.progress or len(files) < 2):
        for name, fringe in load_inputs(path):
            if name in used:  # same stem in two folders (e.g. <id>/fringe.png of a native dataset)
                name = f"{path.parent.name}_{name}"
            base, k = name, 1
            while name in used:
                k += 1
                name = f"{base}_{k}"
            used.add(name)
            if min(fringe.shape) < MIN_SIDE:
                raise ConfigError(f"{path}: image is {fringe.shape[1]}x{fringe.shape[0]}; the model needs at least "
                                  f"{MIN_SIDE}x{MIN_SIDE} pixels")
            if rig is not None and config.ply and (rig.camera.height, rig.camera.width) != fringe.shape:
                raise ConfigError(f"{path}: image is {fringe.shape[1]}x{fringe.shape[0]} but the rig camera "
                                  f"({config.rig}) is {rig.camera.width}x{rig.camera.height}")
            label = predict_labels(model, torch.from_numpy(fringe)[None, None], size)[0, 0].cpu().numpy()
            height = transform.height_mm(label.astype(np.float64)).astype(np.float32)
            if not config.keep_all:
                valid = transform.valid(label) & (fringe > -1 + 1e-6)
                height = np.where(valid, height, np.float32(np.nan))
            if not np.isfinite(height).any():
                result.warnings.append(
                    f"{path} ({name}): no valid pixel in the prediction (every label at or below "
                    f"{transform.invalid_threshold:g}, or a black input); is this a fringe image like the training data?")
            with atomic_path(out / f"{name}_height.npy") as tmp, open(tmp, "wb") as fh:
                np.save(fh, height)
            write_tiff(out / f"{name}_height.tif", height)
            write_preview(out / f"{name}_height.png", height, config.colormap, config.range)
            if config.ply:
                pts = points_from_rig(rig, height) if rig is not None else points_from_grid(height, config.pixel_size)
                grey = np.clip((fringe + 1) * 127.5, 0, 255).round()
                write_ply(out / f"{name}.ply", pts, grey)
            result.names.append(name)
    return result
