"""Reading dataset folders as numpy arrays (no torch): native samples, figshare pairs, any layout.

Layouts (named in :mod:`fppsim.dataio.formats`, the contract): the native per-sample folders
(``manifest.jsonl``, ``<id>/fringe.png``, ``<id>/arrays.npz``), the figshare pair (``f1_80.npy`` +
``Z.npy``, memory-mapped) and the single published real sample (``fringe_pattern.npy`` +
``height_map.npy``); every layout's reader is a :class:`fppsim.dataio.readers.Source`
(:mod:`fppsim.dataio.readers.source`), built on these functions. :func:`read_native_pair` and :func:`open_figshare_pair` give what the networks read (the fringe
in the dataset encoding, intensity / 127.5 - 1), and the checks refuse data the models would silently
misread (NaN/inf, raw 8-bit fringes, a figshare export labelled with another transform, PSP labels of
a ``--no-psp`` dataset). ``uhrnet.data.datasets`` wraps these readers into torch datasets. Every error is a
:class:`fppsim.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from fppsim.dataio.encoding import as_image_stack, encode_fringe, load_npy, read_gray_image
from fppsim.errors import DatasetError, InputError
from fppsim.dataio.formats import LabelTransform, psp_freq, psp_image_name, read_settings

__all__ = ["READ_ERRORS", "LABEL_SOURCES", "load_native_sample", "read_native_label", "read_fringe_image",
           "read_native_pair", "read_native_phase", "read_native_psp", "check_psp_available", "open_figshare_pair", "check_figshare_arrays",
           "check_export_labels", "pick_evenly"]

LABEL_SOURCES = ("true", "psp")  # native ground truth: exact rendered height or phase-shifting height
READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)  # what a damaged file raises


# ============================================================================================ native
def load_native_sample(folder: str | os.PathLike, keys: tuple[str, ...] | None = None, meta: bool = True) -> dict:
    """Read one native sample folder: ``fringe`` (2-D uint8/uint16 grey), arrays from arrays.npz (all,
    or only ``keys`` that exist) and, with ``meta``, the parsed ``meta.json``."""
    folder = Path(folder)
    img = read_gray_image(folder / "fringe.png")
    try:
        with np.load(folder / "arrays.npz", allow_pickle=False) as z:
            out = {k: z[k] for k in z.files if keys is None or k in keys}
    except READ_ERRORS as exc:
        raise DatasetError(f"{folder / 'arrays.npz'}: cannot read ({type(exc).__name__}: {exc})") from None
    try:
        if meta:
            out["meta"] = json.loads((folder / "meta.json").read_text())
    except READ_ERRORS as exc:
        raise DatasetError(f"{folder / 'meta.json'}: cannot read ({type(exc).__name__})") from None
    out["fringe"] = img
    return out


def read_native_label(arrays: dict, npz: str | os.PathLike, shape: tuple[int, ...] | None = None,
                      source: str = "true", finite_required: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(height_mm float, valid bool)`` of a native sample's arrays.

    ``source="true"`` reads ``height``/``mask`` (the exact geometry), ``"psp"`` reads
    ``height_psp``/``mask_psp`` (the phase-shifting measurement, NaN where decoding failed: invalid).
    ``shape`` (the fringe's) must match. With ``finite_required``, NaN/inf on a valid exact-height
    pixel is an error; otherwise such pixels become invalid.
    """
    hkey, mkey = ("height", "mask") if source == "true" else ("height_psp", "mask_psp")
    missing = [k for k in (hkey, mkey) if k not in arrays]
    if missing:
        raise DatasetError(f"{npz}: missing array(s) {missing} (has {sorted(k for k in arrays if k not in ('meta', 'fringe'))})")
    height, valid = arrays[hkey], arrays[mkey]
    if shape is not None and (height.shape != shape or valid.shape != shape):
        raise DatasetError(f"{npz}: {hkey} {height.shape} / {mkey} {valid.shape} do not match fringe.png {shape}")
    valid = valid > 0.5
    if source == "psp" or not finite_required:
        valid &= np.isfinite(height)
    elif not np.isfinite(height[valid]).all():
        raise DatasetError(f"{npz}: {hkey} has NaN/inf on {int((~np.isfinite(height[valid])).sum())} valid pixels")
    return height, valid


def read_fringe_image(path: str | os.PathLike) -> np.ndarray:
    """An 8-bit (or 16-bit) grey image as float32 in the dataset encoding, intensity / 127.5 - 1."""
    return encode_fringe(read_gray_image(path))


