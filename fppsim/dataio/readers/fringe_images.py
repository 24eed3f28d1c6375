"""Real fringe images for fitting the simulator: every layout, read as one list.

:func:`load_fringe_images` reads whatever layout a path holds through its reader
(:func:`fppsim.dataio.readers.open_source`): a figshare folder (``f1_80.npy`` + ``Z.npy``), the published
real-sample pair, a native fppsim folder, the phase-shifting ``PSin/PCos/Fringe/iPattern`` folders (or just
``iPattern/``), a folder of grey images (or one image file), or a layout registered since, and returns
:class:`FringeImage` records: the grey image, its valid pixels, and plane / object pixels where the source tells them apart (height labels, or the real
phase through :func:`fppsim.phase.plane.phase_plane_masks`). ``fppsim fit-rig`` and ``fppsim fit-optics``
measure these.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fppsim.dataio.encoding import to_8bit
from fppsim.dataio.formats import PRESETS
from fppsim.errors import PSPMatError, InputError
from fppsim.phase.plane import phase_plane_masks, plane_level
from fppsim.dataio.readers.samples import pick_evenly
from fppsim.dataio.readers.psp_mat import reading_note
from fppsim.dataio.readers.listing import IMAGE_EXTS, scan_folders_note, skipped_note
from fppsim.dataio.readers.source import Source, grey_sample, open_labelled, open_source

__all__ = ["FringeImage", "load_fringe_images"]


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
    """Real fringe images of whatever layout ``path`` holds, as its reader (:func:`open_source`) provides them:
    figshare (``f1_80.npy`` + ``Z.npy``), the real-sample pair, native fppsim, the PSin/PCos/Fringe/iPattern
    layout (or just ``iPattern/``), a folder of 8- or 16-bit grey images (or one image file), or any layout
    registered since.

    Frames with an absolute phase (:meth:`Source.phase_ids`, read by :meth:`Source.scan`) tell plane from object
    pixels by their phase (:func:`phase_plane_masks`); labelled samples (:func:`grey_sample`) by their heights
    (within / beyond ``plane_mm`` of the plane level); plain images have neither. ``valid`` drops black pixels
    (the datasets' shadow marker) and pixels without phase or label. At most ``max_images`` evenly spaced
    images. ``convention`` / ``negate_sin``: how the public layout's PSin / PCos / Order combine into its phase
    (:func:`fppsim.dataio.readers.load_psp_folder_sample`; each image's ``read_as`` says how ``"auto"`` read one
    written another way). Images are read by :func:`fppsim.dataio.encoding.read_gray_image` (a colour image is
    refused unless its channels are equal) and made 8-bit by :func:`fppsim.dataio.encoding.to_8bit`. Returns
    ``(images, layout)`` (:attr:`Source.layout`); ValueError if nothing is readable.
    """
    src = open_source(path)
    path = src.path
    problem = src.problem()
    if problem:  # a damaged scan folder is named, never read as plain images
        raise InputError(problem)
    try:
        scans = src.phase_ids()
        if scans:
            out = []
            for i in pick_evenly(len(scans), max_images):
                s = src.scan(scans[int(i)], convention=convention, negate_sin=negate_sin)
                valid = s.valid & (s.image > 0)
                plane, obj = phase_plane_masks(s.phase, valid)
                out.append(FringeImage(to_8bit(s.image), valid, scans[int(i)], plane, obj, phase=s.phase,
                                       read_as=reading_note(s.meta)))
            return out, src.layout
        if src.labelled:
            return _labelled_images(open_labelled(path), max_images, plane_mm), src.layout
        ids = src.ids()
        out = []
        for i in pick_evenly(len(ids), max_images):
            gray = to_8bit(src.fringe_image(ids[int(i)]))
            out.append(FringeImage(gray, gray > 0, ids[int(i)]))
    except PSPMatError as exc:
        raise InputError(str(exc)) from None
    if not out:
        if not path.is_dir():
            raise InputError(f"{path}: not a folder or image file")
        raise InputError(f"{path}: no fringe images (figshare f1_80.npy + Z.npy, fringe_pattern.npy + "
                         "height_map.npy, native manifest.jsonl, PSin/PCos/Fringe/iPattern folders, or "
                         f"{'/'.join(IMAGE_EXTS)} files)" + scan_folders_note(path, src.scan_folders())
                         + skipped_note(path, IMAGE_EXTS))
    return out, src.layout


def _labelled_images(src: Source, max_images: int | None, plane_mm: float) -> list[FringeImage]:
    """:class:`FringeImage` records of a labelled reader's samples, labels in the figshare preset's units."""
    label = PRESETS["figshare"]
    out = []
    for i in pick_evenly(len(src.ids()), max_images):
        gray, lab = grey_sample(src, int(i), label)
        marker = np.isclose(lab, label.invalid_value, atol=1e-4) | ~np.isfinite(lab)
        valid = ~marker & (gray > 0)
        plane = obj = np.zeros_like(valid)
        if valid.any():
            level = plane_level(lab, valid)
            plane = valid & (np.abs(lab - level) <= plane_mm * label.units_per_mm)
            obj = valid & (lab > level + plane_mm * label.units_per_mm)
            height = np.where(valid, (lab - level) / label.units_per_mm, np.nan)
        else:
            height = np.full(lab.shape, np.nan)
        out.append(FringeImage(gray, valid, f"{src.layout}[{int(i)}]", plane, obj, height))
    return out
