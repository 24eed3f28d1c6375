"""Height sensitivity of a rig: the projector phase it predicts for a height map, and the check of that
prediction against a labelled real image.

:func:`surface_phase` is the exact forward model ``h -> Phi(h)`` of a height field (each camera ray
meets ``z = h``, the projector sees that point); :func:`centre_sensitivity` its slope at the image
centre (rad per mm; the real figshare rig: about -0.87). :func:`sensitivity_check` demodulates a
labelled real fringe image with the predicted phase: what is left on the object is flat in height
only when the rig's fringe shift per mm matches the real one (``fppsim.fitting.fit_rig.fit_baseline`` chooses
the baseline with it). Units: mm, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fppsim.phase.fringe import poly_basis
from fppsim.phase import demodulate, mean_phasor, wrap
from fppsim.dataio.readers import FringeImage
from fppsim.geometry.rig import Rig, check_image_size

__all__ = ["surface_phase", "centre_sensitivity", "demodulated_residual", "object_residual", "SensitivityCheck",
           "sensitivity_check"]


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
    """Compare the fringe shift a rig predicts for a labelled real image with the real fringes.

    The labelled surface is re-projected through ``rig`` (:func:`surface_phase`, phase ``phi``); the real
    fringe, less its local mean, is demodulated with ``exp(-i phi)`` and low-passed (Gaussian ``smooth``
    px), leaving the phase the rig does NOT explain. On the plane that is the carrier mismatch, a
    smooth field: a ``degree`` polynomial in (x, y) fitted to it (unwrapped) is removed everywhere. On
    the object, what remains is flat in height only when the rig's phase shift per mm matches the real
    one. Returns None when the image has no labels or too few object pixels.
    """
    from scipy import ndimage as ndi  # optional heavy dependencies (SciPy, scikit-image)
    from skimage.restoration import unwrap_phase

    if image.height_mm is None or image.plane is None:
        return None
    h = np.where(image.valid, np.nan_to_num(image.height_mm), 0.0)
    inner = ndi.binary_erosion(image.valid, iterations=int(np.ceil(1.5 * smooth)))
    plane = inner & image.plane
    obj = inner & (h > object_mm)
    if plane.sum() < 1000 or obj.sum() < 200:
        return None
    d = demodulated_residual(rig, image.gray, image.valid, h, smooth)
    du = unwrap_phase(np.ma.array(d, mask=~plane))
    A = poly_basis(*d.shape, degree)
    coef = np.linalg.lstsq(A[plane.ravel()], np.asarray(du)[plane], rcond=None)[0]
    r = wrap(d - (A @ coef).reshape(d.shape))
    coherence, offset, slope = object_residual(r[obj], h[obj])
    return SensitivityCheck(coherence, slope, offset, float(np.std(r[plane])), int(obj.sum()))
