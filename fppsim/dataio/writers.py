"""Writers of the dataset layouts of :mod:`fppsim.dataio.formats`: sample folders, figshare arrays, ``.mat`` folders.

* native: :func:`write_sample_folder` (one atomic rename per sample, PNGs and npz through
  :mod:`fppsim.dataio.encoding`);
* figshare: :func:`figshare_rows` (one sample's rows) is what both :func:`export_figshare` (from native
  folders on disk) and :class:`FigshareRows` (filled from memory while generating, so a figshare run
  need not read every sample back) write, so both give identical files; :class:`NpyRowStream` writes
  one ``.npy`` row by row (ordinary writes: a full disk raises ENOSPC) and publishes it atomically;
* :class:`BackgroundWriter` runs sample writes (PNG encoding, deflate, file IO: all release the GIL)
  on one thread while the caller synthesises the next sample;
* phase-shifting ``.mat`` files (read by :mod:`fppsim.dataio.readers`): :func:`save_psp_mat`,
  :func:`save_psp_folder_sample`, :func:`export_psp_folders` (a native dataset in the folder layout),
  :func:`sums_from_phase`.

Every file goes through :func:`fppsim.files.atomic_path` or a temporary sibling renamed into place.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import threading
from pathlib import Path

import numpy as np

from fppsim.dataio.encoding import encode_fringe, encode_png, save_npz
from fppsim.errors import DatasetError, PSPMatError, InputError
from fppsim.files import atomic_path, clean_stale_tmp, json_text, tmp_path, write_fully
from fppsim.dataio.formats import LabelTransform, is_own_sample, read_manifest
from fppsim.dataio.readers import FOLDERS, check_convention, load_native_sample, wrapped_from_sums

__all__ = ["samples_folder", "write_sample_folder", "figshare_rows", "export_figshare", "FigshareRows", "NpyRowStream",
           "BackgroundWriter", "sums_from_phase", "save_psp_mat", "save_psp_folder_sample", "export_psp_folders"]


# ============================================================================================ native
def samples_folder(out: str | os.PathLike, fmt: str) -> Path:
    """Where a run writing format ``fmt`` keeps its native sample folders: ``out`` itself, or ``out/native``
    beside a figshare export's arrays."""
    return Path(out) / "native" if fmt == "figshare" else Path(out)


def write_sample_folder(root: Path, sid: str, images: dict, arrays: dict, meta: dict) -> None:
    """Write one sample into ``root/sid`` atomically (temporary folder + one rename).

    ``images`` maps relative PNG paths (``fringe.png``, ``psp/f8_s0.png``) to uint8 arrays.
    """
    final = root / sid
    tmp = tmp_path(final)  # ".fppsim-tmp-<pid>-<sid>": recognisably ours, removed on failure or re-run
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        tmp.mkdir(parents=True)
        for sub in sorted({(tmp / rel).parent for rel in images} - {tmp}):  # psp/: once, not per image
            sub.mkdir(parents=True, exist_ok=True)
        for rel, img in images.items():
            (tmp / rel).write_bytes(encode_png(img))
        save_npz(tmp / "arrays.npz", arrays)
        (tmp / "meta.json").write_text(json_text(meta, indent=1))
        if final.exists():
            if not is_own_sample(final):  # never replace (or count) a folder we did not write
                raise DatasetError(f"{final} exists but is not a finished fppsim sample: move it away")
            shutil.rmtree(tmp)  # an earlier run finished it meanwhile: keep the earlier one
            return
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# ============================================================================================ figshare
class NpyRowStream:
    """A float32 ``.npy`` of ``shape`` written row by row into a temporary sibling of ``final``, renamed
    into place by :meth:`commit` (after :meth:`close` flushed and fsynced it); :meth:`discard` removes the
    temporary file (harmless after a commit). Ordinary writes, so a full disk raises ENOSPC (a memmap into
    a sparse file would die of SIGBUS instead)."""

    def __init__(self, final: str | os.PathLike, shape: tuple[int, ...]):
        self.final = Path(final)
        self.tmp = tmp_path(self.final)
        self.fh = open(self.tmp, "wb")
        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)), "fortran_order": False,
                  "shape": tuple(shape)}
        np.lib.format.write_array_header_1_0(self.fh, header)

    def write(self, rows: np.ndarray) -> None:
        """Append ``rows`` (as float32, C order): the next row(s) of the array."""
        try:
            write_fully(self.fh, np.ascontiguousarray(rows, dtype=np.float32))
        except OSError as exc:
            raise self._named(exc) from None

    def close(self) -> None:
        if not self.fh.closed:
            try:
                self.fh.flush()
                os.fsync(self.fh.fileno())
                self.fh.close()
            except OSError as exc:
                try:
                    self.fh.close()
                except OSError:
                    pass
                raise self._named(exc) from None

    def _named(self, exc: OSError) -> OSError:
        """A full disk (or any write error) names the array being written."""
        if exc.filename is None and exc.errno:
            return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(self.final))
        return exc

    def commit(self) -> None:
        self.close()
        os.replace(self.tmp, self.final)

    def discard(self) -> None:
        if not self.fh.closed:
            self.fh.close()
        self.tmp.unlink(missing_ok=True)


