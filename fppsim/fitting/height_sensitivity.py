"""Height sensitivity of a rig: the projector phase it predicts for a height map, and THE check of that
prediction against a labelled real image.

:func:`surface_phase` is the exact forward model ``h -> Phi(h)`` of a height field (each camera ray
meets ``z = h``, the projector sees that point); :func:`centre_sensitivity` its slope at the image
centre (rad per mm; the real figshare rig: about -0.87). :func:`label_residual` is the one rig-vs-labels
check: it demodulates a labelled real fringe image with the predicted phase on the plane and object
pixels of :func:`label_masks`, removes the plane's own phase (one constant or a polynomial) and measures
what is left on the object, which is flat in height only when the rig's fringe shift per mm matches the
real one. Both fits that choose a rig from labels score its result: :func:`sensitivity_check`
(``fppsim.fitting.fit_rig.fit_baseline`` chooses the baseline with it) and
:func:`fppsim.fitting.fit_depth.depth_check` (distance and baseline, adding the projector shadows).
Units: mm, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fppsim.phase.plane import poly_basis
from fppsim.phase import circular_mean, demodulate, mean_phasor, wrap
from fppsim.dataio.readers import FringeImage
from fppsim.geometry.rig import Rig, check_image_size

__all__ = ["surface_phase", "centre_sensitivity", "demodulated_residual", "object_residual", "label_masks",
           "LabelResidual", "label_residual", "SensitivityCheck", "sensitivity_check"]


def surface_phase(rig: Rig, height_mm: np.ndarray) -> np.ndarray:
    """Projector phase (rad, ``2 pi f u_p / W_p``) the rig predicts at every camera pixel for the surface
    ``height_mm`` (H, W) mm above the reference plane (NaN -> 0).

    Exact for a height field: the point a pixel sees at height h is where its camera ray meets z = h.
    """
    h = np.nan_to_num(np.asarray(height_mm, dtype=np.float64))
    check_image_size(rig, h.shape, "height map", sep=" x ",
                     template="{what} {got} px but {who} {camera}")
    return rig.phase_at_height(h)


def centre_sensitivity(rig: Rig, dh: float = 1.0) -> float:
    """Phase change (rad per mm) of a surface raised by ``dh`` mm at the camera's image centre
    (:meth:`fppsim.geometry.rig.Rig.sensitivity`)."""
    return rig.sensitivity(0.0, float(dh))


def demodulated_residual(rig: Rig, gray: np.ndarray, valid: np.ndarray, height_mm: np.ndarray,
                         smooth: float = 4.0, *, rig_phase: np.ndarray | None = None) -> np.ndarray:
    """Wrapped phase (rad, (H, W)) of the real fringe relative to the phase ``rig`` predicts for the
    labelled surface: ``angle(G_smooth[(I - I_local_mean) exp(-i Phi_rig(h))])`` over ``valid`` pixels
    (``smooth``: Gaussian sigma, px; the local mean is a Gaussian of 1.5 x ``smooth``). Positive where
    the real phase is ahead of the rig's. ``rig_phase``: ``surface_phase(rig, h)`` of the valid-masked
    height, when the caller already has it."""
    from scipy import ndimage as ndi  # optional heavy dependency (SciPy)

    g = np.asarray(gray, dtype=np.float64)
    g = g - ndi.gaussian_filter(g, 1.5 * smooth)
    h = np.where(valid, np.nan_to_num(np.asarray(height_mm, dtype=np.float64)), 0.0)
    P = surface_phase(rig, h) if rig_phase is None else rig_phase
    return np.angle(demodulate(g, P, smooth, np.asarray(valid, dtype=np.float64)))


def object_residual(residual: np.ndarray, height_mm: np.ndarray) -> tuple[float, float, float]:
    """How a residual phase (rad) behaves over object pixels of known height (mm), both 1-D:
    ``(coherence, offset, slope)``: |mean phasor| (1 = the residual is one constant), its circular mean
    (rad) and its slope against height (rad/mm, the residual unwrapped around the mean; NaN when the
    heights span 1 mm or less)."""
    phasor = mean_phasor(residual)
    offset = float(np.angle(phasor))
    centred = wrap(residual - offset) + offset
    slope = float(np.polyfit(height_mm, centred, 1)[0]) if np.ptp(height_mm) > 1.0 else float("nan")
    return float(abs(phasor)), offset, slope


def label_masks(valid: np.ndarray, height_mm: np.ndarray, smooth: float = 4.0, plane_mm: float = 1.0,
                object_mm: float = 2.0, steep_mm: float | None = 3.0,
                plane: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Plane and object pixels of a labelled image fit for the residual phase (:func:`label_residual`):
    valid pixels at least 1.5 x ``smooth`` px from an invalid one and, unless ``steep_mm`` is None,
    ``smooth`` px from a height step (more than ``steep_mm`` over 5 px); of those, the plane is
    ``|h| < plane_mm`` (or the given ``plane`` pixels, e.g. the source's own) and the object ``h > object_mm``.
    ``valid`` (H, W) bool; ``height_mm`` (H, W) mm above the plane (NaN and invalid pixels count as 0)."""
    from scipy import ndimage as ndi  # optional heavy dependency (SciPy)

    valid = np.asarray(valid, dtype=bool)
    h = np.where(valid, np.nan_to_num(np.asarray(height_mm, dtype=np.float64)), 0.0)
    inner = ndi.binary_erosion(valid, iterations=int(np.ceil(1.5 * smooth)))
    if steep_mm is not None:
        steep = ndi.maximum_filter(h, 5) - ndi.minimum_filter(h, 5) > steep_mm
        inner &= ~ndi.binary_dilation(steep, iterations=max(1, int(np.ceil(smooth))))
    flat = np.abs(h) < plane_mm if plane is None else np.asarray(plane, dtype=bool)
    return inner & flat, inner & (h > object_mm)


