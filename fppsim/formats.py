"""The on-disk dataset contract: the one module fppsim writes through and uhrnet reads through.

Everything two programs must agree on lives here, written once: the label transform (height in mm
<-> label units), the fringe encoding, array shape normalisation, atomic file writes, the native
per-sample folders with their manifest, the figshare array pair, and the ``dataset.json`` settings
file. It needs numpy and OpenCV only (no rendering, no torch), so readers can import it cheaply.

Native layout::

    <out>/dataset.json          generation settings (checked on resume; :func:`read_settings`)
    <out>/manifest.jsonl        one JSON line per finished sample, sorted by index
    <out>/<id>/fringe.png       8-bit single-shot fringe image
    <out>/<id>/psp/f{f}_s{n}.png
    <out>/<id>/arrays.npz       float32 height, depth, phase_true, mask (+ phase_psp, height_psp, mask_psp)
    <out>/<id>/meta.json        rig, objects, optics, seed, version, ...

A sample folder appears by one atomic rename of a finished temporary folder, so a folder named like a
sample id is always complete; the manifest is rebuilt from the folders on every start (:func:`reconcile`).

Figshare layout (the public real data): ``f1_80.npy`` (N, H, W, 1) float32 fringe = 8-bit/127.5 - 1
and ``Z.npy`` (N, H, W, 1) float32 labels = :meth:`LabelTransform.label_from_height_mm` of the height.
The single published sample uses ``fringe_pattern.npy`` / ``height_map.npy`` (H, W).

Temporary files are named ``.<name>.<pid>.tmp<suffix>`` next to their target (:func:`temp_path`);
:func:`reconcile` removes leftovers of that scheme.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import shutil
import warnings
import zipfile
import zlib
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import DatasetError

__all__ = [
    "LabelTransform", "PRESETS", "DatasetError",
    "encode_fringe", "decode_fringe", "as_image_stack", "read_gray_image",
    "temp_path", "atomic_path", "atomic_write_text", "atomic_write_bytes", "json_default", "save_npz",
    "SAMPLE_ID_RE", "sample_id", "manifest_record", "read_manifest", "manifest_ids", "append_manifest",
    "reconcile", "write_sample_folder", "load_native_sample", "read_native_label",
    "FIGSHARE_PAIRS", "find_figshare_pair", "open_figshare_pair", "export_figshare",
    "read_settings", "normalise_settings", "SampleReader",
]

SAMPLE_ID_RE = re.compile(r"^\d{6,}$")

# ============================================================================================ labels
# Field names of the first file versions (fppsim's dataset.json "label"), still read.
LEGACY_LABEL_KEYS = {"scale": "units_per_mm", "offset": "plane_offset", "invalid": "invalid_value",
                     "threshold": "invalid_threshold"}


@dataclass(frozen=True)
class LabelTransform:
    """Height (mm above the reference plane) <-> label units of a dataset.

    ``label = height_mm * units_per_mm + plane_offset`` on valid pixels, ``invalid_value`` elsewhere;
    a label is valid when ``label > invalid_threshold``. The ``figshare`` preset (estimated from the
    public sample and the reference code, not certainties): 6 label units per mm, the plane at -97 (the
    real plane's median; the reference code masks Z <= -100, so a plane at exactly -100 would vanish),
    shadows at -105. ``data_range`` is the label range SSIM uses (C1 = (0.01 L)^2, C2 = (0.03 L)^2).

    Two conversions to millimetres exist and have distinct names: :meth:`height_mm` is the height above
    the reference plane (subtracts ``plane_offset``); a label *difference* (an error) is in mm after
    multiplying by :attr:`mm_per_unit` (the reference evaluation's ``Z / 6``).
    """

    name: str = "figshare"
    units_per_mm: float = 6.0
    invalid_value: float = -105.0
    invalid_threshold: float = -100.0
    plane_offset: float = -97.0
    data_range: float = 286.0

    @property
    def mm_per_unit(self) -> float:
        """Millimetres per label unit: converts label differences (errors) to mm."""
        return 1.0 / self.units_per_mm

    def height_mm(self, label):
        """Height above the reference plane (mm) of labels (numpy array or torch tensor)."""
        return (label - self.plane_offset) / self.units_per_mm

    def label_from_height_mm(self, height_mm: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """float32 labels of heights above the reference plane (mm), computed in float64.

        ``invalid_value`` where ``mask`` is 0/False (when given) and where the height is not finite.
        """
        h = np.asarray(height_mm, dtype=np.float64)
        label = h * self.units_per_mm + self.plane_offset
        bad = ~np.isfinite(label)
        if mask is not None:
            bad |= ~(np.asarray(mask) > 0)
        return np.where(bad, self.invalid_value, label).astype(np.float32)

    def valid(self, label):
        """Valid-pixel mask (bool) of labels: ``label > invalid_threshold`` (numpy or torch)."""
        return label > self.invalid_threshold

    def check(self) -> "LabelTransform":
        """Raise :class:`DatasetError` unless the numbers make a usable transform; returns self."""
        if not self.units_per_mm > 0:
            raise DatasetError(f"label scale (units per mm) must be > 0, got {self.units_per_mm}")
        if not self.invalid_value <= self.invalid_threshold < self.plane_offset:
            raise DatasetError(f"label preset needs invalid ({self.invalid_value}) <= threshold "
                               f"({self.invalid_threshold}) < plane offset ({self.plane_offset}), "
                               "or the plane would count as invalid")
        return self

    def same_labels(self, other: "LabelTransform") -> bool:
        """True when both map heights to the same labels (name and data_range aside)."""
        return all(math.isclose(getattr(self, k), getattr(other, k), rel_tol=1e-6, abs_tol=1e-6)
                   for k in LEGACY_LABEL_KEYS.values())

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LabelTransform":
        """From :meth:`to_dict`, the old field names (``scale``, ``offset``, ``invalid``, ``threshold``)
        or a ``preset`` name plus overrides; unknown keys are an error."""
        names = {f.name for f in fields(cls)}
        d = {LEGACY_LABEL_KEYS.get(k, k): v for k, v in d.items()}
        unknown = set(d) - names - {"preset"}
        if unknown:
            raise DatasetError(f"label transform: unknown keys {sorted(unknown)} (known: {sorted(names)})")
        base = PRESETS.get(d.get("preset", d.get("name", "figshare")), PRESETS["figshare"])
        return replace(base, **{k: (str(v) if k == "name" else float(v)) for k, v in d.items() if k in names})

    @classmethod
    def resolve(cls, spec: "LabelTransform | str | dict | None") -> "LabelTransform":
        """A transform from a preset name, a dict (e.g. from a checkpoint) or None (figshare)."""
        if spec is None:
            return PRESETS["figshare"]
        if isinstance(spec, LabelTransform):
            return spec
        if isinstance(spec, dict):
            return cls.from_dict(spec)
        if spec in PRESETS:
            return PRESETS[spec]
        raise DatasetError(f"unknown label preset {spec!r} (known: {', '.join(PRESETS)})")


PRESETS: dict[str, LabelTransform] = {"figshare": LabelTransform()}


# ============================================================================================ fringe
def encode_fringe(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Grey image (uint8, or uint16 scaled to 8-bit levels) -> float32 ``I/127.5 - 1`` in [-1, 1];
    -1 on invalid pixels when ``mask`` is given."""
    img = np.asarray(image)
    f = img.astype(np.float32)
    if img.dtype == np.uint16:
        f = f * np.float32(1.0 / 257.0)  # 16-bit -> 8-bit intensity scale
    f = f / np.float32(127.5) - np.float32(1.0)
    if mask is not None:
        f = np.where(np.asarray(mask) > 0, f, np.float32(-1.0)).astype(np.float32)
    return f


def decode_fringe(fringe: np.ndarray) -> np.ndarray:
    """float fringe in [-1, 1] -> uint8 grey levels (inverse of :func:`encode_fringe`)."""
    return np.clip(np.rint((np.asarray(fringe, dtype=np.float64) + 1.0) * 127.5), 0, 255).astype(np.uint8)


def as_image_stack(arr: np.ndarray, name: str | os.PathLike = "array") -> np.ndarray:
    """View an image array as (N, H, W): accepts (N, H, W, 1), (N, H, W), (H, W, 1) and (H, W).

    (H, W, 1) and (H, W) are one image. Raises :class:`DatasetError` naming ``name`` otherwise.
    """
    if arr.ndim == 2:
        return arr[None]
    if arr.ndim == 3 and arr.shape[-1] == 1:
        return arr[None, ..., 0]
    if arr.ndim == 3:
        return arr
    if arr.ndim == 4:
        if arr.shape[-1] != 1:
            raise DatasetError(f"{name}: shape {arr.shape}, expected (N, H, W, 1) with one channel")
        return arr[..., 0]
    raise DatasetError(f"{name}: shape {arr.shape}, expected (N, H, W, 1), (N, H, W) or (H, W)")


def read_gray_image(path: str | os.PathLike) -> np.ndarray:
    """A grey image file as a 2-D uint8 or uint16 array (colour is converted to grey).

    Raises :class:`DatasetError` naming the file when it is missing, unreadable or of another depth.
    OpenCV's own log line is silenced: the one-line error replaces it.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise DatasetError(f"{path}: cannot read as an image")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{path}: {img.dtype} image, expected 8-bit (or 16-bit) grey")
    return img


# ============================================================================================ atomic io
def temp_path(path: str | os.PathLike) -> Path:
    """The temporary name of ``path`` while it is written: ``.<name>.<pid>.tmp<suffix>`` beside it
    (the suffix kept so writers that infer the format from it still work)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")


def _fsync_dir(folder: Path) -> None:
    try:  # make the rename itself durable; not every file system allows opening a folder
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` through; on success fsync it and rename it over ``path``.

    A crash or kill at any moment leaves either the previous file or the new one, never a torn file;
    on an exception the temporary file is removed and ``path`` is untouched. The one write helper
    of both packages (text, bytes, npz, PNG, checkpoints).
    """
    path = Path(path)
    tmp = temp_path(path)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars/arrays and paths (anything else: ``str``)."""
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def save_npz(path: str | os.PathLike, arrays: dict, compresslevel: int = 1) -> None:
    """Write an .npz readable by ``np.load`` with fast deflate (level 1; numpy's default is slow)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as zf:
        for key, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(key + ".npy", buf.getvalue())


# ============================================================================================ native
def sample_id(index: int) -> str:
    return f"{int(index):06d}"


def write_sample_folder(root: Path, sid: str, images: dict, arrays: dict, meta: dict) -> None:
    """Write one sample into ``root/sid`` atomically (temporary folder + one rename).

    ``images`` maps relative PNG paths (``fringe.png``, ``psp/f8_s0.png``) to uint8 arrays.
    """
    import cv2

    final = root / sid
    tmp = root / ".tmp" / f"{sid}.{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for rel, img in images.items():
        p = tmp / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(p), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"cannot write {p}")
    save_npz(tmp / "arrays.npz", arrays)
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    if final.exists():  # an earlier run finished it meanwhile: keep the earlier one
        shutil.rmtree(tmp)
        return
    os.replace(tmp, final)


def _complete_samples(root: Path) -> dict[int, Path]:
    out = {}
    if root.is_dir():
        for p in root.iterdir():
            if p.is_dir() and SAMPLE_ID_RE.match(p.name) and (p / "meta.json").is_file():
                out[int(p.name)] = p
    return out


def manifest_record(sid: str, meta: dict) -> dict:
    return {"id": sid, "index": meta["index"], "seed": meta["seed"], "objects": len(meta["objects"]),
            "valid_fraction": meta.get("stats", {}).get("valid_fraction")}


def reconcile(root: str | os.PathLike) -> list[dict]:
    """Bring ``root`` to a consistent state after any interruption and return the manifest records.

    Removes temporary folders and files, rebuilds ``manifest.jsonl`` from the complete sample folders
    (sorted by index; records of the old manifest are reused when they parse) and writes it atomically.
    """
    root = Path(root)
    shutil.rmtree(root / ".tmp", ignore_errors=True)
    for stale in root.glob(".*.tmp*"):
        if stale.is_file():
            stale.unlink(missing_ok=True)
    old = {}
    for rec in read_manifest(root, strict=False):
        old[str(rec.get("id"))] = rec
    records = []
    for index, folder in sorted(_complete_samples(root).items()):
        rec = old.get(folder.name)
        if rec is None:
            try:
                rec = manifest_record(folder.name, json.loads((folder / "meta.json").read_text()))
            except (ValueError, KeyError):
                shutil.rmtree(folder)  # unreadable meta: not a finished sample of ours
                continue
        records.append(rec)
    atomic_write_text(root / "manifest.jsonl", "".join(json.dumps(r) + "\n" for r in records))
    return records


def read_manifest(root: str | os.PathLike, strict: bool = True) -> list[dict]:
    """Manifest records (JSON objects with an ``id``) of a native dataset.

    A half-written last line (an interrupted run) is skipped with a warning. ``strict``: raise
    :class:`DatasetError` on a missing manifest or any other broken line (else skip them).
    """
    path = Path(root) / "manifest.jsonl"
    if not path.is_file():
        if strict:
            raise DatasetError(f"{root}: no manifest.jsonl (not an fppsim dataset folder)")
        return []
    records = []
    lines = path.read_text().splitlines()
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            if not isinstance(rec, dict) or "id" not in rec:
                raise ValueError
        except ValueError:
            if n == len(lines) and strict:
                warnings.warn(f"{path}:{n}: ignoring unreadable last line")
                continue
            if strict:
                raise DatasetError(f"{path}:{n}: not a JSON object with an 'id'") from None
            continue
        records.append(rec)
    return records


def manifest_ids(root: str | os.PathLike) -> list[str]:
    """Sample ids of the manifest in order, each once (strict :func:`read_manifest`)."""
    ids, seen = [], set()
    for rec in read_manifest(root):
        sid = str(rec["id"])
        if sid not in seen:
            seen.add(sid)
            ids.append(sid)
    return ids


def append_manifest(root: Path, record: dict) -> None:
    with open(root / "manifest.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


def load_native_sample(folder: str | os.PathLike, keys: tuple[str, ...] | None = None, meta: bool = True) -> dict:
    """Read one native sample folder: ``fringe`` (2-D uint8/uint16 grey), arrays from arrays.npz (all,
    or only ``keys`` that exist) and, with ``meta``, the parsed ``meta.json``."""
    folder = Path(folder)
    img = read_gray_image(folder / "fringe.png")
    try:
        with np.load(folder / "arrays.npz", allow_pickle=False) as z:
            out = {k: z[k] for k in z.files if keys is None or k in keys}
    except _READ_ERRORS as exc:
        raise DatasetError(f"{folder / 'arrays.npz'}: cannot read ({type(exc).__name__}: {exc})") from None
    try:
        if meta:
            out["meta"] = json.loads((folder / "meta.json").read_text())
    except _READ_ERRORS as exc:
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


# ============================================================================================ figshare
# File names of known figshare-style pairs: the full dataset and the single published sample.
FIGSHARE_PAIRS = (("f1_80.npy", "Z.npy"), ("fringe_pattern.npy", "height_map.npy"))


def find_figshare_pair(folder: str | os.PathLike) -> tuple[Path, Path] | None:
    """``(fringe, label)`` paths of the first known pair of which ``folder`` holds either file."""
    folder = Path(folder)
    for f, z in FIGSHARE_PAIRS:
        if (folder / f).is_file() or (folder / z).is_file():
            return folder / f, folder / z
    return None


def _load_npy(path: Path, what: str) -> np.ndarray:
    if not path.exists():
        raise DatasetError(f"{path}: {what} file not found")
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, expected a .npy {what} file")
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DatasetError(f"{path}: cannot read as a .npy array ({exc})") from None
    if not isinstance(arr, np.ndarray):
        raise DatasetError(f"{path}: expected a single .npy array, got {type(arr).__name__}")
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


def export_figshare(root: str | os.PathLike, out: str | os.PathLike, transform: LabelTransform,
                    folders: list[Path] | None = None, use_psp_height: bool = False) -> int:
    """Write ``f1_80.npy`` and ``Z.npy`` (N, H, W, 1) float32 from native samples, atomically.

    ``folders`` defaults to the manifest order of ``root``. Invalid pixels get ``transform.invalid_value``
    in Z and -1 in the fringe. ``use_psp_height`` labels with the PSP height (as a lab would) instead
    of the exact one. Returns N.
    """
    root, out = Path(root), Path(out)
    if folders is None:
        folders = [root / r["id"] for r in read_manifest(root)]
    if not folders:
        raise DatasetError(f"{root}: no finished samples to export")
    first = load_native_sample(folders[0], meta=False)
    H, W = first["fringe"].shape
    N = len(folders)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "f1_80.npy") as tmp_f, atomic_path(out / "Z.npy") as tmp_z:
        fr = np.lib.format.open_memmap(tmp_f, mode="w+", dtype=np.float32, shape=(N, H, W, 1))
        zz = np.lib.format.open_memmap(tmp_z, mode="w+", dtype=np.float32, shape=(N, H, W, 1))
        for i, folder in enumerate(folders):
            s = load_native_sample(folder, meta=False)
            if s["fringe"].shape != (H, W):
                raise DatasetError(f"{folder}: image size {s['fringe'].shape} differs from {(H, W)}")
            if use_psp_height:
                h, m = s["height_psp"], (s["mask_psp"] > 0) & np.isfinite(s["height_psp"])
            else:
                h, m = s["height"], s["mask"] > 0
            zz[i, :, :, 0] = transform.label_from_height_mm(np.nan_to_num(h), m)
            fr[i, :, :, 0] = encode_fringe(s["fringe"], m)
        fr.flush(), zz.flush()
        del fr, zz
    return N


# ============================================================================================ settings
def normalise_settings(settings: dict) -> dict:
    """``dataset.json`` contents in today's vocabulary (old label field names translated)."""
    out = dict(settings)
    if isinstance(out.get("label"), dict):
        out["label"] = LabelTransform.from_dict(out["label"]).to_dict()
    return out


def read_settings(root: str | os.PathLike) -> dict | None:
    """The generation settings (``dataset.json``) of a native dataset folder, or None if it has none.

    Rebuild the generator's configuration with ``fppsim.synth.SynthConfig.from_settings``.
    """
    path = Path(root) / "dataset.json"
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except ValueError:
        raise DatasetError(f"{path}: not valid JSON") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    try:
        return normalise_settings(doc)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: {exc}") from None


# ============================================================================================ any layout
class SampleReader:
    """Grey fringe images and labels of any dataset folder, one sample at a time, without torch.

    Layouts, detected in this order: ``figshare`` (``f1_80.npy`` + ``Z.npy``, memory-mapped),
    ``real-sample`` (``fringe_pattern.npy`` + ``height_map.npy``) and ``native`` (``manifest.jsonl``
    with ``<id>/fringe.png`` + ``<id>/arrays.npz``; heights become labels through ``label``).
    :meth:`sample` returns ``(grey uint8 (H, W), label float32 (H, W))``. The torch datasets of
    ``uhrnet.data`` read the same files through the same functions of this module.
    """

    def __init__(self, folder: str | os.PathLike, label: LabelTransform | None = None):
        self.path = Path(folder)
        self.label = label or PRESETS["figshare"]
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: not a folder")
        self._fringes = self._labels = None
        for layout, (f, z) in zip(("figshare", "real-sample"), FIGSHARE_PAIRS):
            if (self.path / f).is_file() and (self.path / z).is_file():
                self.layout = layout
                self._fringes, self._labels = open_figshare_pair(self.path / f, self.path / z)
                self.ids = [str(i) for i in range(len(self._fringes))]
                return
        if (self.path / "manifest.jsonl").is_file():
            self.layout = "native"
            self.ids = [s for s in manifest_ids(self.path)
                        if (self.path / s / "fringe.png").is_file() and (self.path / s / "arrays.npz").is_file()]
            if not self.ids:
                raise DatasetError(f"{self.path}: manifest.jsonl lists no sample with fringe.png and arrays.npz")
            return
        raise DatasetError(
            f"{self.path}: no dataset found (expected f1_80.npy + Z.npy, fringe_pattern.npy + height_map.npy, "
            "or manifest.jsonl with <id>/fringe.png + <id>/arrays.npz)")

    def __len__(self) -> int:
        return len(self.ids)

    def sample(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(grey uint8 (H, W), label float32 (H, W)) of sample ``i``."""
        if self._fringes is not None:
            gray = decode_fringe(np.asarray(self._fringes[i], dtype=np.float32))
            lab = np.asarray(self._labels[i], dtype=np.float32)
        else:
            folder = self.path / self.ids[i]
            s = load_native_sample(folder, keys=("height", "mask"), meta=False)
            gray = s["fringe"]
            if gray.dtype == np.uint16:
                gray = np.clip(np.rint(gray / 257.0), 0, 255).astype(np.uint8)
            if "height" not in s:
                raise DatasetError(f"{folder / 'arrays.npz'}: has no 'height'")
            height = s["height"].astype(np.float64)
            mask = s["mask"] > 0.5 if "mask" in s else np.isfinite(height)
            lab = self.label.label_from_height_mm(height, mask & np.isfinite(height))
        if gray.shape != lab.shape:
            raise DatasetError(f"{self.path}: sample {self.ids[i]}: fringe {gray.shape} and height {lab.shape} "
                               "differ in shape")
        return gray, lab