def read_native_pair(folder: str | os.PathLike, transform: LabelTransform, label: str = "true",
                     mask_fringe: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(fringe, label)`` float32 (H, W) of one native sample folder.

    ``label="psp"`` reads the phase-shifting height (NaN where decoding failed: invalid, as fppsim's
    export does) instead of the exact one; ``mask_fringe`` sets the fringe to -1 off the valid mask, as
    ``fppsim generate --format figshare`` encodes it.
    """
    d = Path(folder)
    fringe = read_fringe_image(d / "fringe.png")
    npz = d / "arrays.npz"
    try:
        with np.load(npz, allow_pickle=False) as z:
            height, valid = read_native_label(z, npz, fringe.shape, source=label)
    except READ_ERRORS as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"{npz}: cannot read ({type(exc).__name__}: {exc})") from None
    lab = transform.label_from_height_mm(height, valid)
    if mask_fringe:
        fringe = np.where(valid, fringe, np.float32(-1.0))
    return fringe, lab


def read_native_phase(folder: str | os.PathLike, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """The exact projector phase ``phase_true`` (H, W) float32, rad (fppsim's convention, ``2 pi f u_p / W_p``),
    of one native sample folder; ``shape`` (the fringe's) must match."""
    npz = Path(folder) / "arrays.npz"
    try:
        with np.load(npz, allow_pickle=False) as z:
            if "phase_true" not in z:
                raise DatasetError(f"{npz}: no phase_true array (has {sorted(z.files)})")
            phase = np.asarray(z["phase_true"], np.float32)
    except READ_ERRORS as exc:
        raise DatasetError(f"{npz}: cannot read ({type(exc).__name__}: {exc})") from None
    if shape is not None and phase.shape != tuple(shape):
        raise DatasetError(f"{npz}: phase_true {phase.shape} does not match fringe.png {tuple(shape)}")
    return phase


def read_native_psp(folder: str | os.PathLike) -> tuple[np.ndarray, dict, np.ndarray, dict]:
    """The phase-shifting images of one native sample folder, as rendered: ``(fringe grey (H, W), {f: grey
    stack (steps, H, W)}, phase shifts (steps,) rad, meta)``: its ``meta.json`` says the ladder
    (``psp``: ``freqs``, ``steps``, ``shifts_rad``); the images are ``psp/f{f}_s{n}.png``. Raises
    :class:`DatasetError` naming the file for a sample without them (``--no-psp``) or a damaged one."""
    folder = Path(folder)
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{folder / 'meta.json'}: cannot read ({exc.strerror if isinstance(exc, OSError) else 'not JSON'})") from None
    psp = meta.get("psp") if isinstance(meta, dict) else None
    if not isinstance(psp, dict) or not psp.get("freqs"):
        raise DatasetError(f"{folder}: no phase-shifting images (generated with --no-psp?); label-real decodes "
                           "psp/f{f}_s{n}.png")
    try:
        freqs = tuple(psp_freq(f) for f in psp["freqs"])
        steps = int(psp["steps"])
        shifts = np.asarray(psp.get("shifts_rad") or [2 * np.pi * n / steps for n in range(steps)], np.float64)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{folder / 'meta.json'}: 'psp' must hold freqs, steps and shifts_rad") from None
    image = read_gray_image(folder / "fringe.png")
    stacks = {}
    for f in freqs:
        imgs = []
        for n in range(steps):
            path = folder / psp_image_name(f, n)
            img = read_gray_image(path)
            if img.shape != image.shape:
                raise DatasetError(f"{path}: shape {img.shape} differs from fringe.png's {image.shape}")
            imgs.append(img)
        stacks[f] = np.stack(imgs)
    return image, stacks, shifts, meta


def check_psp_available(root: str | os.PathLike, first_id: str) -> None:
    """Refuse ``label="psp"`` up front (not at the first batch) for a dataset without PSP heights
    (generated with ``--no-psp``): its ``dataset.json`` says so, or its first sample has no ``height_psp``."""
    root = Path(root)
    try:
        settings = read_settings(root) or {}
        no_psp = not (settings.get("config") or {}).get("psp_freqs", True)
    except (OSError, ValueError, AttributeError):
        no_psp = False
    if not no_psp:
        try:
            with np.load(root / first_id / "arrays.npz", allow_pickle=False) as z:
                no_psp = "height_psp" not in z.files
        except READ_ERRORS:
            pass  # named when the sample is read
    if no_psp:
        raise DatasetError(f"{root}: label 'psp' (--synthetic-label psp) but this dataset has no PSP "
                        "height (generated with --no-psp)")


# ============================================================================================ figshare
def _load_npy(path: Path, what: str) -> np.ndarray:
    if not path.exists():
        raise DatasetError(f"{path}: {what} file not found")
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, expected a .npy {what} file")
    arr = load_npy(path)
    if not np.issubdtype(arr.dtype, np.floating):
        raise DatasetError(f"{path}: dtype {arr.dtype}, expected float32 ({what})")
    arr = as_image_stack(arr, path)
    if 0 in arr.shape:
        raise DatasetError(f"{path}: empty array of shape {arr.shape}")
    return arr


def open_figshare_pair(fringe: str | os.PathLike, label: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Memory-mapped ``(fringes, labels)``, each (N, H, W) of the file's float dtype.

    Accepts (N, H, W, 1), (N, H, W), (H, W, 1) and (H, W) files. Raises :class:`DatasetError` naming
    the file for a missing file, a non-float dtype, an unknown shape, or a pair that disagrees in N
    or image size. Nothing is copied into memory.
    """
    fringe, label = Path(fringe), Path(label)
    fr = _load_npy(fringe, "fringe")
    z = _load_npy(label, "label")
    if fr.shape[0] != z.shape[0]:
        raise DatasetError(f"{label}: {z.shape[0]} samples but {fringe.name} has {fr.shape[0]}")
    if fr.shape[1:] != z.shape[1:]:
        raise DatasetError(f"{label}: image size {z.shape[1:]} differs from {fringe.name}'s {fr.shape[1:]}")
    return fr, z


def check_figshare_arrays(fringes: np.ndarray, labels: np.ndarray, fringe_path, label_path,
                          chunk_bytes: int = 256 << 20) -> None:
    """Scan (N, H, W) fringe/label arrays (memory maps) for NaN/inf and fringe values outside [-1, 1];
    :class:`DatasetError` names the file and the sample."""
    n = int(labels.shape[0])
    step = max(1, chunk_bytes // max(1, labels[0].nbytes))
    for arr, path, name in ((labels, label_path, "label"), (fringes, fringe_path, "fringe")):
        lo, hi = np.inf, -np.inf
        for i in range(0, n, step):
            block = np.asarray(arr[i:i + step])
            finite = np.isfinite(block)
            if not finite.all():
                bad = np.flatnonzero(~finite.reshape(len(block), -1).all(axis=1))[0]
                count = int((~finite[bad]).sum())
                raise DatasetError(f"{path}: sample {i + bad} has {count} NaN/inf {name} values")
            lo, hi = min(lo, float(block.min())), max(hi, float(block.max()))
        if name == "fringe" and (lo < -1.001 or hi > 1.001):
            hint = " (looks like raw 8-bit intensities)" if hi > 2 else ""
            raise DatasetError(
                f"{path}: fringe values span [{lo:g}, {hi:g}], expected [-1, 1] = "
                f"intensity / 127.5 - 1{hint}"
            )


def check_export_labels(root: Path, transform: LabelTransform) -> None:
    """A figshare-format export by fppsim records its label transform in ``native/dataset.json``:
    refuse to read it with a different one (the labels would be silently misinterpreted)."""
    for meta in (root / "native" / "dataset.json", root / "dataset.json"):
        if not meta.is_file():
            continue
        try:
            theirs = LabelTransform.from_dict(json.loads(meta.read_text()).get("label") or {})
        except (json.JSONDecodeError, AttributeError, TypeError, ValueError):
            return
        if not theirs.same_labels(transform):
            diff = ", ".join(f"{k}={getattr(theirs, k):g}" for k in ("units_per_mm", "plane_offset", "invalid_value",
                                                                      "invalid_threshold")
                             if getattr(theirs, k) != getattr(transform, k))
            raise DatasetError(
                f"{meta}: these arrays were labelled with {diff} but are read with another label transform: give "
                f"its native/ folder instead (heights in mm, read in any label units); train can also read these "
                f"arrays with --label-transform {diff.replace(', ', ' ')}"
            )
        return


# ============================================================================================ sampling
def pick_evenly(n: int, max_samples: int | None) -> np.ndarray:
    """Evenly spaced indices (int (k,)) of ``max_samples`` out of ``n`` (all when max_samples is None or >= n)."""
    if max_samples is None or max_samples >= n:
        return np.arange(n)
    if max_samples < 1:
        raise InputError(f"max_samples must be >= 1, got {max_samples}")
    return np.unique(np.linspace(0, n - 1, max_samples).round().astype(int))
