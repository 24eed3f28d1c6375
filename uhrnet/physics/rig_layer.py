"""Differentiable phase <-> height through a calibrated fppsim rig (:class:`RigLayer`).

A fixed ``torch.nn.Module`` that equals fppsim's numpy triangulation (:func:`fppsim.phase.triangulation.triangulate`,
``height_from_phase``) and its forward model (:func:`fppsim.fitting.height_sensitivity.surface_phase`) on every camera
pixel, so a network can predict phase and be trained / checked in height (the physics head
:mod:`uhrnet.models.phase_head`, label-free adaptation :mod:`uhrnet.training.adapt`, :mod:`uhrnet.physics.refine`).

Geometry (conventions of :mod:`fppsim.geometry.rig`: mm, rad, OpenCV pinholes, ``X_dev = R X_world + t``, the
reference plane ``z = 0``, ``+z`` towards the camera). Each pixel's camera ray comes from
:meth:`fppsim.geometry.rig.Device.pixel_rays` (fppsim's own code, so the camera's lens distortion is removed
exactly as fppsim removes it) and is parametrised by height::

    X(h) = P0 + h e          P0 = the ray's point on z = 0,  e = ray direction scaled to e_z = 1

In the projector frame ``X_p(h) = A + h B`` (``A = R_p P0 + t_p``, ``B = R_p e``), so the projector column
the point lights is ``u_p(h) = fx xd + s yd + cx`` with ``(xd, yd)`` the (distorted) normalised
coordinates of ``X_p(h)``, and the absolute phase is ``Phi = 2 pi f u_p / W_p`` (``phase_true``).

* :meth:`RigLayer.phase_from_height`: ``h -> Phi(h)``, the formula above (= ``fppsim.fitting.height_sensitivity.surface_phase``).
* :meth:`RigLayer.height_from_phase`: ``Phi -> h`` with ``u_p(h) = Phi W_p / (2 pi f)``. Without
  projector distortion ``u_p(h)`` is a ratio of two affine functions of ``h`` and the inverse is exact in
  closed form (the ray / column-plane intersection of fppsim). With projector distortion the column is
  a curved surface: Newton's method on ``u_p(h) - u`` from the undistorted solution, to ``tol`` mm (fppsim
  iterates the column plane until the row is still; both converge to the same point, where the ray
  meets the distorted column exactly). Pixels that do not converge in ``max_iter`` steps are invalid,
  as in fppsim. The Newton steps run without autograd; one last step carries the gradient, which is then
  the exact implicit derivative ``dh/dPhi = 1 / (dPhi/dh)`` (first derivatives only: double backward
  through a distorted projector's inverse sees ``dPhi/dh`` as a constant). Tested equal to fppsim
  (1e-10 mm, same valid pixels) from -250 to +250 mm; far beyond (points next to the devices) a
  distorted column can be met twice and the two iterations may pick different points.
* Validity (as fppsim's ``Triangulation.valid``): finite phase, the point in front of the camera and of
  the projector, the ray not parallel to the column (and, distorted, converged). Invalid pixels are NaN;
  their internals are computed on safe stand-in values so NaN never reaches a gradient.

Precision and dtype. The geometry buffers are float64 and STAY float64 (``.to(device)``, ``.float()``,
``.half()`` move them but keep their dtype; on a device without float64, e.g. MPS, they fall back to
float32). Inputs of any floating dtype are computed in the buffers' dtype (float64) and the result is
returned in the input's dtype: the layer is elementwise (a few dozen flops per pixel), so the float64
path costs little next to a network, and float32 callers only lose the rounding of their own float32
phase (about 3e-5 rad at 500 rad; measured max 1.8e-5 to 3.3e-5 mm against fppsim). Pass
``compute_dtype=torch.float32`` to compute in float32 throughout (measured max 0.6e-4 to 1.1e-4 mm,
2.5e-4 mm with a distorted projector; its Newton tolerance is then 1e-3 mm).

Shapes. The layer is built for one image grid ``(H, W)`` (the camera's, a resized camera image, or a
window of it, see :class:`RigLayer`); every method broadcasts over leading dimensions: ``(..., H, W)``,
e.g. ``(B, 1, H, W)``.

Serialisation: :meth:`RigLayer.to_dict` / :meth:`RigLayer.from_dict` (the rig dictionary of
:meth:`fppsim.geometry.rig.Rig.to_dict` plus the grid). The buffers are not in ``state_dict`` (persistent=False):
they follow from the rig, which a checkpoint carries in its config.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from fppsim.geometry.rig import Rig
from uhrnet.errors import InputError

__all__ = ["RigLayer", "wrap", "circular_mean"]

TWO_PI = 2.0 * math.pi


def wrap(phase: torch.Tensor) -> torch.Tensor:
    """Wrap phases (rad) into ``(-pi, pi]``, the torch twin of :func:`fppsim.phase.wrap` (equal in float64;
    values already there unchanged); any shape and floating dtype; differentiable (slope 1)."""
    w = phase - TWO_PI * torch.ceil((phase - math.pi) / TWO_PI)
    return torch.where(w <= -math.pi, w + TWO_PI, torch.where(w > math.pi, w - TWO_PI, w))


def circular_mean(phase: torch.Tensor, weights: torch.Tensor, dim=(1, 2, 3)) -> torch.Tensor:
    """Weighted circular mean (rad, ``atan2(sum w sin, sum w cos)``) over ``dim`` (kept, size 1): one
    phase per image of an ``(N, 1, H, W)`` batch; the torch twin of :func:`fppsim.phase.circular_mean`."""
    return torch.atan2((weights * torch.sin(phase)).sum(dim=dim, keepdim=True),
                       (weights * torch.cos(phase)).sum(dim=dim, keepdim=True))


def _slice_tuple(s: slice) -> list:
    return [s.start, s.stop, s.step]


class RigLayer(nn.Module):
    """Fixed, differentiable phase <-> height layer of a calibrated fppsim rig (module docstring).

    Parameters
    ----------
    rig : :class:`fppsim.geometry.rig.Rig`, or its dictionary (:meth:`fppsim.geometry.rig.Rig.to_dict`).
    periods : fringe periods ``f`` across the projector width (default ``rig.periods``).
    height, width : size of the image grid in pixels (default the camera's). A different size is a
        resized camera image: pixel ``(i, j)`` is camera pixel ``((j + 0.5) W_c / W - 0.5,
        (i + 0.5) H_c / H - 0.5)`` (the pixel-area convention of ``F.interpolate(align_corners=False)``
        and ``cv2.resize``).
    pixels : optional window of that grid: ``(rows, cols)``, two slices (a crop; the layer's grid is
        then the crop), or an explicit float array ``(H', W', 2)`` of camera pixel coordinates
        ``(u, v)`` (u = column, v = row, integer = pixel centre) to sample.
    max_iter, tol : Newton iteration for a distorted projector: at most ``max_iter`` steps, converged
        when the step is below ``tol`` mm (default 1e-9 mm in float64, 1e-3 mm in float32).
    compute_dtype : dtype of the buffers and of all arithmetic (default float64).

    Attributes
    ----------
    grid_shape : ``(H, W)`` of the layer's image grid.
    periods : float, fringe periods.
    rig : the :class:`fppsim.geometry.rig.Rig`.
    """

    _BUFFERS = ("A", "B", "u0", "inv_dz", "ray_ok")

    def __init__(self, rig: Rig | dict, periods: float | None = None, height: int | None = None,
                 width: int | None = None, pixels=None, max_iter: int = 20, tol: float | None = None,
                 compute_dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        if isinstance(rig, dict):
            rig = Rig.from_dict(rig)
        self.rig = rig
        cam, proj = rig.camera, rig.projector
        self.periods = float(rig.periods if periods is None else periods)
        if not (self.periods > 0 and math.isfinite(self.periods)):
            raise InputError(f"periods must be > 0, got {periods!r}")
        self.max_iter = int(max_iter)
        self.tol = tol
        self._window = None
        H = cam.height if height is None else int(height)
        W = cam.width if width is None else int(width)
        if H < 1 or W < 1:
            raise InputError(f"image grid must be at least 1 x 1, got {W} x {H}")
        self._size = (H, W)
        if pixels is not None and not (isinstance(pixels, (tuple, list)) and len(pixels) == 2
                                       and all(isinstance(p, slice) for p in pixels)):
            uv = np.asarray(pixels, dtype=np.float64)
            if uv.ndim != 3 or uv.shape[-1] != 2:
                raise InputError(f"pixels must be (rows, cols) slices or an (H, W, 2) array, got shape {uv.shape}")
            self._size = None  # an explicit sampling: not serialisable as a grid
        else:
            # pixel centres of the (resized) grid in camera pixels; float64 as fppsim's pixel_grid
            u = (np.arange(W) + 0.5) * (cam.width / W) - 0.5
            v = (np.arange(H) + 0.5) * (cam.height / H) - 0.5
            if pixels is not None:
                rows, cols = pixels
                u, v = u[cols], v[rows]
                if u.size == 0 or v.size == 0:
                    raise InputError(f"pixels {pixels} select no pixel of the {W} x {H} grid")
                self._window = (rows, cols)
            uu, vv = np.meshgrid(u, v)
            uv = np.stack([uu, vv], axis=-1)
        self.grid_shape = tuple(int(n) for n in uv.shape[:2])

        origin, d = cam.pixel_rays(uv)  # fppsim's rays: camera distortion removed as fppsim does
        _, P0 = cam.ray_cut(uv, 0.0, rays=(origin, d))  # the ray's point on the plane (fppsim's ray cut)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_dz = 1.0 / d[..., 2]
            e = d * inv_dz[..., None]  # dX/dh
        ray_ok = np.isfinite(P0).all(-1) & np.isfinite(e).all(-1)
        P0 = np.where(ray_ok[..., None], P0, 0.0)
        e = np.where(ray_ok[..., None], e, 0.0)
        inv_dz = np.where(ray_ok, inv_dz, -1.0)
        A = P0 @ proj.R.T + proj.t  # projector-frame plane point and direction per unit height
        B = e @ proj.R.T
        with np.errstate(divide="ignore", invalid="ignore"):  # the plane's column, undistorted model
            u0 = np.where(ray_ok, (A @ proj.K[0]) / A[..., 2], 0.0)
        self._origin_z = float(origin[2])
        self._K0 = tuple(float(x) for x in proj.K[0])  # (fx, skew, cx)
        self._dist = tuple(float(x) for x in proj.dist)
        self._distorted = bool(proj.has_distortion)
        self._col_per_rad = proj.width / (TWO_PI * self.periods)  # u_p = Phi * this
        dt = compute_dtype
        self.register_buffer("A", torch.as_tensor(np.moveaxis(A, -1, 0), dtype=dt), persistent=False)
        self.register_buffer("B", torch.as_tensor(np.moveaxis(B, -1, 0), dtype=dt), persistent=False)
        self.register_buffer("u0", torch.as_tensor(u0, dtype=dt), persistent=False)
        self.register_buffer("inv_dz", torch.as_tensor(inv_dz, dtype=dt), persistent=False)
        self.register_buffer("ray_ok", torch.as_tensor(ray_ok), persistent=False)

    # ------------------------------------------------------------------ device / dtype handling
    def _apply(self, fn, recurse=True):
        """Move the geometry buffers with the module but keep their dtype (``.float()``/``.half()``
        would otherwise round the rig's geometry)."""
        mine = {k: self._buffers.pop(k) for k in self._BUFFERS}
        try:
            super()._apply(fn, recurse)
        finally:
            device = fn(torch.zeros((), device=mine["A"].device)).device
            for k, b in mine.items():
                try:
                    self._buffers[k] = b.to(device)
                except (TypeError, RuntimeError):  # no float64 on this device (MPS)
                    self._buffers[k] = b.to(device, torch.float32 if b.is_floating_point() else b.dtype)
        return self

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of the buffers and of the arithmetic."""
        return self.A.dtype

    def _tol(self) -> float:
        if self.tol is not None:
            return float(self.tol)
        return 1e-9 if self.dtype == torch.float64 else 1e-3

    def _input(self, x: torch.Tensor, name: str) -> torch.Tensor:
        x = torch.as_tensor(x, device=self.A.device)
        if x.shape[-2:] != self.grid_shape:
            raise InputError(f"{name} has shape {tuple(x.shape)}; the layer's grid is {self.grid_shape} (..., H, W)")
        return x.to(self.dtype)

    @staticmethod
    def _out(y: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return y.to(like.dtype) if torch.is_tensor(like) and like.is_floating_point() else y

    # ------------------------------------------------------------------ forward model
    def _column(self, h: torch.Tensor, derivative: bool = False):
        """Projector column ``u_p`` (pixels, distorted) of the ray point at height ``h``; with
        ``derivative`` also ``du_p/dh`` (projector pixels per mm), analytic."""
        A, B = self.A, self.B
        X, Y, Z = A[0] + h * B[0], A[1] + h * B[1], A[2] + h * B[2]
        x, y = X / Z, Y / Z
        fx, sk, cx = self._K0
        if derivative:
            dx, dy = (B[0] - x * B[2]) / Z, (B[1] - y * B[2]) / Z
        if not self._distorted:
            u = fx * x + sk * y + cx
            return (u, fx * dx + sk * dy) if derivative else u
        k1, k2, p1, p2, k3 = self._dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))  # the same expressions as fppsim.geometry.rig._distort
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        u = fx * xd + sk * yd + cx
        if not derivative:
            return u
        dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
        xdx = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        xdy = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        ydx = xdy
        ydy = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        du = fx * (xdx * dx + xdy * dy) + sk * (ydx * dx + ydy * dy)
        return u, du

    def phase_from_height(self, height: torch.Tensor) -> torch.Tensor:
        """Absolute projector phase (rad, fppsim's ``phase_true``) a surface at ``height`` mm shows at
        each pixel: project the camera ray's point at that height into the projector (with its
        distortion). Same as :func:`fppsim.fitting.height_sensitivity.surface_phase`.

        Parameters
        ----------
        height : (..., H, W) tensor, mm above the reference plane, any floating dtype.

        Returns
        -------
        (..., H, W) tensor of the input's dtype, rad. No validity check (a height at or above the
        projector gives a meaningless phase); NaN in, NaN out. Differentiable in ``height``.
        """
        h = self._input(height, "height")
        u = self._column(h)
        phase = torch.where(self.ray_ok, u / self._col_per_rad, torch.full_like(u, math.nan))
        return self._out(phase, height)

    def height_from_phase(self, phase: torch.Tensor, return_valid: bool = False):
        """Height (mm) where each pixel's camera ray meets the projector column of absolute phase ``phase``.

        Equal to :func:`fppsim.phase.triangulation.height_from_phase` (see the module docstring for the method).

        Parameters
        ----------
        phase : (..., H, W) tensor, absolute projector phase in rad (``Phi = 2 pi f u_p / W_p``).
        return_valid : also return the (..., H, W) bool validity mask.

        Returns
        -------
        height : (..., H, W) tensor of the input's dtype, mm, NaN where invalid (module docstring);
            differentiable in ``phase`` (zero gradient on invalid pixels).
        valid : (..., H, W) bool, only with ``return_valid``.
        """
        Phi = self._input(phase, "phase")
        finite = torch.isfinite(Phi) & self.ray_ok
        u = torch.where(finite, Phi, torch.zeros_like(Phi)) * self._col_per_rad
        A, B = self.A, self.B
        fx, sk, cx = self._K0
        # undistorted column: u (A_z + h B_z) = a0 + h a1 with a = fx X + s Y + cx Z (exact, closed form);
        # a0 = u0 A_z, written as A_z (u - u0) so float32 keeps the small difference to the plane
        a1 = fx * B[0] + sk * B[1] + cx * B[2]
        den = a1 - u * B[2]
        ok = finite & (den != 0)
        den = torch.where(ok, den, torch.ones_like(den))
        h = A[2] * (u - self.u0) / den
        if self._distorted:
            h, converged = self._newton(h, u, ok)
            ok = ok & converged
        z_cam = (h - self._origin_z) * self.inv_dz  # camera depth along the ray (fppsim's s)
        z_proj = A[2] + h * B[2]
        ok = ok & torch.isfinite(h) & (z_cam > 0) & (z_proj > 0)
        h = torch.where(ok, h, torch.full_like(h, math.nan))
        h = self._out(h, phase)
        return (h, ok) if return_valid else h

    def _newton(self, h: torch.Tensor, u: torch.Tensor, ok: torch.Tensor):
        """Solve ``u_p(h) = u`` for a distorted projector (module docstring); returns (h, converged)."""
        tol = self._tol()
        with torch.no_grad():
            x = torch.where(ok, h, torch.zeros_like(h)).detach()
            target = u.detach()
            converged = torch.zeros_like(ok)
            for _ in range(self.max_iter):
                c, dc = self._column(x, derivative=True)
                step = (c - target) / dc
                good = torch.isfinite(step)
                x = torch.where(good, x - step, x)
                converged = good & (step.abs() < tol)
                if bool((converged | ~ok).all()):
                    break
            x = torch.where(ok & converged & torch.isfinite(x), x, torch.zeros_like(x))
            c, dc = self._column(x, derivative=True)
            dc = torch.where(dc != 0, dc, torch.ones_like(dc))
        # one more Newton step that carries the gradient: dh/du = 1 / (du_p/dh), the implicit derivative
        return x - (c - u) / dc, converged

    # ------------------------------------------------------------------ the plane and the sensitivity
    def plane_phase(self) -> torch.Tensor:
        """(H, W) absolute phase (rad) of the reference plane ``z = 0`` at each pixel (buffer dtype)."""
        return self.phase_from_height(torch.zeros(self.grid_shape, dtype=self.dtype, device=self.A.device))

    def sensitivity(self, height: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Local sensitivity ``dPhi/dh`` (rad per mm) at each pixel for a surface at ``height`` mm.

        Negative on fppsim's rigs (the phase falls on raised surfaces). ``pi / |sensitivity|`` is the
        height of half a fringe period. ``height``: a number or a (..., H, W) tensor. Returns
        (..., H, W) (``(H, W)`` for a number) in the input tensor's dtype, else the buffers' dtype;
        analytic, differentiable.
        """
        h = height if torch.is_tensor(height) else torch.full(self.grid_shape, float(height), dtype=self.dtype,
                                                              device=self.A.device)
        _, du = self._column(self._input(h, "height"), derivative=True)
        return self._out(du / self._col_per_rad, h)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """JSON-able description: ``{"rig": rig dict, "periods", "height", "width", "pixels"}`` (pixels as
        ``[[start, stop, step], [start, stop, step]]`` or None). Raises ValueError for an explicit
        pixel array (rebuild those with the array)."""
        if self._size is None:
            raise InputError("a layer built on an explicit pixel array cannot be described by a dictionary")
        win = None if self._window is None else [_slice_tuple(s) for s in self._window]
        return {"rig": self.rig.to_dict(), "periods": self.periods, "height": self._size[0], "width": self._size[1],
                "pixels": win, "max_iter": self.max_iter, "tol": self.tol}

    @classmethod
    def from_dict(cls, d: dict, **kwargs) -> "RigLayer":
        """Rebuild a layer from :meth:`to_dict`, or from a bare fppsim rig dictionary
        (:meth:`fppsim.geometry.rig.Rig.to_dict`, as a checkpoint's ``config["rig"]`` holds). ``kwargs`` override."""
        if "rig" in d and isinstance(d["rig"], dict):
            args = {k: d.get(k) for k in ("periods", "height", "width", "max_iter", "tol") if d.get(k) is not None}
            if d.get("pixels") is not None:
                args["pixels"] = tuple(slice(*s) for s in d["pixels"])
            args.update(kwargs)
            return cls(d["rig"], **args)
        return cls(Rig.from_dict(d), **kwargs)

    def extra_repr(self) -> str:
        return (f"grid={self.grid_shape}, periods={self.periods:g}, projector_distortion={self._distorted}, "
                f"dtype={self.dtype}")
