"""Sculpture-like meshes that the project generates itself.

The public figshare FPP dataset shows small plaster sculptures (busts, figurines, masks, vases,
animals, reliefs) lying on a reference plane.  This module builds look-alikes from a seed, so the
repository ships no third-party mesh files:

- implicit "blobby" figures: a few ellipsoids and capsules joined with a smooth minimum
  (plus smooth subtraction for eye sockets and mouths), sampled on a grid and meshed with
  ``skimage.measure.marching_cubes`` (``bust``, ``figurine``, ``animal``, ``mask``, ``blob``);
- a bas-relief: a height field with bumps, ridges and a border on a rectangular plate (``relief``);
- a lathe: a fluted vase revolved from a seeded profile and laid on its side (``vase``).

Conventions (shared by every shape):

- millimetres; the largest extent is drawn from ``size_mm`` (default 70-110 mm);
- +z is the direction the sculpture's front faces (towards the camera); the mesh rests on z = 0
  (its minimum z is exactly 0) and its bounding box is centred on x = y = 0;
- meshes are closed (watertight), consistently wound with outward normals (positive volume), and have
  5k-30k faces.  ``make_shape(kind, seed)`` is deterministic: the same arguments give the same arrays.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh
from fppsim.errors import InputError

__all__ = ["SHAPES", "make_shape", "procedural", "add_detail", "PROCEDURAL_KINDS", "bust", "figurine", "animal", "mask", "blob", "relief", "vase"]

DEFAULT_SIZE_MM = (70.0, 110.0)
TARGET_FACES = 16000
MAX_FACES = 30000
MIN_FACES = 5000


# --------------------------------------------------------------------------- signed distance pieces


def _rotation(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation matrix R = Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    cy, sy = np.cos(pitch), np.sin(pitch)
    cx, sx = np.cos(roll), np.sin(roll)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return rz @ ry @ rx


def _norm(q: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", q, q))


class _Ellipsoid:
    """Approximate signed distance of an (optionally rotated) ellipsoid."""

    def __init__(self, center, radii, rot=None):
        self.c = np.asarray(center, float)
        self.r = np.asarray(radii, float)
        self.rot = np.eye(3) if rot is None else np.asarray(rot, float)
        self.reach = float(self.r.max())

    def __call__(self, p: np.ndarray) -> np.ndarray:
        q = (p - self.c) @ self.rot  # world -> local: R^T (p - c)
        k0 = _norm(q / self.r)
        k1 = _norm(q / (self.r * self.r))
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)

    def bounds(self):
        return self.c - self.reach, self.c + self.reach


class _Capsule:
    """Exact signed distance of a capsule (segment a-b, radius r)."""

    def __init__(self, a, b, r):
        self.a = np.asarray(a, float)
        self.b = np.asarray(b, float)
        self.r = float(r)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        ab = self.b - self.a
        t = np.clip(((p - self.a) @ ab) / float(ab @ ab), 0.0, 1.0)
        d = p - self.a - t[..., None] * ab
        return _norm(d) - self.r

    def bounds(self):
        lo = np.minimum(self.a, self.b) - self.r
        hi = np.maximum(self.a, self.b) + self.r
        return lo, hi


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union) with blend radius k."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth maximum (smooth intersection / subtraction) with blend radius k."""
    return -_smin(-a, -b, k)


def _sub_grid(axes, lo, hi, margin):
    """Slices of the grid ``axes`` inside the box [lo - margin, hi + margin] and its points (..., 3)."""
    sl = []
    for a, l, h in zip(axes, lo, hi):
        i0 = int(np.searchsorted(a, l - margin, side="left"))
        i1 = int(np.searchsorted(a, h + margin, side="right"))
        if i1 <= i0:
            return None, None
        sl.append(slice(i0, i1))
    sub = [a[s] for a, s in zip(axes, sl)]
    return tuple(sl), np.stack(np.meshgrid(*sub, indexing="ij"), axis=-1)


