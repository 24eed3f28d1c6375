"""Phase-shifting profilometry (PSP): N-step phase, temporal unwrapping, the whole decoding chain.

Phase -> 3D (triangulation through a calibrated rig) is
:mod:`fppsim.phase.triangulation`; :func:`decode_stacks` runs both, as a lab does.

Plain numpy functions over arrays (scikit-image / SciPy style); all arithmetic in float64.
Units: radians for phases, millimetres for lengths, pixels for image coordinates.

Conventions (see :mod:`fppsim.geometry.rig`)
------------------------------------------------------------
* Projector phase: the absolute phase of a pattern with ``f`` periods across the projector width
  ``W_p`` is ``Phi = 2*pi*f*u_p/W_p``, where ``u_p`` is the OpenCV projector column (integer =
  pixel centre). ``Phi = 0`` at ``u_p = 0`` and it increases with ``u_p``.
* Pattern ``n`` of an ``N``-step set: ``I_n = A + B*cos(Phi + delta_n)``, ``delta_n = 2*pi*n/N``,
  ``n = 0 .. N-1`` (stack axis 0).
* Phase-shifting sums (the "PSin / PCos" of real PSP data, see :mod:`fppsim.dataio.readers`)::

      PSin = -sum_n I_n sin(delta_n) = (N/2) B sin(Phi)
      PCos = +sum_n I_n cos(delta_n) = (N/2) B cos(Phi)

  wrapped phase ``phi = atan2(PSin, PCos)`` in ``(-pi, pi]``, background ``A = mean_n I_n``,
  modulation ``B = (2/N) sqrt(PSin^2 + PCos^2)``. Four-step: ``phi = atan2(I3 - I1, I0 - I2)``.
* Temporal unwrapping over a ladder of frequencies ``f_0 = 1 < f_1 < ... < f_m`` (periods across the
  projector): ``Phi_0 = phi_0`` wrapped into ``[0, 2*pi)``, then
  ``k_i = round((f_i/f_{i-1} * Phi_{i-1} - phi_i) / (2*pi))`` and ``Phi_i = phi_i + 2*pi*k_i``.
  The result is the absolute phase of the highest frequency, in ``[0, 2*pi*f_m)`` across the projector.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from fppsim.phase import wrap
from fppsim.phase.triangulation import height_from_phase
from fppsim.threads import map_bands, row_bands
from fppsim.errors import InputError

__all__ = ["DEFAULT_FREQS", "Decoded", "PhaseShift", "Unwrapped", "decode_stacks", "order_consistency",
           "phase_from_sums", "phase_shifts", "phase_sums", "quality_mask", "unwrap_temporal", "wrapped_phase"]

DEFAULT_FREQS = (1, 8, 80)
"""Default frequency ladder (periods across the projector width)."""

TWO_PI = 2.0 * np.pi


# ====================================================================== N-step phase shifting
def phase_shifts(n_steps: int) -> np.ndarray:
    """The ``N`` equally spaced phase shifts ``delta_n = 2*pi*n/N`` (rad), float64 of shape (N,)."""
    n = int(n_steps)
    if n != n_steps or n < 3:
        raise InputError(f"phase shifting needs an integer number of steps >= 3, got {n_steps!r}")
    return TWO_PI * np.arange(n) / n


def phase_from_sums(psin: np.ndarray, pcos: np.ndarray) -> np.ndarray:
    """Wrapped phase ``atan2(psin, pcos)`` in ``(-pi, pi]`` (float64) from the sums of :func:`phase_sums`.

    The one place simulated stacks (:func:`wrapped_phase`) and real PSin/PCos data
    (:func:`fppsim.dataio.readers.load_psp_mat`) turn into phase.
    """
    phi = np.arctan2(np.asarray(psin, dtype=np.float64), np.asarray(pcos, dtype=np.float64))
    return np.where(phi <= -np.pi, np.pi, phi)  # atan2(-0.0, x < 0) = -pi -> +pi


def _shift_weights(shifts: np.ndarray) -> np.ndarray:
    """(3, N) weights mapping a stack to ``(A, PCos, PSin)``.

    For shifts whose first and second harmonics cancel (any full-period equal spacing, N >= 3) these
    are the classic sums ``(1/N, cos(delta_n), -sin(delta_n))``; otherwise the least-squares fit of
    ``A + a cos(delta) + b sin(delta)`` scaled to the same ``PCos = (N/2) a``, ``PSin = -(N/2) b``.
    """
    d = np.asarray(shifts, dtype=np.float64).ravel()
    n = d.size
    if n < 3 or not np.all(np.isfinite(d)):
        raise InputError(f"phase shifting needs at least 3 finite shifts, got {d.tolist()}")
    e1, e2 = np.exp(1j * d).sum(), np.exp(2j * d).sum()
    if abs(e1) < 1e-9 * n and abs(e2) < 1e-9 * n:
        w = np.stack([np.full(n, 1.0 / n), np.cos(d), -np.sin(d)])
        half = np.round(w[1:] * 2.0) / 2.0  # exact 0, +-1/2, +-1 (four-step: exactly I3 - I1, I0 - I2)
        w[1:] = np.where(np.abs(w[1:] - half) < 1e-12, half, w[1:])
        return w
    M = np.stack([np.ones(n), np.cos(d), np.sin(d)], axis=1)  # I = A + a cos d + b sin d
    if np.linalg.matrix_rank(M) < 3:
        raise InputError(f"phase shifts {d.tolist()} do not determine A, B and phi (rank < 3)")
    P = np.linalg.pinv(M)  # (3, N): A, a = B cos(phi), b = -B sin(phi)
    return np.stack([P[0], (n / 2.0) * P[1], -(n / 2.0) * P[2]])


def _resolve_shifts(n: int, shifts) -> np.ndarray:
    if shifts is None:
        return phase_shifts(n)
    d = np.asarray(shifts, dtype=np.float64).ravel()
    if d.size != n:
        raise InputError(f"got {n} images but {d.size} phase shifts")
    return d


def phase_sums(images: np.ndarray, shifts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator of the phase-shifting arctangent.

    Parameters
    ----------
    images : (N, ...) array, any real dtype; pattern ``n`` is ``I_n = A + B cos(Phi + delta_n)``.
    shifts : (N,) phase shifts ``delta_n`` (rad); default ``2*pi*n/N``.

    Returns
    -------
    psin, pcos : (...) float64, ``psin = -sum_n I_n sin(delta_n)``, ``pcos = sum_n I_n cos(delta_n)``,
        so that ``Phi = atan2(psin, pcos)`` and ``B = (2/N) sqrt(psin^2 + pcos^2)``. For shifts that are
        not equally spaced over a period the least-squares equivalents (same scale) are returned.
    """
    I = np.asarray(images, dtype=np.float64)
    if I.ndim < 1:
        raise InputError("images must be a stack of shape (N, ...)")
    w = _shift_weights(_resolve_shifts(I.shape[0], shifts))
    return np.tensordot(w[2], I, axes=1), np.tensordot(w[1], I, axes=1)


