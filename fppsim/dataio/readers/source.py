"""One reader per data layout, and the one opener: :func:`open_source` recognises what a path holds.

Every layout (real or synthetic) is a subclass of :class:`Source` registered in :data:`LAYOUTS`: it says
whether it :meth:`~Source.recognise` a path and reads what the layout has. Every command that reads
data from a path the user names asks :func:`open_source` for the reader and uses what it provides,
never testing file names or layout kinds itself (``tests/test_layers.py`` checks that layout names and
``.kind`` tests appear only in :mod:`fppsim.dataio`). The layouts, in the order they are recognised (the
first that fits wins; :func:`register_layout` adds one), are :data:`LAYOUTS`: each class's ``kind`` and
``holds`` (what the path holds) are the one description, which :func:`describe_layouts` lists and the error
naming the labelled layouts (:func:`labelled_hint`) is built from; ``python -c "from fppsim.dataio.readers import
describe_layouts; print(describe_layouts())"`` prints them.

What a reader provides (the base class answers "nothing" where a layout has nothing):

* :meth:`~Source.ids`, :meth:`~Source.fringe_images` (``(id, grey uint8)``), :meth:`~Source.inputs`
  (what ``predict`` reads: ``(name, fringe in the dataset encoding, file)``);
* labelled layouts (``labelled``): :meth:`~Source.sample` ``(fringe, label)`` as the networks read them,
  :meth:`~Source.check_samples` (refuse what would be misread, before training), :meth:`~Source.height_labels`;
  ``array_files`` for layouts stored as two memory-mappable ``.npy`` stacks;
* phase-shifting scans: :meth:`~Source.phase` and :meth:`~Source.phase_ids` (frames with an absolute phase),
  :meth:`~Source.scan_ids` and :meth:`~Source.scan` (one frame: single-shot image, phase, valid pixels, how it
  was read);
* one image by id (:meth:`~Source.fringe_image`), and what would stop the path being read (:meth:`~Source.problem`);
* :meth:`~Source.fppsim_samples`: fppsim's native sample folders behind the path (the samples themselves,
  or the ``native/`` folder a figshare export keeps beside its arrays): where ``dataset.json``, the
  rig and each sample's exact phase are.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path
from typing import Iterator

import numpy as np

from fppsim.dataio.encoding import as_image_stack, decode_fringe, encode_fringe, load_npy, read_gray_image
from fppsim.dataio.formats import FIGSHARE_PAIRS, PRESETS, LabelTransform, find_figshare_pair, manifest_ids
from fppsim.errors import DatasetError, PSPMatError, InputError
from fppsim.dataio.readers.samples import (check_export_labels, check_psp_available, load_native_sample,
                                            open_figshare_pair, pick_evenly, read_native_pair, read_native_phase,
                                            read_native_psp)
from fppsim.dataio.readers.listing import IMAGE_EXTS, scan_folders_note, skipped_note, warn_skipped
from fppsim.dataio.readers.psp_mat import (FOLDERS, PspMat, is_psp_folder, list_psp_ids, load_ipattern,
                                           load_psp_folder_sample)

__all__ = ["IMAGE_EXTS", "PSP_KINDS", "PAIR_KINDS", "LAYOUTS", "Source", "open_source", "is_scan_folder",
           "register_layout", "open_labelled", "grey_sample", "iter_samples", "describe_layouts", "labelled_hint"]

PSP_KINDS = ("psp", "ipattern", "psp-partial")  # a phase-shifting scan folder, whole or in part
PAIR_KINDS = ("figshare", "real-sample")


class Source:
    """A reader of one layout at ``path`` (module docstring). Subclasses set ``kind`` and
    :meth:`recognise`, and override what their layout provides; register them with :func:`register_layout`."""

    kind = "folder"
    labelled = False  # height labels: sample() and height_labels() work
    holds = ""  # what a path of this layout holds, one line: describe_layouts() and labelled_hint() read it
    plain_files = False  # image / .npy files and folders of them: callers apply their own file rules
    described_as: str | None = None  # how reports name the layout (None: its kind)
    is_psp = False  # phase-shifting scans, whole or in part: scan_ids() and scan() read them (or name what is missing)

    def __init__(self, path: str | os.PathLike, pair: tuple[Path, Path] | None = None):
        self.path = Path(path)
        self.pair = pair  # (fringe, label) of a figshare-format pair of which the folder holds either file

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, kind={self.kind!r})"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        """Whether ``path`` holds this layout (asked in :data:`LAYOUTS` order)."""
        return False

    # ------------------------------------------------------------------ what the layout is
    @property
    def layout(self) -> str:
        """How reports name the layout (``fit-rig``'s "layout ..." line, ``compare-real``'s ``layout``)."""
        return self.described_as or self.kind

    def problem(self) -> str | None:
        """One line saying why the path cannot be read as it looks (a damaged scan folder), else None."""
        return None

    @property
    def has_images(self) -> bool:
        """Single-shot images a scan folder holds (``iPattern/``): a whole scan folder or its images alone, not a
        damaged one (:meth:`problem`)."""
        return self.is_psp and self.problem() is None and (self.path / FOLDERS["image"][0]).is_dir()

    @property
    def has_manifest(self) -> bool:
        """fppsim's native samples (``manifest.jsonl``), whatever else the folder holds."""
        return (self.path / "manifest.jsonl").is_file()

    @property
    def complete_pair(self) -> tuple[str, Path, Path] | None:
        """``(kind, fringe, label)`` of the first pair of which BOTH files exist, else None (any kind)."""
        for kind, (f, z) in zip(PAIR_KINDS, FIGSHARE_PAIRS):
            if (self.path / f).is_file() and (self.path / z).is_file():
                return kind, self.path / f, self.path / z
        return None

    @property
    def array_files(self) -> tuple[Path, Path] | None:
        """``(fringes, labels)``: the two ``.npy`` stacks a labelled layout is stored as (memory-mappable),
        else None."""
        return None

    def scan_folders(self, phase_shifting: bool = False) -> list[str]:
        """Names of the sub-folders (sorted) that are scan folders themselves: phase-shifting (whole or damaged) or
        fppsim's native samples; with ``phase_shifting``, the phase-shifting ones only."""
        if not self.path.is_dir():
            return []
        return sorted(d.name for d in self.path.iterdir() if d.is_dir() and is_scan_folder(d, phase_shifting))

    def ipattern_file(self, sid: str) -> Path:
        """The single-shot image file of scan ``sid`` of a scan folder."""
        return self.path / FOLDERS["image"][0] / f"{sid}.mat"

    def fppsim_samples(self) -> "Source | None":
        """The reader of fppsim's native sample folders behind this path (they carry ``dataset.json``, the
        rig and each sample's exact phase): the path itself, a figshare export's ``native/`` folder, else None."""
        native = self.path / "native"
        return NativeSamples(native) if NativeSamples.recognise(native) else None

    # ------------------------------------------------------------------ what it provides
    def ids(self) -> list[str]:
        """The sample / scan / image ids, in reading order."""
        return []

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        """``(id, grey uint8 (H, W))`` of every fringe image the path holds."""
        return iter(())

    def fringe_image(self, sid: str) -> np.ndarray:
        """The grey image of id ``sid`` (one of :meth:`ids`); the base reads :meth:`fringe_images` up to it."""
        for k, gray in self.fringe_images():
            if k == sid:
                return gray
        raise DatasetError(f"{self.path}: no fringe image {sid!r}")

    def inputs(self) -> Iterator[tuple[str, np.ndarray, Path]]:
        """What ``predict`` reads: ``(name, fringe float32 (H, W) in the dataset encoding, file)`` of every
        fringe image, named ``<folder>_<id>``."""
        for sid, gray in self.fringe_images():
            yield f"{self.path.name}_{sid}", encode_fringe(gray), self.path

    def height_labels(self) -> np.ndarray | None:
        """The label stack (N, H, W) float32 (figshare preset) of a labelled layout, else None."""
        return None

    def check_samples(self, transform, label: str = "true") -> None:
        """Refuse (:class:`fppsim.errors.DatasetError`, naming the file) a labelled layout the networks would
        misread with ``transform`` / ``label`` (``"true"`` or ``"psp"`` heights), before training."""
        if not self.labelled:
            raise DatasetError(f"{self.path}: no labelled samples here ({self.kind}); {labelled_hint()}")

    def sample(self, i: int, transform, label: str = "true", mask_fringe: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """``(fringe, label)`` float32 (H, W) of sample ``i`` as the networks read them: the fringe in the
        dataset encoding (intensity / 127.5 - 1), the height in ``transform``'s label units."""
        raise DatasetError(f"{self.path}: no labelled samples here ({self.kind}); {labelled_hint()}")

    def exact_phase(self, i: int, shape: tuple[int, ...] | None = None) -> np.ndarray:
        """The exact projector phase (H, W) float32 of sample ``i`` (fppsim's native samples)."""
        raise DatasetError(f"{self.path}: its samples carry no exact phase (fppsim's native samples do)")

    def phase_ids(self) -> list[str]:
        """The ids of the frames with an absolute phase (phase-shifting scans), else []."""
        return []

    def phase(self, sid: str, **kw) -> np.ndarray | None:
        """The absolute phase (H, W) float64 of scan ``sid`` (``kw``: the phase convention of
        :func:`fppsim.dataio.readers.load_psp_folder_sample`), else None."""
        return None

    def scan_ids(self) -> list[str]:
        """The ids of the phase-shifting scans :meth:`scan` reads. A path without them raises
        :class:`fppsim.errors.PSPMatError`, one line naming what a scan folder would need and what it holds (and
        the scan folders one level down, when it holds them: :func:`fppsim.dataio.readers.scan_folders_note`)."""
        try:
            return list_psp_ids(self.path)
        except PSPMatError as exc:
            note = "" if self.is_psp else scan_folders_note(self.path, self.scan_folders(phase_shifting=True))
            if not note:
                raise
            raise PSPMatError(f"{exc}{note}") from None

    def scan(self, sid: str, convention: str = "benchmark", negate_sin: bool = False) -> PspMat:
        """Phase-shifting scan ``sid`` as a :class:`fppsim.dataio.readers.PspMat`: ``image`` (the single-shot
        uint8 image), ``phase`` (absolute, NaN where there is none), ``valid``, ``path`` and ``meta`` (how it
        was read: :func:`fppsim.dataio.readers.reading_note`); ``convention`` / ``negate_sin`` as
        :func:`fppsim.dataio.readers.load_psp_folder_sample`. :class:`PSPMatError` naming the file otherwise."""
        raise PSPMatError(f"{self.path}: no phase-shifting scans here ({self.kind})")

    def psp_images(self, sid: str) -> tuple[np.ndarray, dict, np.ndarray, dict]:
        """The phase-shifting images of sample ``sid`` as rendered (fppsim's native samples generated with them):
        ``(fringe grey, {f: grey stack (steps, H, W)}, shifts (steps,) rad, meta)``
        (:func:`fppsim.dataio.readers.read_native_psp`); :class:`DatasetError` naming the path otherwise."""
        raise DatasetError(f"{self.path}: no phase-shifting images here ({self.kind})")

    def measured_phase_ids(self) -> list[str]:
        """The ids of the frames with a MEASURED absolute phase (phase-shifting scans: :meth:`phase_ids`; fppsim's
        native samples generated with PSP images), else []."""
        return self.phase_ids()

    def measured_phase(self, sid: str, convention: str = "benchmark", negate_sin: bool = False
                       ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(phase, valid)`` of frame ``sid`` as a lab measured it: the absolute phase (H, W) float64 rad and
        where it exists (a scan's pixels with a phase and a non-black image; a native sample's ``phase_psp`` /
        ``mask_psp``), else None. ``convention`` / ``negate_sin``: how the public layout's files combine
        (:func:`fppsim.dataio.readers.load_psp_folder_sample`); fppsim's native samples hold their decoded
        phase and ignore them. The base reads the frame's :meth:`scan`."""
        if sid not in self.phase_ids():
            return None
        s = self.scan(sid, convention=convention, negate_sin=negate_sin)
        phase = np.asarray(s.phase, np.float64)
        valid = s.valid & np.isfinite(phase) & (s.image > 0 if s.image is not None else True)
        return phase, valid


def is_scan_folder(path: str | os.PathLike, phase_shifting: bool = False) -> bool:
    """Whether ``path`` is a scan folder (:meth:`Source.scan_folders`); False for one it may not look into."""
    try:
        src = open_source(path)
    except OSError:  # another user's folder (lost+found on a disk's root): no scan anyone here could read
        return False
    return src.is_psp or (src.has_manifest and not phase_shifting)


def describe_layouts() -> str:
    """The registered layouts in the order they are recognised, one line each: ``kind: what the path holds``."""
    return "\n".join(f"{cls.kind}: {cls.holds}" for cls in LAYOUTS)


def labelled_hint() -> str:
    """``expected A, B or C``: what the registered labelled layouts hold (a layout is labelled when its
    ``labelled`` is True or decided per path), for the errors that find no labelled samples."""
    kinds = list(dict.fromkeys(cls.holds for cls in LAYOUTS
                               if cls.holds and (inspect.getattr_static(cls, "labelled") is True
                                                 or isinstance(inspect.getattr_static(cls, "labelled"), property))))
    return "expected " + (", ".join(kinds[:-1]) + " or " + kinds[-1] if len(kinds) > 1 else "".join(kinds))


class _File(Source):
    """A single file (image, ``.npy`` or other) or nothing at all."""

    plain_files = True


class ImageFile(_File):
    kind = "image"
    holds = "one image file (IMAGE_EXTS)"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_file() and path.suffix.lower() in IMAGE_EXTS

    def ids(self) -> list[str]:
        return [self.path.stem]

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        yield self.path.stem, read_gray_image(self.path)

    def fringe_image(self, sid: str) -> np.ndarray:
        return read_gray_image(self.path)


class NpyFile(_File):
    kind = "npy"
    holds = "one .npy array file (a fringe or a stack of them)"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_file() and path.suffix.lower() == ".npy"

    def _stack(self) -> np.ndarray:
        return as_image_stack(load_npy(self.path), self.path)

    def ids(self) -> list[str]:
        return [f"{self.path.stem}_{k:04d}" for k in range(self._stack().shape[0])]

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        arr = self._stack()
        for k in range(arr.shape[0]):
            a = np.asarray(arr[k])
            yield f"{self.path.stem}_{k:04d}", a if a.dtype == np.uint8 else decode_fringe(a.astype(np.float32))


class OtherFile(_File):
    kind = "file"
    holds = "any other file"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_file()


class Missing(_File):
    kind = "missing"
    holds = "nothing at that path"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return not path.is_dir()


class _ScanFolder(Source):
    """A phase-shifting scan folder, whole or in part (``PSin/ PCos/ Fringe/ iPattern/``)."""

    is_psp = True

    def ids(self) -> list[str]:
        return self.image_ids()

    def image_ids(self) -> list[str]:
        """The ids of a scan folder's single-shot images (``iPattern/<id>.mat``)."""
        return list_psp_ids(self.path, roles=("image",))

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        for sid in self.image_ids():
            yield sid, load_ipattern(self.ipattern_file(sid))

    def fringe_image(self, sid: str) -> np.ndarray:
        return load_ipattern(self.ipattern_file(sid))

    def scan(self, sid: str, convention: str = "benchmark", negate_sin: bool = False) -> PspMat:
        return load_psp_folder_sample(self.path, sid, convention=convention, negate_sin=negate_sin)

    def inputs(self) -> Iterator[tuple[str, np.ndarray, Path]]:
        for sid in self.image_ids():  # only the single-shot images are read
            f = self.ipattern_file(sid)
            yield f"{self.path.name}_{sid}", encode_fringe(load_ipattern(f)), f


class PspFolder(_ScanFolder):
    kind = "psp"
    holds = "the phase-shifting scan folder: PSin/ and PCos/ (with Fringe/, iPattern/)"
    described_as = "psp-folders"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return is_psp_folder(path)

    def ids(self) -> list[str]:
        return list_psp_ids(self.path)

    def phase_ids(self) -> list[str]:
        return self.ids()

    def phase(self, sid: str, **kw) -> np.ndarray | None:
        return load_psp_folder_sample(self.path, sid, **kw).phase


class IPatternFolder(_ScanFolder):
    kind = "ipattern"
    holds = "its single-shot images only: iPattern/ alone (with some of the others: psp-partial)"

    @classmethod
    def recognise(cls, path: Path) -> bool:  # iPattern/ alone: with some of the others it is a damaged scan
        return (path / FOLDERS["image"][0]).is_dir() and not any(
            (path / sub).is_dir() for r, (sub, _) in FOLDERS.items() if r != "image")


class PartialScanFolder(_ScanFolder):
    kind = "psp-partial"
    holds = "some of those sub-folders, none of the two above (a damaged scan folder)"

    def problem(self) -> str | None:
        return self.incomplete()

    def incomplete(self) -> str:
        """One line naming what the damaged scan folder lacks (and holds)."""
        subs = [sub for sub, _ in FOLDERS.values()]
        missing = [f"{s}/" for s in subs if not (self.path / s).is_dir()]
        found = [f"{s}/" for s in subs if (self.path / s).is_dir()]
        return (f"{self.path}: incomplete phase-shifting scan folder: missing {', '.join(missing)} (found "
                f"{', '.join(found)}); a scan needs PSin/, PCos/, Fringe/ and iPattern/ (iPattern/ alone: its "
                "single-shot images only)")

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return any((path / sub).is_dir() for sub, _ in FOLDERS.values())

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        if (self.path / FOLDERS["image"][0]).is_dir():
            yield from super().fringe_images()

    def inputs(self) -> Iterator[tuple[str, np.ndarray, Path]]:
        return iter(())


class _Pair(Source):
    """A figshare-format pair: a fringe stack in the dataset encoding and its label stack."""

    pair_index = 0

    @classmethod
    def recognise(cls, path: Path) -> bool:
        pair = find_figshare_pair(path)
        return pair is not None and pair[0].name == FIGSHARE_PAIRS[cls.pair_index][0]

    @property
    def labelled(self) -> bool:
        return self.pair is not None and self.pair[1].is_file()

    @property
    def array_files(self) -> tuple[Path, Path] | None:
        return self.pair

    def _fringes(self) -> np.ndarray:
        if not self.pair[0].is_file():
            raise DatasetError(f"{self.pair[0]}: file not found (figshare folder {self.path} without its fringes)")
        return as_image_stack(load_npy(self.pair[0]), self.pair[0])

    def ids(self) -> list[str]:
        return [str(i) for i in range(self._fringes().shape[0])]

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        arr = self._fringes()
        for k in range(arr.shape[0]):
            yield str(k), decode_fringe(np.asarray(arr[k], dtype=np.float32))

    def inputs(self) -> Iterator[tuple[str, np.ndarray, Path]]:
        arr = self._fringes()  # fringes only: labels are never read
        for k in range(arr.shape[0]):
            yield (f"{self.path.name}_{k:04d}" if arr.shape[0] > 1 else self.path.name,
                   np.asarray(arr[k], dtype=np.float32), self.pair[0])

    def fringe_image(self, sid: str) -> np.ndarray:
        return decode_fringe(np.asarray(self._fringes()[int(sid)], dtype=np.float32))

    def sample(self, i: int, transform, label: str = "true", mask_fringe: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The stored fringe and label (already in label units: ``transform`` is what they were labelled with,
        :meth:`check_samples`; the stored fringe is masked as written)."""
        if not self.labelled:
            return super().sample(i, transform, label, mask_fringe)
        fringes, labels = open_figshare_pair(*self.pair)
        return np.asarray(fringes[int(i)], dtype=np.float32), np.asarray(labels[int(i)], dtype=np.float32)

    def height_labels(self) -> np.ndarray | None:
        if not self.labelled:
            return None
        z = load_npy(self.pair[1])
        return z[..., 0] if z.ndim == 4 else z

    def check_samples(self, transform, label: str = "true") -> None:
        super().check_samples(transform, label)
        if label == "psp":
            raise DatasetError(f"{self.path}: --synthetic-label psp needs native samples with PSP arrays, but this "
                               "is a figshare-format export (its Z is the exact height); use its native/ folder")
        open_figshare_pair(*self.pair)  # the two files agree in shape (DatasetError naming the file)
        check_export_labels(self.path, transform)



class FigsharePair(_Pair):
    kind = "figshare"
    holds = "f1_80.npy + Z.npy (a figshare pair)"
    pair_index = 0


class RealSamplePair(_Pair):
    kind = "real-sample"
    holds = "fringe_pattern.npy + height_map.npy (the published real pair)"
    pair_index = 1


class NativeSamples(Source):
    """fppsim's native samples: ``manifest.jsonl`` (or, without one, every ``<id>/arrays.npz`` folder) with
    ``<id>/fringe.png`` and ``<id>/arrays.npz`` per sample."""

    kind = "native"
    holds = "fppsim's native samples (manifest.jsonl with <id>/fringe.png + <id>/arrays.npz)"
    labelled = True
    _ids: list[str] | None = None

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return (path / "manifest.jsonl").is_file() or (path / "dataset.json").is_file()

    def ids(self) -> list[str]:
        if self._ids is None:  # read once per reader: sample() asks for every training sample
            if self.has_manifest:
                self._ids = manifest_ids(self.path)
            else:
                self._ids = (sorted(p.name for p in self.path.iterdir() if (p / "arrays.npz").is_file())
                             if self.path.is_dir() else [])
                if self._ids:
                    warn_skipped(self.path, (), folders=True)  # a sample folder linked from where it no longer is
        return list(self._ids)

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        for sid in self.ids():
            yield sid, self.fringe_image(sid)

    def fringe_image(self, sid: str) -> np.ndarray:
        return read_gray_image(self.path / sid / "fringe.png")

    def check_samples(self, transform, label: str = "true") -> None:
        ids = self.ids()
        if not ids:
            raise DatasetError(
                f"{self.path}: no samples (expected manifest.jsonl with <id>/arrays.npz, or f1_80.npy and Z.npy)")
        for sid in ids:
            for name in ("fringe.png", "arrays.npz"):
                if not (self.path / sid / name).is_file():
                    raise DatasetError(f"{self.path / sid / name}: file not found (listed in manifest.jsonl)")
        if label == "psp":
            check_psp_available(self.path, ids[0])

    def sample(self, i: int, transform, label: str = "true", mask_fringe: bool = True) -> tuple[np.ndarray, np.ndarray]:
        return read_native_pair(self._folder(i), transform, label, mask_fringe)

    def exact_phase(self, i: int, shape: tuple[int, ...] | None = None) -> np.ndarray:
        return read_native_phase(self._folder(i), shape)

    def psp_images(self, sid: str) -> tuple[np.ndarray, dict, np.ndarray, dict]:
        return read_native_psp(self.path / sid)

    def _folder(self, i: int) -> Path:
        self.ids()
        return self.path / self._ids[int(i)]

    def measured_phase_ids(self) -> list[str]:
        ids = self.ids()
        if not ids:
            return []
        try:
            with np.load(self.path / ids[0] / "arrays.npz", allow_pickle=False) as z:
                return ids if "phase_psp" in z.files else []
        except (OSError, ValueError):
            return []

    def measured_phase(self, sid: str, convention: str = "benchmark", negate_sin: bool = False
                       ) -> tuple[np.ndarray, np.ndarray] | None:
        arrays = load_native_sample(self.path / sid, keys=("phase_psp", "mask_psp"), meta=False)
        if "phase_psp" not in arrays:
            return None
        phase = arrays["phase_psp"].astype(np.float64)
        valid = np.isfinite(phase) & (arrays["mask_psp"] > 0 if "mask_psp" in arrays else True)
        return phase, valid

    def fppsim_samples(self) -> Source | None:
        return self


class NativeFolders(NativeSamples):
    """fppsim's native sample folders without a manifest (``<id>/arrays.npz``): readable as samples."""

    holds = "fppsim's native sample folders without a manifest (<id>/arrays.npz)"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_dir() and any(os.path.isfile(p / "arrays.npz") for p in path.iterdir())  # (False unreadable)


class Folder(Source):
    """Anything else: a folder of images (or of scan folders), or an empty one."""

    kind = "folder"
    holds = "anything else: a folder of images, of scan folders, or nothing"
    described_as = "images"
    plain_files = True

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_dir()

    def _images(self) -> list[Path]:
        found = sorted(q for q in self.path.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTS)
        if found:  # (with none, the caller's error names what was skipped)
            warn_skipped(self.path, IMAGE_EXTS)
        return found

    def ids(self) -> list[str]:
        return [p.stem for p in self._images()]

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        for p in self._images():
            yield p.stem, read_gray_image(p)

    def fringe_image(self, sid: str) -> np.ndarray:
        path = next((p for p in self._images() if p.stem == sid), None)
        if path is None:
            raise DatasetError(f"{self.path}: no fringe image {sid!r}")
        return read_gray_image(path)


LAYOUTS: list[type[Source]] = [ImageFile, NpyFile, OtherFile, Missing, PspFolder, IPatternFolder, PartialScanFolder,
                               FigsharePair, RealSamplePair, NativeSamples, NativeFolders, Folder]
"""Every layout's reader, in the order :func:`open_source` asks them (the first that recognises a path wins)."""


def register_layout(cls: type[Source], before: str = "folder") -> type[Source]:
    """Add a layout's reader to :data:`LAYOUTS`, asked before the layout named ``before`` (default: before
    the catch-all ``folder``); usable as a class decorator. A kind registered twice is refused."""
    if any(c.kind == cls.kind for c in LAYOUTS):
        raise InputError(f"layout {cls.kind!r} is registered already")
    at = next((k for k, c in enumerate(LAYOUTS) if c.kind == before), len(LAYOUTS))
    LAYOUTS.insert(at, cls)
    return cls


def open_source(path: str | os.PathLike) -> Source:
    """The reader of what ``path`` holds (module docstring): THE layout recognition of every data path."""
    path = Path(path)
    pair = find_figshare_pair(path) if path.is_dir() else None
    for cls in LAYOUTS:
        if cls.recognise(path):
            return cls(path, pair)
    return Folder(path, pair)



# ============================================================================================ labelled samples
def open_labelled(path: str | os.PathLike, transform: LabelTransform = PRESETS["figshare"]) -> Source:
    """The reader of the labelled layout at ``path`` (:func:`open_source`), checked for ``transform``
    (:meth:`Source.check_samples`): THE numpy opener of labelled data (``compare-real``, fitting). Raises
    :class:`DatasetError` (a ValueError) naming the path when it holds no labelled samples or damaged ones."""
    src = open_source(path)
    if not src.labelled:
        if not src.path.exists():
            raise DatasetError(f"{src.path}: not a folder (no such path)")
        raise DatasetError(f"{src.path}: no dataset found ({labelled_hint()})"  # a pair's file may be a dead link
                           + skipped_note(src.path, (), folders=True))
    src.check_samples(transform)
    return src


def grey_sample(src: Source, i: int, transform: LabelTransform = PRESETS["figshare"]) -> tuple[np.ndarray, np.ndarray]:
    """``(grey uint8 (H, W), label float32 (H, W))`` of sample ``i`` of a labelled reader: its
    :meth:`Source.sample` (fringe not masked), the fringe decoded to 8-bit grey levels."""
    fringe, label = src.sample(int(i), transform, "true", mask_fringe=False)
    gray, label = decode_fringe(fringe), np.asarray(label, dtype=np.float32)
    if gray.shape != label.shape:
        raise DatasetError(f"{src.path}: sample {i}: fringe {gray.shape} and height {label.shape} differ in shape")
    return gray, label


def iter_samples(src: "Source | str | os.PathLike", max_samples: int | None = None,
                 transform: LabelTransform = PRESETS["figshare"]) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """:func:`grey_sample` of up to ``max_samples`` evenly spaced samples of a labelled reader (or path)."""
    src = src if isinstance(src, Source) else open_labelled(src, transform)
    for i in pick_evenly(len(src.ids()), max_samples):
        yield grey_sample(src, int(i), transform)
