"""The one opener of real (and synthetic) data: :func:`open_source` recognises what a path holds.

Every command that reads fringes from a path the user names asks :func:`open_source` which layout it
is, instead of testing for file names itself (``tests/test_layers.py`` checks that the layout names
appear only in :mod:`fppsim.dataio.readers`, :mod:`fppsim.dataio.formats` and :mod:`fppsim.dataio.writers`). Kinds, in the
order they are recognised (the first that fits wins):

=================  ===================================================================================
kind               what the path holds
=================  ===================================================================================
``image``          one image file (:data:`IMAGE_EXTS`)
``npy``            one ``.npy`` array file (a fringe or a stack of them)
``file``           any other file
``psp``            the phase-shifting scan folder: ``PSin/`` and ``PCos/`` (with ``Fringe/``, ``iPattern/``)
``ipattern``       its single-shot images only: ``iPattern/`` without the ``PSin/`` + ``PCos/`` pair
``psp-partial``    some of those sub-folders, none of the two above (a damaged scan folder)
``figshare``       a figshare pair, ``f1_80.npy`` + ``Z.npy`` (either file: the other is then missing)
``real-sample``    the published pair ``fringe_pattern.npy`` + ``height_map.npy`` (likewise)
``native``         fppsim's native samples (``manifest.jsonl``)
``folder``         anything else: a folder of images, of scan folders (:meth:`Source.scan_folders`), or nothing
``missing``        nothing at that path
=================  ===================================================================================

What each kind provides: :meth:`Source.fringe_images` (always; ``(id, grey uint8)``), and where the
layout has them :meth:`Source.height_labels` (figshare labels) and :meth:`Source.phase` (the absolute
phase of a ``psp`` scan); :meth:`Source.ids`. Callers keep their own readers for what they need
beyond that (memory-mapped stacks, torch datasets, labelled scans).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from fppsim.dataio.encoding import as_image_stack, decode_fringe, read_gray_image
from fppsim.dataio.formats import FIGSHARE_PAIRS, find_figshare_pair, manifest_ids
from fppsim.dataio.readers.psp_mat import FOLDERS, is_psp_folder, list_psp_ids, load_ipattern, load_psp_folder_sample

__all__ = ["IMAGE_EXTS", "PSP_KINDS", "PAIR_KINDS", "Source", "open_source"]

IMAGE_EXTS = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
PSP_KINDS = ("psp", "ipattern", "psp-partial")  # a phase-shifting scan folder, whole or in part
PAIR_KINDS = ("figshare", "real-sample")


@dataclass(frozen=True)
class Source:
    """What :func:`open_source` found at ``path``: its ``kind`` (module docstring) and ``pair`` =
    ``(fringe, label)`` paths of the first figshare-format pair of which the folder holds either file
    (whatever its kind: a scan folder may hold one too), else None."""

    path: Path
    kind: str
    pair: tuple[Path, Path] | None = None

    # ------------------------------------------------------------------ what the layout is
    @property
    def is_psp(self) -> bool:
        """Any phase-shifting scan folder (``psp``, ``ipattern`` or ``psp-partial``)."""
        return self.kind in PSP_KINDS

    @property
    def has_images(self) -> bool:
        """Single-shot images a scan folder holds (``iPattern/``): ``psp`` or ``ipattern`` kinds."""
        return self.kind in ("psp", "ipattern") and (self.path / FOLDERS["image"][0]).is_dir()

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

    def scan_folders(self) -> list[str]:
        """Names of the sub-folders (sorted) that are scan folders themselves (phase-shifting or native)."""
        if not self.path.is_dir():
            return []
        return sorted(d.name for d in self.path.iterdir() if d.is_dir() and (
            open_source(d).is_psp or open_source(d).has_manifest))

    def ipattern_file(self, sid: str) -> Path:
        """The single-shot image file of scan ``sid`` of a scan folder."""
        return self.path / FOLDERS["image"][0] / f"{sid}.mat"

    # ------------------------------------------------------------------ what it provides
    def ids(self) -> list[str]:
        """The sample / scan ids: a ``psp`` folder's (scans with every quantity), an ``ipattern`` one's
        (:meth:`image_ids`), a pair's (``0 .. N-1``), native samples' (the manifest's)."""
        if self.kind == "psp":
            return list_psp_ids(self.path)
        if self.kind in PSP_KINDS:
            return self.image_ids()
        if self.kind in PAIR_KINDS:
            return [str(i) for i in range(len(np.load(self.pair[0], mmap_mode="r", allow_pickle=False)))]
        if self.kind == "native":
            return manifest_ids(self.path)
        return [self.path.stem] if self.kind in ("image", "npy") else []

    def image_ids(self) -> list[str]:
        """The ids of a scan folder's single-shot images (``iPattern/<id>.mat``)."""
        return list_psp_ids(self.path, roles=("image",))

    def fringe_images(self) -> Iterator[tuple[str, np.ndarray]]:
        """``(id, grey uint8 (H, W))`` of every fringe image the path holds (scan folders: their
        ``iPattern`` images; a pair's fringes; native samples' ``fringe.png``; image files; ``.npy``
        stacks, uint8 or in the dataset encoding)."""
        if self.kind in PSP_KINDS:
            for sid in self.image_ids():
                yield sid, load_ipattern(self.ipattern_file(sid))
        elif self.kind in PAIR_KINDS:
            arr = as_image_stack(np.load(self.pair[0], mmap_mode="r", allow_pickle=False), self.pair[0])
            for k in range(arr.shape[0]):
                yield str(k), decode_fringe(np.asarray(arr[k], dtype=np.float32))
        elif self.kind == "native":
            for sid in manifest_ids(self.path):
                yield sid, read_gray_image(self.path / sid / "fringe.png")
        elif self.kind == "image":
            yield self.path.stem, read_gray_image(self.path)
        elif self.kind == "npy":
            arr = as_image_stack(np.load(self.path, mmap_mode="r", allow_pickle=False), self.path)
            for k in range(arr.shape[0]):
                a = np.asarray(arr[k])
                yield f"{self.path.stem}_{k:04d}", a if a.dtype == np.uint8 else decode_fringe(a.astype(np.float32))
        elif self.kind == "folder":
            for p in sorted(q for q in self.path.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTS):
                yield p.stem, read_gray_image(p)

    def height_labels(self) -> np.ndarray | None:
        """The label stack (N, H, W) float32 (memory-mapped) of a pair, else None."""
        if self.kind not in PAIR_KINDS or not self.pair[1].is_file():
            return None
        z = np.load(self.pair[1], mmap_mode="r", allow_pickle=False)
        return z[..., 0] if z.ndim == 4 else z

    def phase(self, sid: str, **kw) -> np.ndarray | None:
        """The absolute phase (H, W) float64 of scan ``sid`` of a ``psp`` folder (``kw``: the phase
        convention of :func:`fppsim.dataio.readers.load_psp_folder_sample`), else None."""
        return load_psp_folder_sample(self.path, sid, **kw).phase if self.kind == "psp" else None


def open_source(path: str | os.PathLike) -> Source:
    """Recognise what ``path`` holds (module docstring): THE layout recognition of real data."""
    path = Path(path)
    if path.is_file():
        ext = path.suffix.lower()
        return Source(path, "image" if ext in IMAGE_EXTS else "npy" if ext == ".npy" else "file")
    if not path.is_dir():
        return Source(path, "missing")
    pair = find_figshare_pair(path)
    pair_kind = None if pair is None else PAIR_KINDS[[f for f, _ in FIGSHARE_PAIRS].index(pair[0].name)]
    if is_psp_folder(path):
        kind = "psp"
    elif (path / FOLDERS["image"][0]).is_dir():
        kind = "ipattern"
    elif any((path / sub).is_dir() for sub, _ in FOLDERS.values()):
        kind = "psp-partial"
    elif pair_kind is not None:
        kind = pair_kind
    elif (path / "manifest.jsonl").is_file():
        kind = "native"
    else:
        kind = "folder"
    return Source(path, kind, pair)
