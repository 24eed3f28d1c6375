"""The on-disk dataset contract: what fppsim writes and uhrnet (or anyone) reads, written once.

Everything two programs must agree on lives here: the label transform (height in mm <-> label units,
with its presets), the layouts and file names (the native per-sample folders with their manifest, the
figshare array pair), and the ``dataset.json`` settings file. How arrays and images become bytes (PNG,
npz, the fringe encoding ``I/127.5 - 1``) is :mod:`fppsim.dataio.encoding`; the writers of these layouts are
:mod:`fppsim.dataio.writers` and the readers :mod:`fppsim.dataio.readers`. numpy only (no rendering, no torch).

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
The single published sample uses ``fringe_pattern.npy`` / ``height_map.npy`` (H, W) (:data:`FIGSHARE_PAIRS`).

Every file is written through one helper, :func:`fppsim.files.atomic_path`: a temporary sibling named
``.fppsim-tmp-<pid>-<name>`` (:func:`fppsim.files.tmp_path`), fsync, one rename. :func:`reconcile`
deletes only such names whose process is gone; folders it did not write are never replaced nor counted.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from fppsim.errors import DatasetError
from fppsim.files import atomic_write_text, clean_stale_tmp, json_text

__all__ = [
    "psp_freq", "psp_image_name", "LabelTransform", "PRESETS", "DatasetError", "LEGACY_LABEL_KEYS",
    "SAMPLE_ID_RE", "sample_id", "is_own_sample", "foreign_sample_folders", "finished_indices", "PEDESTAL_PREFIX",
    "manifest_record", "reconcile",
    "read_manifest", "manifest_ids", "append_manifest",
    "FIGSHARE_PAIRS", "find_figshare_pair",
    "read_settings", "normalise_settings",
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


# ============================================================================================ native
def psp_freq(value) -> int | float:
    """A phase-shifting frequency (periods across the projector) as the native layout records it: an int when
    it is whole (``80``), else the float itself (a fitted rig's ``35.6845...``)."""
    v = float(value)
    return int(v) if v.is_integer() else v


def psp_image_name(freq, step: int) -> str:
    """``psp/f{f}_s{n}.png``: a native sample's phase-shifting image of frequency ``freq`` and step ``step``
    (a whole frequency as an integer, ``f80_s0``; another by its repr, ``f35.68451_s0``)."""
    f = psp_freq(freq)
    return f"psp/f{f if isinstance(f, int) else repr(f)}_s{int(step)}.png"


def sample_id(index: int) -> str:
    return f"{int(index):06d}"


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


def finished_indices(root: str | os.PathLike) -> set[int]:
    """Indices of the finished fppsim samples in ``root`` (read only: nothing is written)."""
    return set(_complete_samples(Path(root)))


PEDESTAL_PREFIX = "pedestal:"  # meta.json's "mesh" of a pedestal prism (fppsim.rendering.scene), not an object


def manifest_record(sid: str, meta: dict) -> dict:
    """One manifest line: ``objects`` counts the scene's objects, ``pedestals`` the prisms they stand on
    (meta.json lists both under ``objects``)."""
    pedestals = sum(str(o.get("mesh", "")).startswith(PEDESTAL_PREFIX) for o in meta["objects"])
    return {"id": sid, "index": meta["index"], "seed": meta["seed"], "objects": len(meta["objects"]) - pedestals,
            "pedestals": pedestals, "valid_fraction": meta.get("stats", {}).get("valid_fraction")}


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
        if rec is None or "pedestals" not in rec:  # older records counted pedestals as objects: rebuilt
            try:
                rec = manifest_record(folder.name, json.loads((folder / "meta.json").read_text()))
            except (ValueError, KeyError, TypeError):
                continue  # not a finished sample of ours: not counted, never deleted
        records.append(rec)
    atomic_write_text(root / "manifest.jsonl", "".join(json_text(r) + "\n" for r in records))
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
        fh.write(json_text(record) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


# ============================================================================================ figshare
# File names of known figshare-style pairs: the full dataset and the single published sample.
FIGSHARE_PAIRS = (("f1_80.npy", "Z.npy"), ("fringe_pattern.npy", "height_map.npy"))
SETTINGS_FILE = "dataset.json"  # a native dataset's generation settings


def find_figshare_pair(folder: str | os.PathLike) -> tuple[Path, Path] | None:
    """``(fringe, label)`` paths of the first known pair of which ``folder`` holds either file."""
    folder = Path(folder)
    for f, z in FIGSHARE_PAIRS:
        if (folder / f).is_file() or (folder / z).is_file():
            return folder / f, folder / z
    return None


def figshare_pair_paths(folder: str | os.PathLike) -> tuple[Path, Path]:
    """:func:`find_figshare_pair`, else the paths the figshare layout would have in ``folder`` (so that
    a reader's error names the file it expected)."""
    folder = Path(folder)
    return find_figshare_pair(folder) or (folder / FIGSHARE_PAIRS[0][0], folder / FIGSHARE_PAIRS[0][1])


# ============================================================================================ settings
def normalise_settings(settings: dict) -> dict:
    """``dataset.json`` contents in today's vocabulary (old label field names translated)."""
    out = dict(settings)
    if isinstance(out.get("label"), dict):
        out["label"] = LabelTransform.from_dict(out["label"]).to_dict()
    return out


def read_settings(root: str | os.PathLike) -> dict | None:
    """The generation settings (``dataset.json``) of a native dataset folder, or None if it has none.

    Rebuild the generator's configuration with ``fppsim.rendering.synth.SynthConfig.from_settings``.
    """
    path = Path(root) / SETTINGS_FILE
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
