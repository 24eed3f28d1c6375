"""What a folder listing leaves out: the entries a reader skips although they look meant as its input.

A reader lists a folder for the suffixes it takes (:data:`IMAGE_EXTS`, ``.npy``, ``.mat``) and passes over
everything else. Two kinds of entry are worth a word, since the user most likely meant them as input: a
symbolic link whose target is gone (a moved scan), and an image in a format the readers do not take
(``.webp``, ``.gif``, ``.jp2``, ``.heic``, ...: :data:`OTHER_IMAGE_EXTS`). :func:`skipped_entries` finds them;
:func:`warn_skipped` prints each once per process (``PROG COMMAND: warning: PATH: skipped: REASON`` on stderr,
:func:`fppsim.files.warn`) when the listing found something else to read, and :func:`skipped_note` adds them to
the error when it found nothing. Hidden entries and other files (a README, a ``.json``) are never mentioned.

The other clauses of those "nothing to read" errors live here too, one owner each: :func:`plain_images_note` (plain
images where scans are needed; :func:`plain_images` lists them) and :func:`scan_folders_note` (scan folders one
level down where one scan folder is needed; :func:`scan_folders_words`, the words they are named by).

The memory behind "once" is per process: a folder is looked through again once its modification time changed (an
entry added, removed or renamed: a notebook reading a folder again after changing it hears of the new entries,
not of those it was told about), and :func:`forget_skipped` clears it all (a long-lived process, a test, that
wants every warning again). A link whose target went away since changes no folder time: not looked at again.
"""

from __future__ import annotations

import os
from pathlib import Path

from fppsim.files import warn

__all__ = ["IMAGE_EXTS", "OTHER_IMAGE_EXTS", "skipped_entries", "warn_skipped", "forget_skipped", "skipped_note",
           "plain_images", "plain_images_note", "native_samples_note", "scan_folders_note", "scan_folders_words",
           "name_list"]

IMAGE_EXTS = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
"""The image files the readers take (:func:`fppsim.dataio.encoding.read_gray_image`)."""
OTHER_IMAGE_EXTS = (".webp", ".gif", ".jp2", ".j2k", ".jpx", ".jpe", ".jfif", ".heic", ".heif", ".avif", ".jxl",
                    ".pgm", ".ppm", ".pbm", ".pnm", ".pfm", ".exr", ".hdr", ".psd", ".tga", ".ico", ".svg", ".dng",
                    ".raw", ".cr2", ".nef", ".arw")
"""Image formats the readers do not take: a file of one in an input folder is skipped with a warning."""

_listed: set[tuple] = set()  # (folder, its mtime, taken, folders) already looked through by warn_skipped
_warned: set[str] = set()  # and the lines it printed: once per entry, however often and however it is listed


def skipped_entries(folder: str | os.PathLike, taken: tuple[str, ...],
                    folders: bool = False) -> list[tuple[Path, str]]:
    """``(entry, reason)`` of each entry of ``folder`` that a listing of the suffixes ``taken`` skips although it looks
    meant as input: a dangling symbolic link named like an input or an image, and a file of an image format not
    in ``taken``; with ``folders`` (a listing of sample folders), any dangling link and nothing else. Sorted by
    name; [] when ``folder`` cannot be listed."""
    try:
        entries = sorted(Path(folder).iterdir())
    except OSError:
        return []
    images = set(IMAGE_EXTS) | set(OTHER_IMAGE_EXTS)
    out = []
    for q in entries:
        suffix = q.suffix.lower()
        if q.name.startswith("."):
            continue
        if q.is_symlink() and not q.exists():
            if folders or suffix in taken or suffix in images:
                out.append((q, f"a symbolic link to {os.readlink(q)}, which does not exist"))
        elif not folders and suffix in images and suffix not in taken and q.is_file():
            out.append((q, f"{q.suffix} is not a format read here"))
    return out


