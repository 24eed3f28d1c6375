"""Which files in an output folder a tool wrote: the ownership record both packages keep.

"Tools never delete or replace what they did not write." Every command that writes a fixed set of file
names into a folder the user names (``uhrnet train``, ``uhrnet adapt``, ``fppsim label-real``, ``fppsim generate``
and ``merge``: :mod:`fppsim.dataio.dataset_folder`) claims
those names here BEFORE it writes them: the folder's ``.fppsim-owned.json`` maps each relative path to
the tool that wrote it. A claim is refused (:class:`fppsim.errors.ForeignFiles`, one line naming the
file) when a path to be written already exists and

* no tool recorded it (someone else's file), or
* another tool recorded it (``uhrnet adapt --out`` a training run would replace the run's ``last.pt``).

Folders written before the record existed are recognised by the tool itself (``legacy``: the names
it can prove are its own, e.g. a loadable checkpoint of its kind) and adopted into the record. A tool
deletes a file only through :func:`remove_own`: one the record says it wrote.

:func:`output_folder` is the one way such a command opens its folder: created if needed (and proved
writable), locked (:func:`fppsim.files.folder_lock`), stale temp files of a killed run removed, and on a
failure the claims whose files were never written are dropped again; a folder the run created and
left empty is removed.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

from fppsim.errors import ForeignFiles
from fppsim.files import atomic_write_text, check_writable_dir, json_text, clean_stale_tmp, folder_lock, unlink_quietly

__all__ = ["RECORD", "ForeignFiles", "owners", "claim", "stamp", "record_created", "forget", "remove_own", "output_folder",
           "same_folder"]

RECORD = ".fppsim-owned.json"


def owners(folder: str | os.PathLike) -> dict[str, str] | None:
    """``{relative path: tool}`` of ``folder``'s record; None when the folder has no record."""
    path = Path(folder) / RECORD
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        raise ForeignFiles(f"{path}: unreadable ownership record; move it away or choose another --out") from None
    files = doc.get("files") if isinstance(doc, dict) else None
    if not isinstance(files, dict):
        raise ForeignFiles(f"{path}: not an ownership record of fppsim/uhrnet; move it away or choose another --out")
    return {str(k): str(v) for k, v in files.items()}


def _stamps(folder: Path) -> dict[str, list]:
    """``{relative path: [size, mtime_ns]}`` recorded by :func:`stamp`; {} when none (or unreadable)."""
    try:
        doc = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return {}
    stamps = doc.get("stamps") if isinstance(doc, dict) else None
    return stamps if isinstance(stamps, dict) else {}


def _stamp_of(path: Path) -> list:
    st = path.lstat()
    return [st.st_size, st.st_mtime_ns]


def _changed(folder: Path, name: str, stamps: dict[str, list]) -> bool:
    """Was ``name`` (existing) changed or replaced since :func:`stamp` recorded it? False without a stamp."""
    return name in stamps and _stamp_of(folder / name) != stamps[name]


def _write(folder: Path, record: dict[str, str], stamps: dict[str, list] | None = None) -> None:
    if record:
        stamps = {k: v for k, v in (_stamps(folder) if stamps is None else stamps).items() if k in record}
        doc = {"files": dict(sorted(record.items()))}
        if stamps:
            doc["stamps"] = dict(sorted(stamps.items()))
        atomic_write_text(folder / RECORD, json_text(doc, indent=1))
    else:
        unlink_quietly(folder / RECORD)


def stamp(folder: str | os.PathLike, names: Iterable[str]) -> None:
    """Record the size and modification time of ``names`` just written: a later :func:`claim` of the
    same tool then refuses a file that someone changed or replaced since (it is no longer the tool's)."""
    folder = Path(folder)
    record = owners(folder) or {}
    stamps = _stamps(folder)
    for name in names:
        if name in record and (folder / name).exists():
            stamps[name] = _stamp_of(folder / name)
    _write(folder, record, stamps)


