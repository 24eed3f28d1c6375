"""Phase -> 3D: triangulation through a calibrated rig.

A camera pixel's ray meets the projector's plane of constant column ``u_p = Phi W_p / (2 pi f)`` (exact
without projector distortion; iterated to a fixed point with it): :func:`triangulate` gives the
points, heights and depths, :func:`height_from_phase` just the heights (the same bits). The camera's
rays are cached for the last few cameras (:func:`_camera_rays`; thread-safe, read-only arrays). (The
classic reference-plane formula ``h = L dphi / (dphi + 2 pi f0 d)`` of parallel-axis rigs is the
independent truth the tests check it against: ``tests/_helpers.py``.) Conventions: :mod:`fppsim.geometry.rig` (mm, OpenCV pinholes) and
:mod:`fppsim.phase.psp` (the projector phase ``Phi = 2 pi f u_p / W_p``). All arithmetic in float64.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from fppsim.geometry.rig import along_rays
from fppsim.errors import InputError

__all__ = ["Triangulation", "triangulate", "height_from_phase"]


@dataclass
class Triangulation:
    """Result of :func:`triangulate` (arrays of the camera pixel shape ``S``, usually (H, W)).

    points : (*S, 3) float64 world points (mm), NaN where not valid.
    height : (*S,) float64 world z (mm) = height above the reference plane, NaN where not valid.
    depth : (*S,) float64 camera-frame depth (mm), NaN where not valid.
    column : (*S,) float64 projector column ``u_p`` of the phase.
    row : (*S,) float64 projector row where the camera ray meets that column, NaN where not valid.
    valid : (*S,) bool: finite phase, inside ``mask``, the ray meets the column plane in front of both
        devices, and (with projector distortion) the row iteration converged.
    """

    points: np.ndarray
    height: np.ndarray
    depth: np.ndarray
    column: np.ndarray
    row: np.ndarray
    valid: np.ndarray


def _column_plane_normal(proj, u: np.ndarray, v: np.ndarray | None) -> np.ndarray:
    """World-frame normal of the plane through the projector centre holding column ``u`` near row ``v``.

    Without distortion the column is exactly the plane ``fx x + s y + (cx - u) z = 0`` (device frame).
    With distortion, the plane through the undistorted rays of ``(u, v)`` and ``(u, v + 1)``: it holds
    the ray of ``(u, v)`` exactly and follows the column's local direction.
    """
    if v is None or not proj.has_distortion:
        K = proj.K
        n_dev = np.stack([np.full_like(u, K[0, 0]), np.full_like(u, K[0, 1]), K[0, 2] - u], axis=-1)
    else:
        r1 = proj.normalized_rays(np.stack([u, v], axis=-1))
        r2 = proj.normalized_rays(np.stack([u, v + 1.0], axis=-1))
        n_dev = np.cross(r1, r2)  # orientation is irrelevant to the intersection
    return n_dev @ proj.R  # R^T n for row vectors


_RAYS: dict = {}
_RAYS_LOCK = threading.RLock()  # threads (decode_stacks(threads=2)) share the cache


def _camera_rays(cam) -> tuple[np.ndarray, np.ndarray]:
    """``cam.pixel_rays(cam.pixel_grid())``, kept for the last few cameras (they rarely change).

    The arrays are read-only: callers must not modify them.
    """
    key = (cam.K.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.dist.tobytes(), cam.width, cam.height)
    with _RAYS_LOCK:  # one thread computes a camera's rays, the other waits for them
        if key not in _RAYS:
            if len(_RAYS) >= 4:
                _RAYS.pop(next(iter(_RAYS)))
            origin, d = cam.pixel_rays(cam.pixel_grid())
            origin.setflags(write=False)
            d.setflags(write=False)
            _RAYS[key] = (origin, d)
        return _RAYS[key]


def triangulate(rig, phase: np.ndarray, periods: float | None = None, mask: np.ndarray | None = None,
                pixels: np.ndarray | None = None, max_iter: int = 20, tol: float = 1e-9) -> Triangulation:
    """Phase -> 3D by intersecting each camera ray with the projector's plane of constant column.

    Parameters
    ----------
    rig : :class:`fppsim.geometry.rig.Rig` (camera and projector, mm).
    phase : absolute projector phase (rad) of the ``periods``-period pattern, ``Phi = 2 pi f u_p / W_p``,
        shape (H, W) of the camera image (or any shape matching ``pixels``).
    periods : fringe periods ``f`` across the projector width; default ``rig.periods``.
    mask : optional bool array (phase shape); False pixels are left invalid.
    pixels : optional (..., 2) camera pixel coordinates (u = column, v = row) of the phase samples;
        default the camera's pixel-centre grid (then ``phase`` must be (H, W)).
    max_iter, tol : projector-distortion iteration (see Notes): at most ``max_iter`` steps, stop when
        every pixel's row moved less than ``tol`` projector pixels.

    Returns
    -------
    :class:`Triangulation` (points, height, depth, column, row, valid).

    Notes
    -----
    ``u_p = Phi W_p / (2 pi f)``. Camera rays come from :meth:`Device.pixel_rays` (camera distortion
    removed). Without projector distortion the pixels of column ``u_p`` form an exact plane through the
    projector centre and one ray-plane intersection is exact. With projector distortion the column is a
    curved surface: start from the undistorted plane, project the intersection into the projector
    (with distortion) to get its row ``v``, replace the plane by the one through the undistorted rays of
    ``(u_p, v)`` and ``(u_p, v + 1)`` and intersect again, until ``v`` stops moving. At the fixed point the
    intersection projects exactly to ``(u_p, v)``, so the result is exact up to ``tol``; the iteration
    contracts quickly for the mild distortion of projection lenses. Pixels that have not converged after
    ``max_iter`` steps are marked invalid.
    """
    return _triangulate(rig, phase, periods, mask, pixels, max_iter, tol)


def _triangulate(rig, phase, periods=None, mask=None, pixels=None, max_iter=20, tol=1e-9, height_only=False,
                 rows: slice | None = None):
    """:func:`triangulate`; with ``height_only`` just its ``height`` array (the same bits), without the
    arrays only the full result needs (projector pixels of the points, the NaN-filled points, depth,
    column and row). ``rows``: ``phase`` holds only these camera rows (a band of the image; the
    arithmetic per pixel is the same; not with a distorted projector, whose iteration stops for the
    whole array at once)."""
    cam, proj = rig.camera, rig.projector
    Phi = np.asarray(phase, dtype=np.float64)
    if rows is not None:
        if pixels is not None or proj.has_distortion:
            raise InputError("rows= needs the camera grid (no pixels=) and a projector without distortion")
        band = range(cam.height)[rows]
        if band.step != 1 or Phi.shape != (len(band), cam.width):
            raise InputError(f"phase has shape {Phi.shape}, not the {len(band)} x {cam.width} of camera rows {rows}")
        origin, d = _camera_rays(cam)
        d = d[band.start:band.stop]
    elif pixels is None:
        if Phi.shape != (cam.height, cam.width):
            raise InputError(f"phase has shape {Phi.shape} but the camera is {cam.height} x {cam.width} "
                             "(pass pixels= for other sampling grids)")
        origin, d = _camera_rays(cam)
    else:
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.shape != Phi.shape + (2,):
            raise InputError(f"pixels has shape {pixels.shape}, expected {Phi.shape + (2,)} for phase {Phi.shape}")
        origin, d = cam.pixel_rays(pixels)
    f = rig.periods if periods is None else float(periods)
    u = rig.column_of_phase(Phi, f)
    valid = np.isfinite(u)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != Phi.shape:
            raise InputError(f"mask has shape {m.shape}, phase has {Phi.shape}")
        valid &= m
    u = np.where(valid, u, proj.K[0, 2])

    C = proj.center
    co = C - origin

    def intersect(n):
        with np.errstate(divide="ignore", invalid="ignore"):
            return (n @ co) / np.einsum("...i,...i->...", n, d)

    s = intersect(_column_plane_normal(proj, u, None))
    row = np.full(Phi.shape, np.nan)
    if proj.has_distortion:
        good = np.isfinite(s)
        X = along_rays(origin, np.where(good, s, 0.0), d)
        row = proj.project(X)[0][..., 1]
        converged = np.zeros(Phi.shape, dtype=bool)
        for _ in range(int(max_iter)):
            s = intersect(_column_plane_normal(proj, u, row))
            good = np.isfinite(s)
            X = along_rays(origin, np.where(good, s, 0.0), d)
            new_row = proj.project(X)[0][..., 1]
            step = np.abs(new_row - row)
            row = new_row
            converged = step < tol
            if np.all(converged | ~valid | ~good):
                break
        valid &= converged
    X = along_rays(origin, np.where(np.isfinite(s), s, 0.0), d)
    if height_only:  # z_p is what proj.project(X) returns as depth: the same expression
        z_p = proj.world_to_device(X)[..., 2]
        valid &= np.isfinite(s) & (s > 0) & (z_p > 0)
        return np.where(valid, X[..., 2], np.nan)
    uv_p, z_p = proj.project(X)
    valid &= np.isfinite(s) & (s > 0) & (z_p > 0)
    if not proj.has_distortion:
        row = uv_p[..., 1]
    X = np.where(valid[..., None], X, np.nan)
    return Triangulation(points=X, height=X[..., 2], depth=np.where(valid, s, np.nan),
                         column=np.where(valid, u, np.nan), row=np.where(valid, row, np.nan), valid=valid)


def height_from_phase(rig, phase: np.ndarray, periods: float | None = None, mask: np.ndarray | None = None,
                      **kwargs) -> np.ndarray:
    """Height above the reference plane (mm, float64 (H, W)) from absolute phase; NaN where invalid.

    Shorthand for ``triangulate(rig, phase, periods, mask, **kwargs).height``.
    """
    return _triangulate(rig, phase, periods=periods, mask=mask, height_only=True, **kwargs)
