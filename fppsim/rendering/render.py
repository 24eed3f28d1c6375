"""Off-screen depth rendering (pyrender on OSMesa) and exact per-pixel geometry.

Only the objects are rasterised; the reference plane z = 0 is intersected analytically in float64, so
background pixels are exact and the depth buffer range stays tight around the objects.

Per camera pixel (optionally on a k x k supersampled grid, k odd so sub-pixel centres include the
pixel centres) :func:`scene_geometry` returns the first surface seen, its world point and normal, the
projector coordinates of that point, whether the projector lights it (inside the projector image, not
shadowed, facing it) and the incidence cosine.
"""

from __future__ import annotations

import sys
import os
from concurrent.futures import wait
from dataclasses import dataclass, field

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
BACKENDS = ("osmesa", "egl")

import numpy as np

from fppsim.threads import beside
from fppsim.errors import BackendError, InputError
from fppsim.geometry.rig import Device, along_rays

__all__ = ["BACKENDS", "BackendError", "DepthRenderer", "Geometry", "Instance", "scene_geometry", "ShadowSettings",
           "plane_geometry", "projector_incidence"]


@dataclass(frozen=True)
class Instance:
    """One mesh placed in the world: ``X_world = transform[:3, :3] @ v + transform[:3, 3]``.

    ``key`` identifies the vertex/face arrays (e.g. the mesh file) so renderers can keep them on the GL
    side between samples; ``None`` means "upload every time".
    """
    vertices: np.ndarray
    faces: np.ndarray
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    key: object = None

    @classmethod
    def world(cls, vertices, faces) -> "Instance":
        return cls(np.asarray(vertices, float), np.asarray(faces), np.eye(4), None)


_PARK = np.eye(4)
_PARK[2, 3] = 1e7  # far behind every device: a parked (hidden) node keeps its mesh on the GL side


def select_backend(backend: str | None = None) -> str:
    """Choose the process's GL platform (``osmesa`` or ``egl``) before OpenGL is imported.

    ``None`` keeps ``$PYOPENGL_PLATFORM`` (osmesa unless set). PyOpenGL binds its platform once per
    process, so asking for another one after the first render raises :class:`BackendError`.
    """
    current = os.environ.get("PYOPENGL_PLATFORM", "osmesa")
    backend = current if backend is None else backend
    if backend not in BACKENDS:
        raise BackendError(f"unknown GL backend '{backend}' (choose {' or '.join(BACKENDS)})")
    if backend != current and "OpenGL.GL" in sys.modules:
        raise BackendError(f"GL backend '{current}' is already in use in this process; "
                           f"choose --backend before anything renders")
    os.environ["PYOPENGL_PLATFORM"] = backend
    return backend


def _single_sample_framebuffer(offscreen) -> None:
    """Make pyrender's off-screen framebuffer single-sampled (EGL path).

    With framebuffer objects pyrender renders into a 4x multisampled buffer and blits its depth,
    which returns the depth of one sub-sample position instead of the pixel centre (up to a third of
    a pixel's depth slope off). Depth ground truth needs the pixel centre, as OSMesa's single-sampled
    window buffer gives, so allocate the "multisampled" buffers with 0 samples.
    """
    import pyrender.renderer as prr

    inner = offscreen._renderer
    configure = type(inner)._configure_main_framebuffer

    def single_sampled():
        original = prr.glRenderbufferStorageMultisample
        prr.glRenderbufferStorageMultisample = lambda target, samples, fmt, w, h: original(target, 0, fmt, w, h)
        try:
            configure(inner)
        finally:
            prr.glRenderbufferStorageMultisample = original

    inner._configure_main_framebuffer = single_sampled


