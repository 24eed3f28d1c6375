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

Every file is written through one helper, :func:`atomic_path` (from :mod:`fppsim._fs`): a temporary
sibling named ``.fppsim-tmp-<pid>-<name>`` (:func:`tmp_path`), fsync, one rename. :func:`reconcile`
deletes only such names whose process is gone; folders it did not write are never replaced nor counted.
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
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from ._fs import atomic_path, atomic_write_bytes, atomic_write_text, clean_stale_tmp, tmp_path, write_fully
from .errors import DatasetError

try:  # the same deflate format as the stdlib zlib, written 2x (PNG) to 10x (npz, level 1) faster
    from zlib_ng import zlib_ng as _deflate
except ImportError:  # a tree installed before zlib-ng became a dependency: the same files, slower
    _deflate = zlib

__all__ = [
    "LabelTransform", "PRESETS", "DatasetError",
    "encode_fringe", "decode_fringe", "as_image_stack", "read_gray_image", "colour_to_grey", "COLOUR_TOLERANCE",
    "tmp_path", "atomic_path", "atomic_write_text", "atomic_write_bytes", "json_default", "save_npz",
    "SAMPLE_ID_RE", "sample_id", "manifest_record", "read_manifest", "manifest_ids", "append_manifest",
    "reconcile", "write_sample_folder", "is_own_sample", "foreign_sample_folders", "load_native_sample",
    "read_native_label",
    "FIGSHARE_PAIRS", "find_figshare_pair", "open_figshare_pair", "figshare_rows", "export_figshare",
    "read_settings", "normalise_settings", "SampleReader",
]

SAMPLE_ID_RE = re.compile(r"^\d{6,}$")

# ============================================================================================ labels
# Field names of the first file versions (fppsim's dataset.json "label"), still read.
LEGACY_LABEL_KEYS = {"scale": "units_per_mm", "offset": "plane_offset", "invalid": "invalid_value",
                     "threshold": "invalid_threshold"}