@dataclass
class PhaseShift:
    """Result of :func:`wrapped_phase` (arrays of the stack's trailing shape, float64).

    phase : wrapped phase ``phi`` in ``(-pi, pi]`` (rad).
    background : ``A`` (image units).
    modulation : ``B`` (image units), >= 0.
    """
    phase: np.ndarray
    background: np.ndarray
    modulation: np.ndarray

    def __iter__(self):  # allows ``phi, A, B = wrapped_phase(stack)``
        return iter((self.phase, self.background, self.modulation))


def wrapped_phase(images: np.ndarray, shifts: np.ndarray | None = None) -> PhaseShift:
    """N-step phase shifting of a stack ``I_n = A + B cos(phi + delta_n)``.

    Parameters
    ----------
    images : (N, ...) array (N >= 3), any real dtype (converted to float64), stack axis first.
    shifts : (N,) phase shifts (rad); default ``delta_n = 2*pi*n/N``. Non-uniform shifts are solved
        by least squares.

    Returns
    -------
    PhaseShift(phase, background, modulation), each of shape ``images.shape[1:]``:
    ``phase = atan2(-sum I_n sin delta_n, sum I_n cos delta_n)`` in ``(-pi, pi]``,
    ``background = mean_n I_n``, ``modulation = (2/N) sqrt(S^2 + C^2)``.
    Four-step: ``phase = atan2(I3 - I1, I0 - I2)``, ``modulation = 0.5 sqrt((I3-I1)^2 + (I0-I2)^2)``.
    """
    I = np.asarray(images)
    if I.ndim < 1:
        raise InputError("images must be a stack of shape (N, ...)")
    n = I.shape[0]
    w = _shift_weights(_resolve_shifts(n, shifts))
    sums = _exact_int_sums(I, w)
    if sums is not None:
        (a, sa, _), (ic, sc, _), (is_, ss, _) = sums
        A = a * sa
        tables = _phase_tables(n, sums, I.dtype) if I.ndim > 1 else None
        if tables is not None:  # phase and modulation of every possible integer (PSin, PCos) pair
            phase_t, mod_t, n_c, offset = tables
            idx = is_  # the table entry of (PSin, PCos), in place
            idx *= n_c
            idx += ic
            idx += offset
            return PhaseShift(phase=np.take(phase_t, idx), background=A, modulation=np.take(mod_t, idx))
        c, s = ic * sc, is_ * ss
    else:
        I = np.asarray(I, dtype=np.float64)
        A = np.tensordot(w[0], I, axes=1)
        s, c = phase_sums(I, shifts)  # PSin = (N/2) B sin(phi), PCos = (N/2) B cos(phi)
    return PhaseShift(phase=phase_from_sums(s, c), background=A, modulation=(2.0 / n) * np.hypot(s, c))


