"""Reading real PSP data in the common "PSin / PCos / fringe-order" MATLAB .mat layouts.

Many FPP labs store a phase-shifting measurement as three same-shaped arrays:

* ``PSin`` — numerator of the phase-shifting arctangent, ``PSin = -sum_n I_n sin(delta_n)``;
* ``PCos`` — denominator, ``PCos = +sum_n I_n cos(delta_n)``;
* ``Order`` — the integer fringe order ``k`` of the same frequency (from temporal unwrapping),

with ``I_n = A + B cos(Phi + delta_n)`` and ``delta_n = 2 pi n / N``. Then
``wrapped = atan2(PSin, PCos)`` in ``(-pi, pi]`` and ``absolute = wrapped + 2 pi Order`` — exactly what
:func:`fppsim.phase.psp.wrapped_phase` and :func:`fppsim.phase.psp.unwrap_temporal` give for simulated stacks
(:func:`fppsim.phase.psp.phase_sums` returns the two sums), so real and simulated phase share one code
path. Data written with the opposite sine sign (``PSin = +sum I_n sin delta_n``) loads correctly with
``negate_sin=True``.

A second layout, one folder per quantity and one variable per file (``<root>/PSin/<id>.mat``,
``PCos/``, ``Fringe/`` holding ``Order``, ``iPattern/`` holding the uint8 single-shot image), is how the
public benchmarks republish the figshare rig's frames: :func:`list_psp_ids`, :func:`load_psp_folder_sample`,
:func:`iter_psp_folder` read it (see :data:`CONVENTIONS` for how wrapped phase and order combine
there); the writers (``save_psp_mat``, ``save_psp_folder_sample``, ``export_psp_folders`` converting a
native fppsim dataset) live in :mod:`fppsim.dataio.writers`.

MATLAB v4/v5/v7 files are read with :func:`scipy.io.loadmat`; v7.3 (HDF5) files need ``h5py``.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fppsim.dataio.readers.listing import native_samples_note, plain_images_note, skipped_note, warn_skipped
from fppsim.errors import NoPhaseError, PSPMatError, UsageError
from fppsim.phase.psp import phase_from_sums

__all__ = ["PSPMatError", "NoPhaseError", "PspMat", "SIN_KEYS", "COS_KEYS", "ORDER_KEYS", "load_psp_mat", "FOLDERS",
           "CONVENTIONS", "check_convention", "wrapped_from_sums", "is_psp_folder", "list_psp_ids", "read_mat_variable",
           "load_ipattern", "load_psp_folder_sample", "iter_psp_folder", "AUTO", "READINGS", "phase_jump_share",
           "reading_check", "reading_words", "reading_note", "READ_CONVENTIONS", "check_read_convention"]

SIN_KEYS = ("PSin", "psin", "Psin", "PS", "ps", "Sin", "sin", "S", "num", "numerator", "sin_sum", "SinSum")
COS_KEYS = ("PCos", "pcos", "Pcos", "PC", "pc", "Cos", "cos", "C", "den", "denominator", "cos_sum", "CosSum")
ORDER_KEYS = ("Order", "order", "k", "K", "FringeOrder", "fringe_order", "fringeorder", "kmap", "KMap",
              "n_order", "ord")


@dataclass
class PspMat:
    """PSP data loaded from a .mat file (arrays of one shape).

    psin, pcos : float64 phase-shifting sums (see module docstring).
    order : int64 fringe order ``k``; 0 where the stored order is not finite.
    wrapped : float64 wrapped phase ``atan2(psin, pcos)`` in ``(-pi, pi]`` (rad).
    phase : float64 absolute phase ``wrapped + 2 pi order`` (rad); NaN where any input is not finite.
    valid : bool, all three inputs finite.
    modulation : float64 ``B = (2/N) sqrt(psin^2 + pcos^2)`` when the file stores ``n_steps``, else None.
    keys : the variable names used, ``{"sin": ..., "cos": ..., "order": ...}``.
    meta : other scalar variables found in the file (e.g. ``n_steps``, ``periods``); for the folder
        layout ``id``, ``convention`` and ``root``.
    path : the file (the PSin file of the folder layout).
    image : uint8 (H, W) single-shot image (iPattern of the folder layout), else None.
    """

    psin: np.ndarray
    pcos: np.ndarray
    order: np.ndarray
    wrapped: np.ndarray
    phase: np.ndarray
    valid: np.ndarray
    modulation: np.ndarray | None
    keys: dict
    meta: dict = field(default_factory=dict)
    path: str = ""
    image: np.ndarray | None = None

    def digest(self) -> str:
        """A content hash of the frame: its sums (the sine as stored, ``negate_sin`` undone), fringe orders and
        single-shot image, dtypes and shapes included. A copy of its files, in another folder or under another
        id, hashes the same whatever convention reads it; another frame (the same phase under another image
        too: another input) does not."""
        # undone by negation, which flips every sign bit back (a NaN's too: -1.0 * NaN keeps its sign on x86)
        sin = np.negative(self.psin) if self.meta.get("negate_sin") else self.psin
        h = hashlib.sha256()
        for name, a in (("sin", sin), ("cos", self.pcos), ("order", self.order), ("image", self.image)):
            if a is not None:
                a = np.ascontiguousarray(a)
                h.update(f"{name}{a.dtype}{a.shape}".encode())
                h.update(a.tobytes())
        return h.hexdigest()


def _pick(found: dict, wanted: str | None, candidates: tuple, role: str, path: Path) -> str:
    names = [k for k in found if not k.startswith("__")]
    if wanted is not None:
        if wanted in found:
            return wanted
        raise PSPMatError(f"{path}: no variable '{wanted}' for {role} (variables: {', '.join(names) or 'none'})")
    for c in candidates:
        if c in found:
            return c
    lower = {k.lower(): k for k in names}
    for c in candidates:
        if c.lower() in lower:
            return lower[c.lower()]
    raise PSPMatError(f"{path}: no {role} variable (tried {', '.join(candidates[:6])}, ...; "
                      f"variables: {', '.join(names) or 'none'}); pass {role}_key=")


def _read_mat(path: Path) -> dict:
    import scipy.io

    try:
        major, _ = scipy.io.matlab.matfile_version(str(path))
    except Exception as exc:
        raise PSPMatError(f"{path}: not a MATLAB .mat file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if major == 2:
        try:
            import h5py
        except ImportError:
            raise PSPMatError(f"{path}: MATLAB v7.3 (HDF5) file; install h5py to read it, or re-save it in MATLAB "
                              "with save(..., '-v7')") from None
        out = {}
        with h5py.File(path, "r") as h5:
            for k, v in h5.items():
                if isinstance(v, h5py.Dataset):
                    out[k] = np.asarray(v).T  # MATLAB stores column-major: transpose back
        return out
    try:
        return scipy.io.loadmat(str(path))
    except Exception as exc:
        raise PSPMatError(f"{path}: cannot read .mat file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None


def load_psp_mat(path: str | os.PathLike, sin_key: str | None = None, cos_key: str | None = None,
                 order_key: str | None = None, negate_sin: bool = False, squeeze: bool = True,
                 order_tol: float = 1e-6) -> PspMat:
    """Load PSin / PCos / fringe order from a .mat file and form wrapped and absolute phase.

    Parameters
    ----------
    path : .mat file (v4-v7 via scipy; v7.3 needs h5py).
    sin_key, cos_key, order_key : variable names; default: the first of :data:`SIN_KEYS`,
        :data:`COS_KEYS`, :data:`ORDER_KEYS` present (exact spelling first, then case-insensitive).
    negate_sin : the file stores ``+sum I_n sin(delta_n)`` (the other common sign convention).
    squeeze : drop singleton axes (MATLAB stores vectors and scalars as 2-D).
    order_tol : stored orders may be floating point but must be within this of an integer.

    Returns
    -------
    :class:`PspMat`. Raises :class:`PSPMatError` (one line naming the file) for a missing variable,
    mismatched shapes, non-numeric data or non-integer orders.
    """
    path = Path(path)
    if not path.is_file():
        raise PSPMatError(f"{path}: no such file")
    found = _read_mat(path)
    ks = _pick(found, sin_key, SIN_KEYS, "sin", path)
    kc = _pick(found, cos_key, COS_KEYS, "cos", path)
    ko = _pick(found, order_key, ORDER_KEYS, "order", path)
    arrays = {}
    for role, key in (("sin", ks), ("cos", kc), ("order", ko)):
        a = np.asarray(found[key])
        if a.dtype.kind not in "biuf":
            raise PSPMatError(f"{path}: variable '{key}' ({role}) is not a real numeric array (dtype {a.dtype})")
        a = a.astype(np.float64)
        arrays[role] = np.squeeze(a) if squeeze else a
    shapes = {k: arrays[r].shape for r, k in (("sin", ks), ("cos", kc), ("order", ko))}
    if len(set(shapes.values())) != 1:
        raise PSPMatError(f"{path}: shapes differ: " + ", ".join(f"{k} {s}" for k, s in shapes.items()))
    psin, pcos, order_f = arrays["sin"], arrays["cos"], arrays["order"]
    if negate_sin:
        psin = -psin
    valid = np.isfinite(psin) & np.isfinite(pcos) & np.isfinite(order_f)
    of = np.where(np.isfinite(order_f), order_f, 0.0)
    ok = np.rint(of)
    bad = np.abs(of - ok) > order_tol
    if np.any(bad):
        first = of[bad].ravel()[0]
        raise PSPMatError(f"{path}: fringe order '{ko}' is not integer at {int(bad.sum())} pixels (e.g. {first!r})")
    order = ok.astype(np.int64)
    wrapped = phase_from_sums(psin, pcos)
    phase = np.where(valid, wrapped + 2.0 * np.pi * order, np.nan)
    meta = {}
    for k, v in found.items():
        if k.startswith("__") or k in (ks, kc, ko):
            continue
        a = np.asarray(v)
        if a.size == 1 and a.dtype.kind in "biuf":
            meta[k] = a.item()
        elif a.dtype.kind == "U" and a.size == 1:
            meta[k] = str(a.item())
    modulation = None
    n = meta.get("n_steps")
    if n is not None and n >= 3:
        modulation = 2.0 / n * np.hypot(psin, pcos)
    return PspMat(psin=psin, pcos=pcos, order=order, wrapped=wrapped, phase=phase, valid=valid,
                  modulation=modulation, keys={"sin": ks, "cos": kc, "order": ko}, meta=meta, path=str(path))


# ====================================================================== one folder per quantity
# The layout the public phase-retrieval benchmarks use for the figshare rig's frames:
#   <root>/PSin/<id>.mat (PSin), <root>/PCos/<id>.mat (PCos), <root>/Fringe/<id>.mat (Order),
#   <root>/iPattern/<id>.mat (iPattern, uint8 single-shot image).

FOLDERS = {"sin": ("PSin", "PSin"), "cos": ("PCos", "PCos"), "order": ("Fringe", "Order"),
           "image": ("iPattern", "iPattern")}
"""role -> (sub-folder, variable name) of the folder layout."""

CONVENTIONS = ("benchmark", "fppsim")
"""How wrapped phase and fringe order combine.

