"""The fixed files of a generated dataset folder, and the checks that keep ``generate`` / ``merge`` off anyone else's.

``fppsim generate`` and ``fppsim merge`` write fixed names into ``--out``: ``dataset.json`` and ``manifest.jsonl``
beside the samples (``--out`` itself, or ``--out/native`` for the figshare format), ``f1_80.npy`` + ``Z.npy``
(figshare format) and ``preview.png``. They claim those names in ``--out``'s ownership record
(:mod:`fppsim.owned`) before writing anything, under ONE tool name (:data:`DATASET_TOOL`): a merged folder
then resumes with ``generate``, and shards merge into a folder ``generate`` wrote. A folder generated before
the record existed is adopted when its ``dataset.json`` is fppsim's (:func:`legacy_files`: only the names it
can show are fppsim's). Sample folders are not recorded: each proves itself (``meta.json``,
:func:`fppsim.dataio.formats.is_own_sample`), and a foreign one is refused up front by the run. A folder holding
the user's own fringe frames (plain images, a scan in the public layout, or such scans one level down) is refused
whole (:func:`check_no_frames`): a dataset written beside them would mix with them, and the readers would then
take the folder for generate's dataset.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from fppsim.errors import DatasetError, GenerateError, UsageError
from fppsim.dataio.encoding import load_npy, png_size
from fppsim.files import TMP_PREFIX, unlink_quietly
from fppsim.owned import owners, same_folder
from fppsim.dataio.formats import (FIGSHARE_PAIRS, SAMPLE_ID_RE, SETTINGS_FILE, finished_indices, read_settings,
                                   sample_id)
from fppsim.dataio.readers import is_scan_folder, name_list, plain_images, scan_folders_words
from fppsim.dataio.writers import samples_folder

__all__ = ["DATASET_TOOL", "MANIFEST", "PREVIEW_NAME", "dataset_files", "legacy_files", "check_format",
           "check_no_frames", "check_shards", "discard_empty_dataset"]

DATASET_TOOL = "fppsim generate"  # the record's name for a dataset's files, whether generate or merge wrote them
MANIFEST = "manifest.jsonl"
PREVIEW_NAME = "preview.png"


def _samples_rel(fmt: str) -> str:
    """Where format ``fmt`` keeps its samples, relative to ``--out``, as a name prefix ("" or "native/")."""
    sub = samples_folder(Path(), fmt)
    return "" if sub == Path() else f"{sub.as_posix()}/"


def dataset_files(fmt: str, preview: bool = False) -> list[str]:
    """The fixed names (relative to ``--out``) a run writing format ``fmt`` writes."""
    sub = _samples_rel(fmt)
    names = [f"{sub}{SETTINGS_FILE}", f"{sub}{MANIFEST}"]
    if fmt == "figshare":
        names += list(FIGSHARE_PAIRS[0])
    return names + ([PREVIEW_NAME] if preview else [])


def _fppsim_settings(folder: Path) -> dict | None:
    """``folder``'s ``dataset.json`` when fppsim wrote it (``"generator": "fppsim"``), else None."""
    try:
        settings = read_settings(folder)
    except (OSError, ValueError):
        return None
    return settings if isinstance(settings, dict) and settings.get("generator") == "fppsim" else None


def _is_manifest(path: Path) -> bool:
    """Every line a manifest record (a JSON object with an ``id``); a torn last line after a good one is
    allowed (a run killed while appending); an empty file is one (a run stopped before its first sample)."""
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError):
        return False
    good = 0
    for k, line in enumerate(lines):
        try:
            rec = json.loads(line)
            ok = isinstance(rec, dict) and "id" in rec
        except ValueError:
            ok = False
        if not ok and not (k == len(lines) - 1 and good):
            return False
        good += ok
    return True


def _is_figshare_array(path: Path, camera: dict) -> bool:
    """A float32 (N, H, W, 1) ``.npy`` of the dataset's camera size: what ``generate`` writes."""
    try:
        a = load_npy(path)
    except DatasetError:  # damaged, empty, an .npz under its name: not what generate writes
        return False
    size = (camera.get("height"), camera.get("width")) if isinstance(camera, dict) else None
    return a.dtype == np.float32 and a.ndim == 4 and a.shape[3] == 1 and tuple(a.shape[1:3]) == size


def _is_preview(path: Path) -> bool:
    """A PNG of the size ``fppsim.rendering.preview.write_preview`` makes (1200 px wide, 240 px a row, 1-3 rows)."""
    size = png_size(path)
    return size is not None and size[0] == 1200 and size[1] in (240, 480, 720)


