"""Real fringe images for fitting the simulator: the five real-data layouts, read as one list.

:func:`load_fringe_images` reads a figshare folder (``f1_80.npy`` + ``Z.npy``), the published
real-sample pair, a native fppsim folder (all three through :class:`fppsim.dataio.readers.SampleReader`), the
phase-shifting ``PSin/PCos/Fringe/iPattern`` folders (or just ``iPattern/``) and a folder of 8-bit
images (or one image file), and returns :class:`FringeImage` records: the grey image, its valid
pixels, and plane / object pixels where the source tells them apart (height labels, or the real
phase through :func:`fppsim.phase.plane.phase_plane_masks`). ``fppsim fit-rig`` and ``fppsim fit-optics``
measure these.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fppsim.errors import PSPMatError
from fppsim.phase.plane import phase_plane_masks, plane_level
from fppsim.dataio.readers.datasets import open_samples, pick_evenly
from fppsim.dataio.readers.psp_mat import load_ipattern, load_psp_folder_sample, reading_note
from fppsim.dataio.readers.source import IMAGE_EXTS, open_source

__all__ = ["FringeImage", "IMAGE_EXTS", "load_fringe_images", "read_image_file"]


@dataclass
class FringeImage:
    """One real fringe image.

    gray : uint8 (H, W). valid : bool (H, W), pixels with a fringe (not the black shadow marker, phase
    present). plane, obj : bool (H, W) reference-plane and object pixels when the source tells them
    apart (height labels, or real phase), else None. name : for messages. height_mm : labels (mm) when
    known. phase : float (H, W), the real absolute phase (rad) of phase-shifting scans, else None.
    """

    gray: np.ndarray
    valid: np.ndarray
    name: str = ""
    plane: np.ndarray | None = None
    obj: np.ndarray | None = None
    height_mm: np.ndarray | None = None
    phase: np.ndarray | None = None  # real absolute phase (rad), phase-shifting scans only
    read_as: str | None = None  # how --convention auto read a scan written another way (psp_mat.reading_note)

    @property
    def plane_or_valid(self) -> np.ndarray:
        return self.valid if self.plane is None else self.plane


def load_fringe_images(path, max_images: int | None = 20, plane_mm: float = 2.0, convention: str = "benchmark",
                       negate_sin: bool = False) -> tuple[list[FringeImage], str]:
    """Real fringe images from a folder: figshare (``f1_80.npy`` + ``Z.npy``), the real-sample pair,
    native fppsim, the PSin/PCos/Fringe/iPattern layout (or just ``iPattern/``), or a folder of 8-bit
    images (or one image file).

    ``valid`` drops black pixels (the datasets' shadow marker) and pixels without phase. Plane and
    object pixels come from the height labels (within / beyond ``plane_mm`` of the plane level) or from
    the real phase (:func:`phase_plane_masks`); plain images have neither. At most ``max_images``
    evenly spaced images. ``convention`` / ``negate_sin``: how the public layout's PSin / PCos / Order combine
    into its phase (:func:`fppsim.dataio.readers.load_psp_folder_sample`; each image's ``read_as`` says how
    ``"auto"`` read one written another way). Returns ``(images, layout)``;
    ValueError if nothing is readable.
    """
    src = open_source(path)
    path = src.path
    if src.kind == "image":
        return [read_image_file(path)], "image"
    if not path.is_dir():
        raise ValueError(f"{path}: not a folder or image file")

    if src.kind == "psp-partial":  # a damaged scan folder is named, never read as plain images
        raise ValueError(src.incomplete())
    if src.kind in ("psp", "ipattern"):
        full = src.kind == "psp"
        try:
            ids = src.ids()
            out = []
            for i in pick_evenly(len(ids), max_images):
                sid = ids[int(i)]
                if full:
                    s = load_psp_folder_sample(path, sid, convention=convention, negate_sin=negate_sin)
                    valid = s.valid & (s.image > 0)
                    plane, obj = phase_plane_masks(s.phase, valid)
                    out.append(FringeImage(s.image, valid, sid, plane, obj, phase=s.phase, read_as=reading_note(s.meta)))
                else:
                    img = load_ipattern(src.ipattern_file(sid))
                    out.append(FringeImage(img, img > 0, sid))
        except PSPMatError as exc:
            raise ValueError(str(exc)) from None
        return out, "psp-folders" if full else "ipattern"
    files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS)
    try:
        ds = open_samples(path)
    except ValueError:
        if not files:
            raise ValueError(f"{path}: no fringe images (figshare f1_80.npy + Z.npy, fringe_pattern.npy + "
                             "height_map.npy, native manifest.jsonl, PSin/PCos/Fringe/iPattern folders, or "
                             f"{'/'.join(IMAGE_EXTS)} files)") from None
        files = [files[i] for i in pick_evenly(len(files), max_images)]
        return [read_image_file(f) for f in files], "images"
    out = []
    for i in pick_evenly(len(ds), max_images):
        gray, label = ds.sample(int(i))
        marker = np.isclose(label, ds.label.invalid_value, atol=1e-4) | ~np.isfinite(label)
        valid = ~marker & (gray > 0)
        plane = obj = np.zeros_like(valid)
        if valid.any():
            level = plane_level(label, valid)
            plane = valid & (np.abs(label - level) <= plane_mm * ds.label.units_per_mm)
            obj = valid & (label > level + plane_mm * ds.label.units_per_mm)
            height = np.where(valid, (label - level) / ds.label.units_per_mm, np.nan)
        else:
            height = np.full(label.shape, np.nan)
        out.append(FringeImage(gray, valid, f"{ds.layout}[{int(i)}]", plane, obj, height))
    return out, ds.layout


def read_image_file(path: Path) -> FringeImage:
    """One 8- or 16-bit grey (or colour, converted) image file as a :class:`FringeImage` (16-bit scaled
    to 8-bit; black pixels invalid); ValueError naming the file otherwise."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot read this image")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = np.clip(np.rint(img / 257.0), 0, 255).astype(np.uint8)
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: expected an 8- or 16-bit gray image, got {img.dtype}")
    return FringeImage(img, img > 0, path.name)