def figshare_rows(fringe: np.ndarray, arrays: dict, transform: LabelTransform,
                  use_psp_height: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One native sample's figshare ``(fringe, label)`` rows, float32 (H, W): what :func:`export_figshare`
    writes (and :class:`FigshareRows` streams while generating), so both give identical files."""
    if use_psp_height:
        h, m = arrays["height_psp"], (arrays["mask_psp"] > 0) & np.isfinite(arrays["height_psp"])
    else:
        h, m = arrays["height"], arrays["mask"] > 0
    return encode_fringe(fringe, m), transform.label_from_height_mm(np.nan_to_num(h), m)


def export_figshare(root: str | os.PathLike, out: str | os.PathLike, transform: LabelTransform,
                    folders: list[Path] | None = None, use_psp_height: bool = False) -> int:
    """Write ``f1_80.npy`` and ``Z.npy`` (N, H, W, 1) float32 from native samples, atomically.

    ``folders`` defaults to the manifest order of ``root``. Invalid pixels get ``transform.invalid_value``
    in Z and -1 in the fringe. ``use_psp_height`` labels with the PSP height (as a lab would) instead
    of the exact one. Returns N.
    """
    root, out = Path(root), Path(out)
    if folders is None:
        folders = [root / r["id"] for r in read_manifest(root)]
    if not folders:
        raise DatasetError(f"{root}: no finished samples to export")
    first = load_native_sample(folders[0])
    H, W = first["fringe"].shape
    N = len(folders)

    def fill(folder, fr, zz):
        s = load_native_sample(folder)
        if s["fringe"].shape != (H, W):
            raise DatasetError(f"{folder}: image size {s['fringe'].shape} differs from {(H, W)}")
        if use_psp_height and "height_psp" not in s:
            raise DatasetError(f"{folder}: no PSP height (made with --no-psp)")
        fr[0, :, :, 0], zz[0, :, :, 0] = figshare_rows(s["fringe"], s, transform, use_psp_height)

    out.mkdir(parents=True, exist_ok=True)
    clean_stale_tmp(out)
    # sample by sample (a full disk raises ENOSPC); the temp files are removed on any failure
    streams: list[NpyRowStream] = []
    try:
        for name in ("f1_80.npy", "Z.npy"):
            streams.append(NpyRowStream(out / name, (N, H, W, 1)))
        fr1 = np.empty((1, H, W, 1), np.float32)
        zz1 = np.empty((1, H, W, 1), np.float32)
        for folder in folders:
            fill(folder, fr1, zz1)
            streams[0].write(fr1)
            streams[1].write(zz1)
        for stream in streams:
            stream.close()
        for stream in streams:
            stream.commit()
    except OSError as exc:
        raise DatasetError(f"cannot write the figshare arrays in {out}: {exc.strerror or exc}") from None
    finally:
        for stream in streams:
            stream.discard()
    return N


class FigshareRows:
    """``f1_80.npy`` + ``Z.npy`` (N, H, W, 1) float32 filled row by row, published atomically.

    ``put(k, fringe, label)`` writes row ``k``; :meth:`commit` renames the temporary files into place
    once every row is there; :meth:`discard` removes them.
    """

    def __init__(self, out: str | os.PathLike, n: int, height: int, width: int):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.shape = (int(n), int(height), int(width), 1)
        self._tmp = {name: tmp_path(self.out / name) for name in ("f1_80.npy", "Z.npy")}
        self._maps = {}
        try:
            for name, p in self._tmp.items():
                self._maps[name] = np.lib.format.open_memmap(p, mode="w+", dtype=np.float32, shape=self.shape)
                # reserve the blocks now: a full disk then fails here with ENOSPC, where writes into a
                # sparse memmap would kill the process with SIGBUS
                with open(p, "r+b") as fh:
                    os.posix_fallocate(fh.fileno(), 0, os.path.getsize(p))
        except OSError as exc:
            self.discard()
            raise DatasetError(f"cannot write the figshare arrays in {self.out}: {exc.strerror or exc}") from None
        self._filled = np.zeros(n, dtype=bool)

    def put(self, k: int, fringe: np.ndarray, label: np.ndarray) -> None:
        if fringe.shape != self.shape[1:3] or label.shape != self.shape[1:3]:
            raise InputError(f"figshare row {k}: image size {fringe.shape} differs from {self.shape[1:3]}")
        self._maps["f1_80.npy"][k, :, :, 0] = fringe
        self._maps["Z.npy"][k, :, :, 0] = label
        self._filled[k] = True

    @property
    def complete(self) -> bool:
        return bool(self._filled.all())

    def commit(self) -> int:
        if not self.complete:
            raise InputError(f"figshare arrays: {int((~self._filled).sum())} of {self.shape[0]} rows missing")
        for m in self._maps.values():
            m.flush()
        self._maps.clear()
        for name, p in self._tmp.items():
            os.replace(p, self.out / name)
        return self.shape[0]

    def discard(self) -> None:
        self._maps.clear()
        for p in self._tmp.values():
            Path(p).unlink(missing_ok=True)


# ============================================================================================ writing behind the caller
class BackgroundWriter:
    """Run ``fn(*args)`` jobs in order on one background thread.

    At most ``depth`` jobs wait behind the running one (``submit`` blocks beyond that, which bounds the
    memory held by pending samples). The first error a job raises is re-raised by the next
    :meth:`submit`, :meth:`flush` or :meth:`close`; later jobs are skipped until then.
    """

    def __init__(self, depth: int = 1):
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="fppsim-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    fn, args = job
                    fn(*args)
            except BaseException as exc:  # handed to the caller's thread
                self._error = exc
            finally:
                self._queue.task_done()

    def _reraise(self) -> None:
        if self._error is not None:
            exc, self._error = self._error, None
            raise exc

    def submit(self, fn, *args) -> None:
        self._reraise()
        if not self._thread.is_alive():
            raise RuntimeError("background writer is closed")
        self._queue.put((fn, args))

    def flush(self) -> None:
        """Wait until every submitted job has finished; re-raise a job's error."""
        self._queue.join()
        self._reraise()

    def close(self) -> None:
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._reraise()


# ============================================================================================ phase-shifting .mat files
def save_psp_mat(path: str | os.PathLike, psin: np.ndarray, pcos: np.ndarray, order: np.ndarray, *,
                 n_steps: int | None = None, periods: float | None = None,
                 keys: tuple[str, str, str] = ("PSin", "PCos", "Order"), compress: bool = True,
                 **extra) -> None:
    """Write PSin / PCos / order in the layout :func:`load_psp_mat` reads (MATLAB v5, atomic write).

    ``psin, pcos`` as from :func:`fppsim.phase.psp.phase_sums` (stored float64), ``order`` integer fringe
    orders (stored int32). ``n_steps`` and ``periods`` (fringe periods across the projector) are
    stored as scalars when given; ``extra`` adds further variables.
    """
    psin = np.asarray(psin, dtype=np.float64)
    pcos = np.asarray(pcos, dtype=np.float64)
    order = np.asarray(order)
    if not (psin.shape == pcos.shape == order.shape):
        raise PSPMatError(f"{path}: shapes differ: psin {psin.shape}, pcos {pcos.shape}, order {order.shape}")
    if order.dtype.kind == "f":
        if not np.all(np.isfinite(order)) or np.any(order != np.rint(order)):
            raise PSPMatError(f"{path}: fringe orders must be finite integers")
    elif order.dtype.kind not in "iub":
        raise PSPMatError(f"{path}: fringe orders must be integers, got dtype {order.dtype}")
    if len(keys) != 3 or len(set(keys)) != 3:
        raise PSPMatError(f"{path}: keys must be three distinct names, got {keys}")
    data = {keys[0]: psin, keys[1]: pcos, keys[2]: order.astype(np.int32)}
    if n_steps is not None:
        data["n_steps"] = np.int32(n_steps)
    if periods is not None:
        data["periods"] = np.float64(periods)
    data.update(extra)
    _savemat_atomic(Path(path), data, compress)


def sums_from_phase(phase: np.ndarray, valid: np.ndarray | None = None, modulation=1.0,
                    convention: str = "benchmark") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Absolute phase (rad) -> ``(PSin, PCos, Order)`` that the folder reader turns back into ``phase``.

    ``modulation`` scales the sums (``(N/2) B`` of real data; any positive value keeps the phase);
    pixels where ``valid`` is False (or the phase is not finite) get ``PSin = PCos = 0, Order = 0``,
    the benchmark's invalid marker. Orders are int32.
    """
    check_convention(convention)
    phi = np.asarray(phase, dtype=np.float64)
    ok = np.isfinite(phi) if valid is None else (np.asarray(valid, bool) & np.isfinite(phi))
    p = np.where(ok, phi, 0.0)
    m = np.broadcast_to(np.asarray(modulation, dtype=np.float64), phi.shape)
    psin = np.where(ok, m * np.sin(p), 0.0)
    pcos = np.where(ok, m * np.cos(p), 0.0)
    # the order from the wrapped phase the reader will compute (benchmark (0, 2 pi], fppsim (-pi, pi]), not
    # from rounding phi / 2 pi: at a wrap (phi = k pi exactly, common in phases decoded from 8-bit images)
    # sin(phi) is a rounding residue of either sign, and the two roundings could disagree by one period
    order = np.rint((p - wrapped_from_sums(psin, pcos, convention)) / (2 * np.pi))
    return psin, pcos, np.where(ok, order, 0).astype(np.int32)


def _savemat_atomic(path: Path, data: dict, compress: bool = True) -> None:
    """``scipy.io.savemat`` (MATLAB v5) through :func:`fppsim.files.atomic_path`."""
    import scipy.io

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        scipy.io.savemat(fh, data, do_compression=compress, oned_as="column")


def save_psp_folder_sample(root: str | os.PathLike, sid: str, psin: np.ndarray, pcos: np.ndarray,
                           order: np.ndarray, image: np.ndarray | None = None, compress: bool = True) -> list[Path]:
    """Write one id in the folder layout (MATLAB v5 files, each written atomically); returns the paths.

    ``psin, pcos`` float (stored float64), ``order`` integer (stored as MATLAB double, as the public
    data do), ``image`` uint8 (H, W) iPattern. Use :func:`sums_from_phase` to make the three from an
    absolute phase. Sub-folders are created; existing files of other ids are left alone.
    """
    root = Path(root)
    sid = str(sid)
    if not sid or "/" in sid or "\\" in sid or sid.startswith("."):
        raise PSPMatError(f"{root}: invalid sample id {sid!r}")
    psin = np.asarray(psin, dtype=np.float64)
    pcos = np.asarray(pcos, dtype=np.float64)
    order = np.asarray(order)
    arrays = {"sin": psin, "cos": pcos, "order": order}
    if image is not None:
        arrays["image"] = np.asarray(image)
    for r, a in arrays.items():
        if a.shape != psin.shape or a.ndim != 2:
            raise PSPMatError(f"{root}/{FOLDERS[r][0]}/{sid}.mat: shape {a.shape} differs from PSin's {psin.shape} "
                              "(all must be the same 2-D shape)")
    if order.dtype.kind == "f" and (not np.all(np.isfinite(order)) or np.any(order != np.rint(order))):
        raise PSPMatError(f"{root}/Fringe/{sid}.mat: fringe orders must be finite integers")
    if image is not None and arrays["image"].dtype != np.uint8:
        raise PSPMatError(f"{root}/iPattern/{sid}.mat: iPattern must be uint8, got {arrays['image'].dtype}")
    written = []
    for r, a in arrays.items():
        sub, var = FOLDERS[r]
        (root / sub).mkdir(parents=True, exist_ok=True)
        value = a.astype(np.float64) if r == "order" else a
        path = root / sub / f"{sid}.mat"
        _savemat_atomic(path, {var: value}, compress)
        written.append(path)
    return written


def export_psp_folders(native_root: str | os.PathLike, out_root: str | os.PathLike, source: str = "psp",
                       convention: str = "benchmark", modulation: float = 100.0) -> list[str]:
    """Write a native fppsim dataset in the folder layout (e.g. a synthetic held-out set for
    ``uhrnet evaluate-phase``); returns the ids written (the native sample ids).

    ``source``: ``"psp"`` uses the decoded phase ``phase_psp`` and ``mask_psp`` (what a lab measures;
    needs samples generated with PSP), ``"true"`` the exact ``phase_true`` and ``mask``. The iPattern is
    the sample's ``fringe.png``; pixels outside the mask get ``PSin = PCos = 0``.
    """
    if source not in ("psp", "true"):
        raise PSPMatError(f"source must be 'psp' or 'true', got {source!r}")
    keys = ("phase_psp", "mask_psp") if source == "psp" else ("phase_true", "mask")
    ids = []
    for rec in read_manifest(native_root):
        sid = str(rec.get("id"))
        s = load_native_sample(Path(native_root) / sid, keys=keys, meta=False)
        missing = [k for k in keys if k not in s]
        if missing:
            raise PSPMatError(f"{Path(native_root) / sid / 'arrays.npz'}: no {', '.join(missing)} "
                              f"({'generate with PSP, or use source=true' if source == 'psp' else 'not a native sample'})")
        img = s["fringe"]
        if img.ndim != 2 or img.dtype != np.uint8:
            raise PSPMatError(f"{Path(native_root) / sid / 'fringe.png'}: expected an 8-bit gray image")
        phase, mask = s[keys[0]].astype(np.float64), s[keys[1]] > 0.5
        save_psp_folder_sample(out_root, sid, *sums_from_phase(phase, mask, modulation, convention), img)
        ids.append(sid)
    return ids