_LABEL_NUMBERS = ("units_per_mm", "invalid_value", "invalid_threshold", "plane_offset", "data_range")


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

    def checked(self) -> "LabelTransform":
        """Self, after refusing numbers that make every label meaningless (what a reader needs): all
        finite, ``units_per_mm > 0``, ``data_range > 0``, ``invalid_value <= invalid_threshold``.
        Raises :class:`DatasetError` naming the field."""
        for k in _LABEL_NUMBERS:
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise DatasetError(f"label transform: {k} must be a finite number, got {v!r}")
        if not self.units_per_mm > 0:
            raise DatasetError(f"label transform: units_per_mm must be > 0, got {self.units_per_mm:g}")
        if not self.data_range > 0:
            raise DatasetError(f"label transform: data_range must be > 0, got {self.data_range:g}")
        if not self.invalid_value <= self.invalid_threshold:
            raise DatasetError(f"label transform: invalid_value ({self.invalid_value:g}) must be <= invalid_threshold "
                               f"({self.invalid_threshold:g}), or invalid pixels would count as valid")
        return self

    def check(self) -> "LabelTransform":
        """:meth:`checked`, and the reference plane must count as valid (``invalid_threshold <
        plane_offset``), as a writer of labels needs; returns self."""
        self.checked()
        if not self.invalid_threshold < self.plane_offset:
            raise DatasetError(f"label preset needs invalid ({self.invalid_value:g}) <= threshold "
                               f"({self.invalid_threshold:g}) < plane offset ({self.plane_offset:g}), "
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
        values = {}
        for k, v in d.items():
            if k not in names:
                continue
            if k == "name":
                values[k] = str(v)
                continue
            try:
                values[k] = float(v)
            except (TypeError, ValueError):
                raise DatasetError(f"label transform: {k} must be a number, got {v!r}") from None
        return replace(base, **values).checked()

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


COLOUR_TOLERANCE = 8.0  # mean |channel - grey| in 8-bit levels above which a colour image is refused


def colour_to_grey(img: np.ndarray, path: str | os.PathLike = "image") -> np.ndarray:
    """BGR(A) image -> grey, the way a grey camera would have recorded the same scene.

    A fringe image saved in colour (equal channels, or a colour camera's near-grey white-light image)
    becomes its luminance ``0.299 R + 0.587 G + 0.114 B`` (OpenCV's BGR2GRAY): equal channels give
    exactly the grey image. An image whose channels differ more than :data:`COLOUR_TOLERANCE` levels on
    average (a colour-mapped picture, tinted light) has no grey equivalent the models were trained on,
    so it is refused (:class:`DatasetError`) with a hint instead of giving heights off by tens of mm.
    """
    import cv2

    if img.shape[2] == 4:
        img = img[..., :3]
    elif img.shape[2] != 3:
        raise DatasetError(f"{path}: {img.shape[2]}-channel image, expected grey (or colour with equal channels)")
    img = np.ascontiguousarray(img)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    scale = 257.0 if img.dtype == np.uint16 else 1.0
    spread = float(np.abs(img.astype(np.float32) - grey[..., None].astype(np.float32)).mean()) / scale
    if spread > COLOUR_TOLERANCE:
        raise DatasetError(f"{path}: colour image whose channels differ by {spread:.1f} gray levels on average; the "
                           "models take grey fringe images: save the camera's grey (monochrome) image instead")
    return grey


def read_gray_image(path: str | os.PathLike) -> np.ndarray:
    """A grey image file as a 2-D uint8 or uint16 array (a grey scene saved in colour is converted,
    other colour images are refused: :func:`colour_to_grey`).

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
        img = colour_to_grey(img, path)
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{path}: {img.dtype} image, expected 8-bit (or 16-bit) grey")
    return img


# ============================================================================================ atomic io
# atomic_path / atomic_write_text / atomic_write_bytes / tmp_path live in fppsim._fs (one helper for
# both packages, imported above and re-exported here as part of the contract).


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars/arrays and paths (anything else: ``str``)."""
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: identical runs give identical bytes


def save_npz(path: str | os.PathLike, arrays: dict, compresslevel: int = 1, min_gain: float = 0.25) -> None:
    """Write an .npz readable by ``np.load`` with fast deflate (level 1; numpy's default is slow).

    An array whose sampled rows deflate by less than ``min_gain`` (noisy float mantissas such as
    ``phase_psp``) is stored uncompressed: deflating it would cost most of the write for a few percent.
    Entries carry a fixed timestamp, so the same arrays give the same bytes. Each entry is streamed
    into the zip (``.npy`` header, then the array's own memory): no copies of the arrays are made.
    """
    with zipfile.ZipFile(path, "w") as zf:
        for key, arr in arrays.items():
            arr = np.asarray(arr, order="C")  # (np.ascontiguousarray would make a 0-d array 1-d)
            if arr.dtype.hasobject:
                raise ValueError(f"save_npz: '{key}' holds Python objects (not allowed without pickle)")
            header = _npy_header(arr)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED if _deflate_pays(arr, compresslevel, min_gain) \
                else zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            info.file_size = len(header) + arr.nbytes  # as writestr sets it: decides zip64 like writestr
            if hasattr(info, "compress_level"):  # Python >= 3.13
                info.compress_level = compresslevel
            else:
                info._compresslevel = compresslevel
            with zf.open(info, "w") as dest:
                if info.compress_type == zipfile.ZIP_DEFLATED and _deflate is not zlib \
                        and getattr(dest, "_compressor", None) is not None:
                    # zipfile deflates with the stdlib zlib; the member is the same raw deflate stream
                    dest._compressor = _deflate.compressobj(compresslevel, _deflate.DEFLATED, -15)
                dest.write(header)
                dest.write(arr.reshape(-1).view(np.uint8))


def _npy_header(arr: np.ndarray) -> bytes:
    """The ``.npy`` header ``np.lib.format.write_array`` writes for ``arr`` (format 1.0, or 2.0 when the
    header does not fit 1.0)."""
    buf = io.BytesIO()
    d = np.lib.format.header_data_from_array_1_0(arr)
    try:
        np.lib.format.write_array_header_1_0(buf, d)
    except ValueError:
        buf = io.BytesIO()
        np.lib.format.write_array_header_2_0(buf, d)
    return buf.getvalue()


def _deflate_pays(arr: np.ndarray, level: int, min_gain: float, rows: int = 16) -> bool:
    """Deflate a few evenly spaced rows: does compression save at least ``min_gain`` of the bytes?"""
    if arr.nbytes < 65536 or arr.ndim < 1:
        return True
    step = max(1, arr.shape[0] // rows)
    sample = arr[::step].tobytes()
    return len(_deflate.compress(sample, level)) <= (1.0 - min_gain) * len(sample)


# ============================================================================================ native
def sample_id(index: int) -> str:
    return f"{int(index):06d}"


def encode_png(img: np.ndarray) -> bytes:
    """PNG file bytes of a uint8 (H, W) grey image, written for speed (the pixels are exact).

    Every row uses the "up" filter (the row minus the row above; the first row's "above" is zero, as
    PNG defines it) and the filtered rows are deflated Huffman-only at level 1: noisy 8-bit camera
    images gain nothing from string matching, and trying libpng's five filters per row costs twice the
    time for about 3 % smaller files. Any other image (colour, 16-bit) goes through OpenCV's encoder.
    """
    img = np.asarray(img)
    if img.dtype not in (np.uint8, np.uint16) or 0 in img.shape \
            or not (img.ndim == 2 or img.ndim == 3 and img.shape[2] in (3, 4)):
        raise ValueError(f"encode_png: a PNG holds a non-empty uint8/uint16 image of shape (H, W), (H, W, 3) "
                         f"or (H, W, 4), got {img.dtype} {img.shape}")
    if img.dtype != np.uint8 or img.ndim != 2:
        import cv2

        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise ValueError(f"encode_png: OpenCV cannot encode a {img.dtype} array of shape {img.shape}")
        return buf.tobytes()
    h, w = img.shape
    rows = np.empty((h, w + 1), np.uint8)
    rows[:, 0] = 2  # filter type "up"
    rows[0, 1:] = img[0]
    np.subtract(img[1:], img[:-1], out=rows[1:, 1:])  # modulo 256, as PNG's filter arithmetic is
    z = _deflate.compressobj(1, _deflate.DEFLATED, 15, 9, _deflate.Z_HUFFMAN_ONLY)
    idat = z.compress(rows) + z.flush()

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = _deflate.crc32(data, _deflate.crc32(kind))
        return len(data).to_bytes(4, "big") + kind + data + crc.to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes((8, 0, 0, 0, 0))  # 8-bit grey, no interlace
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def write_sample_folder(root: Path, sid: str, images: dict, arrays: dict, meta: dict) -> None:
    """Write one sample into ``root/sid`` atomically (temporary folder + one rename).

    ``images`` maps relative PNG paths (``fringe.png``, ``psp/f8_s0.png``) to uint8 arrays.
    """
    final = root / sid
    tmp = tmp_path(final)  # ".fppsim-tmp-<pid>-<sid>": recognisably ours, removed on failure or re-run
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        tmp.mkdir(parents=True)
        for sub in sorted({(tmp / rel).parent for rel in images} - {tmp}):  # psp/: once, not per image
            sub.mkdir(parents=True, exist_ok=True)
        for rel, img in images.items():
            (tmp / rel).write_bytes(encode_png(img))
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


def figshare_rows(fringe: np.ndarray, arrays: dict, transform: LabelTransform,
                  use_psp_height: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One native sample's figshare ``(fringe, label)`` rows, float32 (H, W): what :func:`export_figshare`
    writes (and ``fppsim.pipeline.FigshareRows`` streams while generating), so both give identical files."""
    if use_psp_height:
        h, m = arrays["height_psp"], (arrays["mask_psp"] > 0) & np.isfinite(arrays["height_psp"])
    else:
        h, m = arrays["height"], arrays["mask"] > 0
    return encode_fringe(fringe, m), transform.label_from_height_mm(np.nan_to_num(h), m)


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
    first = load_native_sample(folders[0])
    H, W = first["fringe"].shape
    N = len(folders)

    def fill(folder, fr, zz):
        s = load_native_sample(folder)
        if s["fringe"].shape != (H, W):
            raise DatasetError(f"{folder}: image size {s['fringe'].shape} differs from {(H, W)}")
        if use_psp_height and "height_psp" not in s:
            raise DatasetError(f"{folder}: no PSP height (made with --no-psp)")
        fr[0, :, :, 0], zz[0, :, :, 0] = figshare_rows(s["fringe"], s, transform, use_psp_height)

    out.mkdir(parents=True, exist_ok=True)
    clean_stale_tmp(out)
    tmp_f, tmp_z = tmp_path(out / "f1_80.npy"), tmp_path(out / "Z.npy")
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