def _keep_shader_programs(offscreen) -> None:
    """Make pyrender reuse its compiled shader programs (one GL context per off-screen renderer).

    pyrender keys its program cache by ``OpenGL.contextdata.getContext()``, which under OSMesa is a new
    ctypes pointer object on every call (hashed by identity): no lookup ever hits, so each draw call
    compiled and linked a fresh program (about 1-2 ms) and kept it until the renderer closed. This
    renderer owns one context, so the cache is keyed by shader files and defines alone; the programs
    are pyrender's own, compiled from the same sources, so the depth is unchanged.
    """
    from pyrender.shader_program import ShaderProgramCache

    class OneContextProgramCache(ShaderProgramCache):
        def __init__(self):
            super().__init__()
            self._by_source = {}

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            program = self._by_source.get(key)
            if program is None:
                program = super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)
                self._by_source[key] = program
            return program

        def clear(self):
            super().clear()
            self._by_source = {}

    inner = offscreen._renderer
    if getattr(inner, "_program_cache", None) is not None and not inner._program_cache._program_cache:
        inner._program_cache = OneContextProgramCache()


class DepthRenderer:
    """Reusable pyrender off-screen depth renderer.

    ``depth(device, instances, scale)`` returns the device-frame z-depth (mm, float64) of the first
    object surface for every pixel of ``device`` at ``scale``-times resolution, ``inf`` where no object is
    hit. Meshes with a key stay uploaded (a parked node keeps them in each scene), so a dataset's meshes
    are sent to GL once per renderer.

    ``backend``: ``osmesa`` (software, no display; the default) or ``egl`` (headless GPU rendering,
    or Mesa's software device where no GPU exists); None keeps ``$PYOPENGL_PLATFORM``. One backend
    per process (see :func:`select_backend`).
    """
    def __init__(self, backend: str | None = None):
        self.backend = select_backend(backend)
        # OSMesa has no resizable framebuffers: pyrender rebuilds the GL context on every size change,
        # so keep one renderer (and one scene: GL buffers are per context) per resolution.
        self._slots = {}
        self._bounds = {}

    def _corners(self, inst: Instance) -> np.ndarray:
        """(8, 3) bounding-box corners of the instance's vertices (kept per key: a min/max over a large
        mesh costs as much as a small render)."""
        if inst.key is not None and inst.key in self._bounds:
            return self._bounds[inst.key]
        lo, hi = inst.vertices.min(0), inst.vertices.max(0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        if inst.key is not None:
            self._bounds[inst.key] = corners
        return corners

    def _slot(self, width: int, height: int):
        import pyrender

        key = (width, height)
        if key not in self._slots:
            scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[0, 0, 0])
            try:
                offscreen = pyrender.OffscreenRenderer(width, height)
            except Exception as exc:
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                hint = ("needs libEGL with a GPU driver or Mesa's EGL (apt libegl1 libegl-mesa0 libgbm1)"
                        if self.backend == "egl" else "needs libOSMesa (apt libosmesa6)")
                raise BackendError(f"GL backend '{self.backend}' unavailable: {reason} ({hint}; "
                                   f"or try --backend {'osmesa' if self.backend == 'egl' else 'egl'})") from None
            if self.backend == "egl":
                _single_sample_framebuffer(offscreen)
            _keep_shader_programs(offscreen)
            self._slots[key] = (offscreen, scene, {})
        return self._slots[key]

    @staticmethod
    def _make_mesh(vertices, faces):
        import pyrender

        prim = pyrender.Primitive(positions=np.ascontiguousarray(vertices, dtype=np.float32),
                                  indices=np.ascontiguousarray(faces, dtype=np.uint32), mode=4)
        return pyrender.Mesh([prim])

    def depth(self, device, instances: list[Instance], scale: int = 1) -> np.ndarray:
        import pyrender

        fx, fy, cx, cy, W, H = device.gl_intrinsics(scale)
        # Tight clip range from the transformed bounding boxes keeps the depth buffer precise.
        zs = []
        for inst in instances:
            world = self._corners(inst) @ inst.transform[:3, :3].T + inst.transform[:3, 3]
            zs.append(world @ device.R[2] + device.t[2])
        zs = np.concatenate(zs) if zs else np.zeros(0)
        if zs.size == 0 or zs.max() <= 0:
            return np.full((H, W), np.inf)
        znear = max(float(zs[zs > 0].min()) * 0.9, 1e-3) if np.any(zs > 0) else 1e-3
        zfar = float(zs.max()) * 1.1 + 1.0
        renderer, scene, meshes = self._slot(W, H)
        # A keyed mesh lives in the scene on one parked, invisible node (so its GL buffers stay);
        # this render moves that node into place and shows it. Hidden meshes cost no draw call and no
        # vertex processing, however many meshes the dataset has.
        nodes, shown = [], []
        for inst in instances:
            if inst.key is None:
                nodes.append(scene.add(self._make_mesh(inst.vertices, inst.faces), pose=inst.transform))
                continue
            if inst.key not in meshes:
                mesh = self._make_mesh(inst.vertices, inst.faces)
                mesh.is_visible = False
                meshes[inst.key] = (mesh, scene.add(mesh, pose=_PARK))
            mesh, parked = meshes[inst.key]
            if mesh.is_visible:  # the same mesh twice in one scene: a second node
                nodes.append(scene.add(mesh, pose=inst.transform))
            else:
                scene.set_pose(parked, inst.transform)
                mesh.is_visible = True
                shown.append(mesh)
        cam = scene.add(pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=znear, zfar=zfar), pose=device.gl_pose())
        try:
            d = renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY | pyrender.RenderFlags.SKIP_CULL_FACES)
        finally:
            for node in nodes + [cam]:
                scene.remove_node(node)
            for mesh in shown:
                mesh.is_visible = False
        d = np.asarray(d, dtype=np.float64)
        return np.where(d > 0, d, np.inf)

    def close(self):
        for renderer, _, _ in self._slots.values():
            renderer.delete()
        self._slots.clear()


