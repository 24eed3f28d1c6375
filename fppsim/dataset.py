"""On-disk formats: the native per-sample folders, the manifest, and the figshare array layout.

Native layout (DESIGN.md §5)::

    <out>/dataset.json          generation settings (checked on resume)
    <out>/manifest.jsonl        one JSON line per finished sample, sorted by index
    <out>/<id>/fringe.png       8-bit single-shot fringe image
    <out>/<id>/psp/f{f}_s{n}.png
    <out>/<id>/arrays.npz       float32 height, depth, phase_true, mask (+ phase_psp, height_psp, mask_psp)
    <out>/<id>/meta.json        rig, objects, optics, seed, version, ...

A sample folder appears by one atomic rename of a finished temporary folder, so a folder named like a
sample id is always complete; the manifest is rebuilt from the folders on every start.

Figshare layout: ``f1_80.npy`` (N, H, W, 1) float32 fringe = 8-bit/127.5 - 1 and ``Z.npy``
(N, H, W, 1) float32 labels = :class:`LabelTransform` of the height.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ._fs import clean_stale_tmp, tmp_path, write_fully

__all__ = [
    "LabelTransform", "encode_fringe", "decode_fringe", "save_npz", "atomic_write_text",
    "manifest_record", "sample_id", "reconcile", "read_manifest", "append_manifest", "write_sample_folder",
    "load_native_sample", "export_figshare", "DatasetError", "SAMPLE_ID_RE",
]

SAMPLE_ID_RE = re.compile(r"^\d{6,}$")


class DatasetError(ValueError):
    """A dataset folder that cannot be read or written as asked."""


@dataclass(frozen=True)
class LabelTransform:
    """Height (mm above the reference plane) <-> label units of a dataset.

    ``label = height_mm * scale + offset`` on valid pixels, ``invalid`` elsewhere; a label
    ``<= threshold`` counts as invalid when reading. Preset ``figshare`` (estimated from the public
    sample and the reference code, not certainties): 6 label units per mm, the plane at -97 (the real
    plane's median; the reference code masks Z <= -100, so a plane at exactly -100 would vanish),
    shadows at -105.
    """

    scale: float = 6.0
    offset: float = -97.0
    invalid: float = -105.0
    threshold: float = -100.0
    name: str = "figshare"

    def to_label(self, height_mm: np.ndarray, mask: np.ndarray) -> np.ndarray:
        h = np.asarray(height_mm, dtype=np.float64) * self.scale + self.offset
        return np.where(np.asarray(mask) > 0, h, self.invalid).astype(np.float32)

    def to_mm(self, label: np.ndarray) -> np.ndarray:
        return (np.asarray(label, dtype=np.float64) - self.offset) / self.scale

    def valid(self, label: np.ndarray) -> np.ndarray:
        return np.asarray(label) > self.threshold

    @property
    def mm_per_unit(self) -> float:
        return 1.0 / self.scale

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LabelTransform":
        return cls(**{k: d[k] for k in ("scale", "offset", "invalid", "threshold", "name") if k in d})

    def check(self) -> None:
        for name in ("scale", "offset", "invalid", "threshold"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise DatasetError(f"label {name} must be a finite number, got {v!r}")
        if not self.scale > 0:
            raise DatasetError(f"label scale must be > 0, got {self.scale}")
        if not self.invalid <= self.threshold < self.offset:
            raise DatasetError(f"label preset needs invalid ({self.invalid}) <= threshold ({self.threshold}) "
                               f"< plane offset ({self.offset}), or the plane would count as invalid")


def encode_fringe(image_u8: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """8-bit image -> float32 in [-1, 1] (``I/127.5 - 1``); -1 on invalid pixels when ``mask`` is given."""
    f = np.asarray(image_u8, dtype=np.float32) / 127.5 - 1.0
    if mask is not None:
        f = np.where(np.asarray(mask) > 0, f, -1.0).astype(np.float32)
    return f


def decode_fringe(fringe: np.ndarray) -> np.ndarray:
    """float fringe in [-1, 1] -> uint8 (inverse of :func:`encode_fringe`)."""
    return np.clip(np.rint((np.asarray(fringe, dtype=np.float64) + 1.0) * 127.5), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------- atomic io
def _tmp_name(path: Path) -> Path:
    return tmp_path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to a temp sibling, fsync, rename; a failure (disk full) leaves no temp file."""
    path = Path(path)
    tmp = _tmp_name(path)
    try:
        with open(tmp, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: identical runs give identical bytes


def save_npz(path: str | os.PathLike, arrays: dict, compresslevel: int = 1, min_gain: float = 0.25) -> None:
    """Write an .npz readable by ``np.load`` with fast deflate (level 1; numpy's default is slow).

    An array whose sampled rows deflate by less than ``min_gain`` (noisy float mantissas such as
    ``phase_psp``) is stored uncompressed: deflating it would cost most of the write for a few percent.
    Entries carry a fixed timestamp, so the same arrays give the same bytes.
    """
    with zipfile.ZipFile(path, "w") as zf:
        for key, arr in arrays.items():
            arr = np.ascontiguousarray(arr)
            buf = io.BytesIO()
            np.lib.format.write_array(buf, arr, allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED if _deflate_pays(arr, compresslevel, min_gain) \
                else zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compress_type=info.compress_type, compresslevel=compresslevel)


def _deflate_pays(arr: np.ndarray, level: int, min_gain: float, rows: int = 16) -> bool:
    """Deflate a few evenly spaced rows: does compression save at least ``min_gain`` of the bytes?"""
    if arr.nbytes < 65536 or arr.ndim < 1:
        return True
    step = max(1, arr.shape[0] // rows)
    sample = arr[::step].tobytes()
    return len(zlib.compress(sample, level)) <= (1.0 - min_gain) * len(sample)


# ----------------------------------------------------------------------------------------- native
def sample_id(index: int) -> str:
    return f"{int(index):06d}"


def write_sample_folder(root: Path, sid: str, images: dict, arrays: dict, meta: dict) -> None:
    """Write one sample into ``root/sid`` atomically (temporary folder + one rename).

    ``images`` maps relative PNG paths (``fringe.png``, ``psp/f8_s0.png``) to uint8 arrays.
    """
    import cv2

    # Huffman-only deflate: noisy 8-bit camera images gain nothing from string matching; skipping it
    # makes the PNGs faster to write and smaller than zlib's default strategy (same pixels).
    png_flags = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    final = root / sid
    tmp = tmp_path(final)  # ".fppsim-tmp-<pid>-<sid>": recognisably ours, removed on failure or re-run
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        tmp.mkdir(parents=True)
        for rel, img in images.items():
            p = tmp / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(p), img, png_flags):
                raise OSError(f"cannot write {p}")
        save_npz(tmp / "arrays.npz", arrays)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
        if final.exists():
            if not is_own_sample(final):  # never replace (or count) a folder we did not write
                raise DatasetError(f"{final} exists but is not a finished fppsim sample: move it away")
            shutil.rmtree(tmp)  # an earlier run finished it meanwhile: keep the earlier one
            return
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def is_own_sample(folder: Path) -> bool:
    """True when ``folder`` is a finished fppsim sample: its meta.json parses and names this index."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
        return isinstance(meta, dict) and int(meta["index"]) == int(folder.name) and "seed" in meta
    except (OSError, ValueError, KeyError, TypeError):
        return False


def foreign_sample_folders(root: str | os.PathLike, indices=None) -> list[Path]:
    """Folders named like sample ids (of ``indices``, or any) that are not finished fppsim samples."""
    root = Path(root)
    if not root.is_dir():
        return []
    out = []
    for p in sorted(root.iterdir()):
        if SAMPLE_ID_RE.match(p.name) and (indices is None or int(p.name) in indices) and not is_own_sample(p):
            out.append(p)
    return out


def _complete_samples(root: Path) -> dict[int, Path]:
    out = {}
    if root.is_dir():
        for p in root.iterdir():
            if p.is_dir() and SAMPLE_ID_RE.match(p.name) and is_own_sample(p):
                out[int(p.name)] = p
    return out


def manifest_record(sid: str, meta: dict) -> dict:
    return {"id": sid, "index": meta["index"], "seed": meta["seed"], "objects": len(meta["objects"]),
            "valid_fraction": meta.get("stats", {}).get("valid_fraction")}


def reconcile(root: str | os.PathLike) -> list[dict]:
    """Bring ``root`` to a consistent state after any interruption and return the manifest records.

    Removes fppsim's own temporary files of dead processes (``.fppsim-tmp-<pid>-*``; nothing else is
    ever deleted), rebuilds ``manifest.jsonl`` from the finished sample folders (sorted by index;
    records of the old manifest are reused when they parse) and writes it atomically. Folders named
    like samples that fppsim did not finish are left alone and not counted.
    """
    root = Path(root)
    clean_stale_tmp(root)
    old = {}
    for rec in read_manifest(root, strict=False):
        old[str(rec.get("id"))] = rec
    records = []
    for index, folder in sorted(_complete_samples(root).items()):
        rec = old.get(folder.name)
        if rec is None:
            try:
                rec = manifest_record(folder.name, json.loads((folder / "meta.json").read_text()))
            except (ValueError, KeyError, TypeError):
                continue  # not a finished sample of ours: not counted, never deleted
        records.append(rec)
    atomic_write_text(root / "manifest.jsonl", "".join(json.dumps(r) + "\n" for r in records))
    return records


def read_manifest(root: str | os.PathLike, strict: bool = True) -> list[dict]:
    """Manifest records of a native dataset (``strict``: raise on a missing or broken manifest)."""
    path = Path(root) / "manifest.jsonl"
    if not path.is_file():
        if strict:
            raise DatasetError(f"{root}: no manifest.jsonl (not an fppsim dataset folder)")
        return []
    records = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except ValueError:
            if strict:
                raise DatasetError(f"{path}: line {n} is not valid JSON") from None
    return records


def append_manifest(root: Path, record: dict) -> None:
    with open(root / "manifest.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def load_native_sample(folder: str | os.PathLike, keys: tuple[str, ...] | None = None, meta: bool = True) -> dict:
    """Read one native sample folder: ``fringe`` (uint8 H x W), arrays from arrays.npz (all, or only
    ``keys`` that exist) and, with ``meta``, the parsed ``meta.json``."""
    import cv2

    folder = Path(folder)
    img = cv2.imread(str(folder / "fringe.png"), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{folder / 'fringe.png'}: missing or unreadable")
    bad = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)
    try:
        with np.load(folder / "arrays.npz") as z:
            out = {k: z[k] for k in z.files if keys is None or k in keys}
    except bad as exc:
        raise DatasetError(f"{folder / 'arrays.npz'}: cannot read ({type(exc).__name__})") from None
    try:
        if meta:
            out["meta"] = json.loads((folder / "meta.json").read_text())
    except bad as exc:
        raise DatasetError(f"{folder / 'meta.json'}: cannot read ({type(exc).__name__})") from None
    out["fringe"] = img
    return out


def export_figshare(root: str | os.PathLike, out: str | os.PathLike, transform: LabelTransform,
                    folders: list[Path] | None = None, use_psp_height: bool = False) -> int:
    """Write ``f1_80.npy`` and ``Z.npy`` (N, H, W, 1) float32 from native samples, atomically.

    ``folders`` defaults to the manifest order of ``root``. Invalid pixels get ``transform.invalid``
    in Z and -1 in the fringe. ``use_psp_height`` labels with the PSP height (as a lab would) instead
    of the exact one. Returns N.
    """
    root, out = Path(root), Path(out)
    if folders is None:
        folders = [root / r["id"] for r in read_manifest(root)]
    if not folders:
        raise DatasetError(f"{root}: no finished samples to export")
    first = load_native_sample(folders[0])
    H, W = first["fringe"].shape
    N = len(folders)

    def fill(folder, fr, zz):
        s = load_native_sample(folder)
        if s["fringe"].shape != (H, W):
            raise DatasetError(f"{folder}: image size {s['fringe'].shape} differs from {(H, W)}")
        if use_psp_height:
            if "height_psp" not in s:
                raise DatasetError(f"{folder}: no PSP height (made with --no-psp)")
            h, m = s["height_psp"], (s["mask_psp"] > 0) & np.isfinite(s["height_psp"])
        else:
            h, m = s["height"], s["mask"] > 0
        zz[0, :, :, 0] = transform.to_label(np.nan_to_num(h), m)
        fr[0, :, :, 0] = encode_fringe(s["fringe"], m)

    out.mkdir(parents=True, exist_ok=True)
    clean_stale_tmp(out)
    tmp_f, tmp_z = _tmp_name(out / "f1_80.npy"), _tmp_name(out / "Z.npy")
    # ordinary writes, sample by sample: a full disk raises ENOSPC here (a memmap into a sparse file
    # would die of SIGBUS instead); the temp files are removed on any failure
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)), "fortran_order": False,
              "shape": (N, H, W, 1)}
    try:
        with open(tmp_f, "wb") as ff, open(tmp_z, "wb") as fz:
            for fh in (ff, fz):
                np.lib.format.write_array_header_1_0(fh, header)
            fr1 = np.empty((1, H, W, 1), np.float32)
            zz1 = np.empty((1, H, W, 1), np.float32)
            for folder in folders:
                fill(folder, fr1, zz1)
                write_fully(ff, fr1)
                write_fully(fz, zz1)
            for fh in (ff, fz):
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp_f, out / "f1_80.npy")
        os.replace(tmp_z, out / "Z.npy")
    except OSError as exc:
        raise DatasetError(f"cannot write the figshare arrays in {out}: {exc.strerror or exc}") from None
    finally:
        tmp_f.unlink(missing_ok=True)
        tmp_z.unlink(missing_ok=True)
    return N