class _Figure:
    """An implicit solid: smooth union of parts, smooth subtraction of cuts, optional flat base."""

    def __init__(self, blend: float, floor: float | None = None, floor_blend: float = 1.0):
        self.parts: list[tuple[object, float]] = []
        self.cuts: list[tuple[object, float]] = []
        self.blend = blend
        self.floor = floor
        self.floor_blend = floor_blend

    def add(self, prim, blend: float | None = None) -> "_Figure":
        self.parts.append((prim, self.blend if blend is None else blend))
        return self

    def cut(self, prim, blend: float = 2.0) -> "_Figure":
        self.cuts.append((prim, blend))
        return self

    def grid(self, axes) -> np.ndarray:
        """Field values on the grid ``axes`` (x, y, z coordinate vectors), shape (nx, ny, nz).

        Each primitive is evaluated only inside its bounding box grown by twice its blend radius
        (plus a small margin); outside it cannot change the sign of the field or its values near
        the surface, which is all marching cubes uses.  This makes meshing several times faster.
        """
        shape = tuple(len(a) for a in axes)
        big = 4.0 * max(float(a[-1] - a[0]) for a in axes) + 1.0
        d = np.full(shape, big)
        for prim, k in self.parts:
            sl, pts = _sub_grid(axes, *prim.bounds(), 2.0 * k + 1.0)
            if sl is not None:
                d[sl] = _smin(d[sl], prim(pts), k)
        for prim, k in self.cuts:
            sl, pts = _sub_grid(axes, *prim.bounds(), 2.0 * k + 1.0)
            if sl is not None:
                d[sl] = _smax(d[sl], -prim(pts), k)
        if self.floor is not None:
            k = self.floor_blend
            nz = int(np.searchsorted(axes[2], self.floor + 2.0 * k + 1.0, side="right"))
            z = axes[2][:nz]
            d[:, :, :nz] = _smax(d[:, :, :nz], np.broadcast_to(self.floor - z, d[:, :, :nz].shape), k)
        return d

    def bounds(self):
        lo = np.min([prim.bounds()[0] for prim, _ in self.parts], axis=0)
        hi = np.max([prim.bounds()[1] for prim, _ in self.parts], axis=0)
        if self.floor is not None:
            lo[2] = max(lo[2], self.floor)
        return lo, hi


# --------------------------------------------------------------------------- meshing helpers


def _march(fig: "_Figure", lo, hi, spacing: float) -> trimesh.Trimesh:
    """Mesh the zero level set of ``fig`` (negative inside) on a padded grid."""
    from skimage.measure import marching_cubes

    lo = np.asarray(lo, float) - 3.0 * spacing
    hi = np.asarray(hi, float) + 3.0 * spacing
    n = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[i] + spacing * np.arange(n[i]) for i in range(3)]
    values = fig.grid(axes).astype(np.float32)
    # the padding must lie outside the solid, or the surface would be open
    values[[0, -1], :, :] = np.maximum(values[[0, -1], :, :], spacing)
    values[:, [0, -1], :] = np.maximum(values[:, [0, -1], :], spacing)
    values[:, :, [0, -1]] = np.maximum(values[:, :, [0, -1]], spacing)
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=(spacing,) * 3, allow_degenerate=False)
    mesh = trimesh.Trimesh(verts + lo, faces, process=True)
    return _clean(mesh)