def claim(folder: str | os.PathLike, tool: str, names: Iterable[str], legacy: Callable[[], Iterable[str]] | None = None,
          hint: str = "move it away or choose another --out") -> None:
    """Record ``names`` (paths relative to ``folder``) as ``tool``'s before ``tool`` writes them.

    Raises :class:`ForeignFiles` naming the first path that exists and is not ``tool``'s (``hint`` ends the
    message). ``legacy``: the names ``tool`` recognises as its own, written before it kept a record: asked for a
    folder without a record, and for a name that the folder's record (another tool's files) does not list.
    """
    folder = Path(folder)
    names = list(dict.fromkeys(str(n) for n in names))
    record = owners(folder)
    before = None if record is None else dict(record)
    own = None  # legacy's names, asked once: also where another tool's record lists none of this tool's files
    if record is None:
        own = set(legacy()) if legacy is not None else set()
        record = {n: tool for n in own if (folder / n).exists()}
    stamps = _stamps(folder)
    for name in names:
        path = folder / name
        owner = record.get(name)
        if not (path.exists() or path.is_symlink()):
            continue
        if owner is None and legacy is not None:
            own = set(legacy()) if own is None else own
            if name in own:  # written before this tool kept a record, in a folder another tool records
                owner = record[name] = tool
        if owner == tool:
            if _changed(folder, name, stamps):
                raise ForeignFiles(f"{path} was changed since {tool} wrote it: {hint}")
            continue
        if owner is None:
            raise ForeignFiles(f"{path} exists and was not written by {tool}: {hint}")
        raise ForeignFiles(f"{path} was written by {owner}, not {tool}: {hint}")
    record.update({n: tool for n in names})
    if record != before:  # an unchanged record is not rewritten (a re-run touches nothing)
        _write(folder, record)


def record_created(folder: str | os.PathLike, tool: str, name: str) -> None:
    """Record ``name`` as ``tool``'s AFTER ``tool`` created it under a name nobody else could have used (a
    file named by time, host and process, such as a TensorBoard event file): :func:`claim` cannot, since the
    file already exists."""
    folder = Path(folder)
    record = owners(folder) or {}
    if record.get(name) != tool:
        record[name] = tool
        _write(folder, record)


def forget(folder: str | os.PathLike, names: Iterable[str]) -> None:
    """Drop ``names`` from ``folder``'s record (files their tool has just deleted)."""
    folder = Path(folder)
    record = owners(folder)
    if record is None:
        return
    kept = {n: t for n, t in record.items() if n not in set(names)}
    if kept != record:
        _write(folder, kept)


def remove_own(folder: str | os.PathLike, tool: str, names: Iterable[str]) -> list[str]:
    """Delete those of ``names`` that ``folder``'s record gives to ``tool`` (files it wrote earlier and that are
    now stale) and forget them; a name the record gives to no one or to another tool, or a file changed since
    :func:`stamp` recorded it, is left alone. Returns the names deleted."""
    folder = Path(folder)
    record, stamps = owners(folder) or {}, _stamps(folder)
    mine = [n for n in dict.fromkeys(map(str, names)) if record.get(n) == tool
            and not ((folder / n).exists() and _changed(folder, n, stamps))]
    there = [n for n in mine if (folder / n).exists() or (folder / n).is_symlink()]
    for name in there:
        unlink_quietly(folder / name)
    left = {n for n in there if (folder / n).exists() or (folder / n).is_symlink()}  # (a read-only folder)
    forget(folder, [n for n in mine if n not in left])
    return [n for n in there if n not in left]


def _drop_unwritten(folder: Path) -> None:
    """Forget claims whose files do not exist (a run that failed before writing them)."""
    try:
        record = owners(folder)
    except ForeignFiles:
        return
    if record is None:
        return
    kept = {n: t for n, t in record.items() if (folder / n).exists()}
    if kept != record:
        _write(folder, kept)


def same_folder(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Do ``a`` and ``b`` name the same existing folder (symlinks, ``..`` and spelling aside)?"""
    try:
        return Path(a).resolve() == Path(b).resolve() or os.path.samefile(a, b)
    except OSError:
        return False


@contextmanager
def output_folder(folder: str | os.PathLike, what: str, flag: str = "--out", error=ValueError) -> Iterator[Path]:
    """Create (if needed), prove writable, lock and clean ``folder`` for one run of ``what``; on a
    failure drop the run's unwritten claims and remove the folder again if this run created it and left
    it empty. ``error``: the exception class a folder that cannot be written raises (one line)."""
    folder = Path(folder)
    created = [] if folder.exists() else [folder, *[a for a in folder.parents if not a.exists()]]  # leaf first
    try:
        check_writable_dir(folder, flag)
    except ValueError as exc:
        raise error(str(exc)) from None
    try:
        with folder_lock(folder, what):
            clean_stale_tmp(folder)
            try:
                yield folder
            except BaseException:
                _drop_unwritten(folder)
                raise
    except BaseException:
        if created:
            subs = sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts))
            for made in subs + created:  # only empty folders this run made (figures/, --out and its parents)
                try:
                    made.rmdir()
                except OSError:
                    pass
        raise