@dataclass
class LabelResidual:
    """What a rig does not explain on one labelled real image (:func:`label_residual`); maps are (H, W).

    height : float64 mm, the labels (0 where invalid or NaN). plane, obj : bool, the pixels of
    :func:`label_masks`. rig_phase : :func:`surface_phase` of ``height`` (rad). demodulated : the wrapped
    residual phase before the plane's phase is removed (:func:`demodulated_residual`, rad). residual :
    ``wrap(demodulated - plane phase)``. plane_offset : the constant removed (the plane's circular mean;
    NaN when a polynomial was). coherence, offset, slope : :func:`object_residual` of ``residual`` over
    the object pixels.
    """

    height: np.ndarray
    plane: np.ndarray
    obj: np.ndarray
    rig_phase: np.ndarray
    demodulated: np.ndarray
    residual: np.ndarray
    plane_offset: float
    coherence: float
    offset: float
    slope: float


def label_residual(rig: Rig, image: FringeImage, smooth: float = 4.0, *, degree: int | None = None,
                   own_plane: bool = False, plane_mm: float = 1.0, object_mm: float = 2.0,
                   steep_mm: float | None = 3.0, min_object: int = 200) -> LabelResidual | None:
    """THE check of a rig against one labelled real fringe image: the phase the rig does not explain.

    The labelled surface is re-projected through ``rig`` (:func:`surface_phase`, phase ``Phi``); the real
    fringe, less its local mean, is demodulated with ``exp(-i Phi)`` and low-passed (Gaussian ``smooth``
    px, :func:`demodulated_residual`), leaving the wrapped phase the rig does NOT explain. On the plane
    that is the carrier mismatch; it is removed everywhere: ``degree`` None, one constant (its circular
    mean on the plane, no unwrapping); else a ``degree`` polynomial in (x, y) fitted to it unwrapped
    (:func:`fppsim.phase.plane.poly_basis`). On the object what remains is flat in height only when the
    rig's phase shift per mm matches the real one (:func:`object_residual`).

    Pixels: :func:`label_masks` (``plane_mm``, ``object_mm``, ``steep_mm``; ``own_plane``: the plane is the
    image's own ``plane`` pixels instead of ``|h| < plane_mm``). Returns None without height labels (or,
    with ``own_plane``, without plane pixels), or with fewer than 1000 plane or ``min_object`` object pixels.
    """
    if image.height_mm is None or (own_plane and image.plane is None):
        return None
    valid = np.asarray(image.valid, dtype=bool)
    h = np.where(valid, np.nan_to_num(np.asarray(image.height_mm, dtype=np.float64)), 0.0)
    plane, obj = label_masks(valid, h, smooth, plane_mm, object_mm, steep_mm, image.plane if own_plane else None)
    if plane.sum() < 1000 or obj.sum() < min_object:
        return None
    P = surface_phase(rig, h)  # one projection serves the residual and the caller (shadow bridges)
    d = demodulated_residual(rig, image.gray, valid, h, smooth, rig_phase=P)
    if degree is None:
        o = circular_mean(d, mask=plane)
        r = wrap(d - o)
    else:
        from skimage.restoration import unwrap_phase  # optional heavy dependency (scikit-image)

        o = float("nan")
        du = unwrap_phase(np.ma.array(d, mask=~plane))
        A = poly_basis(*d.shape, degree)
        coef = np.linalg.lstsq(A[plane.ravel()], np.asarray(du)[plane], rcond=None)[0]
        r = wrap(d - (A @ coef).reshape(d.shape))
    coherence, offset, slope = object_residual(r[obj], h[obj])
    return LabelResidual(h, plane, obj, P, d, r, o, coherence, offset, slope)


@dataclass
class SensitivityCheck:
    """How well a rig's height sensitivity matches one labelled real image (:func:`sensitivity_check`).

    coherence : |mean phasor| of the residual phase on object pixels (1 = the rig predicts how the real
    fringes shift with height everywhere on the object; low = the shift per mm differs).
    slope : residual phase per mm of height on the object (rad/mm; 0 when the sensitivity matches).
    offset : circular mean of the object residual (rad). plane_std : residual std on the plane (rad).
    n_object : object pixels used.
    """

    coherence: float
    slope: float
    offset: float
    plane_std: float
    n_object: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def sensitivity_check(rig: Rig, image: FringeImage, smooth: float = 4.0, degree: int = 3,
                      object_mm: float = 2.0) -> SensitivityCheck | None:
    """How the fringe shift a rig predicts for a labelled real image matches the real fringes:
    :func:`label_residual` with the image's own plane pixels (no step exclusion) and a ``degree``
    polynomial plane phase, scored by the object residual's coherence and slope. None when the image
    has no labels or too few plane (1000) or object (200) pixels.
    """
    res = label_residual(rig, image, smooth, degree=degree, own_plane=True, object_mm=object_mm, steep_mm=None)
    if res is None:
        return None
    return SensitivityCheck(res.coherence, res.slope, res.offset, float(np.std(res.residual[res.plane])),
                            int(res.obj.sum()))
