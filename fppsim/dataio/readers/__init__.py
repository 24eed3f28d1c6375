"""Readers of every real and synthetic layout, numpy only (no torch, no rendering): import them from here.

============================  =====================================================================
layout                        readers
============================  =====================================================================
native fppsim folders         :func:`load_native_sample`, :func:`read_native_label`,
                              :func:`read_native_pair` (fringe + label as the networks read them)
figshare pair / real sample   :func:`open_figshare_pair` (memory-mapped), :func:`check_figshare_arrays`,
                              :func:`check_export_labels`
any labelled layout           :func:`open_labelled` (its :class:`Source`, checked), :func:`grey_sample`,
                              :func:`iter_samples` (grey uint8 image + label, e.g. ``compare-real``)
phase-shifting ``.mat``       :func:`load_psp_mat` (one file), :func:`list_psp_ids`,
                              :func:`load_psp_folder_sample`, :func:`iter_psp_folder` (PSin/PCos/Fringe/
                              iPattern folders), ``PspMat.digest()`` (a frame's content hash)
real images for fitting       :func:`load_fringe_images` (every layout, through :func:`open_source`)
which layout a path holds     :func:`open_source` -> the layout's reader, a :class:`Source` (``ids()``,
                              ``fringe_images()``, ``inputs()``, ``sample()``, ``phase()``, ...): THE
                              recognition of every layout, which every command asks; a new layout is
                              one :class:`Source` subclass and :func:`register_layout`
============================  =====================================================================

The file names and the label transform are the contract of :mod:`fppsim.dataio.formats`; the writers of the
same layouts are in :mod:`fppsim.dataio.writers`. Submodules: :mod:`.samples` (native, figshare, any
layout), :mod:`.psp_mat` (``.mat`` files), :mod:`.fringe_images` (real images for fitting),
:mod:`.source` (which layout a path holds).
"""

from __future__ import annotations

from fppsim.dataio.readers.samples import (LABEL_SOURCES, READ_ERRORS, check_export_labels, check_figshare_arrays,
                       check_psp_available, load_native_sample, open_figshare_pair, pick_evenly, read_fringe_image, read_native_label, read_native_pair,
                       read_native_phase, read_native_psp)
from fppsim.dataio.readers.fringe_images import FringeImage, load_fringe_images
from fppsim.dataio.readers.listing import (IMAGE_EXTS, OTHER_IMAGE_EXTS, name_list, plain_images, plain_images_note,
                                          scan_folders_note, scan_folders_words, skipped_note, warn_skipped)
from fppsim.dataio.readers.psp_mat import (CONVENTIONS, COS_KEYS, FOLDERS, ORDER_KEYS, SIN_KEYS, PspMat, PSPMatError, check_convention,
                      is_psp_folder, iter_psp_folder, list_psp_ids, load_ipattern, load_psp_folder_sample,
                      load_psp_mat, phase_jump_share, read_mat_variable, reading_check, reading_note, reading_words,
                      wrapped_from_sums, check_read_convention, AUTO, READINGS, READ_CONVENTIONS)
from fppsim.dataio.readers.source import (LAYOUTS, PAIR_KINDS, PSP_KINDS, Source, describe_layouts, grey_sample,
                                          iter_samples, is_scan_folder, labelled_hint, open_labelled, open_source,
                                          register_layout)

__all__ = [
    # native, figshare, any layout
    "LABEL_SOURCES", "READ_ERRORS", "pick_evenly",
    "load_native_sample", "read_native_label", "read_fringe_image", "read_native_pair", "read_native_phase", "read_native_psp", "check_psp_available",
    "open_figshare_pair", "check_figshare_arrays", "check_export_labels",
    # phase-shifting .mat files
    "PSPMatError", "PspMat", "SIN_KEYS", "COS_KEYS", "ORDER_KEYS", "FOLDERS", "CONVENTIONS", "check_convention",
    "load_psp_mat", "wrapped_from_sums", "is_psp_folder", "list_psp_ids", "read_mat_variable", "load_ipattern",
    "phase_jump_share", "reading_check", "reading_words", "reading_note", "check_read_convention", "AUTO",
    "READINGS", "READ_CONVENTIONS",
    "load_psp_folder_sample", "iter_psp_folder",
    # which layout a path holds
    "Source", "open_source", "is_scan_folder", "register_layout", "LAYOUTS", "PSP_KINDS", "PAIR_KINDS",
    # any labelled layout, as grey images and labels
    "open_labelled", "grey_sample", "iter_samples", "describe_layouts", "labelled_hint",
    # real images for fitting
    "FringeImage", "IMAGE_EXTS", "load_fringe_images",
    # what a folder listing skips that looks meant as input
    "OTHER_IMAGE_EXTS", "name_list", "plain_images", "plain_images_note", "scan_folders_note", "scan_folders_words", "skipped_note",
    "warn_skipped",
]
