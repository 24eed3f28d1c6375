"""Safe file-system machinery shared by fppsim and uhrnet: own temp names, folder locks, signals.

Rules this module implements:

* Our temporary files and folders are named ``.fppsim-tmp-<pid>-<name>``; only entries with that name
  are ever deleted by a clean-up, and only when the process ``<pid>`` is gone (or is us).
* A folder a tool writes into is locked with ``flock`` on the folder itself for the whole run, so a
  second run on the same folder refuses instead of destroying the first one's work; the kernel
  releases the lock when the process dies, even after kill -9.
* Every file either package writes goes through :func:`atomic_path` (or :func:`atomic_write_text` /
  :func:`atomic_write_bytes` on top of it): temp sibling, fsync, one rename, fsync of the folder; a
  failure (disk full, Ctrl-C) removes the temp file and leaves the previous file untouched.
* SIGTERM (e.g. a Slurm timeout) is turned into :class:`Interrupted`, a ``KeyboardInterrupt``, so the
  same clean-up path as Ctrl-C runs (worker pools terminated, temp files removed) and the command exits
  ``128 + signum`` with one line.
* Every JSON file either package writes is strict JSON (:func:`json_text`): a non-finite number is ``null``.
* A warning the library prints itself (:func:`warn`) begins as the running command's own lines do
  (``fppsim fit-rig: warning: ...``; :func:`command_named`, which the command framework enters).
"""

from __future__ import annotations

import ctypes
import json
import errno
import math
import numbers
import fcntl
import os
import re
import shutil
import signal
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from fppsim.errors import DatasetError, FolderBusy, UsageError, InputError

__all__ = ["TMP_PREFIX", "FolderBusy", "Interrupted", "tmp_path", "pid_alive",
           "clean_stale_tmp", "folder_lock", "signals_raise", "die_with_parent", "ignore_sigint",
           "check_writable_dir", "check_output_file", "Output", "check_outputs", "RIG_SUFFIXES", "JSON_SUFFIXES",
           "YAML_SUFFIXES", "holds_keys", "starts_with", "write_fully", "atomic_path", "atomic_write_text",
           "atomic_write_bytes", "fsync_dir", "unlink_quietly", "finite_or_null", "json_text", "command_named", "warn"]

TMP_PREFIX = ".fppsim-tmp-"
_TMP_RE = re.compile(r"^\.fppsim-tmp-(\d+)-")
# temp names written by earlier versions (".f1_80.npy.1234.tmp", ".best.pt.tmp-1234", ...): also ours
_LEGACY_RE = re.compile(r"^\.(?:f1_80\.npy|Z\.npy|manifest\.jsonl|dataset\.json)\.(\d+)\.tmp$"
                        r"|^\.(?:best|last)\.pt\.tmp-(\d+)$")


class Interrupted(KeyboardInterrupt):
    """SIGTERM/SIGINT received; ``signum`` says which (exit status ``128 + signum``)."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def tmp_path(final: str | os.PathLike, pid: int | None = None) -> Path:
    """The temporary sibling of ``final`` this process writes before renaming it into place."""
    final = Path(final)
    return final.with_name(f"{TMP_PREFIX}{os.getpid() if pid is None else pid}-{final.name}")


def fsync_dir(folder: str | os.PathLike) -> None:
    """Make a rename in ``folder`` durable; silently skipped where a folder cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield the temporary path (:func:`tmp_path`) to write ``path`` through; on success fsync it and
    rename it over ``path``.

    The one write helper of both packages (text, bytes, .mat, PNG figures, checkpoints): a crash or
    kill at any moment leaves either the previous file or the new one, never a torn file; on an
    exception (disk full, Ctrl-C) the temporary file is removed and ``path`` is untouched. A temp file
    left by kill -9 is ours by name and removed by :func:`clean_stale_tmp` once its process is gone.
    The suffix of ``path`` ends the temp name too, so writers that pick the format from it still work.
    """
    path = Path(path)
    tmp = tmp_path(path)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        unlink_quietly(tmp)
        if exc.filename is None and exc.errno:  # disk full, quota ... : name the file it happened to
            raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path)) from None
        raise
    except BaseException:
        unlink_quietly(tmp)
        raise
    fsync_dir(path.parent)


def unlink_quietly(path: str | os.PathLike) -> None:
    """Remove a file we wrote, if it is there; a folder that refuses (read-only) must not hide the
    error that made us clean up."""
    try:
        Path(path).unlink(missing_ok=True)
    except OSError:
        pass


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_path`."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        write_fully(fh, data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`atomic_path`."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def finite_or_null(value, default=None):
    """``value`` with every non-finite float (NaN, +-inf; numpy's too) replaced by None, dicts, lists and tuples
    walked; an object JSON does not know goes through ``default`` (``json.dumps``'s) first, then is walked."""
    if value is None or isinstance(value, (str, bool, numbers.Integral)):
        return value
    if isinstance(value, numbers.Real):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v, default) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v, default) for v in value]
    return value if default is None else finite_or_null(default(value), default)


