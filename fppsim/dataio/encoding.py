"""Encodings: how fringes, grey images and arrays become bytes and back (the dataset files' codecs).

* the fringe encoding of the dataset contract: 8-bit intensity ``I/127.5 - 1`` in [-1, 1]
  (:func:`encode_fringe` / :func:`decode_fringe`), shape normalisation of image stacks
  (:func:`as_image_stack`), grey image files (:func:`read_gray_image`, THE image reader: colour refused unless
  grey, :func:`colour_to_grey`) and the one 16-bit to 8-bit conversion (:func:`to_8bit`);
* the writers' fast codecs: :func:`encode_png` (8-bit grey PNG) and :func:`save_npz` (an ``.npz`` that
  ``np.load`` reads), both through zlib-ng when installed (the same formats, faster), with fixed
  timestamps so the same arrays give the same bytes; :func:`json_default` for numpy values in JSON.

numpy and OpenCV only.
"""

from __future__ import annotations

import io
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from fppsim.errors import DatasetError, InputError

try:  # the same deflate format as the stdlib zlib, written 2x (PNG) to 10x (npz, level 1) faster
    from zlib_ng import zlib_ng as _deflate
except ImportError:  # a tree installed before zlib-ng became a dependency: the same files, slower
    _deflate = zlib

__all__ = ["encode_fringe", "decode_fringe", "load_npy", "as_image_stack", "COLOUR_TOLERANCE", "colour_to_grey", "read_gray_image",
           "LEVELS_16_PER_8", "to_8bit", "json_default", "save_npz", "encode_png", "PNG_SIGNATURE", "png_size"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ============================================================================================ fringe and grey images
LEVELS_16_PER_8 = 257.0  # 16-bit grey levels per 8-bit level: 65535 = 255 * 257


def to_8bit(image: np.ndarray) -> np.ndarray:
    """A grey image as uint8: uint8 as it is, uint16 scaled to 8-bit levels (``I / 257``, rounded): THE 16-bit to
    8-bit conversion of every reader. Any other dtype: :class:`DatasetError`."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return img
    if img.dtype != np.uint16:
        raise DatasetError(f"{img.dtype} image, expected 8-bit (or 16-bit) grey")
    return np.clip(np.rint(img / LEVELS_16_PER_8), 0, 255).astype(np.uint8)


def encode_fringe(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Grey image (uint8, or uint16 scaled to 8-bit levels) -> float32 ``I/127.5 - 1`` in [-1, 1];
    -1 on invalid pixels when ``mask`` is given."""
    img = np.asarray(image)
    f = img.astype(np.float32)
    if img.dtype == np.uint16:
        f = f * np.float32(1.0 / LEVELS_16_PER_8)  # 16-bit -> 8-bit intensity scale (not rounded)
    f = f / np.float32(127.5) - np.float32(1.0)
    if mask is not None:
        f = np.where(np.asarray(mask) > 0, f, np.float32(-1.0)).astype(np.float32)
    return f


def decode_fringe(fringe: np.ndarray) -> np.ndarray:
    """float fringe in [-1, 1] -> uint8 grey levels (inverse of :func:`encode_fringe`)."""
    return np.clip(np.rint((np.asarray(fringe, dtype=np.float64) + 1.0) * 127.5), 0, 255).astype(np.uint8)


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """THE reader of a user's ``.npy`` array file: memory-mapped, read-only, no pickles. Raises
    :class:`DatasetError` naming the file when it is not one array (damaged or empty, a pickle, an ``.npz``
    archive under a ``.npy`` name): numpy's own errors (or an ``NpzFile``) were tracebacks in the readers."""
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DatasetError(f"{path}: cannot read as a .npy array ({exc})") from None
    if not isinstance(arr, np.ndarray):  # np.load opens an .npz archive whatever its name
        arr.close()
        raise DatasetError(f"{path}: an .npz archive, not a .npy array (save one array with np.save)")
    return arr


def as_image_stack(arr: np.ndarray, name: str | os.PathLike = "array") -> np.ndarray:
    """View an image array as (N, H, W): accepts (N, H, W, 1), (N, H, W), (H, W, 1) and (H, W).

    (H, W, 1) and (H, W) are one image. Raises :class:`DatasetError` naming ``name`` otherwise, and for an
    empty array or a channel-last colour array (H, W, 3): not N images 3 px wide.
    """
    if arr.size == 0:
        raise DatasetError(f"{name}: empty array (shape {arr.shape})")
    if arr.ndim == 3 and arr.shape[-1] in (2, 3, 4) and min(arr.shape[:2]) >= 16:
        raise DatasetError(f"{name}: shape {arr.shape} looks like a colour (H, W, {arr.shape[-1]}) array; give grey "
                           "images, (H, W) or (N, H, W)")
    if arr.ndim == 2:
        return arr[None]
    if arr.ndim == 3 and arr.shape[-1] == 1:
        return arr[None, ..., 0]
    if arr.ndim == 3:
        return arr
    if arr.ndim == 4:
        if arr.shape[-1] != 1:
            raise DatasetError(f"{name}: shape {arr.shape}, expected (N, H, W, 1) with one channel")
        return arr[..., 0]
    raise DatasetError(f"{name}: shape {arr.shape}, expected (N, H, W, 1), (N, H, W) or (H, W)")


COLOUR_TOLERANCE = 8.0  # mean |channel - grey| in 8-bit levels above which a colour image is refused


def colour_to_grey(img: np.ndarray, path: str | os.PathLike = "image") -> np.ndarray:
    """BGR(A) image -> grey, the way a grey camera would have recorded the same scene.

    A fringe image saved in colour (equal channels, or a colour camera's near-grey white-light image)
    becomes its luminance ``0.299 R + 0.587 G + 0.114 B`` (OpenCV's BGR2GRAY): equal channels give
    exactly the grey image. An image whose channels differ more than :data:`COLOUR_TOLERANCE` levels on
    average (a colour-mapped picture, tinted light) has no grey equivalent the models were trained on,
    so it is refused (:class:`DatasetError`) with a hint instead of giving heights off by tens of mm.
    """
    import cv2

    if img.shape[2] == 4:
        img = img[..., :3]
    elif img.shape[2] != 3:
        raise DatasetError(f"{path}: {img.shape[2]}-channel image, expected grey (or colour with equal channels)")
    img = np.ascontiguousarray(img)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    scale = LEVELS_16_PER_8 if img.dtype == np.uint16 else 1.0
    spread = float(np.abs(img.astype(np.float32) - grey[..., None].astype(np.float32)).mean()) / scale
    if spread > COLOUR_TOLERANCE:
        raise DatasetError(f"{path}: colour image whose channels differ by {spread:.1f} gray levels on average; the "
                           "models take grey fringe images: save the camera's grey (monochrome) image instead")
    return grey


def read_gray_image(path: str | os.PathLike) -> np.ndarray:
    """A grey image file as a 2-D uint8 or uint16 array (a grey scene saved in colour is converted,
    other colour images are refused: :func:`colour_to_grey`).

    Raises :class:`DatasetError` naming the file when it is missing, unreadable, of another depth or a TIFF of
    several pages (a stack: imread reads its first page), or a 16-bit image holds no value of 4096 or more (10- or
    12-bit data: read as 16-bit it would be all but black).
    OpenCV's own log line is silenced: the one-line error replaces it.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        pages = cv2.imcount(str(path)) if img is not None and path.suffix.lower() in (".tif", ".tiff") else 1
        if pages > 1:  # frames of the first page's size: a reduced-size page (a thumbnail) is no frame
            ok, every = cv2.imreadmulti(str(path), flags=cv2.IMREAD_UNCHANGED)
            pages = sum(p.shape == img.shape for p in every) if ok else pages
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise DatasetError(f"{path}: cannot read as an image")
    if pages > 1:  # imread reads the first page alone: the other frames would be lost without a word
        raise DatasetError(f"{path}: a TIFF of {pages} pages (a stack); save one image per file, or the stack as "
                           "a .npy (N, H, W)")
    if img.ndim == 3:
        img = colour_to_grey(img, path)
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{path}: {img.dtype} image, expected 8-bit (or 16-bit) grey")
    if img.dtype == np.uint16 and 0 < int(img.max()) < 4096:  # read as /257 it would be all but black
        raise DatasetError(f"{path}: a 16-bit image whose brightest pixel is {int(img.max())} of 65535 (10- or 12-bit "
                           "data in a 16-bit file?): scale it to the full range, or save it as 8-bit")
    return img


# ============================================================================================ npz, PNG, JSON


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars/arrays and paths (anything else: ``str``)."""
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: identical runs give identical bytes


def save_npz(path: str | os.PathLike, arrays: dict, compresslevel: int = 1, min_gain: float = 0.25) -> None:
    """Write an .npz readable by ``np.load`` with fast deflate (level 1; numpy's default is slow).

    An array whose sampled rows deflate by less than ``min_gain`` (noisy float mantissas such as
    ``phase_psp``) is stored uncompressed: deflating it would cost most of the write for a few percent.
    Entries carry a fixed timestamp, so the same arrays give the same bytes. Each entry is streamed
    into the zip (``.npy`` header, then the array's own memory): no copies of the arrays are made.
    """
    with zipfile.ZipFile(path, "w") as zf:
        for key, arr in arrays.items():
            arr = np.asarray(arr, order="C")  # (np.ascontiguousarray would make a 0-d array 1-d)
            if arr.dtype.hasobject:
                raise InputError(f"save_npz: '{key}' holds Python objects (not allowed without pickle)")
            header = _npy_header(arr)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED if _deflate_pays(arr, compresslevel, min_gain) \
                else zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            info.file_size = len(header) + arr.nbytes  # as writestr sets it: decides zip64 like writestr
            if hasattr(info, "compress_level"):  # Python >= 3.13
                info.compress_level = compresslevel
            else:
                info._compresslevel = compresslevel
            with zf.open(info, "w") as dest:
                if info.compress_type == zipfile.ZIP_DEFLATED and _deflate is not zlib \
                        and getattr(dest, "_compressor", None) is not None:
                    # zipfile deflates with the stdlib zlib; the member is the same raw deflate stream
                    dest._compressor = _deflate.compressobj(compresslevel, _deflate.DEFLATED, -15)
                dest.write(header)
                dest.write(arr.reshape(-1).view(np.uint8))


def _npy_header(arr: np.ndarray) -> bytes:
    """The ``.npy`` header ``np.lib.format.write_array`` writes for ``arr`` (format 1.0, or 2.0 when the
    header does not fit 1.0)."""
    buf = io.BytesIO()
    d = np.lib.format.header_data_from_array_1_0(arr)
    try:
        np.lib.format.write_array_header_1_0(buf, d)
    except ValueError:
        buf = io.BytesIO()
        np.lib.format.write_array_header_2_0(buf, d)
    return buf.getvalue()


def _deflate_pays(arr: np.ndarray, level: int, min_gain: float, rows: int = 16) -> bool:
    """Deflate a few evenly spaced rows: does compression save at least ``min_gain`` of the bytes?"""
    if arr.nbytes < 65536 or arr.ndim < 1:
        return True
    step = max(1, arr.shape[0] // rows)
    sample = arr[::step].tobytes()
    return len(_deflate.compress(sample, level)) <= (1.0 - min_gain) * len(sample)


def png_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` of the PNG file ``path`` from its signature and header; None when it is no PNG (or
    cannot be read). Reads 24 bytes: the tools that adopt their own older figures tell them by this."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if len(head) < 24 or not head.startswith(PNG_SIGNATURE):
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def encode_png(img: np.ndarray) -> bytes:
    """PNG file bytes of a uint8 (H, W) grey image, written for speed (the pixels are exact).

    Every row uses the "up" filter (the row minus the row above; the first row's "above" is zero, as
    PNG defines it) and the filtered rows are deflated Huffman-only at level 1: noisy 8-bit camera
    images gain nothing from string matching, and trying libpng's five filters per row costs twice the
    time for about 3 % smaller files. Any other image (colour, 16-bit) goes through OpenCV's encoder.
    """
    img = np.asarray(img)
    if img.dtype not in (np.uint8, np.uint16) or 0 in img.shape \
            or not (img.ndim == 2 or img.ndim == 3 and img.shape[2] in (3, 4)):
        raise InputError(f"encode_png: a PNG holds a non-empty uint8/uint16 image of shape (H, W), (H, W, 3) "
                         f"or (H, W, 4), got {img.dtype} {img.shape}")
    if img.dtype != np.uint8 or img.ndim != 2:
        import cv2

        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise InputError(f"encode_png: OpenCV cannot encode a {img.dtype} array of shape {img.shape}")
        return buf.tobytes()
    h, w = img.shape
    rows = np.empty((h, w + 1), np.uint8)
    rows[:, 0] = 2  # filter type "up"
    rows[0, 1:] = img[0]
    np.subtract(img[1:], img[:-1], out=rows[1:, 1:])  # modulo 256, as PNG's filter arithmetic is
    z = _deflate.compressobj(1, _deflate.DEFLATED, 15, 9, _deflate.Z_HUFFMAN_ONLY)
    idat = z.compress(rows) + z.flush()

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = _deflate.crc32(data, _deflate.crc32(kind))
        return len(data).to_bytes(4, "big") + kind + data + crc.to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes((8, 0, 0, 0, 0))  # 8-bit grey, no interlace
    return PNG_SIGNATURE + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")