@dataclass
class ShadowSettings:
    """Depth-comparison bias of the projector shadow test: ``bias_mm + slope_pixels * |grad D|``."""
    bias_mm: float = 0.3
    slope_pixels: float = 1.0


@dataclass
class Geometry:
    """Exact geometry on the camera grid (H x W, or the supersampled grid). Units mm.

    depth : device z-depth of the first surface (inf where nothing is seen)
    points : (H, W, 3) world points; height = points[..., 2]
    normals : (H, W, 3) unit world normals facing the camera
    on_object : bool, the first surface is an object (not the reference plane)
    u_p, v_p : projector pixel coordinates (with projector distortion)
    lit : seen and lit by the projector (inside its image, not shadowed, facing it)
    cos_incidence : cosine between normal and direction to the projector (0 where not lit)
    falloff : projector irradiance per unit cos(incidence), 1 at the world origin
              (:meth:`fppsim.geometry.rig.Device.irradiance_falloff`: equal flux per projector pixel)
    """
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    on_object: np.ndarray
    u_p: np.ndarray
    v_p: np.ndarray
    lit: np.ndarray
    cos_incidence: np.ndarray
    falloff: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.depth)

    @property
    def height(self) -> np.ndarray:
        return np.where(self.seen, self.points[..., 2], 0.0)

    def cropped(self, rows: slice, cols: slice) -> "Geometry":
        """The geometry of an image window (e.g. without a rendering margin)."""
        return Geometry(**{k: getattr(self, k)[rows, cols] for k in self.__dataclass_fields__})

    def at_pixel_centres(self, scale: int) -> "Geometry":
        """Sub-sample a ``scale``-times supersampled geometry at the pixel centres (scale odd)."""
        if scale == 1:
            return self
        c = scale // 2
        return Geometry(**{k: getattr(self, k)[c::scale, c::scale] for k in self.__dataclass_fields__})