def json_text(doc, **dumps) -> str:
    """``json.dumps(doc, **dumps)`` as strict JSON: Python writes a bare ``NaN`` / ``Infinity``, which strict
    parsers (JavaScript, jq, most other languages) refuse, so a non-finite number comes out as ``null``;
    ``allow_nan=False`` after that makes any that slips through a ValueError here, not a broken file."""
    return json.dumps(finite_or_null(doc, dumps.get("default")), allow_nan=False, **dumps)


def _owner_pid(name: str) -> int | None:
    m = _TMP_RE.match(name) or _LEGACY_RE.match(name)
    if not m:
        return None
    return int(next(g for g in m.groups() if g is not None))


def pid_alive(pid: int) -> bool:
    """Is process ``pid`` running? A zombie is not: a worker orphaned by kill -9 can stay one for
    seconds where PID 1 reaps slowly (containers), and its temporary folders are stale all the same."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        pass
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            state = fh.read().rsplit(b")", 1)[1].split()[0]
    except FileNotFoundError:  # gone meanwhile, or no /proc at all (macOS: then kill(0) is what we know)
        return not os.path.isdir("/proc/self")
    except (OSError, IndexError):
        return True
    return state not in (b"Z", b"X")


def clean_stale_tmp(folder: str | os.PathLike) -> list[Path]:
    """Remove our temp files/folders in ``folder`` whose writer is dead (or is this process).

    Nothing else is touched: foreign dot-files, ``.tmp`` folders of other tools, unknown folders stay.
    Returns what was removed.
    """
    folder = Path(folder)
    removed = []
    try:
        entries = list(folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return removed
    me = os.getpid()
    for p in entries:
        pid = _owner_pid(p.name)
        if pid is None or (pid != me and pid_alive(pid)):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


@contextmanager
def folder_lock(folder: str | os.PathLike, what: str = "fppsim"):
    """Hold an exclusive ``flock`` on the folder itself; raise :class:`FolderBusy` if another process has it.

    Locking the directory's own file descriptor leaves no lock file behind, and the kernel drops the
    lock when the holder dies (even by kill -9), so a stale lock cannot block a re-run.
    """
    folder = Path(folder)
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise FolderBusy(f"{folder} is in use by another {what} run; wait for it to finish "
                             "or use another output folder") from None
        yield folder
    finally:
        os.close(fd)  # releases the flock


def _raise_interrupted(signum, frame):
    raise Interrupted(signum)


@contextmanager
def signals_raise(signums=(signal.SIGTERM, signal.SIGINT)):
    """Inside the block, SIGTERM/SIGINT raise :class:`Interrupted` in the main thread."""
    old = {}
    for s in signums:
        try:
            old[s] = signal.signal(s, _raise_interrupted)
        except ValueError:  # not the main thread: leave signals alone
            pass
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


_COMMAND: list[str] = []  # "PROG COMMAND" of the command line running (command_named), innermost last


@contextmanager
def command_named(where: str):
    """Inside the block, :func:`warn` begins its lines ``WHERE: warning:`` (``where``: ``"uhrnet predict"``), as
    the command's own warnings and its error line begin (:func:`fppsim.commands.run_commands` enters it)."""
    _COMMAND.append(where)
    try:
        yield
    finally:
        _COMMAND.pop()


def warn(text: str) -> None:
    """One warning line on stderr from library code: ``PROG COMMAND: warning: TEXT`` while a command runs
    (:func:`command_named`), else ``warning: TEXT``."""
    print(f"{_COMMAND[-1]}: warning: {text}" if _COMMAND else f"warning: {text}", file=sys.stderr, flush=True)


def ignore_sigint() -> None:
    """For pool workers: Ctrl-C goes to the whole process group; only the parent should react to it
    (it terminates the pool), so workers print no KeyboardInterrupt/BrokenPipeError tracebacks."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def die_with_parent() -> None:
    """Linux: SIGKILL this worker when its parent dies (kill -9 of the parent leaves no orphans)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the parent's pool.terminate() still stops workers
        pass