``benchmark``: ``Phi = atan2(-PSin, -PCos) + pi + 2 pi Order`` (wrapped in ``(0, 2 pi]``: the order counts
periods starting at the phase zero), as the public benchmark data store it; ``fppsim``:
``Phi = atan2(PSin, PCos) + 2 pi Order`` (wrapped in ``(-pi, pi]``), what :func:`fppsim.phase.psp.unwrap_temporal`
produces. Both read ``PSin`` as proportional to ``+sin Phi``; ``negate_sin=True`` flips it.
"""
AUTO = "auto"
READ_CONVENTIONS = (AUTO,) + CONVENTIONS
"""The readers' third ``convention``: the public data's (``benchmark``, with the given ``negate_sin``) unless the
files are clearly written another way (:func:`reading_check`), then that way."""


def check_convention(convention: str) -> str:
    """``convention`` if it is one of :data:`CONVENTIONS`, else :class:`PSPMatError`."""
    if convention not in CONVENTIONS:
        raise PSPMatError(f"unknown phase convention {convention!r} (known: {', '.join(CONVENTIONS)})")
    return convention


def wrapped_from_sums(psin: np.ndarray, pcos: np.ndarray, convention: str = "benchmark") -> np.ndarray:
    """Wrapped phase (rad, float64) of the sums: ``(0, 2 pi]`` for 'benchmark', ``(-pi, pi]`` for 'fppsim'."""
    check_convention(convention)
    s = np.asarray(psin, dtype=np.float64)
    c = np.asarray(pcos, dtype=np.float64)
    if convention == "benchmark":
        return np.arctan2(-s, -c) + np.pi
    return phase_from_sums(s, c)


def is_psp_folder(root: str | os.PathLike) -> bool:
    """True when ``root`` holds at least the PSin and PCos sub-folders of the folder layout."""
    root = Path(root)
    return (root / "PSin").is_dir() and (root / "PCos").is_dir()


def _short(items, n: int = 8) -> str:
    items = list(items)
    return ", ".join(items[:n]) + (f", ... ({len(items)} in all)" if len(items) > n else "")


def list_psp_ids(root: str | os.PathLike, roles: tuple[str, ...] = ("sin", "cos", "order", "image")) -> list[str]:
    """Sample ids present in every sub-folder of ``roles`` (sorted; numeric names in numeric order).

    Raises :class:`PSPMatError` (one line naming ``root``) when a sub-folder is missing, when one holds
    no ``.mat`` file, or when the ids differ between sub-folders (listing which ids are missing where).
    """
    root = Path(root)
    if not root.is_dir():
        raise PSPMatError(f"{root}: not a folder")
    missing = [FOLDERS[r][0] for r in roles if not (root / FOLDERS[r][0]).is_dir()]
    if missing:
        found = sorted(p.name for p in root.iterdir() if p.is_dir())
        raise PSPMatError(f"{root}: missing folder(s) {', '.join(missing)} (found: {_short(found) or 'none'}); "
                          f"expected PSin/, PCos/, Fringe/, iPattern/ with one <id>.mat each{plain_images_note(root)}"
                          f"{native_samples_note(root)}")
    ids = {}
    for r in roles:
        sub = FOLDERS[r][0]
        ids[sub] = {p.stem for p in (root / sub).iterdir() if p.is_file() and p.suffix.lower() == ".mat"}
        if not ids[sub]:
            raise PSPMatError(f"{root / sub}: no .mat files" + skipped_note(root / sub, (".mat",)))
    every = set.union(*ids.values())
    common = set.intersection(*ids.values())
    if every != common:
        parts = [f"{sub} lacks {_short(sorted(every - s, key=_id_key))}" for sub, s in ids.items() if every - s]
        raise PSPMatError(f"{root}: ids differ between folders: " + "; ".join(parts)
                          + "".join(skipped_note(root / FOLDERS[r][0], (".mat",), within=root) for r in roles))
    for r in roles:
        warn_skipped(root / FOLDERS[r][0], (".mat",))
    return sorted(common, key=_id_key)


def _id_key(sid: str):
    return (0, int(sid), sid) if sid.isdigit() else (1, 0, sid)


def read_mat_variable(path: Path, name: str) -> np.ndarray:
    """The real numeric variable ``name`` of one .mat file (exact spelling first, then any case), squeezed;
    :class:`PSPMatError` naming the file (and the variables it holds) otherwise."""
    if not path.is_file():
        raise PSPMatError(f"{path}: no such file")
    found = _read_mat(path)
    names = [k for k in found if not k.startswith("__")]
    key = name if name in found else next((k for k in names if k.lower() == name.lower()), None)
    if key is None:
        raise PSPMatError(f"{path}: no variable '{name}' (variables: {', '.join(names) or 'none'})")
    a = np.asarray(found[key])
    if a.dtype.kind not in "biuf":
        raise PSPMatError(f"{path}: variable '{key}' is not a real numeric array (dtype {a.dtype})")
    return np.squeeze(a)


def _image_u8(a: np.ndarray, path: Path) -> np.ndarray:
    """An iPattern array as uint8 grey levels (a [0, 1] float image is scaled by 255); a 2-D image only."""
    if a.ndim != 2:  # (H, W, 3) saved in colour would read as H images 3 px wide
        raise PSPMatError(f"{path}: iPattern must be a 2-D grey image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    f = a.astype(np.float64)
    if not np.all(np.isfinite(f)):
        raise PSPMatError(f"{path}: iPattern holds NaN or inf")
    if a.dtype.kind == "f" and f.max(initial=0) <= 1.0:
        f = f * 255.0  # a [0, 1] image (im2double)
    if f.min(initial=0) < 0 or f.max(initial=0) > 255.5:
        raise PSPMatError(f"{path}: iPattern values {f.min():g}..{f.max():g} are not 8-bit gray levels")
    return np.rint(f).astype(np.uint8)


def load_ipattern(path: str | os.PathLike) -> np.ndarray:
    """The uint8 (H, W) single-shot image of one ``iPattern/<id>.mat`` file."""
    path = Path(path)
    return _image_u8(read_mat_variable(path, "iPattern"), path)


def load_psp_folder_sample(root: str | os.PathLike, sid: str, convention: str = "benchmark",
                           negate_sin: bool = False, image: bool = True, order_tol: float = 1e-6) -> PspMat:
    """One id of the folder layout as a :class:`PspMat` (``image`` = the uint8 iPattern, or None).

    Invalid pixels: ``PSin = PCos = 0`` (the benchmark's marker) or any input not finite; their
    ``phase`` is NaN. ``convention``: see :data:`CONVENTIONS`, or :data:`AUTO`: then ``meta`` says how the
    files were read (``convention``, ``negate_sin``) and, when that is not as given, ``read_as``: the
    :func:`reading_check` that chose it. Raises :class:`PSPMatError` naming the
    file for a missing file or variable (listing the variables found), non-numeric data, non-integer
    orders, or a shape that differs from PSin's.
    """
    auto = convention == AUTO
    convention = "benchmark" if auto else check_convention(convention)
    root = Path(root)
    roles = ("sin", "cos", "order") + (("image",) if image else ())
    arrays, paths = {}, {}
    for r in roles:
        sub, var = FOLDERS[r]
        paths[r] = root / sub / f"{sid}.mat"
        arrays[r] = read_mat_variable(paths[r], var)
    shape = arrays["sin"].shape
    if len(shape) != 2:
        raise PSPMatError(f"{paths['sin']}: PSin must be a 2-D image, got shape {shape}")
    for r in roles[1:]:
        if arrays[r].shape != shape:
            raise PSPMatError(f"{paths[r]}: shape {arrays[r].shape} differs from PSin's {shape} ({paths['sin']})")
    psin = arrays["sin"].astype(np.float64)
    pcos = arrays["cos"].astype(np.float64)
    if negate_sin:
        psin = -psin
    of = arrays["order"].astype(np.float64)
    valid = np.isfinite(psin) & np.isfinite(pcos) & np.isfinite(of) & ~((psin == 0) & (pcos == 0))
    if not valid.any():  # name the file that leaves no pixel a phase
        for r, a in (("sin", psin), ("cos", pcos), ("order", of)):
            if not np.isfinite(a).any():
                raise NoPhaseError(f"{paths[r]}: {FOLDERS[r][1]} holds no finite value (all NaN or inf): no pixel "
                                  "has a phase")
        raise NoPhaseError(f"{paths['sin']}: no pixel has a phase (PSin and PCos are 0, the invalid marker, or NaN "
                          f"wherever {paths['order'].parent.name}/ and {paths['cos'].parent.name}/ are finite)")
    of = np.where(np.isfinite(of), of, 0.0)
    ok = np.rint(of)
    bad = valid & (np.abs(of - ok) > order_tol)
    if np.any(bad):
        raise PSPMatError(f"{paths['order']}: fringe order is not integer at {int(bad.sum())} pixels "
                          f"(e.g. {of[bad].ravel()[0]!r})")
    order = ok.astype(np.int64)
    wrapped, phase = _read_phase(psin, pcos, order, valid, convention)
    img = _image_u8(arrays["image"], paths["image"]) if image else None
    s = PspMat(psin=psin, pcos=pcos, order=order, wrapped=wrapped, phase=phase, valid=valid,
               modulation=None, keys={"sin": "PSin", "cos": "PCos", "order": "Order"},
               meta={"id": sid, "convention": convention, "negate_sin": bool(negate_sin), "root": str(root)},
               path=str(paths["sin"]), image=img)
    # how well the reading fits is measured whether it was given or detected (its phase jump share);
    # auto chooses the convention, and the sine's sign too unless negate_sin fixes it (docs/own_rig.md)
    given = (convention, bool(negate_sin))
    if auto:
        pick = reading_check(s, convention, negate_sin,
                             readings=[r for r in READINGS if r[1]] if negate_sin else READINGS)
        if pick["best"] is not None:  # written another way: read it that way
            conv, neg = pick["best"]
            s.psin = -psin if neg != bool(negate_sin) else psin
            s.wrapped, s.phase = _read_phase(s.psin, pcos, order, valid, conv)
            s.meta.update(convention=conv, negate_sin=neg, read_as=pick | {"from": given})
    conv, neg = s.meta["convention"], s.meta["negate_sin"]
    check = reading_check(s, conv, neg)
    s.meta["jump_share"] = check["given"]
    # every reading wraps (one that does not is a misreading, noted below): Order is no order
    if min(check["given"], check["best_share"]) >= WRAPPED_SHARE and np.ptp(order[valid]) == 0:
        raise PSPMatError(f"{paths['order']}: Order is {int(order[valid][0])} at every valid pixel and the phase jumps "
                          f"by more than pi between {check['given']:.1%} of neighbouring pixels: a wrapped phase, "
                          "not an absolute one: Fringe/ must hold each pixel's fringe order (temporal unwrapping)")
    if check["best"] is not None:  # read as given, and clearly not how the files are written: said, not changed
        s.meta["misread"] = check | {"from": (conv, neg)}
    return s


WRAPPED_SHARE = 0.01
"""A phase with one fringe order everywhere that jumps by more than pi between this share of neighbouring pixels or more
is wrapped (FP672/541 with Order 0: 9.2 %; the public frames as written 0.2-0.4 %, FP672 on black 1.5 % with its
orders)."""


def _read_phase(psin, pcos, order, valid, convention: str) -> tuple[np.ndarray, np.ndarray]:
    """``(wrapped, phase)`` of the sums and orders in ``convention``; the phase is NaN where not ``valid``."""
    with np.errstate(invalid="ignore"):
        wrapped = wrapped_from_sums(np.where(valid, psin, 0.0), np.where(valid, pcos, 0.0), convention)
    return wrapped, np.where(valid, wrapped + 2.0 * np.pi * order, np.nan)


def check_read_convention(value: str, flag: str = "--convention", error=UsageError) -> str:
    """``value`` if it is one of :data:`READ_CONVENTIONS`, else ``error`` (exit 2) naming ``flag``."""
    if value not in READ_CONVENTIONS:
        raise error(f"{flag} must be one of {', '.join(READ_CONVENTIONS)}, got {value!r}")
    return value


def iter_psp_folder(root: str | os.PathLike, ids: list[str] | None = None, **kw):
    """Yield ``(id, PspMat)`` for every id of the folder layout (or the given ``ids``), in order."""
    image = kw.get("image", True)
    roles = ("sin", "cos", "order") + (("image",) if image else ())
    for sid in (list_psp_ids(root, roles) if ids is None else ids):
        yield sid, load_psp_folder_sample(root, sid, **kw)


# ====================================================================== which way a folder's phase is written
READINGS = (("benchmark", False), ("benchmark", True), ("fppsim", False), ("fppsim", True))
"""Every ``(convention, negate_sin)`` a folder's PSin / PCos / Order can be read with."""


def phase_jump_share(phase: np.ndarray, valid: np.ndarray) -> float:
    """The share of neighbouring valid pixel pairs whose absolute phase (rad) differs by more than pi, the
    larger of the two image directions. A phase read the way it was written jumps only at object and shadow
    edges (0.1-0.4 % on the public frames); read another way it jumps every period or half period (5-19 %)."""
    phase = np.asarray(phase, np.float64)
    valid = np.asarray(valid, bool) & np.isfinite(phase)
    p = np.where(valid, phase, 0.0)
    shares = []
    for d, both in ((p[1:] - p[:-1], valid[1:] & valid[:-1]), (p[:, 1:] - p[:, :-1], valid[:, 1:] & valid[:, :-1])):
        shares.append(float(np.mean(np.abs(d[both]) > np.pi)) if both.any() else 0.0)
    return max(shares)


def reading_check(s: PspMat, convention: str = "benchmark", negate_sin: bool = False, factor: float = 4.0,
                  floor: float = 0.01, readings=READINGS) -> dict:
    """Whether a folder-layout sample (:func:`load_psp_folder_sample`, read with ``convention`` /
    ``negate_sin``) is written another way: the phase jump share (:func:`phase_jump_share`) of every
    reading in ``readings`` (:data:`READINGS`) from the same files: ``{"given": share, "best": (convention, negate_sin),
    "best_share": share}``, with ``best`` None when the given one is the smoothest or within ``factor`` of
    it, or jumps at fewer than ``floor`` of the pixel pairs (it fits)."""
    psin = -s.psin if negate_sin else s.psin  # the files' own PSin
    valid = s.valid & (s.image > 0) if s.image is not None else s.valid
    shares = {}
    for conv, neg in {*readings, (convention, bool(negate_sin))}:
        shares[conv, neg] = phase_jump_share(_read_phase(-psin if neg else psin, s.pcos, s.order, s.valid, conv)[1], valid)
    given = shares[convention, bool(negate_sin)]
    best = min(readings, key=lambda r: shares[r])
    if given < floor or given <= factor * shares[best]:
        return {"given": given, "best": None, "best_share": shares[best]}
    return {"given": given, "best": best, "best_share": shares[best]}


_READ_AS = {"benchmark": "atan2(-PSin, -PCos) + pi + 2 pi Order", "fppsim": "atan2(PSin, PCos) + 2 pi Order"}


def reading_words(convention: str, negate_sin: bool) -> str:
    """How a reading combines the files, in words: ``atan2(-PSin, -PCos) + pi + 2 pi Order`` (the public data's)
    and so on, ``with PSin negated`` when ``negate_sin``."""
    return _READ_AS[convention] + (" with PSin negated" if negate_sin else "")


def reading_note(meta: dict, flags: tuple[str, str] = ("--convention", "--negate-sin")) -> str | None:
    """One report line for a sample that :data:`AUTO` read another way than given, or that was read as given
    although its files are clearly written another way (``meta`` of :func:`load_psp_folder_sample`: a
    warning), naming the options ``flags`` that read it so; None when the reading fits."""
    wrong = meta.get("misread")
    if wrong:
        conv, neg = wrong["best"]
        where = f"{meta.get('root', '')}/{meta['id']}" if meta.get("id") else meta.get("root", "")
        return (f"{where}: read as {reading_words(*wrong['from'])} its phase jumps by more than pi between "
                f"{wrong['given']:.1%} of neighbouring pixels, {wrong['best_share']:.1%} read as "
                f"{reading_words(conv, neg)}: the files are written that way ({flags[0]} {conv}"
                + (f" {flags[1]}" if neg else "") + f", or {flags[0]} auto): the phase read is WRONG")
    check = meta.get("read_as")
    if not check:
        return None
    conv, neg = check["best"]
    return (f"{meta.get('root', '')}: the phase is written as {reading_words(conv, neg)} (its phase jumps by more "
            f"than pi between {check['best_share']:.1%} of neighbouring pixels so, {check['given']:.1%} read as "
            f"{reading_words(*check['from'])}): read that way ({flags[0]} {conv}" + (f" {flags[1]}" if neg else "")
            + ")")