def _normals_from_points(P: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
    """Normals of a point map from one-sided differences that do not straddle depth edges.

    ``P`` (h, w, 3) float32 world points (NaN where nothing is seen); returns (h, w, 3) unit normals
    facing ``camera_center`` ((0, 0, 1) where undefined). Works on the three coordinate planes
    separately (contiguous arrays, no (h, w, 3) reductions); the arithmetic per element is the
    textbook ``(x*x + y*y) + z*z`` and cross product, in P's dtype.
    """
    X = [np.ascontiguousarray(P[..., i]) for i in range(3)]

    def steps(axis):
        """Forward and backward differences along ``axis``; the edge step is P - P (0, or NaN)."""
        fwd, bwd = [], []
        for c in X:
            d = np.diff(c, axis=axis)
            f, b = np.empty_like(c), np.empty_like(c)
            if axis == 1:
                f[:, :-1], b[:, 1:] = d, d
                f[:, -1] = c[:, -1] - c[:, -1]
                b[:, 0] = c[:, 0] - c[:, 0]
            else:
                f[:-1], b[1:] = d, d
                f[-1] = c[-1] - c[-1]
                b[0] = c[0] - c[0]
            fwd.append(f)
            bwd.append(b)
        return fwd, bwd

    def length(v):
        return np.sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2])

    def smaller_step(axis):
        fwd, bwd = steps(axis)
        fwd_n, bwd_n = length(fwd), length(bwd)
        fwd_n = np.where(np.isfinite(fwd_n) & (fwd_n > 0), fwd_n, np.inf)
        bwd_n = np.where(np.isfinite(bwd_n) & (bwd_n > 0), bwd_n, np.inf)
        take_fwd = fwd_n <= bwd_n
        return [np.where(take_fwd, f, b) for f, b in zip(fwd, bwd)]

    du, dv = smaller_step(1), smaller_step(0)
    n = [du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2], du[0] * dv[1] - du[1] * dv[0]]
    norm = length(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = [c / norm for c in n]
    to_cam = [camera_center[i] - X[i] for i in range(3)]
    flip = ((n[0] * to_cam[0] + n[1] * to_cam[1]) + n[2] * to_cam[2]) < 0
    out = np.empty(P.shape, dtype=n[0].dtype)
    for i, c in enumerate(n):
        np.negative(c, out=c, where=flip)
        out[..., i] = c
    bad = ~(np.isfinite(n[0]) & np.isfinite(n[1]) & np.isfinite(n[2]))
    out[bad] = (0.0, 0.0, 1.0)
    return out


class _GridCache:
    """Per-rig camera rays and plane depths (they do not change between samples)."""
    def __init__(self):
        self.key = None
        self.value = None

    def get(self, camera, scale):
        # by value: every sample builds its margin-expanded camera anew
        key = (camera.K.tobytes(), camera.R.tobytes(), camera.t.tobytes(), camera.dist.tobytes(),
               camera.width, camera.height, scale)
        if key != self.key:
            grid = camera.pixel_grid(scale)
            origin, dirs = camera.pixel_rays(grid)
            self.value = (origin, dirs, camera.plane_depth(grid))
            for a in self.value:
                a.setflags(write=False)  # shared between samples
            self.key = key
        return self.value


_GRID = _GridCache()


def _camera_side(cam, proj, obj_depth, origin, dirs, plane_depth):
    """Everything :func:`scene_geometry` derives from the camera's depth alone (points, normals,
    projector coordinates): computed on a helper thread while the projector's shadow map renders."""
    on_object = obj_depth < plane_depth
    depth = np.where(on_object, obj_depth, plane_depth)
    seen = np.isfinite(depth)
    all_seen = bool(seen.all())
    P = along_rays(origin, depth if all_seen else np.where(seen, depth, 0.0), dirs)
    if not all_seen:
        P[~seen] = np.nan
    P[..., 2] = np.where(on_object | ~seen, P[..., 2], 0.0)  # plane points exactly on z = 0

    # Plane normals are exact; object normals from the point map, only inside the objects' bounding box.
    normals = np.zeros(P.shape)
    normals[..., 2] = 1.0
    rows, cols = np.flatnonzero(on_object.any(1)), np.flatnonzero(on_object.any(0))
    if rows.size:
        box = (slice(max(rows[0] - 1, 0), rows[-1] + 2), slice(max(cols[0] - 1, 0), cols[-1] + 2))
        n_box = _normals_from_points(P[box].astype(np.float32), origin.astype(np.float32))
        obj, nb = on_object[box], normals[box]
        for i in range(3):  # = np.where(obj[..., None], n_box, normals[box]), one plane at a time
            np.copyto(nb[..., i], n_box[..., i], where=obj)

    # Projector: coordinates with distortion (pattern lookup), ideal ones for the shadow map lookup.
    if all_seen:
        Ps = P  # = np.where(seen[..., None], P, 0.0); read only below
    else:
        Ps = P.copy()
        Ps[~seen] = 0.0
    uv_p, z_p = proj.project(Ps)
    uv_ideal = proj.project(Ps, distort=False)[0] if proj.has_distortion else uv_p
    W, H = proj.width, proj.height
    inside = (seen & (z_p > 0) & (uv_p[..., 0] >= -0.5) & (uv_p[..., 0] <= W - 0.5)
              & (uv_p[..., 1] >= -0.5) & (uv_p[..., 1] <= H - 0.5))
    return on_object, depth, seen, P, normals, Ps, uv_p, z_p, uv_ideal, inside


def scene_geometry(rig, meshes: list[Instance], renderer: DepthRenderer,
                   scale: int = 1, shadow: ShadowSettings | None = None) -> Geometry:
    """Exact camera-grid geometry of the mesh instances on the reference plane.

    Two depth renders: the camera (what is seen) and the projector (shadow map).
    """
    if scale < 1 or scale % 2 == 0:
        raise InputError(f"supersampling factor must be an odd integer >= 1, got {scale}")
    shadow = shadow or ShadowSettings()
    cam, proj = rig.camera, rig.projector
    origin, dirs, plane_depth = _GRID.get(cam, scale)
    obj_depth = _distorted_depth(cam, renderer, meshes, scale) if cam.has_distortion \
        else renderer.depth(cam, meshes, scale)
    # the camera side needs no shadow map: it runs beside the projector render (GL stays on this thread)
    camera_side = beside(_camera_side, cam, proj, obj_depth, origin, dirs, plane_depth)
    try:
        shadow_depth = renderer.depth(proj, meshes, 1)
    finally:
        wait([camera_side])  # a failed render re-raises its own error, with the helper done
    on_object, depth, seen, P, normals, Ps, uv_p, z_p, uv_ideal, inside = camera_side.result()
    W, H = proj.width, proj.height
    ui = np.clip(np.rint(uv_ideal[..., 0]), 0, W - 1).astype(np.intp)
    vi = np.clip(np.rint(uv_ideal[..., 1]), 0, H - 1).astype(np.intp)
    # texel lookups as flat indices (np.take): the same values as shadow_depth[vi, ui], several times faster
    row = vi * W
    occluder = shadow_depth.ravel().take(row + ui)
    # Depth slope of the shadow map at the looked-up texel (central differences, only where needed):
    # a steep occluder surface needs a larger bias; next to its silhouette the slope is infinite (lit).
    # (D = the map with 1e9 where it is empty, looked up at the four neighbours)
    flat = shadow_depth.ravel()

    def D(index):
        d = flat.take(index)
        return np.where(np.isfinite(d), d, 1e9)

    gx = np.abs(D(row + np.minimum(ui + 1, W - 1)) - D(row + np.maximum(ui - 1, 0))) / 2
    gy = np.abs(D(np.minimum(vi + 1, H - 1) * W + ui) - D(np.maximum(vi - 1, 0) * W + ui)) / 2
    tolerance = shadow.bias_mm + shadow.slope_pixels * np.maximum(gx, gy)
    unshadowed = ~(z_p > occluder + tolerance)

    cos_inc, falloff = projector_incidence(proj, Ps, normals, z_p)
    lit = inside & unshadowed & (cos_inc > 0)
    cos_inc = np.where(lit, cos_inc, 0.0)
    return Geometry(depth=depth, points=P, normals=normals, on_object=on_object & seen,
                    u_p=uv_p[..., 0], v_p=uv_p[..., 1], lit=lit, cos_incidence=cos_inc, falloff=falloff)


def projector_incidence(proj, points: np.ndarray, normals: np.ndarray,
                        z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """How the projector's light falls on surfaces: ``(cos_incidence, falloff)``, (H, W) float64.

    ``points``, ``normals``: (H, W, 3) world points (mm, finite) and unit normals; ``z``: the points'
    projector depth when known. ``cos_incidence`` is negative where a surface faces away; ``falloff`` is
    :meth:`fppsim.geometry.rig.Device.irradiance_falloff`.
    """
    # Dot products per coordinate plane: the same (x + y) + z sums as np.sum(..., axis=-1), faster;
    # in place: dist2 = (tp0 * tp0 + tp1 * tp1) + tp2 * tp2, cos_inc = ((n0 tp0 + n1 tp1) + n2 tp2) / sqrt(dist2)
    tp = [proj.center[i] - points[..., i] for i in range(3)]
    tmp = np.empty_like(tp[0])
    dist2 = tp[0] * tp[0]
    dist2 += np.multiply(tp[1], tp[1], out=tmp)
    dist2 += np.multiply(tp[2], tp[2], out=tmp)
    cos_inc = normals[..., 0] * tp[0]
    cos_inc += np.multiply(normals[..., 1], tp[1], out=tmp)
    cos_inc += np.multiply(normals[..., 2], tp[2], out=tmp)
    dist = np.sqrt(dist2, out=dist2)
    cos_inc /= dist
    return cos_inc, proj.irradiance_falloff(points, z=z, dist=dist)


class _NothingToRender:
    """Stands in for a :class:`DepthRenderer` when there are no meshes: no surface in front of any device."""
    @staticmethod
    def depth(device, instances, scale: int = 1) -> np.ndarray:
        *_, W, H = device.gl_intrinsics(scale)
        return np.full((H, W), np.inf)


def plane_geometry(rig, scale: int = 1) -> Geometry:
    """The geometry of the bare reference plane: :func:`scene_geometry` without meshes (no GL needed)."""
    return scene_geometry(rig, [], _NothingToRender(), scale)


def _distorted_depth(cam, renderer: DepthRenderer, meshes: list[Instance], scale: int) -> np.ndarray:
    """Object depth on a distorted camera's (supersampled) pixel grid.

    GL renders ideal pinholes only: render the ideal camera with enough margin to hold every
    undistorted pixel position, then interpolate 1/z bilinearly there (exact inside a planar triangle);
    where the four neighbours straddle a depth edge or a silhouette, take the nearest sample.
    """
    xy = cam.normalized_rays(cam.pixel_grid(scale))
    K = cam.K
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    m = int(np.ceil(max(0.0, -u.min(), u.max() - (cam.width - 1), -v.min(), v.max() - (cam.height - 1)))) + 1
    ideal = Device(K=K, R=cam.R, t=cam.t, width=cam.width, height=cam.height).expanded(m)
    D = renderer.depth(ideal, meshes, scale)
    inv = np.where(np.isfinite(D), 1.0 / D, 0.0)
    x = (u + m + 0.5) * scale - 0.5
    y = (v + m + 0.5) * scale - 0.5
    Hs, Ws = D.shape
    x0 = np.clip(np.floor(x).astype(np.intp), 0, Ws - 2)
    y0 = np.clip(np.floor(y).astype(np.intp), 0, Hs - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    c00, c01, c10, c11 = inv[y0, x0], inv[y0, x0 + 1], inv[y0 + 1, x0], inv[y0 + 1, x0 + 1]
    lerp = (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy
    corners = np.stack([c00, c01, c10, c11])
    hi, lo = corners.max(0), corners.min(0)
    smooth = (lo > 0) & (hi - lo < 0.01 * hi)  # all four on one surface (1 % depth spread)
    nearest = inv[np.clip(np.rint(y), 0, Hs - 1).astype(np.intp), np.clip(np.rint(x), 0, Ws - 1).astype(np.intp)]
    inv_z = np.where(smooth, lerp, nearest)
    with np.errstate(divide="ignore"):
        return np.where(inv_z > 0, 1.0 / inv_z, np.inf)