def check_writable_dir(folder: str | os.PathLike, flag: str = "--out") -> Path:
    """Create ``folder`` if needed and prove it is a writable directory; ``OSError`` -> one-line ValueError."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{flag} {folder} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = tmp_path(folder / "write-test")
        probe.write_bytes(b"ok")
        probe.unlink()
    except OSError as exc:
        raise InputError(f"{flag} {folder}: cannot write there ({exc.strerror or exc})") from None
    return folder


def check_output_file(path: str | os.PathLike, force: bool = False) -> Path:
    """``path`` as a Path once it may be written: it must not exist unless ``force`` (replace it), and its
    folder must exist; one-line ValueError otherwise."""
    out = Path(path)
    if out.exists() and not force:
        raise InputError(f"{out} exists; pass --force to replace it")
    if not out.parent.is_dir():
        raise InputError(f"{out.parent}: output folder does not exist")
    return out

RIG_SUFFIXES = (".json", ".yaml", ".yml")  # what fppsim.geometry.rig_files writes
JSON_SUFFIXES = (".json",)
YAML_SUFFIXES = (".yaml", ".yml")


class Output:
    """One output FILE of a command, for :func:`check_outputs`: the ``flag`` naming it (``--out``), the user's
    ``path``, the ``suffixes`` that fit what is written (``(".json",)``; empty: any), ``what`` it is, and
    ``ours(path) -> bool``: whether an existing file is one the command writes (what it may replace with
    ``--force`` inside an input folder; see :func:`holds_keys`, :func:`starts_with`)."""

    __slots__ = ("flag", "path", "suffixes", "what", "ours")

    def __init__(self, flag: str, path: str | os.PathLike, suffixes: tuple[str, ...] = (), what: str = "file",
                 ours=None):
        self.flag, self.path, self.suffixes, self.what = flag, path, tuple(s.lower() for s in suffixes), what
        self.ours = ours


def _document(path: Path):
    text = path.read_text()
    if path.suffix.lower() in YAML_SUFFIXES:
        import yaml

        return yaml.safe_load(text)
    return json.loads(text)


def holds_keys(*keys: str):
    """An :attr:`Output.ours` predicate: the file is a JSON / YAML mapping holding every one of ``keys``."""
    def ours(path: Path) -> bool:
        try:
            doc = _document(path)
        except Exception:  # noqa: BLE001 - anything unreadable is not ours
            return False
        return isinstance(doc, dict) and all(k in doc for k in keys)
    return ours


def starts_with(text: str):
    """An :attr:`Output.ours` predicate: the file's text starts with ``text`` (a header the command writes)."""
    def ours(path: Path) -> bool:
        try:
            with open(path, encoding="utf-8", errors="replace") as fh:
                return fh.read(len(text)) == text
        except OSError:
            return False
    return ours


def _key(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return path.absolute()


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
        return True
    except ValueError:
        return False


def check_outputs(outputs, inputs=(), force: bool = False) -> list[Path]:
    """THE up-front check of a command's output files, before any work (every command that writes a file the
    user names calls it once with all of them). Each :class:`Output` (None entries and empty paths skipped):

    * its extension fits what is written (``--out rig.mat`` for a rig: refused);
    * it is not one of the ``inputs`` (files or folders the command reads) nor a file that exists inside an
      input folder (``--out FRAMES/PSin/1201.mat --force`` would replace a scan; a new name there is fine,
      and with ``force`` a file the output's ``ours`` recognises as the command's own);
    * it is not another output of the same command (``--out x.json --json x.json``: one would destroy the other);
    * it is not a folder; it exists only with ``force``;
    * its folder exists and is writable (proved by writing a probe there).

    Returns the paths (as given) of the outputs checked, in order. Raises :class:`UsageError` (exit 2) for a
    path that cannot be right (extension, input, twice) and :class:`DatasetError` (exit 1) for what the file
    system refuses; the one line names the flag and the user's path."""
    outs = [o for o in outputs if o is not None and o.path not in (None, "")]
    ins = [(Path(p), _key(Path(p))) for p in inputs if p not in (None, "")]
    seen: dict[Path, Output] = {}
    checked = []
    for o in outs:
        path = Path(o.path)
        key = _key(path)
        if o.suffixes and path.suffix.lower() not in o.suffixes:
            raise UsageError(f"{o.flag} {o.path}: {o.what} must end in {', '.join(o.suffixes[:-1]) + ' or ' if len(o.suffixes) > 1 else ''}{o.suffixes[-1]}")
        if (path.exists() or path.is_symlink()) and not force and not path.is_dir():
            raise DatasetError(f"{o.flag} {o.path} exists; pass --force to replace it")
        for given, ikey in ins:
            if key == ikey or (path.exists() and _same_file(path, given)):
                raise UsageError(f"{o.flag} {o.path}: is an input of this command ({given}); write elsewhere")
            if (path.exists() or path.is_symlink()) and ikey.is_dir() and _inside(key, ikey) \
                    and not (force and o.ours is not None and path.is_file() and o.ours(path)):
                raise UsageError(f"{o.flag} {o.path}: is a file of the input folder {given}; write elsewhere")
        if key in seen:
            raise UsageError(f"{o.flag} {o.path}: is also {seen[key].flag}; give each output its own file")
        seen[key] = o
        if path.is_dir():
            raise UsageError(f"{o.flag} {o.path}: is a folder; give a file name")
        folder = path.parent
        if not folder.is_dir():
            raise DatasetError(f"{o.flag} {o.path}: its folder {folder} does not exist")
        try:
            probe = tmp_path(folder / "write-test")
            probe.write_bytes(b"ok")
            probe.unlink()
        except OSError as exc:
            raise DatasetError(f"{o.flag} {o.path}: cannot write in {folder} ({exc.strerror or exc})") from None
        checked.append(path)
    return checked


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def write_fully(fh, data) -> None:
    """``fh.write`` of a bytes-like object; a short write or ENOSPC raises ``OSError`` (never SIGBUS)."""
    view = memoryview(data).cast("B")
    n = fh.write(view)
    if n is not None and n != len(view):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