def warn_skipped(folder: str | os.PathLike, taken: tuple[str, ...], folders: bool = False) -> None:
    """Print ``PROG COMMAND: warning: ENTRY: skipped: REASON`` on stderr (:func:`fppsim.files.warn`) for each of
    :func:`skipped_entries`, once per process: a folder is listed again for every frame read from it, and is
    looked through only the first time (a second look cost as much as the listing itself), or again once it changed
    (module docstring)."""
    try:
        mtime = os.stat(folder).st_mtime_ns
    except OSError:
        mtime = None
    key = (os.path.abspath(folder), mtime, tuple(taken), folders)
    if key in _listed:
        return
    _listed.add(key)
    for path, reason in skipped_entries(folder, taken, folders):
        line = f"{path}: skipped: {reason}" + ("" if path.is_symlink() else f" (only {', '.join(taken)})")
        if line not in _warned:
            _warned.add(line)
            warn(line)


def forget_skipped() -> None:
    """Forget which folders :func:`warn_skipped` looked through and what it said: each is looked through, and each
    skipped entry warned of, again."""
    _listed.clear()
    _warned.clear()


def skipped_note(folder: str | os.PathLike, taken: tuple[str, ...], folders: bool = False,
                 within: str | os.PathLike | None = None) -> str:
    """``"; skipped: NAME (REASON), ..."`` for an error saying ``folder`` holds nothing to read ("" when
    nothing was skipped); NAME relative to ``within`` (the folder the error names), else the entry's name."""
    found = skipped_entries(folder, taken, folders)
    if not found:
        return ""
    shown = ", ".join(f"{p.relative_to(within) if within else p.name} ({reason})" for p, reason in found[:4])
    return f"; skipped: {shown}" + (f", ... ({len(found)} in all)" if len(found) > 4 else "")


def plain_images(folder: str | os.PathLike) -> list[Path]:
    """The plain image files (:data:`IMAGE_EXTS`, any case) directly in ``folder``, sorted; [] when it cannot
    be listed."""
    try:
        return sorted(q for q in Path(folder).iterdir() if q.suffix.lower() in IMAGE_EXTS and q.is_file())
    except OSError:
        return []


def plain_images_note(folder: str | os.PathLike) -> str:
    """``''``, or the clause an error ends with when ``folder``, given where phase-shifting scans are needed, holds
    plain fringe images (:data:`IMAGE_EXTS`): they carry no phase-shifting phase. ``''`` too when it cannot be listed."""
    n = len(plain_images(folder))
    return f"; it holds {n} plain image(s), which carry no phase-shifting phase: this needs the scans" if n else ""


def native_samples_note(folder: str | os.PathLike) -> str:
    """``''``, or the clause an error ends with when ``folder``, given where the public layout (PSin/ PCos/ Fringe/
    iPattern/) is needed, holds fppsim's own phase-shifting samples (``<id>/psp/``): fit-rig, fit-optics and
    label-real read those, evaluate-phase and train's --val-phase read the public layout only, which said no more
    than 'missing folder(s)'. ``''`` too when it cannot be listed."""
    try:
        n = sum(1 for q in Path(folder).iterdir() if (q / "psp").is_dir() and (q / "arrays.npz").is_file())
    except OSError:
        return ""
    return (f"; it holds {n} of fppsim's own phase-shifting sample(s) (<id>/psp/), which this does not read: write "
            "them in the public layout (fppsim.dataio.writers.export_psp_folders(DATASET, OUT), DATASET the folder "
            "fppsim generate wrote)") if n else ""


def scan_folders_note(folder: str | os.PathLike, inner: list[str]) -> str:
    """``''``, or the clause an error ends with when ``folder``, given where ONE scan folder is needed, holds scan
    folders one level down: ``inner``, their names (:meth:`fppsim.dataio.readers.Source.scan_folders`, the one
    recognition of them). Each is read on its own, never the folder of them as one scan."""
    if not inner:
        return ""
    return f"; it holds {scan_folders_words(inner)}: give one of them, e.g. {Path(folder) / inner[0]}"


def scan_folders_words(inner: list[str]) -> str:
    """``'2 scan folder(s) one level down (a/, b/)'`` (four names at most): the words :func:`scan_folders_note`
    and :func:`fppsim.dataio.dataset_folder.check_no_frames` name scan folders one level down by."""
    return f"{len(inner)} scan folder(s) one level down ({name_list([f'{name}/' for name in inner])})"


def name_list(names: list[str], n: int = 4) -> str:
    """``'a, b, c, d, ...'``: the first ``n`` of ``names``, as the clauses here name what a folder holds."""
    return ", ".join(names[:n]) + (", ..." if len(names) > n else "")