def _exact_int_sums(I: np.ndarray, w: np.ndarray, max_bits: int = 8):
    """``[(acc, scale, weights)]`` per weight row (A, PCos, PSin) of an unsigned-integer stack, with
    ``acc * scale`` the exact float64 weighted sum, or None.

    When every weight is ``k / 2**m`` (``m <= max_bits``; the four-step weights 1/4, 0, +-1 are) and the
    images are unsigned integers of at most 16 bits, every product and partial sum of the float64
    weighted sum is exactly representable, so the float result does not depend on the summation order:
    summing ``k * I`` in integers and scaling by ``2**-m`` gives the very same float64 bits, several times
    faster than converting the stack to float64. Each row needs a positive weight so that a zero sum is
    +0.0 on both paths (non-negative images).

    ``acc`` is the integer sum with the row's integer ``weights``, ``k = w * 2**m`` divided by their
    common divisor ``g`` (four-step PCos: ``I0 - I2``), and ``scale = g / 2**m``: ``acc * scale`` equals
    ``(g * acc) * 2**-m`` exactly (both are exact), so dividing out ``g`` changes no bit.
    """
    if I.dtype.kind != "u" or I.dtype.itemsize > 2 or I.shape[0] > 256:
        return None
    for m in range(max_bits + 1):
        k = w * float(2 ** m)
        if np.all(k == np.round(k)):
            break
    else:
        return None
    if not np.all(np.max(w, axis=1) > 0):
        return None
    k = np.round(k).astype(np.int64)
    acc_type = np.int32 if I.dtype.itemsize == 1 else np.int64
    out = []
    for row in k:
        g = int(np.gcd.reduce(np.abs(row)))  # > 0: every row has a positive weight
        weights = tuple((row // g).tolist())
        acc = np.zeros(I.shape[1:], dtype=acc_type)
        for weight, img in zip(weights, I):
            if weight == 1:
                acc += img
            elif weight == -1:
                acc -= img
            elif weight:
                acc += weight * img.astype(acc_type)
        out.append((acc, g / 2 ** m, weights))
    return out


_PHASE_TABLES: dict = {}
_CACHE_LOCK = threading.RLock()
_MAX_TABLE = 1 << 19  # entries per table (the 8-bit four-step table has 511 x 511)


def _phase_tables(n: int, sums, dtype):
    """Lookup tables of :func:`phase_from_sums` and the modulation over every integer (PSin, PCos) pair
    an unsigned stack of ``dtype`` can give with the integer weights behind ``sums``, or None (too many
    pairs). ``(phase, modulation, columns, offset)``: the entry of ``(acc_s, acc_c)`` is
    ``acc_s * columns + acc_c + offset``. The tables hold what the float path computes for exactly those
    float64 sums, element by element, so a lookup returns the very same bits.
    """
    (_, sc, wc), (_, ss, ws) = sums[1], sums[2]
    key = (n, dtype.str, sc, ss, wc, ws)
    with _CACHE_LOCK:  # one thread builds a table, the other waits for it
        if key not in _PHASE_TABLES:
            _PHASE_TABLES[key] = _build_phase_tables(n, sc, ss, wc, ws, dtype)
        return _PHASE_TABLES[key]


def _build_phase_tables(n, sc, ss, wc, ws, dtype):
    top = int(np.iinfo(dtype).max)
    lo_c, hi_c = top * sum(k for k in wc if k < 0), top * sum(k for k in wc if k > 0)
    lo_s, hi_s = top * sum(k for k in ws if k < 0), top * sum(k for k in ws if k > 0)
    n_c, n_s = hi_c - lo_c + 1, hi_s - lo_s + 1
    tables = None
    if n_c * n_s <= _MAX_TABLE:
        c = np.tile(np.arange(lo_c, hi_c + 1) * sc, n_s)  # contiguous float64, as the sums arrays are
        s = np.repeat(np.arange(lo_s, hi_s + 1) * ss, n_c)
        phase_t, mod_t = phase_from_sums(s, c), (2.0 / n) * np.hypot(s, c)
        for t in (phase_t, mod_t):
            t.setflags(write=False)
        tables = (phase_t, mod_t, n_c, -lo_s * n_c - lo_c)
    return tables


def quality_mask(background: np.ndarray, modulation: np.ndarray, min_modulation: float,
                 min_ratio: float = 0.0) -> np.ndarray:
    """Pixels whose phase can be trusted: ``B >= min_modulation`` and ``B >= min_ratio * A``.

    Parameters
    ----------
    background, modulation : ``A`` and ``B`` from :func:`wrapped_phase` (same units, e.g. gray levels).
    min_modulation : absolute modulation threshold (image units). The phase noise of N-step phase
        shifting is ``sigma_phi = sqrt(2/N) * sigma_I / B`` (independent Gaussian image noise ``sigma_I``,
        small-noise limit), so choose it from the image noise and the noise the unwrapping ladder
        tolerates: never a wrong order while every wrapped phase is within ``pi / (1 + r_max)`` of the
        truth, ``r_max`` the largest ratio of neighbouring frequencies (``pi/11 = 0.286`` rad for
        ``(1, 8, 80)``; derivation and the Gaussian order-error rate in ``tests/fppsim/test_psp.py``).
    min_ratio : threshold on the fringe contrast ``B/A`` (0..1 for non-negative images); rejects
        saturated / ambient-dominated pixels.

    Returns
    -------
    bool array; False also where A or B is not finite.
    """
    A = np.asarray(background, dtype=np.float64)
    B = np.asarray(modulation, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(A) & np.isfinite(B) & (B >= min_modulation) & (B >= min_ratio * A)


# ====================================================================== temporal unwrapping
def _check_ladder(freqs) -> np.ndarray:
    f = np.asarray(freqs, dtype=np.float64).ravel()
    if f.size < 1 or not np.all(np.isfinite(f)):
        raise InputError(f"frequency ladder must be finite numbers, got {list(freqs)}")
    if f[0] != 1:
        raise InputError(f"frequency ladder must start at 1 period (unambiguous phase), got {f.tolist()}")
    if np.any(np.diff(f) <= 0):
        raise InputError(f"frequency ladder must be strictly increasing, got {f.tolist()}")
    return f


@dataclass
class Unwrapped:
    """Result of :func:`unwrap_temporal` (arrays of the input phase shape).

    phase : float64 absolute phase of the highest frequency (rad), NaN where an input is not finite.
    order : int64 fringe order ``k`` of the highest frequency (``phase = wrapped + 2*pi*k``); 0 where
        an input is not finite.
    reliable : bool, False where any step's rounding residual exceeds ``max_residual``, where the
        lowest-frequency phase is within ``seam_margin`` of its 0/2pi seam, or where an input is not finite.
    residual : float64 largest ``|r_i Phi_{i-1} - phi_i - 2 pi k_i|`` over the steps (rad, in [0, pi]).
    freqs : the ladder used.
    """
    phase: np.ndarray
    order: np.ndarray
    reliable: np.ndarray
    residual: np.ndarray
    freqs: tuple

    def __iter__(self):  # allows ``Phi, k, ok = unwrap_temporal(...)``
        return iter((self.phase, self.order, self.reliable))


def _mod_two_pi(x: np.ndarray) -> np.ndarray:
    """``np.mod(x, 2*pi)`` (float64), faster where every ``x`` lies in ``(-2*pi, 2*pi)``.

    There numpy's remainder (``fmod``, exact, then ``+ 2*pi`` when the signs differ, +0.0 for a zero
    remainder) is ``x + 2*pi`` for ``x < 0`` and ``x + 0.0`` otherwise: the same single rounding.
    """
    if x.ndim and x.size and x.min() > -TWO_PI and x.max() < TWO_PI:
        return np.where(x < 0, x + TWO_PI, x + 0.0)
    return np.mod(x, TWO_PI)


def unwrap_temporal(wrapped, freqs=None, max_residual: float = np.pi / 2, seam_margin: float | None = None,
                    phase_origin: float = 0.0) -> Unwrapped:
    """Hierarchical temporal phase unwrapping over a frequency ladder starting at 1 period.

    Parameters
    ----------
    wrapped : mapping ``{f: phi_f}`` or sequence ``[phi_f0, phi_f1, ...]`` of wrapped phases (rad, any
        range; wrapped again into ``(-pi, pi]``), all of one shape.
    freqs : ladder (periods across the projector), strictly increasing, starting at 1. Default: the
        sorted keys of a mapping, or :data:`DEFAULT_FREQS` ``(1, 8, 80)`` for a sequence.
    max_residual : rounding residual (rad) above which a pixel's order is reported unreliable. A wrong
        order means the true residual noise ``e`` had ``|e| > pi``; its observed residual is then
        ``2 pi - |e|`` (for ``|e| < 2 pi``), so the default ``pi/2`` flags every wrong order caused by
        ``|e| < 3 pi/2`` and also flags correct orders with ``|e| > pi/2`` (conservative).
    seam_margin : pixels whose lowest-frequency phase lies within this distance (rad) of the seam
        (``phase_origin`` = ``phase_origin + 2 pi``) are reported unreliable: noise may have carried
        them across it, which shifts the absolute phase by ``2 pi f_max`` and no residual shows it.
        Default ``max_residual / (f_1/f_0)``, the lowest-frequency noise the first step tolerates
        (0 for a single frequency).
    phase_origin : the lowest-frequency phase is wrapped into ``[phase_origin, phase_origin + 2 pi)``.
        0 gives ``Phi`` in ``[0, 2 pi f_max)``, i.e. projector columns ``[0, W_p)``; pass ``-pi/W_p``
        to accept the left half of the projector's first pixel column.

    Returns
    -------
    :class:`Unwrapped` (phase, order, reliable, residual, freqs).
    """
    if isinstance(wrapped, dict):
        if freqs is None:
            freqs = sorted(wrapped)
        missing = [f for f in freqs if f not in wrapped]
        if missing:
            raise InputError(f"no wrapped phase for frequencies {missing} (have {sorted(wrapped)})")
        phases = [wrapped[f] for f in freqs]
    else:
        phases = list(wrapped)
        if freqs is None:
            freqs = DEFAULT_FREQS
        if len(phases) != len(freqs):
            raise InputError(f"got {len(phases)} wrapped phases for the {len(freqs)}-frequency ladder {tuple(freqs)}")
    f = _check_ladder(freqs)
    phases = [np.asarray(p, dtype=np.float64) for p in phases]
    shape = phases[0].shape
    if any(p.shape != shape for p in phases):
        raise InputError(f"wrapped phases differ in shape: {[p.shape for p in phases]}")
    if seam_margin is None:
        seam_margin = max_residual / (f[1] / f[0]) if f.size > 1 else 0.0

    finite = np.ones(shape, dtype=bool)
    for p in phases:
        finite &= np.isfinite(p)
    phi0 = np.where(finite, phases[0], 0.0)
    Phi = _mod_two_pi(phi0 - phase_origin)
    reliable = finite & (Phi >= seam_margin) & (Phi <= TWO_PI - seam_margin)
    Phi = Phi + phase_origin
    residual = np.zeros(shape)
    k = np.zeros(shape, dtype=np.int64)
    for i in range(1, f.size):
        phi = wrap(np.where(finite, phases[i], 0.0))
        pred = (f[i] / f[i - 1]) * Phi
        kf = np.round((pred - phi) / TWO_PI)
        Phi = phi + TWO_PI * kf
        res = np.abs(pred - Phi)
        residual = np.maximum(residual, res)
        k = kf.astype(np.int64)
        reliable &= res <= max_residual
    if f.size == 1:  # order of the 1-period pattern relative to its wrapped phase
        k = np.round((Phi - wrap(phi0)) / TWO_PI).astype(np.int64)
    Phi = np.where(finite, Phi, np.nan)
    k = np.where(finite, k, 0)
    return Unwrapped(phase=Phi, order=k, reliable=reliable, residual=residual, freqs=tuple(freqs))


# --------------------------------------------------------------------------------------------- decoding
def order_consistency(phase: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Neighbour check of the fringe order: True where the pixel agrees with its 3 x 3 neighbourhood.

    A neighbour agrees when its absolute phase differs by less than ``pi`` (half a period: on the
    default rig 6.5 mm of height between adjacent pixels). A pixel is consistent when at least as many
    valid neighbours agree as disagree; an isolated wrong order (all neighbours off by 2*pi*k) fails,
    while a pixel on a genuine depth edge keeps its own surface's neighbours. (H, W) bool.
    """
    phase = np.asarray(phase, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(phase)
    H, W = phase.shape
    pp = np.pad(np.where(valid, phase, 0.0), 1)
    vp = np.pad(valid, 1)
    agree = np.zeros((H, W), np.int8)
    neighbours = np.zeros((H, W), np.int8)  # valid ones; those that do not agree disagree
    diff = np.empty((H, W))
    close = np.empty((H, W), bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            nv = vp[dy:dy + H, dx:dx + W]
            np.subtract(pp[dy:dy + H, dx:dx + W], phase, out=diff)
            np.less(np.abs(diff, out=diff), np.pi, out=close)
            close &= nv
            agree += close
            neighbours += nv
    return valid & (agree >= neighbours - agree)  # agree >= disagree


@dataclass
class Decoded:
    """Result of :func:`decode_stacks` (all (H, W)).

    phase : absolute phase of the highest frequency, rad.
    height : triangulated height, mm (NaN where not ``valid``).
    quality : modulation and B/A thresholds met at every frequency.
    reliable : the temporal unwrapping residuals are small (see :func:`unwrap_temporal`).
    consistent : the order agrees with the neighbourhood (see :func:`order_consistency`).
    valid : all of the above and a finite triangulation.
    """
    phase: np.ndarray
    order: np.ndarray
    height: np.ndarray
    quality: np.ndarray
    reliable: np.ndarray
    consistent: np.ndarray
    valid: np.ndarray


def decode_stacks(stacks, rig, freqs=DEFAULT_FREQS, min_modulation: float = 3.0, min_ratio: float = 0.0,
                  neighbour_check: bool = True, shifts=None, threads: int = 1) -> Decoded:
    """The whole PSP chain as a lab runs it: N-step phases per frequency, quality mask, temporal
    unwrapping, order consistency check, triangulation with ``rig``.

    Parameters
    ----------
    stacks : mapping ``{f: images}`` with ``images`` of shape (N, H, W) (any real dtype, e.g. uint8
        camera images) for every frequency of ``freqs``.
    min_modulation, min_ratio : thresholds of :func:`quality_mask` (gray levels, B/A), applied at every
        frequency.
    neighbour_check : also reject pixels failing :func:`order_consistency`.
    rig : the calibrated rig for triangulation; None skips it (``height`` is then None).
    threads : 2 decodes the top and bottom of the image on two threads (this one and
        :func:`fppsim.threads.helper_pool`'s): every step is per pixel, or (the order check) reads a
        one-row halo, so the result is the very same; 1 (default) decodes in one piece.
    """
    freqs = tuple(int(f) if float(f).is_integer() else float(f) for f in freqs)  # a fitted rig's need not be whole
    if threads > 1:
        return _decode_in_bands(stacks, rig, freqs, min_modulation, min_ratio, neighbour_check, shifts, threads)
    quality, un = _phases(stacks, freqs, shifts, min_modulation, min_ratio)
    ok = quality & un.reliable
    consistent = order_consistency(un.phase, ok) if neighbour_check else ok.copy()
    ok &= consistent
    height = None
    if rig is not None:
        height, ok = _heights(rig, un.phase, ok, freqs[-1])
    return Decoded(phase=un.phase, order=un.order, height=height, quality=quality,
                   reliable=un.reliable, consistent=consistent, valid=ok)


def _phases(stacks, freqs, shifts, min_modulation, min_ratio, rows: slice | None = None):
    """``(quality, unwrapped)`` of :func:`decode_stacks`, of the whole stacks or of their ``rows``."""
    quality, wrapped = None, []
    for f in freqs:
        stack = np.asarray(stacks[f])
        if rows is not None:  # contiguous like a whole stack: numpy then takes the same path (dot's checks too)
            stack = np.ascontiguousarray(stack[:, rows])
        res = wrapped_phase(stack, shifts)  # uint8 stacks take the exact integer path
        wrapped.append(res.phase)
        q = quality_mask(res.background, res.modulation, min_modulation=min_modulation, min_ratio=min_ratio)
        quality = q if quality is None else (quality & q)
    return quality, unwrap_temporal(wrapped, freqs)


def _heights(rig, phase, ok, periods, rows: slice | None = None):
    """``(height, ok)`` of :func:`decode_stacks`: triangulated where ``ok``, which keeps only the finite
    heights; NaN elsewhere. ``rows``: ``phase`` holds these camera rows (see :func:`_triangulate`)."""
    height = height_from_phase(rig, phase, periods=periods, mask=ok, rows=rows)
    ok = ok & np.isfinite(height)
    return np.where(ok, height, np.nan), ok


def _decode_in_bands(stacks, rig, freqs, min_modulation, min_ratio, neighbour_check, shifts, threads) -> Decoded:
    """:func:`decode_stacks` on row bands (:func:`fppsim.threads.map_bands`): the same arrays."""
    stacks = {f: np.asarray(stacks[f]) for f in freqs}
    shapes = {s.shape[1:] if s.ndim == 3 else None for s in stacks.values()}
    shape = shapes.pop() if len(shapes) == 1 else None
    cam = rig.camera if rig is not None else None
    H = shape[0] if shape is not None and (cam is None or shape == (cam.height, cam.width)) else 0
    bands = row_bands(H, threads)
    if len(bands) < 2:  # (also every input the one-piece decode refuses, which then says why)
        return decode_stacks(stacks, rig, freqs, min_modulation, min_ratio, neighbour_check, shifts)

    parts = map_bands(lambda rows: _phases(stacks, freqs, shifts, min_modulation, min_ratio, rows), bands)
    quality = np.concatenate([q for q, _ in parts])
    phase = np.concatenate([u.phase for _, u in parts])
    reliable = np.concatenate([u.reliable for _, u in parts])
    ok = quality & reliable
    banded_height = rig is not None and not rig.projector.has_distortion

    def check(rows):
        if neighbour_check:  # with a one-row halo (the image border is padded as in one piece)
            a, z = max(rows.start - 1, 0), min(rows.stop + 1, H)
            consistent = order_consistency(phase[a:z], ok[a:z])[rows.start - a:rows.stop - a]
        else:
            consistent = ok[rows].copy()
        good = ok[rows] & consistent
        height = None
        if banded_height:
            height, good = _heights(rig, phase[rows], good, freqs[-1], rows)
        return consistent, good, height

    checked = map_bands(check, bands)
    consistent = np.concatenate([c for c, _, _ in checked])
    ok = np.concatenate([g for _, g, _ in checked])
    height = np.concatenate([h for _, _, h in checked]) if banded_height else None
    if rig is not None and not banded_height:
        height, ok = _heights(rig, phase, ok, freqs[-1])
    return Decoded(phase=phase, order=np.concatenate([u.order for _, u in parts]), height=height, quality=quality,
                   reliable=reliable, consistent=consistent, valid=ok)