def legacy_files(out: str | os.PathLike) -> list[str]:
    """For a folder without an ownership record: the fixed names a run of fppsim before the record wrote there,
    told by its ``dataset.json`` (``"generator": "fppsim"``) and each file's own form; [] when it holds none."""
    out = Path(out)
    for fmt in ("native", "figshare"):
        sub = _samples_rel(fmt)
        settings = _fppsim_settings(out / sub)
        if settings is None or settings.get("format", "native") != fmt:
            continue
        own = [f"{sub}{SETTINGS_FILE}"]
        if _is_manifest(out / sub / MANIFEST):
            own.append(f"{sub}{MANIFEST}")
        if fmt == "figshare":
            camera = (settings.get("rig") or {}).get("camera") if isinstance(settings.get("rig"), dict) else None
            own += [name for name in FIGSHARE_PAIRS[0] if _is_figshare_array(out / name, camera)]
        if _is_preview(out / PREVIEW_NAME):
            own.append(PREVIEW_NAME)
        return own
    return []


def check_format(out: str | os.PathLike, fmt: str) -> None:
    """Refuse (:class:`GenerateError`, one line) to write format ``fmt`` into ``out`` when ``out`` holds a
    dataset of the other format: the run would build a second dataset beside it (a native one next to
    ``native/``), or render every sample again into ``native/`` instead of resuming."""
    out = Path(out)
    for other in ("native", "figshare"):
        if other == fmt:
            continue
        settings = _fppsim_settings(out / _samples_rel(other))
        if settings is not None and settings.get("format", "native") == other:
            raise GenerateError(f"{out} holds a dataset generated with --format {other} "
                                f"({out / _samples_rel(other) / SETTINGS_FILE}): re-run with --format {other} to "
                                f"resume it, or use another --out for --format {fmt}")


def check_no_frames(out: str | os.PathLike, claimed, flag: str = "--out",
                    error: type[Exception] = GenerateError) -> None:
    """Refuse (``error``, one line naming ``out`` and what it found) to write a dataset into ``out`` when it holds
    fringe frames fppsim did not write: plain images (:func:`fppsim.dataio.readers.plain_images`), a scan in the
    public layout, or such scans one level down (each recognised by :func:`fppsim.dataio.readers.is_scan_folder`:
    a folder it may not look into, such as ``lost+found``, holds none).
    The dataset would be written beside them, and the readers would then take the folder for generate's dataset
    (``fit-rig DIR`` read the samples, not the frames). ``claimed``: the names this run claims
    (:func:`fppsim.owned.claim` rules on those); an image the folder's record (or, in a folder from before the
    record, :func:`legacy_files`) gives to fppsim is its own. Other files (a README, a ``.json``) are no frames:
    they stay, and the dataset is written beside them as before."""
    out = Path(out)
    record = owners(out)
    own = set(claimed) | ({n for n, tool in record.items() if tool == DATASET_TOOL} if record is not None
                          else set(legacy_files(out)))
    found = ["a scan in the public layout (PSin/ PCos/ Fringe/ iPattern/)"] if is_scan_folder(out, True) else []
    with os.scandir(out) as entries:  # generate's own sample folders are not looked into (a resume of 100,000)
        inner = sorted(e.name for e in entries if e.is_dir() and not SAMPLE_ID_RE.match(e.name)
                       and is_scan_folder(e.path, True))
    if inner:
        found.append(scan_folders_words(inner))
    images = [p.name for p in plain_images(out) if p.name not in own and not p.name.startswith(TMP_PREFIX)]
    if images:
        found.append(f"{len(images)} fringe image(s) ({name_list(images)})")
    if found:
        raise error(f"{flag} {out} already holds {' and '.join(found)} that {DATASET_TOOL} did not write: "
                    "choose another folder")


def discard_empty_dataset(folder: str | os.PathLike, folder_too: bool = False) -> None:
    """Remove the ``dataset.json`` and ``manifest.jsonl`` a failed run started in ``folder`` beside no finished
    sample (and ``folder`` itself when ``folder_too`` and it is left empty): the corrected re-run then starts
    afresh instead of being refused for the failed run's settings. Only call it for files that run wrote."""
    folder = Path(folder)
    for name in (SETTINGS_FILE, MANIFEST):
        unlink_quietly(folder / name)
    if folder_too:
        try:
            folder.rmdir()
        except OSError:  # not empty: someone else's files stay
            pass


def check_shards(out: str | os.PathLike, shard_dirs, natives) -> None:
    """``fppsim merge``'s checks before anything is written: OUT is none of the shards (:class:`UsageError`: the
    shard would become the merged set), and every finished sample of a shard (``natives``: their sample folders)
    holds its ``arrays.npz`` (a damaged sample, merged, broke every reader of the merged set later)."""
    out = Path(out)
    for d, nd in zip(map(Path, shard_dirs), natives):
        if same_folder(out, d) or same_folder(out, nd) or same_folder(out / "native", nd):
            raise UsageError(f"OUT {out} is the shard {d}: merge into another folder")
    for nd in map(Path, natives):
        for index in sorted(finished_indices(nd)):
            if not (nd / sample_id(index) / "arrays.npz").is_file():
                raise DatasetError(f"{nd / sample_id(index)}: damaged sample (no arrays.npz): remove the folder and "
                                   "generate its shard again before merging")