def _clean(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Drop degenerate/duplicate faces, keep the largest closed component, orient outwards."""
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: (abs(m.volume), len(m.faces)))
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _mesh_implicit(fig: _Figure, target_faces: int = TARGET_FACES) -> trimesh.Trimesh:
    """Marching cubes with a grid spacing chosen so the mesh has about ``target_faces`` faces."""
    lo, hi = fig.bounds()
    extent = float(np.max(hi - lo))
    coarse = extent / 40.0
    m = _march(fig, lo, hi, coarse)
    # faces scale as area / spacing^2: predict the spacing for the target from the coarse pass
    spacing = coarse * np.sqrt(len(m.faces) / float(target_faces))
    return _march(fig, lo, hi, spacing)


def _finish(mesh: trimesh.Trimesh, rng: np.random.Generator, size_mm) -> trimesh.Trimesh:
    """Scale to the drawn size, rest on z = 0, centre x and y; fixed vertex precision."""
    size = float(rng.uniform(*size_mm)) if np.ndim(size_mm) else float(size_mm)
    v = np.asarray(mesh.vertices, float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])) * (size / float(np.max(hi - lo)))
    out = trimesh.Trimesh(v, np.asarray(mesh.faces), process=False)
    if out.volume < 0:
        out.invert()
    return out


# --------------------------------------------------------------------------- implicit sculptures
# Nominal build units are arbitrary (about 100 across); _finish rescales to millimetres.


def bust(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Head-and-shoulders bust lying on its back, face up (+z), head towards +y."""
    rng = np.random.default_rng([seed, 1])
    j = lambda s=0.1: 1.0 + rng.uniform(-s, s)  # noqa: E731 - proportion jitter
    fig = _Figure(blend=6.0, floor=0.0, floor_blend=2.0)
    hw, hl, hd = 17 * j(), 22 * j(), 19 * j()  # head half-width, half-length, half-depth
    hy = 28.0
    fig.add(_Ellipsoid([0, hy, 14], [hw, hl, hd], _rotation(roll=rng.uniform(-0.15, 0.15))))
    fig.add(_Capsule([0, 2, 12], [0, 14, 13], 9 * j()))  # neck
    sw = 40 * j()
    fig.add(_Ellipsoid([0, -12, 10], [sw, 17 * j(), 13 * j()]), blend=10.0)  # shoulders / chest
    fig.add(_Ellipsoid([0, -28, 7], [sw * 0.75, 10, 9]), blend=8.0)  # lower chest
    fig.add(_Capsule([0, hy + 3, 14 + hd], [0, hy - 6, 14 + hd + 4.5 * j()], 2.6 * j()), blend=2.5)  # nose
    fig.add(_Ellipsoid([0, hy + 8, 14 + hd * 0.72], [hw * 0.65, 3.5, 3.0]), blend=5.0)  # brow
    fig.add(_Ellipsoid([0, hy - 18, 14 + hd * 0.62], [5.0, 4.0, 3.5]), blend=5.0)  # chin
    fig.add(_Ellipsoid([0, hy - 8.2, 14 + hd * 0.93], [3.8, 1.3, 1.5]), blend=1.5)  # upper lip
    fig.add(_Ellipsoid([0, hy - 10.8, 14 + hd * 0.9], [3.4, 1.3, 1.5]), blend=1.5)  # lower lip
    for s in (-1, 1):
        fig.add(_Ellipsoid([s * hw, hy, 14], [2.2, 5.5, 3.5]), blend=2.0)  # ears
        fig.cut(_Ellipsoid([s * 6.5, hy + 4, 14 + hd + 1.0], [3.8, 2.4, 3.5]), blend=2.5)  # eye sockets
    fig.cut(_Capsule([-3.5, hy - 9.5, 14 + hd + 0.6], [3.5, hy - 9.5, 14 + hd + 0.6], 0.7), blend=0.8)  # mouth
    if rng.random() < 0.6:  # hair bun / cap
        fig.add(_Ellipsoid([0, hy + hl * 0.8, 16], [hw * 0.8, 8 * j(), hd * 0.7]), blend=5.0)
    return _finish(_mesh_implicit(fig), rng, size_mm)


def figurine(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Standing figure lying on its back (front up), head towards +y, limbs in a seeded pose."""
    rng = np.random.default_rng([seed, 2])
    j = lambda s=0.12: 1.0 + rng.uniform(-s, s)  # noqa: E731
    fig = _Figure(blend=5.0, floor=0.0, floor_blend=1.5)
    z = 9.0
    fig.add(_Ellipsoid([0, 8, z], [12 * j(), 18 * j(), 8 * j()]))  # torso
    fig.add(_Ellipsoid([0, -10, z], [13 * j(), 9, 8]))  # hips
    fig.add(_Ellipsoid([0, 37, z + 1], [8 * j(), 9.5 * j(), 8.5 * j()]), blend=4.0)  # head
    fig.add(_Capsule([0, 24, z], [0, 30, z], 4.0), blend=3.0)  # neck
    for s in (-1, 1):
        sh = np.array([s * 11.0, 22.0, z])
        a = rng.uniform(0.15, 1.3)  # arm angle away from the body
        elbow = sh + 15 * j() * np.array([s * np.sin(a), -np.cos(a), 0.0])
        b = a + rng.uniform(-0.9, 0.9)
        hand = elbow + 14 * j() * np.array([s * np.sin(b), -np.cos(b), rng.uniform(-0.2, 0.4)])
        fig.add(_Capsule(sh, elbow, 3.6), blend=3.0)
        fig.add(_Capsule(elbow, hand, 3.0), blend=2.0)
        fig.add(_Ellipsoid(hand, [3.5, 3.5, 3.0]), blend=1.5)
        hip = np.array([s * 6.0, -14.0, z])
        c = rng.uniform(0.0, 0.35)
        knee = hip + 20 * j() * np.array([s * np.sin(c), -np.cos(c), 0.0])
        d = rng.uniform(-0.2, 0.2)
        ankle = knee + 19 * j() * np.array([s * np.sin(d), -np.cos(d), 0.0])
        fig.add(_Capsule(hip, knee, 5.0), blend=3.0)
        fig.add(_Capsule(knee, ankle, 3.8), blend=2.0)
        fig.add(_Ellipsoid(ankle + [0, -1, 3.5], [3.5, 3.0, 5.5]), blend=2.0)  # feet point up (+z)
    fig.add(_Ellipsoid([0, 37, z + 9.0], [2.0, 3.5, 2.5]), blend=2.0)  # nose
    return _finish(_mesh_implicit(fig), rng, size_mm)


def animal(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Four-legged animal lying on its side (profile up, +z), head towards +x."""
    rng = np.random.default_rng([seed, 3])
    j = lambda s=0.15: 1.0 + rng.uniform(-s, s)  # noqa: E731
    fig = _Figure(blend=6.0, floor=0.0, floor_blend=1.0)
    leg_h = 18 * j(0.3)
    bz = leg_h + 10
    bl, bw, bh = 30 * j(), 13 * j(), 12 * j()
    fig.add(_Ellipsoid([0, 0, bz], [bl, bw, bh], _rotation(pitch=rng.uniform(-0.1, 0.1))))  # body
    neck_top = np.array([bl * 0.95, 0, bz + 14 * j()])
    fig.add(_Capsule([bl * 0.6, 0, bz + 2], neck_top, 6.5 * j()), blend=5.0)  # neck
    head_c = neck_top + [6, 0, 2]
    fig.add(_Ellipsoid(head_c, [10 * j(), 7 * j(), 7 * j()], _rotation(pitch=0.3)), blend=4.0)  # head
    fig.add(_Ellipsoid(head_c + [9, 0, -3], [6 * j(), 4.5, 4.0]), blend=3.0)  # snout
    for s in (-1, 1):
        fig.add(_Ellipsoid(head_c + [-3, s * 5, 7], [2.0, 2.5, 5.0 * j(0.4)], _rotation(roll=s * 0.4)), blend=2.0)
        for xl in (bl * 0.6, -bl * 0.6):
            top = np.array([xl, s * bw * 0.55, bz - 2])
            foot = np.array([xl + rng.uniform(-4, 4), s * bw * 0.6, 2.5])
            fig.add(_Capsule(top, foot, 4.2 * j(0.1)), blend=4.0)
            fig.add(_Ellipsoid(foot + [1.5, 0, -1.0], [5.0, 4.0, 3.0]), blend=2.0)
    tail_end = np.array([-bl - 14 * j(), rng.uniform(-6, 6), bz + rng.uniform(-10, 10)])
    fig.add(_Capsule([-bl * 0.9, 0, bz + 3], tail_end, 2.4), blend=3.0)
    mesh = _mesh_implicit(fig)  # built standing, flat soles at z = 0
    side = np.eye(4)
    side[:3, :3] = _rotation(roll=-np.pi / 2)  # +z (up) -> +y, its side faces the camera
    mesh.apply_transform(side)
    return _finish(mesh, rng, size_mm)


def mask(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Face mask: a domed oval with brow, nose, lips and eye sockets, flat back on the plane."""
    rng = np.random.default_rng([seed, 4])
    j = lambda s=0.1: 1.0 + rng.uniform(-s, s)  # noqa: E731
    fig = _Figure(blend=4.0, floor=0.0, floor_blend=1.5)
    w, l, d = 34 * j(), 44 * j(), 22 * j()
    fig.add(_Ellipsoid([0, 0, -4], [w, l, d]))  # face dome, cut flat by the floor
    fig.add(_Ellipsoid([0, 13, d - 7], [w * 0.7, 5, 4.5]), blend=8.0)  # brow ridge
    nose_len = 16 * j()
    fig.add(_Capsule([0, 10, d - 5], [0, 10 - nose_len, d + 3 * j()], 3.5 * j()), blend=4.0)  # nose
    fig.add(_Ellipsoid([0, 10 - nose_len, d], [6, 3, 3.5]), blend=2.5)  # nostrils
    fig.add(_Ellipsoid([0, -14, d - 5.5], [8 * j(), 2.6, 3.0]), blend=2.0)  # upper lip
    fig.add(_Ellipsoid([0, -19, d - 6.5], [7 * j(), 2.6, 3.0]), blend=2.0)  # lower lip
    fig.add(_Ellipsoid([0, -31, d - 12], [9, 6, 5]), blend=4.0)  # chin
    for s in (-1, 1):
        fig.add(_Ellipsoid([s * 17, -6, d - 9], [8, 9, 5]), blend=6.0)  # cheeks
        fig.cut(_Ellipsoid([s * 11.5, 6, d - 1], [6.5 * j(), 4.0, 5.0]), blend=3.0)  # eye sockets
        fig.add(_Ellipsoid([s * 11.5, 5.5, d - 6], [3.5, 2.5, 2.5]), blend=1.5)  # eyeballs
    fig.cut(_Capsule([-5.5, -16.5, d - 3], [5.5, -16.5, d - 3], 1.1), blend=1.0)  # mouth line
    return _finish(_mesh_implicit(fig), rng, size_mm)


def blob(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Abstract sculpture: 4-8 random ellipsoids and capsules melted together, flat base."""
    rng = np.random.default_rng([seed, 5])
    fig = _Figure(blend=10.0, floor=0.0, floor_blend=2.0)
    n = int(rng.integers(4, 9))
    centers = [np.array([0.0, 0.0, 12.0])]
    for _ in range(n):
        base = centers[int(rng.integers(len(centers)))]
        c = base + rng.normal(0, 1, 3) * [14, 14, 8]
        c[2] = abs(c[2]) + 4
        if rng.random() < 0.7:
            radii = rng.uniform(6, 18, 3)
            fig.add(_Ellipsoid(c, radii, _rotation(*rng.uniform(-np.pi, np.pi, 3))))
        else:
            fig.add(_Capsule(base, c, rng.uniform(4, 8)))
        centers.append(c)
    fig.add(_Ellipsoid(centers[0], [15, 15, 12]))
    return _finish(_mesh_implicit(fig), rng, size_mm)


# --------------------------------------------------------------------------- explicit constructions


def _closed_heightfield(x: np.ndarray, y: np.ndarray, h: np.ndarray) -> trimesh.Trimesh:
    """Closed solid: top surface z = h[i, j] over the grid (x[j], y[i]), vertical walls, flat bottom z = 0."""
    ny, nx = h.shape
    xx, yy = np.meshgrid(x, y)
    top = np.column_stack([xx.ravel(), yy.ravel(), h.ravel()])
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = [np.column_stack([a, b, c]), np.column_stack([a, c, d])]
    # boundary loop of the top grid, counter-clockwise seen from +z
    ring = np.concatenate([idx[0, :-1], idx[:-1, -1], idx[-1, :0:-1], idx[:0:-1, 0]])
    nt = len(top)
    bottom = top[ring].copy()
    bottom[:, 2] = 0.0
    center = np.array([[x.mean(), y.mean(), 0.0]])
    m = len(ring)
    k = np.arange(m)
    k1 = (k + 1) % m
    tb, bb, ctr = ring, nt + k, nt + m
    faces.append(np.column_stack([tb[k], bb[k], bb[k1]]))  # walls
    faces.append(np.column_stack([tb[k], bb[k1], tb[k1]]))
    faces.append(np.column_stack([np.full(m, ctr), bb[k1], bb[k]]))  # bottom fan
    verts = np.vstack([top, bottom, center])
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def relief(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Bas-relief plaque: a plate with a raised rim and a seeded composition of bumps and ridges."""
    rng = np.random.default_rng([seed, 6])
    W, L = 100.0, 100.0 * rng.uniform(0.65, 0.9)
    nx = 104
    ny = int(round(nx * L / W))
    x = np.linspace(-W / 2, W / 2, nx)
    y = np.linspace(-L / 2, L / 2, ny)
    X, Y = np.meshgrid(x, y)
    h = np.full_like(X, 4.0)
    # raised rim, smooth profile
    edge = np.minimum(W / 2 - np.abs(X), L / 2 - np.abs(Y))
    h += 3.0 * np.exp(-(((edge - 4.0) / 2.2) ** 2))
    inner = 1.0 / (1.0 + np.exp(-(edge - 8.0) / 1.0))  # 0 at the rim, 1 inside
    relief_h = np.zeros_like(X)
    for _ in range(int(rng.integers(4, 8))):  # rounded, flat-topped masses (bodies, heads)
        cx, cy = rng.uniform(-0.3, 0.3) * W, rng.uniform(-0.3, 0.3) * L
        sx, sy = rng.uniform(5, 15, 2)
        t = rng.uniform(0, np.pi)
        u = (X - cx) * np.cos(t) + (Y - cy) * np.sin(t)
        v = -(X - cx) * np.sin(t) + (Y - cy) * np.cos(t)
        q = (u / sx) ** 2 + (v / sy) ** 2
        relief_h += rng.uniform(5, 12) * np.exp(-0.5 * q * q)
    for _ in range(int(rng.integers(2, 5))):  # ridges (limbs, folds): soft tubes along segments
        p0 = rng.uniform(-0.35, 0.35, 2) * [W, L]
        p1 = p0 + rng.normal(0, 18, 2)
        ab = p1 - p0
        t = np.clip(((X - p0[0]) * ab[0] + (Y - p0[1]) * ab[1]) / (ab @ ab), 0, 1)
        dist = np.hypot(X - p0[0] - t * ab[0], Y - p0[1] - t * ab[1])
        relief_h += rng.uniform(3, 7) * np.exp(-0.5 * (dist / rng.uniform(2.0, 3.5)) ** 2)
    for _ in range(int(rng.integers(1, 3))):  # incised grooves
        p0 = rng.uniform(-0.35, 0.35, 2) * [W, L]
        p1 = p0 + rng.normal(0, 20, 2)
        ab = p1 - p0
        t = np.clip(((X - p0[0]) * ab[0] + (Y - p0[1]) * ab[1]) / (ab @ ab), 0, 1)
        dist = np.hypot(X - p0[0] - t * ab[0], Y - p0[1] - t * ab[1])
        relief_h -= 2.0 * np.exp(-0.5 * (dist / 1.2) ** 2)
    # soft saturation keeps the relief low (bas-relief) and smooth
    relief_h = 16.0 * np.tanh(relief_h / 16.0)
    h = np.maximum(h + relief_h * inner, 1.0)
    return _finish(_closed_heightfield(x, y, h), rng, size_mm)


def vase(seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Fluted vase revolved from a seeded profile, lying on its side (axis along x)."""
    rng = np.random.default_rng([seed, 7])
    n_theta, n_z = 96, 84
    H = 100.0
    s = np.linspace(0.0, 1.0, n_z)
    # profile: foot, belly, neck, lip; radii in build units
    belly = rng.uniform(0.3, 0.6)
    r = (
        10.0
        + rng.uniform(14, 22) * np.exp(-(((s - belly) / rng.uniform(0.18, 0.3)) ** 2))
        + rng.uniform(3, 8) * np.exp(-(((s - 0.97) / 0.05) ** 2))  # lip
        - rng.uniform(2, 5) * np.exp(-(((s - 0.85) / 0.08) ** 2))  # neck
        + 3.0 * np.exp(-(((s - 0.02) / 0.04) ** 2))  # foot ring
    )
    theta = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    k = int(rng.integers(6, 13))
    flute = 1.0 + rng.uniform(0.0, 0.05) * np.cos(k * theta)[None, :] * np.sin(np.pi * s)[:, None]
    R = r[:, None] * flute
    ring = np.stack([R * np.cos(theta), R * np.sin(theta), np.broadcast_to(s[:, None] * H, R.shape)], axis=-1)
    verts = np.vstack([ring.reshape(-1, 3), [[0.0, 0.0, 0.0]], [[0.0, 0.0, H]]])
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), nxt[:-1].ravel(), nxt[1:].ravel(), idx[1:].ravel()
    bot, top = n_z * n_theta, n_z * n_theta + 1
    faces = np.vstack(
        [
            np.column_stack([a, b, c]),
            np.column_stack([a, c, d]),
            np.column_stack([np.full(n_theta, bot), nxt[0], idx[0]]),
            np.column_stack([np.full(n_theta, top), idx[-1], nxt[-1]]),
        ]
    )
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    # lay it on its side: vase axis (z) -> x, with a random roll about the axis
    rot = np.eye(4)
    rot[:3, :3] = _rotation(roll=rng.uniform(0, 2 * np.pi)) @ _rotation(pitch=np.pi / 2)
    mesh.apply_transform(rot)
    return _finish(mesh, rng, size_mm)


# --------------------------------------------------------------------------- registry

_REGISTRY: dict[str, Callable[..., trimesh.Trimesh]] = {
    "bust": bust,
    "figurine": figurine,
    "animal": animal,
    "mask": mask,
    "relief": relief,
    "vase": vase,
    "blob": blob,
}
SHAPES: list[str] = list(_REGISTRY)


def make_shape(kind: str, seed: int = 0, size_mm=DEFAULT_SIZE_MM) -> trimesh.Trimesh:
    """Build a sculpture-like watertight mesh in millimetres.

    kind: one of ``SHAPES``; seed: any non-negative int (same seed, same mesh); size_mm: the largest
    extent in mm, a number or a (low, high) range drawn from the seed.
    """
    try:
        fn = _REGISTRY[kind]
    except KeyError:
        raise InputError(f"unknown shape kind {kind!r}; choose one of {', '.join(SHAPES)}") from None
    if int(seed) < 0:
        raise InputError(f"seed must be non-negative, got {seed}")
    return fn(int(seed), size_mm=size_mm)


# --------------------------------------------------------------------------- unlimited procedural source

# Kinds drawn by :func:`procedural` and their weights: busts dominate, as in the real figshare data.
PROCEDURAL_KINDS: tuple[tuple[str, float], ...] = (
    ("bust", 0.30), ("mask", 0.10), ("figurine", 0.10), ("animal", 0.15), ("relief", 0.10), ("vase", 0.10),
    ("blob", 0.15),
)
# Surface detail: (wavelength mm, amplitude mm) of band-limited noise displacing the surface along its
# normals (folds, tool marks, hair and cloth texture), each amplitude drawn from [0.3, 1] x this.
DETAIL_SCALES: tuple[tuple[float, float], ...] = ((12.0, 1.2), (5.0, 0.5), (2.0, 0.15))


def _noise_field(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, wavelength: float):
    """A smooth zero-mean, unit-std random field on the box [lo, hi] (mm) with the given wavelength,
    returned as a function of (N, 3) points (trilinear interpolation of a filtered white-noise grid)."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    step = wavelength / 4.0
    n = np.maximum(np.ceil((hi - lo) / step).astype(int) + 9, 9)
    g = gaussian_filter(rng.standard_normal(tuple(n)), sigma=wavelength / (2.0 * np.pi * step) * 2.0, mode="wrap")
    g = (g - g.mean()) / (g.std() + 1e-12)
    origin = lo - 4 * step

    def field(points: np.ndarray) -> np.ndarray:
        idx = ((points - origin) / step).T
        return map_coordinates(g, idx, order=1, mode="nearest")

    return field


def add_detail(mesh: trimesh.Trimesh, rng: np.random.Generator,
               scales: tuple[tuple[float, float], ...] = DETAIL_SCALES) -> trimesh.Trimesh:
    """Displace the vertices along their normals by multi-scale band-limited noise (mm).

    Only the part of the surface facing up (normal z > -0.2) is displaced, so the flat base on the
    plane stays flat; the displacement fades out near the base. Topology (and watertightness) is kept.
    """
    v = np.asarray(mesh.vertices, float)
    nrm = np.asarray(mesh.vertex_normals, float)
    lo, hi = v.min(0), v.max(0)
    disp = np.zeros(len(v))
    for wavelength, amp in scales:
        a = amp * float(rng.uniform(0.3, 1.0))
        disp += a * _noise_field(rng, lo, hi, wavelength)(v)
    fade = np.clip((v[:, 2] - lo[2]) / 3.0, 0.0, 1.0) * np.clip((nrm[:, 2] + 0.2) / 0.4, 0.0, 1.0)
    out = trimesh.Trimesh(v + (disp * fade)[:, None] * nrm, np.asarray(mesh.faces), process=False)
    return out


def procedural(seed: int, size_mm=DEFAULT_SIZE_MM, detail: bool = True) -> tuple[str, trimesh.Trimesh]:
    """One sculpture of an unlimited seeded family: ``(kind, mesh)``.

    The seed picks a kind (weights :data:`PROCEDURAL_KINDS`), that kind's own seed, a non-uniform
    stretch of its proportions (x, y by 0.8-1.25, z by 0.8-1.45: taller sculptures too) and, with
    ``detail``, surface detail at three scales (:func:`add_detail`). Deterministic in ``seed``.
    """
    if int(seed) < 0:
        raise InputError(f"seed must be non-negative, got {seed}")
    rng = np.random.default_rng([int(seed), 99])
    kinds, weights = zip(*PROCEDURAL_KINDS)
    kind = kinds[int(rng.choice(len(kinds), p=np.asarray(weights) / np.sum(weights)))]
    mesh = _REGISTRY[kind](int(rng.integers(0, 2**31 - 1)), size_mm=100.0)
    stretch = np.array([rng.uniform(0.8, 1.25), rng.uniform(0.8, 1.25), rng.uniform(0.8, 1.45)])
    mesh = trimesh.Trimesh(np.asarray(mesh.vertices) * stretch, np.asarray(mesh.faces), process=False)
    if detail:
        mesh = add_detail(mesh, rng)
    return kind, _finish(mesh, rng, size_mm)


# The meshes shipped in assets/meshes (written by pipelines/make_assets.py): (kind, seed) pairs.
ASSETS: tuple[tuple[str, int], ...] = (
    ("bust", 0),
    ("figurine", 0),
    ("animal", 0),
    ("mask", 0),
    ("relief", 0),
    ("vase", 0),
)


def asset_name(kind: str, seed: int) -> str:
    """File name of a shipped shape: ``<kind>_s<seed>.ply``."""
    return f"{kind}_s{int(seed)}.ply"


def export_ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    """Binary little-endian PLY (float32 vertices, no normals or colours): same mesh, same bytes."""
    from trimesh.exchange.ply import export_ply

    return export_ply(mesh, encoding="binary", vertex_normal=False, include_attributes=False)
