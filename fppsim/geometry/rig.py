"""Calibrated FPP rig: a camera and a projector as OpenCV pinholes above the reference plane z = 0.

Conventions (the single reference for the whole package):

* Units are millimetres, angles radians.
* World frame: the reference plane is ``z = 0`` and ``+z`` points from the plane towards the camera.
  Height is the world ``z`` of the first surface a camera pixel sees.
* Each device is an OpenCV pinhole: x right, y down, z forward; ``K = [[fx,0,cx],[0,fy,cy],[0,0,1]]``
  with integer pixel centres (pixel ``(u, v)`` = column ``u``, row ``v``); ``X_dev = R @ X_world + t``;
  distortion ``(k1, k2, p1, p2, k3)`` as in OpenCV.
* The projector is an inverse camera; its pattern varies along projector columns ``u_p``.
* pyrender uses OpenGL axes (y up, z backwards) and pixel centres at +0.5. The conversion lives in
  exactly one place: :meth:`Device.gl_pose` and :meth:`Device.gl_intrinsics`.

Calibration files (fppsim JSON/YAML, OpenCV stereo FileStorage) are read and written by
:mod:`fppsim.geometry.rig_files` (:meth:`Rig.load` / :meth:`Rig.save` call it).
"""

from __future__ import annotations

import importlib.resources
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fppsim.errors import RigError, InputError
from fppsim.geometry.rig_files import checked_matrix, read_rig_file, save_rig

__all__ = ["Device", "Rig", "RigError", "check_image_size", "checked_matrix", "data_path", "default_rig_path", "load_rig",
           "usable_rig",
           "make_default_rig",
           "make_figshare_like_rig", "make_parallel_rig", "projector_for", "rotation", "along_rays"]



def data_path(*parts: str) -> Path:
    """A file shipped inside the package (``fppsim/data/...``: the default rig, the asset meshes),
    found through importlib.resources so it works from a wheel as from a checkout. In the repository
    ``fppsim/data`` is a link to the top-level ``assets/`` folder (the files live there once); a wheel
    holds real copies."""
    return Path(str(importlib.resources.files("fppsim").joinpath("data", *parts)))


MAX_PIXELS = 1 << 16  # per side: anything larger is a typo, not a sensor
RIG_FORMAT = "fppsim-rig/1"  # the rig document's "format": what Rig.to_dict writes and Rig.from_dict reads


