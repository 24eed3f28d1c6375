"""Real PSP data in the common "PSin / PCos / fringe-order" MATLAB .mat layout.

Many FPP labs store a phase-shifting measurement as three same-shaped arrays:

* ``PSin`` — numerator of the phase-shifting arctangent, ``PSin = -sum_n I_n sin(delta_n)``;
* ``PCos`` — denominator, ``PCos = +sum_n I_n cos(delta_n)``;
* ``Order`` — the integer fringe order ``k`` of the same frequency (from temporal unwrapping),

with ``I_n = A + B cos(Phi + delta_n)`` and ``delta_n = 2 pi n / N``. Then
``wrapped = atan2(PSin, PCos)`` in ``(-pi, pi]`` and ``absolute = wrapped + 2 pi Order`` — exactly what
:func:`fppsim.psp.wrapped_phase` and :func:`fppsim.psp.unwrap_temporal` give for simulated stacks
(:func:`fppsim.psp.phase_sums` returns the two sums), so real and simulated phase share one code
path. Data written with the opposite sine sign (``PSin = +sum I_n sin delta_n``) loads correctly with
``negate_sin=True``.

MATLAB v4/v5/v7 files are read with :func:`scipy.io.loadmat`; v7.3 (HDF5) files need ``h5py``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import PSPMatError
from .psp import phase_from_sums

__all__ = ["PSPMatError", "PspMat", "SIN_KEYS", "COS_KEYS", "ORDER_KEYS", "load_psp_mat", "save_psp_mat"]

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
    meta : other scalar variables found in the file (e.g. ``n_steps``, ``periods``).
    path : the file.
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


def save_psp_mat(path: str | os.PathLike, psin: np.ndarray, pcos: np.ndarray, order: np.ndarray, *,
                 n_steps: int | None = None, periods: float | None = None,
                 keys: tuple[str, str, str] = ("PSin", "PCos", "Order"), compress: bool = True,
                 **extra) -> None:
    """Write PSin / PCos / order in the layout :func:`load_psp_mat` reads (MATLAB v5, atomic write).

    ``psin, pcos`` as from :func:`fppsim.psp.phase_sums` (stored float64), ``order`` integer fringe
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
    import scipy.io

    path = Path(path)
    from .formats import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        scipy.io.savemat(fh, data, do_compression=compress, oned_as="column")
