"""Reading samples as numpy arrays (no torch): what :mod:`uhrnet.data` wraps into torch datasets.

Every file is read through the dataset contract :mod:`fppsim.formats`; this module adds what the
networks need on top: the fringe in the dataset encoding (intensity / 127.5 - 1), native heights
turned into labels, the checks that refuse data the models would silently misread (NaN/inf, raw 8-bit
fringes, a figshare export labelled with another transform, PSP labels of a ``--no-psp`` dataset).
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from fppsim.formats import LabelTransform, encode_fringe, read_gray_image, read_native_label, read_settings
from uhrnet.errors import DataError

__all__ = ["LABEL_SOURCES", "read_fringe_image", "read_native_pair", "check_figshare_arrays", "check_export_labels",
           "check_psp_available"]

LABEL_SOURCES = ("true", "psp")  # native ground truth: exact rendered height or phase-shifting height


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
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        if isinstance(exc, DataError):
            raise
        raise DataError(f"{npz}: cannot read ({type(exc).__name__}: {exc})") from None
    lab = transform.label_from_height_mm(height, valid)
    if mask_fringe:
        fringe = np.where(valid, fringe, np.float32(-1.0))
    return fringe, lab


def check_figshare_arrays(fringes: np.ndarray, labels: np.ndarray, fringe_path, label_path,
                          chunk_bytes: int = 256 << 20) -> None:
    """Scan (N, H, W) fringe/label arrays (memory maps) for NaN/inf and fringe values outside [-1, 1];
    :class:`DataError` names the file and the sample."""
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
                raise DataError(f"{path}: sample {i + bad} has {count} NaN/inf {name} values")
            lo, hi = min(lo, float(block.min())), max(hi, float(block.max()))
        if name == "fringe" and (lo < -1.001 or hi > 1.001):
            hint = " (looks like raw 8-bit intensities)" if hi > 2 else ""
            raise DataError(
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
            raise DataError(
                f"{meta}: these arrays were labelled with {diff} but the label transform differs "
                f"(set --label-transform {diff.replace(', ', ' ')})"
            )
        return


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
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error):
            pass  # named when the sample is read
    if no_psp:
        raise DataError(f"{root}: label 'psp' (--synthetic-label psp) but this dataset has no PSP "
                        "height (generated with --no-psp)")