@dataclass
class Device:
    """One OpenCV pinhole device (camera or projector).

    Attributes
    ----------
    K : (3, 3) float64 intrinsics in pixels (integer pixel centres).
    R : (3, 3) float64 rotation world -> device.
    t : (3,) float64 translation world -> device, mm.
    width, height : int resolution in pixels.
    dist : (5,) float64 OpenCV distortion (k1, k2, p1, p2, k3); zeros for an ideal pinhole.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        self.K = checked_matrix(self.K, (3, 3), "K")
        self.R = checked_matrix(self.R, (3, 3), "R")
        self.t = checked_matrix(self.t, (3,), "t")
        d = np.zeros(5)
        try:
            dist = np.asarray(self.dist, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise RigError(f"dist must hold at most 5 finite numbers (k1,k2,p1,p2,k3), got {self.dist!r:.80}") from None
        if dist.size > 5 or not np.all(np.isfinite(dist)):
            raise RigError(f"dist must hold at most 5 finite numbers (k1,k2,p1,p2,k3), got {dist.tolist()}")
        d[: dist.size] = dist
        self.dist = d
        self.width, self.height = _pixels(self.width, "width"), _pixels(self.height, "height")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0 or self.K[2, 2] != 1 or self.K[2, 0] or self.K[2, 1]:
            raise RigError(f"K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, got {self.K.tolist()}")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            raise RigError("R must be a proper rotation matrix (orthonormal, det +1)")

    # ------------------------------------------------------------------ basic geometry
    @property
    def center(self) -> np.ndarray:
        """(3,) optical centre in world coordinates, mm."""
        return -self.R.T @ self.t

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def world_to_device(self, X: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) device-frame points (mm)."""
        X = np.asarray(X, dtype=np.float64)
        Xd = X @ self.R.T
        if Xd.ndim < 2:
            return Xd + self.t
        for i in range(3):  # + t one coordinate plane at a time: the same sums, no length-3 inner loops
            Xd[..., i] += self.t[i]
        return Xd

    def project(self, X: np.ndarray, distort: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels.

        Parameters
        ----------
        X : (..., 3) world points, mm.
        distort : apply the lens distortion (False gives the ideal pinhole pixel).

        Returns
        -------
        uv : (..., 2) float64 pixel coordinates (u = column, v = row; integer = pixel centre).
        z : (...,) float64 depth along the device's optical axis, mm (<= 0 means behind the device).
        """
        Xd = self.world_to_device(X)
        z = Xd[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = Xd[..., 0] / z
            y = Xd[..., 1] / z
        if distort and self.has_distortion:
            x, y = _distort(x, y, self.dist)
        K = self.K
        u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
        v = K[1, 1] * y + K[1, 2]
        return np.stack([u, v], axis=-1), z

    def irradiance_falloff(self, X: np.ndarray, z: np.ndarray | None = None,
                           dist: np.ndarray | None = None) -> np.ndarray:
        """Relative irradiance a projector delivers at world points, per unit of cos(incidence).

        A projector sends the same flux through every pixel of its image (for a uniform pattern), so
        its radiant intensity grows off axis as ``1 / cos^3(theta)`` (a pixel's solid angle is
        ``cos^3(theta) / (fx fy)``) and the irradiance on a surface is ``E ~ cos_inc * r / z^3``
        (``r`` = distance from the projection centre, ``z`` = depth along the optical axis). It is
        normalised to 1 at the world origin. A surface square to the optical axis is lit evenly (each
        pixel's footprint has the same area); an isotropic point source (``1 / r^2``) would darken its
        edges as ``cos^3(theta)``. Lens shift does not enter (the DMD stays square to the axis); lens
        distortion is ignored (a sub-percent effect within calibration tolerance).

        Parameters
        ----------
        X : (..., 3) world points, mm.
        z, dist : optional, the points' depth along the axis (from :meth:`project`) and distance to
            :attr:`center` (mm), when the caller already has them.

        Returns
        -------
        (...,) float64, 0 where a point is not in front of the device. Raises RigError when the world
        origin is not in front of it.
        """
        z0 = float(self.t[2])  # the world origin's depth
        if not z0 > 0:
            raise RigError("the world origin (the scene centre, where the irradiance is normalised) is behind "
                           "the projector")
        z = self.world_to_device(X)[..., 2] if z is None else np.asarray(z, dtype=np.float64)
        if dist is None:
            dist = np.sqrt(np.sum((self.center - np.asarray(X, dtype=np.float64)) ** 2, axis=-1))
        dist = np.asarray(dist, dtype=np.float64)
        scale = z0 ** 3 / float(np.sqrt(np.sum(self.center ** 2)))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            f = np.divide(1.0, z)  # in place from here: this runs on every rendered pixel
            f *= f * f
            f *= dist
            f *= scale
        if np.ndim(f) == 0:
            return np.float64(f if z > 0 else 0.0)
        f[~(z > 0)] = 0.0
        return f

    def normalized_rays(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) pixels -> (..., 3) device-frame ray directions (x, y, 1), distortion removed."""
        uv = np.asarray(uv, dtype=np.float64)
        K = self.K
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        if self.has_distortion:
            x, y = _undistort(x, y, self.dist)
        return np.stack([x, y, np.ones_like(x)], axis=-1)

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels to world rays.

        Returns ``origin`` (3,) and ``directions`` (..., 3) in world coordinates. Directions are
        scaled so that a step of 1 along them advances 1 mm along the optical axis, i.e.
        ``X = origin + depth * direction`` for a device-frame depth ``depth``.
        """
        d = self.normalized_rays(uv) @ self.R  # R^T applied to row vectors
        return self.center, d

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(..., 2) pixels and (...,) device-frame depths (mm) -> (..., 3) world points."""
        origin, d = self.pixel_rays(uv)
        return along_rays(origin, np.asarray(depth, dtype=np.float64), d)

    def pixel_grid(self, scale: int = 1) -> np.ndarray:
        """(H*scale, W*scale, 2) pixel-centre coordinates of a ``scale``-times supersampled grid.

        Sub-pixel centres of an odd ``scale`` include the integer pixel centres.
        """
        s = int(scale)
        u = (np.arange(self.width * s) + 0.5) / s - 0.5
        v = (np.arange(self.height * s) + 0.5) / s - 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def plane_depth(self, uv: np.ndarray, plane_z: float = 0.0) -> np.ndarray:
        """Device-frame depth (mm) at which pixel rays meet the world plane z = plane_z (inf if never)."""
        s, _ = self.ray_cut(uv, plane_z)
        return np.where(np.isfinite(s) & (s > 0), s, np.inf)

    def ray_cut(self, uv: np.ndarray, z=0.0, rays: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Where the rays of pixels ``uv`` (..., 2) meet the world plane ``z = z`` (mm: a number, or an
        array broadcasting with ``uv[..., 0]`` such as a height map): the one ray cut of both packages.

        Returns ``(depth, X)``: the device-frame depth (...,) mm (``<= 0``, inf or NaN where the ray does
        not meet the plane in front of the device) and the world points (..., 3) mm. ``rays``: the
        ``(origin, directions)`` of :meth:`pixel_rays` for ``uv``, when the caller already has them.
        """
        origin, d = self.pixel_rays(uv) if rays is None else rays
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            s = (np.asarray(z, dtype=np.float64) - origin[2]) / d[..., 2]
            return s, along_rays(origin, s, d)

    def expanded(self, margin: int) -> "Device":
        """The same device with ``margin`` extra pixels on every side (pixel (u, v) becomes (u+m, v+m))."""
        K = self.K.copy()
        K[0, 2] += margin
        K[1, 2] += margin
        return Device(K=K, R=self.R, t=self.t, width=self.width + 2 * margin, height=self.height + 2 * margin,
                      dist=self.dist)

    # ------------------------------------------------------------------ OpenGL conversion (the one place)
    def gl_pose(self) -> np.ndarray:
        """4x4 world-from-device pose in OpenGL axes (x right, y up, z backwards), for pyrender."""
        pose = np.eye(4)
        pose[:3, :3] = self.R.T @ np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = self.center
        return pose

    def gl_intrinsics(self, scale: int = 1) -> tuple[float, float, float, float, int, int]:
        """(fx, fy, cx, cy, width, height) for pyrender.IntrinsicsCamera at ``scale``-times resolution.

        OpenGL samples pixel ``i`` at window coordinate ``i + 0.5``, OpenCV at ``i``: hence the +0.5.
        """
        s = int(scale)
        K = self.K
        return (K[0, 0] * s, K[1, 1] * s, (K[0, 2] + 0.5) * s, (K[1, 2] + 0.5) * s,
                self.width * s, self.height * s)

    # ------------------------------------------------------------------ io
    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(), "dist": self.dist.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
            "width": self.width, "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict, name: str = "device") -> "Device":
        missing = [k for k in ("K", "R", "t", "width", "height") if k not in d]
        if missing:
            raise RigError(f"{name} is missing {', '.join(missing)}")
        try:
            return cls(K=d["K"], R=d["R"], t=d["t"], width=d["width"], height=d["height"],
                       dist=d.get("dist", np.zeros(5)))
        except RigError as exc:
            raise RigError(f"{name}: {exc}") from None

    @classmethod
    def looking_down(cls, center, fx, fy, cx, cy, width, height, dist=None) -> "Device":
        """A device at world ``center`` whose optical axis points straight down (-z), x along world x."""
        R = np.diag([1.0, -1.0, -1.0])
        return cls(K=[[fx, 0, cx], [0, fy, cy], [0, 0, 1]], R=R, t=-R @ np.asarray(center, float),
                   width=width, height=height, dist=np.zeros(5) if dist is None else dist)


def along_rays(origin: np.ndarray, depth: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Points ``origin + depth[..., None] * dirs`` (..., 3) on rays ``dirs`` (..., 3) from ``origin`` (3,).

    Computed one coordinate plane at a time: the same two roundings per element as the broadcast
    expression, without numpy's slow inner loops over the length-3 axis. Other shapes fall back to it.
    """
    origin, depth = np.asarray(origin), np.asarray(depth)
    if depth.shape != dirs.shape[:-1] or origin.shape != (3,) or dirs.shape[-1:] != (3,):
        return origin + depth[..., None] * dirs
    P = np.empty(dirs.shape, dtype=np.result_type(origin, depth, dirs))
    for i in range(3):
        plane = P[..., i]
        np.multiply(depth, dirs[..., i], out=plane)
        plane += origin[i]
    return P


def _pixels(value, name: str) -> int:
    """A resolution field: a whole number of pixels in [1, MAX_PIXELS]."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if ok:
        ok = bool(np.isfinite(value)) and float(value) == int(value) and 1 <= int(value) <= MAX_PIXELS
    if not ok:
        raise RigError(f"{name} must be a whole number of pixels in 1..{MAX_PIXELS}, got {value!r}")
    return int(value)


def _distort(x, y, dist):
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _undistort(xd, yd, dist, iterations: int = 20):
    """Invert :func:`_distort` by fixed-point iteration (as cv2.undistortPoints), vectorised."""
    k1, k2, p1, p2, k3 = dist
    x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


@dataclass
class Rig:
    """Camera + projector + fringe design.

    Attributes
    ----------
    camera, projector : :class:`Device`.
    periods : number of fringe periods across the projector width (the single-shot frequency, 80).
    name : free text.
    plane_in_view : False for a rig fitted to frames that show no reference plane (objects on black: ``fppsim
        fit-rig`` with ``--distance``, ``--baseline``, ``--projector-side``); its pose is assumed, and the commands
        that measure the plane in the frames (``fit-optics``, ``label-real``) do not look for one. Written to the
        document only when False (``"plane_in_view": false``).
    """

    camera: Device
    projector: Device
    periods: float = 80.0
    name: str = "rig"
    plane_in_view: bool = True

    # -------------------------------------------------------------- phase <-> projector column
    def phase_of_column(self, u_p: np.ndarray, periods: float | None = None) -> np.ndarray:
        """Absolute projector phase (rad) of projector column ``u_p``: ``2*pi*f*u_p/W_p``."""
        f = self.periods if periods is None else periods
        return 2.0 * np.pi * f * np.asarray(u_p, dtype=np.float64) / self.projector.width

    def column_of_phase(self, phase: np.ndarray, periods: float | None = None) -> np.ndarray:
        """Projector column ``u_p = Phi * W_p / (2*pi*f)`` of an absolute phase (rad)."""
        f = self.periods if periods is None else periods
        return np.asarray(phase, dtype=np.float64) * self.projector.width / (2.0 * np.pi * f)

    # -------------------------------------------------------------- height -> phase (the forward model)
    def phase_at_height(self, height, uv: np.ndarray | None = None, periods: float | None = None) -> np.ndarray:
        """Absolute projector phase (rad, ``2 pi f u_p / W_p``, projector distortion applied) at camera
        pixels ``uv`` (..., 2) (default: the whole camera grid, (H, W)) whose surface lies ``height`` mm
        above the reference plane (a number or an array broadcasting with ``uv[..., 0]``): each camera
        ray cut at its height (:meth:`Device.ray_cut`), that point projected into the projector. NaN
        where the ray does not meet ``z = height`` in front of the camera or the point is behind the
        projector. :class:`uhrnet.physics.rig_layer.RigLayer` is its torch twin."""
        cam = self.camera
        s, X = cam.ray_cut(cam.pixel_grid() if uv is None else uv, height)
        with np.errstate(invalid="ignore"):
            uv_p, zp = self.projector.project(X)
        return np.where(np.isfinite(s) & (s > 0) & (zp > 0), self.phase_of_column(uv_p[..., 0], periods), np.nan)

    def sensitivity(self, lo: float = 0.0, hi: float = 1.0, uv: np.ndarray | None = None,
                    periods: float | None = None):
        """Phase change per mm of height (rad/mm) between surfaces ``lo`` and ``hi`` mm above the plane,
        ``(Phi(hi) - Phi(lo)) / (hi - lo)`` (:meth:`phase_at_height`), at camera pixels ``uv`` (..., 2)
        (an array of that shape) or, by default, at the image centre ``(W // 2, H // 2)`` (a float).
        Negative when raised surfaces lower the phase (the default rig: about -0.87 at the centre)."""
        cam = self.camera
        if uv is None:
            px = np.array([[cam.width // 2, cam.height // 2]] * 2, dtype=np.float64)
            z = np.array([lo, hi], dtype=np.float64)
        else:
            one = np.asarray(uv, dtype=np.float64)
            px, z = np.stack([one, one]), np.array([lo, hi], dtype=np.float64).reshape((2,) + (1,) * (one.ndim - 1))
        ph = self.phase_at_height(z, px, periods)
        slope = (ph[1] - ph[0]) / (hi - lo)
        return float(slope) if uv is None else slope

    # -------------------------------------------------------------- io
    def to_dict(self) -> dict:
        return {
            "format": RIG_FORMAT,
            "name": self.name,
            "units": "mm",
            "convention": "OpenCV pinholes, X_dev = R X_world + t; reference plane z = 0, +z towards camera",
            "reference_plane": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
            "periods": float(self.periods),
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
        } | ({} if self.plane_in_view else {"plane_in_view": False})

    @classmethod
    def from_dict(cls, d: dict) -> "Rig":
        if not isinstance(d, dict):
            raise RigError("rig document must be a mapping with 'camera' and 'projector'")
        for key in ("camera", "projector"):
            if not isinstance(d.get(key), dict):
                raise RigError(f"rig document has no '{key}' section")
        if d.get("format", RIG_FORMAT) != RIG_FORMAT:
            raise RigError(f"format {d['format']!r} is not {RIG_FORMAT!r}, the only rig format this version reads")
        if d.get("units", "mm") != "mm":
            raise RigError(f"units {d['units']!r}: a rig is read in mm only (K in px; t, the plane and every "
                           "length in mm); convert it and set \"units\": \"mm\"")
        plane = d.get("reference_plane")
        if plane is not None and not isinstance(plane, dict):
            raise RigError("reference_plane must be a mapping {point: [0,0,0], normal: [0,0,1]}, "
                           f"got {type(plane).__name__}")
        if plane is not None and not (np.allclose(plane.get("point", [0, 0, 0]), 0)
                                      and np.allclose(plane.get("normal", [0, 0, 1]), [0, 0, 1])):
            raise RigError("reference_plane must be z = 0 with normal +z (re-express the extrinsics in that frame)")
        try:
            periods = float(d.get("periods", 80.0))
        except (TypeError, ValueError):
            raise RigError(f"periods must be a number, got {d.get('periods')!r}") from None
        if not (periods > 0 and np.isfinite(periods)):
            raise RigError(f"periods must be > 0, got {periods}")
        plane_in_view = d.get("plane_in_view", True)
        if not isinstance(plane_in_view, bool):
            raise RigError(f"plane_in_view must be true or false, got {plane_in_view!r}")
        rig = cls(camera=Device.from_dict(d["camera"], "camera"),
                  projector=Device.from_dict(d["projector"], "projector"),
                  periods=periods, name=str(d.get("name", "rig")), plane_in_view=plane_in_view)
        rig.check()
        return rig

    def check(self) -> None:
        """Raise RigError unless both devices sit above the plane (at least 1 mm: a rig in metres is refused) and
        look at it."""
        for name, dev in (("camera", self.camera), ("projector", self.projector)):
            c = dev.center
            if c[2] <= 0:
                raise RigError(f"{name} centre is at z = {c[2]:.1f} mm: it must be above the reference plane (z > 0)")
            if c[2] < 1.0:
                raise RigError(f"{name} centre is {c[2]:.3g} mm above the reference plane: t must be in mm (metres?)")
            axis = dev.R[2]  # optical axis in world coordinates
            if axis[2] >= 0:
                raise RigError(f"{name} looks away from the reference plane (optical axis z = {axis[2]:+.3f})")

    def check_usable(self, min_lit: float = 0.05, min_shift_px: float = 0.01) -> None:
        """Raise RigError unless the rig can measure heights at all (checked before generating).

        * the projector must light at least ``min_lit`` of the camera's view of the reference plane;
        * a 1 mm height change at the view centre must move the seen projector column by at least
          ``min_shift_px`` projector pixels (zero baseline, or a baseline along the fringes, gives 0:
          the fringes would not encode height).
        """
        cam, proj = self.camera, self.projector
        step = max(1, min(cam.width, cam.height) // 32)
        uv = cam.pixel_grid()[::step, ::step].reshape(-1, 2)
        depth = cam.plane_depth(uv)
        hit = np.isfinite(depth)
        if not hit.any():
            raise RigError("the camera does not see the reference plane")
        X = cam.backproject(uv[hit], depth[hit])
        puv, z = proj.project(X)
        lit = (z > 0) & (puv[:, 0] >= -0.5) & (puv[:, 0] <= proj.width - 0.5) \
            & (puv[:, 1] >= -0.5) & (puv[:, 1] <= proj.height - 0.5)
        frac = float(lit.mean())
        if not proj.t[2] > 0:
            raise RigError("the world origin (the scene centre) is behind the projector: check the projector pose (R, t)")
        if frac < min_lit:
            raise RigError(f"the projector lights {100 * frac:.1f}% of the camera's view of the reference plane "
                           f"(need >= {100 * min_lit:.0f}%): check the projector pose (R, t) and resolution")
        centre = np.array([[(cam.width - 1) / 2.0, (cam.height - 1) / 2.0]] * 2)
        _, X = cam.ray_cut(centre, np.array([0.0, 1.0]))  # the view centre's ray at 0 and 1 mm
        u0, u1 = proj.project(X)[0][:, 0]
        shift = abs(float(u1 - u0))
        if not shift >= min_shift_px:
            base = float(np.linalg.norm(cam.center - proj.center))
            raise RigError(f"fringes do not move with height ({shift:.3g} projector px per mm at the view centre; "
                           f"baseline {base:.1f} mm): camera and projector need a baseline across the fringes")

    def save(self, path: str | os.PathLike) -> None:
        """Write JSON or YAML (by extension), atomically (:func:`fppsim.geometry.rig_files.save_rig`)."""
        save_rig(self.to_dict(), path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Rig":
        """Read a rig from JSON/YAML (fppsim format) or an OpenCV FileStorage stereo calibration
        (:func:`fppsim.geometry.rig_files.read_rig_file`)."""
        return cls._from_file(path, read_rig_file(path))

    @classmethod
    def _from_file(cls, path, doc) -> "Rig":
        """The rig of a file's document, checked; errors name the file."""
        try:
            return cls.from_dict(doc)
        except RigError as exc:
            raise RigError(f"{Path(path)}: {exc}") from None

    @classmethod
    def default(cls) -> "Rig":
        """The packaged default rig (``fppsim/data/default_rig.json``)."""
        return cls.load(default_rig_path())


def default_rig_path() -> Path:
    return data_path("default_rig.json")


def load_rig(path: str | os.PathLike | None, usable: bool = True) -> Rig:
    """Rig from a file, or the default rig when ``path`` is None; with ``usable`` (every command that
    measures or renders through it) it must pass :func:`usable_rig`."""
    rig = Rig.default() if path is None else Rig.load(path)
    return usable_rig(rig, path) if usable else rig


def usable_rig(rig: Rig, source=None) -> Rig:
    """``rig`` once :meth:`Rig.check_usable` passed: THE check of every rig that enters a command (a file,
    a checkpoint's or a dataset's record); :class:`RigError` naming ``source`` otherwise."""
    try:
        rig.check_usable()
    except RigError as exc:
        raise RigError(f"{source}: {exc}" if source is not None else str(exc)) from None
    return rig


def check_image_size(rig, shape, what: str, *, who: str = "the rig's camera is", hint: str = "", error=RigError,
                     template: str = "{what}: image is {got} but {who} {camera}{hint}", sep: str = "x") -> None:
    """THE check that an image (``shape`` (H, W)) is what a rig's camera sees: every command that reads
    images through a rig calls it. ``rig``: a :class:`Rig`, a :class:`Device` or a rig document (dict);
    raises ``error`` with ``template`` filled in (``got`` / ``camera``: ``W{sep}H``; ``who`` names the rig and
    its verb, e.g. ``"the rig used by --refine (x.json) sees"``; ``hint``: the remedy)."""
    cam = rig.camera if isinstance(rig, Rig) else rig if isinstance(rig, Device) else rig["camera"]
    w, h = (cam.width, cam.height) if isinstance(cam, Device) else (int(cam["width"]), int(cam["height"]))
    shape = tuple(shape)
    if shape != (h, w):
        got = f"{shape[1]}{sep}{shape[0]}" if len(shape) == 2 else str(shape)
        raise error(template.format(what=what, got=got, who=who, camera=f"{w}{sep}{h}", hint=hint))


# The real figshare rig is close to, but not exactly, parallel: its fringe period falls steadily from
# left to right (12.06 -> 11.39 px over four column bands, 11.96 | 11.49 px between halves, nothing
# top to bottom). A projector turned about its y axis towards the scene reproduces that trend; the
# focal length is then refitted so the four column bands match (band RMS 0.008 px).
# Its height sensitivity was measured by re-projecting the real pair's labelled surface (label / 6 mm
# above the plane) through candidate rigs and demodulating the real fringe with the phase each rig
# predicts (fppsim.fitting.fit_rig.sensitivity_fit): the residual phase on the object is flat in height and
# coherent (R = 0.988) only near a 330 mm baseline, 0.87 rad per mm at the image centre; the former
# 180 mm parallel rig had 0.48 rad/mm (R = 0.20), i.e. it taught networks 1.8x too little fringe
# shift per mm.
# Its fringe lines are not vertical either: on the plane they lean by -1.34 deg (8.6 px over the 352
# rows; fppsim.phase.measure.fringe_tilt), which a projector rolled by -1.29 deg about its optical axis
# reproduces (fit-rig fits it from the tilt).
DEFAULT_BASELINE = 330.0  # mm
DEFAULT_PROJECTOR_YAW = 0.07499517978544548  # rad (4.30 deg)
DEFAULT_PROJECTOR_FOCAL = 1309.7183169905145  # px
DEFAULT_PROJECTOR_ROLL = -0.02250633517859773  # rad (-1.29 deg)


def rotation(axis: str, angle: float) -> np.ndarray:
    """(3, 3) float64 right-handed rotation by ``angle`` rad about the coordinate axis ``"x"``, ``"y"``
    or ``"z"`` (the one helper for fit-rig, rig jitter and scene placement)."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if axis == "z":
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    raise InputError(f"rotation axis must be x, y or z, got {axis!r}")


def projector_for(camera: Device, yaw: float = 0.0, focal: float = 1208.8, baseline: float = 180.0,
                  height: float = 500.0, width: int = 912, rows: int = 1140, roll: float = 0.0) -> Device:
    """A projector at ``(baseline, 0, height)`` mm looking down, turned ``yaw`` rad about its own y axis
    (positive: its axis leans towards -x, the scene), then ``roll`` rad about its optical axis (tilts
    the fringes; as :func:`fppsim.fitting.fit_periods.adjust_rig` applies it), principal point shifted so the world
    origin lands in the middle of the DMD (lens shift, as DLP projectors have)."""
    R = rotation("z", float(roll)) @ rotation("y", float(yaw)) @ np.diag([1.0, -1.0, -1.0])
    t = -R @ np.array([float(baseline), 0.0, float(height)])
    z = t[2]  # the world origin in the projector frame is t
    cx = (width - 1) / 2 - focal * t[0] / z
    cy = (rows - 1) / 2 - focal * t[1] / z
    return Device(K=[[focal, 0, cx], [0, focal, cy], [0, 0, 1]], R=R, t=t, width=width, height=rows)


def make_parallel_rig() -> Rig:
    """The ideal parallel-axis rig: camera 500 mm above the plane, fx = fy = 1230 px, 640 x 352;
    projector 180 mm to the +x side at the same height, 912 x 1140, fx = fy = 1208.8 px, lens shift so
    the scene centre lands mid-projector. 80 periods give a uniform 11.6 px period on the plane (the
    classic reference-plane formula is exact for it)."""
    cam = Device.looking_down([0.0, 0.0, 500.0], 1230.0, 1230.0, 319.5, 175.5, 640, 352)
    return Rig(camera=cam, projector=projector_for(cam), periods=80.0, name="parallel axes, projector lens shift")


def make_default_rig() -> Rig:
    """Build the default rig (what assets/default_rig.json holds): :func:`make_figshare_like_rig`, the
    rig fitted to the real figshare data (period trend and height sensitivity). The former default,
    :func:`make_parallel_rig`, is ``assets/parallel_rig.json``."""
    rig = make_figshare_like_rig()
    rig.name = "default: " + rig.name
    return rig


def make_figshare_like_rig() -> Rig:
    """Build the figshare-like rig (what assets/figshare_like_rig.json holds; ``--rig`` it).

    Like the real figshare rig: the projector ``DEFAULT_BASELINE`` (330 mm) to the +x side at the
    camera's height, turned by ``DEFAULT_PROJECTOR_YAW`` (4.30 deg) towards the scene, ``fx = fy =
    DEFAULT_PROJECTOR_FOCAL``, rolled by ``DEFAULT_PROJECTOR_ROLL`` (-1.29 deg) about its axis, lens
    shift so the scene centre lands mid-projector. The plane's fringe period falls from 12.06 px (left
    quarter) to 11.40 px (right quarter), 11.95 px in the left half and 11.51 px in the right half,
    with no trend down the image; the fringe lines lean by -1.34 deg (8.6 px over the 352 rows) as the
    real ones do; a raised surface shifts the phase by about -0.87 rad per mm at the image centre (one
    period per 7.2 mm).
    """
    cam = Device.looking_down([0.0, 0.0, 500.0], 1230.0, 1230.0, 319.5, 175.5, 640, 352)
    proj = projector_for(cam, yaw=DEFAULT_PROJECTOR_YAW, focal=DEFAULT_PROJECTOR_FOCAL, baseline=DEFAULT_BASELINE,
                         roll=DEFAULT_PROJECTOR_ROLL)
    return Rig(camera=cam, projector=proj, periods=80.0,
               name="figshare-like (330 mm baseline, projector yawed 4.30 deg, rolled -1.29 deg), lens shift")
