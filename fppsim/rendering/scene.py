"""Scenes: meshes loaded, validated, normalised in size and posed on the reference plane.

A scene is one to three objects resting on the plane z = 0, posed by a seeded sampler. Meshes arrive in
any units (a 0.16-unit bunny, a 1000-unit alligator), so each is first normalised: its principal axes
are aligned with x, y, z (smallest extent vertical, like a relief facing the camera), and it is later
scaled so that its footprint and relief match the real figshare data.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from fppsim.errors import MeshError, InputError
from fppsim.dataio.formats import PEDESTAL_PREFIX
from fppsim.geometry.rig import RigError, rotation
from fppsim.rendering.meshio import PlyError, ply_has_tristrips, read_ply_tristrips
from fppsim.rendering.render import Instance
from fppsim.rendering.shapes import procedural

__all__ = [
    "MeshError", "MeshAsset", "PlacedObject", "Scene", "SceneRanges", "load_mesh", "find_meshes",
    "sample_scene", "MESH_EXTENSIONS", "OTHER_MESH_EXTENSIONS", "unread_mesh_files", "asset_from_arrays",
    "changed_meshes", "procedural_asset", "PROCEDURAL_PREFIX",
    "PEDESTAL_PREFIX", "pedestal_prism", "render_faces",
]

MESH_EXTENSIONS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
OTHER_MESH_EXTENSIONS = (".fbx", ".3mf", ".dae", ".blend", ".3ds", ".max", ".usd", ".usda", ".usdc", ".usdz", ".x3d",
                         ".wrl", ".vrml", ".amf", ".step", ".stp", ".iges", ".igs", ".dxf", ".ifc", ".ma", ".mb",
                         ".c4d", ".lwo", ".x", ".md2", ".md3", ".ms3d", ".xyz", ".pcd", ".las", ".e57")
"""Mesh and scan formats the loader does not take: a file of one under ``--meshes`` is reported, not drawn."""


@dataclass
class MeshAsset:
    """A validated mesh in canonical orientation.

    ``vertices`` (V, 3) float64 are centred (x, y at the bounding-box centre, min z = 0) and rotated so
    the principal axes are x (longest), y, z (shortest); ``faces`` (F, 3) int32. Units are the file's.
    ``canonical`` is the 4x4 transform file coordinates -> these vertices. ``render_faces``: the faces
    the depth renders draw, which cull back faces: ``faces`` for a closed mesh wound outward (the
    default), both windings of every face for anything else (see :func:`render_faces`).
    """
    path: str
    vertices: np.ndarray
    faces: np.ndarray
    canonical: np.ndarray
    hull: np.ndarray = field(default=None, repr=False)  # convex-hull vertices: cheap rotated extents
    render_faces: np.ndarray = field(default=None, repr=False)

    def __post_init__(self):
        if self.render_faces is None:
            self.render_faces = self.faces
        if self.hull is None:
            from scipy.spatial import ConvexHull, QhullError

            try:
                self.hull = self.vertices[ConvexHull(self.vertices).vertices]
            except (QhullError, ValueError):
                self.hull = self.vertices

    @property
    def extents(self) -> np.ndarray:
        return self.vertices.max(0) - self.vertices.min(0)


def find_meshes(paths, extensions=MESH_EXTENSIONS) -> list[str]:
    """Expand files and folders (recursively, by ``extensions``) into a sorted, de-duplicated list.

    Linked folders are followed (each real folder once, so a link loop ends); a broken link named like a
    mesh is kept, so loading it reports it instead of dropping it without a word. A file given by name is
    kept whatever its suffix (the loader names what it cannot read)."""
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            out += _mesh_files(p, extensions)
        elif p.is_file():
            out.append(str(p))
        else:
            raise MeshError(f"mesh path not found: {p}")
    seen, unique = set(), []
    for p in out:
        key = os.path.realpath(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def unread_mesh_files(paths) -> list[tuple[str, str]]:
    """``(path, reason)`` for each file under the folders among ``paths`` in a format the loader does not take
    (:data:`OTHER_MESH_EXTENSIONS`): :func:`find_meshes` leaves them out, and the user most likely meant them."""
    folders = [p for p in paths if Path(p).is_dir()]
    return [(p, f"{p}: {Path(p).suffix.lower()} is not a mesh format read here ({' '.join(MESH_EXTENSIONS)})")
            for p in find_meshes(folders, OTHER_MESH_EXTENSIONS)]


def changed_meshes(recorded, paths) -> tuple[list[str], list[str]]:
    """How the mesh files a dataset was made from (``recorded``: ``dataset.json``'s ``meshes``, the absolute paths of
    those generate loaded) differ from what ``paths`` (files and folders, as ``--meshes``) give now, by real path:
    ``(recorded but not given, the first given but not recorded)``; both empty: the same meshes. A given file that
    does not load is none (generate skipped it, so the record lacks it); only files not recorded are loaded, until
    one does. Paths are compared, not contents. :class:`MeshError` for a path that is not there."""
    had = {os.path.realpath(p): p for p in recorded}
    found = {os.path.realpath(p): p for p in find_meshes(paths)}
    gone = [p for key, p in had.items() if key not in found]
    for key, p in found.items():
        if key not in had:
            try:
                load_mesh(p)
            except MeshError:
                continue
            return gone, [p]
    return gone, []


def _mesh_files(folder: Path, extensions=MESH_EXTENSIONS) -> list[str]:
    """The mesh files under ``folder``: its own tree's under their own paths (their names and order as before
    links were followed), and each linked folder's once, unless the tree holds it (a link loop ends)."""
    own = {root for root, _, _ in os.walk(folder)}
    out, visited = [], {os.path.realpath(root) for root in own}
    for root, dirs, files in os.walk(folder, followlinks=True):
        if root not in own:  # reached through a link
            real = os.path.realpath(root)
            if real in visited:
                dirs[:] = []
                continue
            visited.add(real)
        dirs.sort()
        named = [os.path.join(root, f) for f in files if Path(f).suffix.lower() in extensions]
        out += [q for q in named if os.path.isfile(q) or not os.path.exists(q)]  # files, and broken links
    return sorted(out, key=lambda q: Path(q).parts)


def load_mesh(path: str | os.PathLike, flat_ratio: float = 1e-3) -> MeshAsset:
    """Load any mesh trimesh reads, validate it and bring it to canonical orientation.

    Raises :class:`MeshError` with the reason for: unreadable files, no triangles, non-finite vertices,
    zero size, or a flat mesh (smallest principal extent below ``flat_ratio`` x the largest).
    """
    import trimesh


    path = str(path)
    if not os.path.isfile(path):
        raise MeshError(f"{path}: not a readable file (a broken link?)")
    if os.path.getsize(path) == 0:  # trimesh's own reason for one is an IndexError (.glb) or a parse error
        raise MeshError(f"{path}: an empty file (0 bytes), not a mesh")
    kind = Path(path).suffix[1:].upper() or "mesh"
    if kind == "GLTF":
        check_gltf_json(path)
    try:
        if path.lower().endswith(".ply") and ply_has_tristrips(path):  # trimesh ignores triangle strips
            v, f = read_ply_tristrips(path)
            loaded = trimesh.Trimesh(vertices=v, faces=f, process=False)
        else:
            loaded = trimesh.load(path, force="mesh", process=False)
    except PlyError as exc:
        raise MeshError(str(exc)) from None
    except ImportError:  # trimesh guesses the text encoding of undecodable bytes with an optional module
        raise MeshError(f"{path}: not a readable {kind} file (its content is binary or garbage, not mesh "
                        "text)") from None
    except Exception as exc:  # the reader's own words stay as a detail: they say where it stopped
        detail = f"{type(exc).__name__}: {str(exc).splitlines()[0]}" if str(exc) else type(exc).__name__
        raise MeshError(f"{path}: not a readable {kind} file (the reader stopped with {detail})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: no triangle mesh found in this {kind} file")
    try:
        return asset_from_arrays(loaded.vertices, loaded.faces, path, flat_ratio)
    except MeshError as exc:  # text that is not a mesh reads as no triangle (.stl, .obj), garbage bytes as NaN
        if len(loaded.faces) == 0:
            raise MeshError(f"{path}: not a readable {kind} file (no triangle in it: empty, or not {kind} "
                            "content)") from None
        raise MeshError(f"{path}: unusable mesh in this {kind} file: {str(exc).removeprefix(f'{path}: ')}") from None


def check_gltf_json(path: str) -> None:
    """:class:`MeshError` for a ``.gltf`` that is not a JSON object: trimesh then looks for a ``model.gltf`` inside it
    as in a zip and names that missing file instead."""
    try:
        doc = json.loads(Path(path).read_bytes())
    except json.JSONDecodeError as exc:
        raise MeshError(f"{path}: not a readable GLTF file (not JSON text: {exc})") from None
    except ValueError:  # bytes in no Unicode encoding
        raise MeshError(f"{path}: not a readable GLTF file (its content is binary or garbage, not JSON text)") from None
    if not isinstance(doc, dict):
        raise MeshError(f"{path}: not a readable GLTF file (its JSON is a {type(doc).__name__}, not an object)")


def asset_from_arrays(vertices, faces, path: str, flat_ratio: float = 1e-3) -> MeshAsset:
    """Validate (V, 3) vertices and (F, 3) faces and bring them to canonical orientation (see load_mesh)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or len(v) < 3:
        raise MeshError(f"{path}: empty mesh (no faces)")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{path}: face indices out of range")
    used = np.unique(f)
    if len(used) < len(v):  # vertices no face uses (a stray point, a scan's NaN grid) would count in the size
        v, f = v[used], np.searchsorted(used, f)
        used = np.arange(len(v))
    if not np.all(np.isfinite(v)):
        raise MeshError(f"{path}: vertices contain NaN or inf")
    pts = v[used]
    centre = pts.mean(0)
    cov = np.cov((pts - centre).T)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    axes = evecs[:, ::-1].T  # rows: longest, middle, shortest
    if np.linalg.det(axes) < 0:
        axes[2] *= -1
    local = (pts - centre) @ axes.T
    ext = local.max(0) - local.min(0)
    if not ext[0] > 0:
        raise MeshError(f"{path}: zero-size mesh (all vertices coincide)")
    if ext[2] < flat_ratio * ext[0]:
        raise MeshError(f"{path}: flat mesh (thickness {ext[2]:.3g} vs size {ext[0]:.3g}: zero volume)")
    areas = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    if not np.any(areas > 0):
        raise MeshError(f"{path}: all faces are degenerate (zero area)")
    lo, hi = local.min(0), local.max(0)
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    T = np.eye(4)
    T[:3, :3] = axes
    T[:3, 3] = -axes @ centre - shift
    verts = v @ T[:3, :3].T + T[:3, 3]
    f = f.astype(np.int32)
    return MeshAsset(path=path, vertices=verts, faces=f, canonical=T, render_faces=render_faces(verts, f))


def render_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The faces to rasterise so the depth renders (which cull back faces) see the nearest surface.

    ``faces`` itself when the mesh is closed and wound outward (every directed edge once, its reverse
    once, each connected part of positive volume; vertices at one point, e.g. split at a texture seam or
    an STL's triangle soup, count as one); otherwise (inside out, open, inconsistently wound, a part
    inside out beside a larger outward one) every face in both windings, so a flipped mesh or an open
    scan seen from behind is not rendered see-through.
    """
    f = np.asarray(faces, dtype=np.int64)
    p = np.asarray(vertices, dtype=np.float64)
    if _closed_outward(p, f):
        return faces
    points, at = np.unique(p, axis=0, return_inverse=True)  # one index per point: seams and soups are closed too
    if len(points) < len(p) and _closed_outward(points, at.reshape(-1)[f]):
        return faces
    return np.concatenate([faces, faces[:, ::-1]])


def _closed_outward(p: np.ndarray, f: np.ndarray) -> bool:
    """Whether faces ``f`` (indices into points ``p``) are closed, wound consistently, and each connected
    part encloses a positive volume (a sum over the parts would hide a small part wound inside out)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    n = int(f.max()) + 1
    fwd = np.sort(edges[:, 0] * n + edges[:, 1])
    rev = np.sort(edges[:, 1] * n + edges[:, 0])
    if not (np.all(fwd[1:] != fwd[:-1]) and np.array_equal(fwd, rev)):
        return False
    _, part = connected_components(coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)),
                                   directed=False)
    q = p - p.mean(0)
    volume = np.einsum("ij,ij->i", q[f[:, 0]], np.cross(q[f[:, 1]], q[f[:, 2]]))
    return bool(np.all(np.bincount(part[f[:, 0]], weights=volume)[np.unique(part[f[:, 0]])] > 0))


@dataclass
class SceneRanges:
    """Ranges of the seeded scene sampler (mm, radians). Defaults follow the real figshare data."""
    objects: tuple[int, int] = (1, 3)           # objects per scene, inclusive
    footprint: tuple[float, float] = (70.0, 140.0)  # longest horizontal size of one object, mm
    max_relief: tuple[float, float] = (35.0, 55.0)  # cap on an object's height above the plane, mm
    tilt: float = np.deg2rad(10.0)              # max tilt about a random horizontal axis
    view_margin: float = 0.15                   # keep object centres this fraction inside the view (0.05: often
                                                # partly out of view, as in the real data; opt-in, unmeasured)
    overlap_probability: float = 0.35           # chance that a multi-object scene overlaps in depth
    flip_probability: float = 0.5               # chance to flip the canonical mesh upside down
    procedural_share: float = 0.0               # chance that an object is a procedural sculpture (opt-in)
    procedural_pool: int = 96                   # procedural shapes are fppsim.rendering.shapes.procedural(0..pool-1)
    # Plaster casts stand on thick flat backs or plinths: the real figshare pair's visible object lies
    # 30-46 mm above the plane behind near-vertical walls, so nothing but the shadow tells its height.
    pedestal_probability: float = 0.5           # chance that an object stands on a prism pedestal
    pedestal_height: tuple[float, float] = (10.0, 35.0)  # pedestal height, mm (object + pedestal <= max_relief[1])
    pedestal_shrink: tuple[float, float] = (0.7, 1.0)    # pedestal outline / object's convex outline

    def __post_init__(self):
        for name in ("footprint", "max_relief"):
            lo, hi = getattr(self, name)
            if not (0.0 < lo <= hi and np.isfinite(hi)):
                raise InputError(f"{name} must satisfy 0 < lo <= hi (mm), got {getattr(self, name)}")
        lo, hi = self.objects
        if not (1 <= lo <= hi):
            raise InputError(f"objects range must satisfy 1 <= lo <= hi, got {self.objects}")
        if not 0.0 <= self.procedural_share <= 1.0:
            raise InputError(f"procedural_share must be in [0, 1], got {self.procedural_share}")
        if self.procedural_pool < 1:
            raise InputError(f"procedural_pool must be >= 1, got {self.procedural_pool}")
        if not 0.0 <= self.pedestal_probability <= 1.0:
            raise InputError(f"pedestal_probability must be in [0, 1], got {self.pedestal_probability}")
        lo, hi = self.pedestal_height
        if not (0.0 < lo <= hi and np.isfinite(hi)):
            raise InputError(f"pedestal_height must satisfy 0 < lo <= hi (mm), got {self.pedestal_height}")
        lo, hi = self.pedestal_shrink
        if not (0.0 < lo <= hi <= 1.0):
            raise InputError(f"pedestal_shrink must satisfy 0 < lo <= hi <= 1, got {self.pedestal_shrink}")


@dataclass
class PlacedObject:
    """One object in a scene.

    ``pose`` (4x4) maps file coordinates multiplied by ``scale`` (mm) to world; ``transform`` maps the
    asset's canonical vertices to world (rotation times scale, translation).
    """
    mesh: str
    scale: float
    pose: np.ndarray
    asset: MeshAsset = field(repr=False)
    transform: np.ndarray = field(repr=False)

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) world vertices, mm."""
        return self.asset.vertices @ self.transform[:3, :3].T + self.transform[:3, 3]

    @property
    def faces(self) -> np.ndarray:
        return self.asset.faces

    def instance(self):
        # procedural shapes are many and short-lived: do not keep them uploaded in the renderer
        key = None if self.asset.path.startswith((PROCEDURAL_PREFIX, PEDESTAL_PREFIX)) else self.asset.path
        return Instance(self.asset.vertices, self.asset.render_faces, self.transform, key=key)

    def to_dict(self) -> dict:
        return {"mesh": self.mesh, "scale": float(self.scale), "pose": np.asarray(self.pose).tolist()}


@dataclass
class Scene:
    objects: list[PlacedObject]
    layout: str

    def to_dict(self) -> dict:
        return {"layout": self.layout, "objects": [o.to_dict() for o in self.objects]}


PROCEDURAL_PREFIX = "procedural:"
# PEDESTAL_PREFIX (imported above): a pedestal's "mesh" name, defined by the contract so the manifest counts it apart


def pedestal_prism(outline_xy: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed prism over a convex outline: (V, 3) vertices (mm) and (F, 3) outward-facing faces.

    outline_xy : (N, 2) convex polygon, counter-clockwise seen from +z. The prism spans z = 0 .. height.
    """
    xy = np.asarray(outline_xy, dtype=np.float64)
    n = len(xy)
    bottom = np.c_[xy, np.zeros(n)]
    top = np.c_[xy, np.full(n, float(height))]
    v = np.concatenate([bottom, top])
    i = np.arange(n)
    j = (i + 1) % n
    fan = np.arange(1, n - 1)
    faces = np.concatenate([
        np.stack([np.full(n - 2, n), n + fan, n + fan + 1], 1),   # top, normal +z
        np.stack([np.zeros(n - 2, int), fan + 1, fan], 1),         # bottom, normal -z
        np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1),  # walls, outward
    ])
    return v, faces.astype(np.int32)


def _pedestal(outline_xy: np.ndarray, centre_xy: np.ndarray, height: float, shrink: float, index: int) -> "PlacedObject":
    from scipy.spatial import ConvexHull

    hull = outline_xy[ConvexHull(outline_xy).vertices]  # counter-clockwise
    c = hull.mean(0)
    ring = c + shrink * (hull - c) + centre_xy
    v, f = pedestal_prism(ring, height)
    asset = MeshAsset(path=f"{PEDESTAL_PREFIX}{index}", vertices=v, faces=f, canonical=np.eye(4), hull=v)
    return PlacedObject(mesh=asset.path, scale=1.0, pose=np.eye(4), asset=asset, transform=np.eye(4))


@lru_cache(maxsize=256)
def procedural_asset(seed: int) -> MeshAsset:
    """Procedural sculpture ``seed`` (:func:`fppsim.rendering.shapes.procedural`) as a canonical asset, cached per
    process; its ``path`` is ``procedural:<kind>:<seed>``."""

    kind, mesh = procedural(int(seed))
    return asset_from_arrays(mesh.vertices, mesh.faces, f"{PROCEDURAL_PREFIX}{kind}:{int(seed)}")


def _rot_axis(axis, a):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)


def view_rectangle(rig, margin: float = 0.0) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of the camera's view on the plane z = 0, shrunk by ``margin``.

    Uses the image border rays that meet the plane (an oblique camera may see the horizon).
    """
    cam = rig.camera
    t = np.linspace(0.0, 1.0, 17)
    W, H = cam.width - 1, cam.height - 1
    border = np.concatenate([np.stack([t * W, 0 * t], -1), np.stack([t * W, H + 0 * t], -1),
                             np.stack([0 * t, t * H], -1), np.stack([W + 0 * t, t * H], -1)])
    depth = cam.plane_depth(border)
    ok = np.isfinite(depth)
    if ok.sum() < 3:
        raise RigError("the camera does not see the reference plane (z = 0): check the rig's extrinsics")
    X = cam.backproject(border[ok], depth[ok])
    xmin, xmax, ymin, ymax = X[:, 0].min(), X[:, 0].max(), X[:, 1].min(), X[:, 1].max()
    dx, dy = (xmax - xmin) * margin, (ymax - ymin) * margin
    return xmin + dx, xmax - dx, ymin + dy, ymax - dy


def sample_scene(assets: list[MeshAsset], rig, rng: np.random.Generator,
                 ranges: SceneRanges | None = None, pedestal_rng: np.random.Generator | None = None) -> Scene:
    """Draw a scene of 1-3 posed objects resting on the plane from ``rng``.

    Each object: canonical mesh (optionally flipped), scaled so its longest horizontal size is drawn
    from ``ranges.footprint`` and its relief does not exceed a draw from ``ranges.max_relief``, rotated
    about z, tilted, then lowered onto the plane (min z = 0) and translated inside the camera view.
    Multi-object scenes are either isolated (footprint circles apart) or overlapping in depth.

    With ``ranges.pedestal_probability`` > 0, each object may instead stand on a prism pedestal (its
    convex outline shrunk by a draw from ``pedestal_shrink``, height from ``pedestal_height`` cut so that
    pedestal + object stay below ``max_relief[1]``; no pedestal when less than half the lowest height
    remains). The object keeps its size. Those draws come from
    ``pedestal_rng`` alone, so scenes without pedestals are the same as before they existed.
    """
    r = ranges or SceneRanges()
    n = int(rng.integers(r.objects[0], r.objects[1] + 1))
    layout = "single"
    if n > 1:
        layout = "overlapping" if rng.random() < r.overlap_probability else "isolated"
    xmin, xmax, ymin, ymax = view_rectangle(rig, r.view_margin)
    placed: list[PlacedObject] = []
    circles: list[tuple[float, float, float]] = []
    for _ in range(n):
        if r.procedural_share > 0 and (not assets or rng.random() < r.procedural_share):
            asset = procedural_asset(int(rng.integers(r.procedural_pool)))
        elif not assets:
            raise MeshError("no meshes to draw from (give mesh files or a procedural share > 0)")
        else:
            asset = assets[int(rng.integers(len(assets)))]
        v = asset.hull
        flip = rng.random() < r.flip_probability
        R0 = _rot_axis([1, 0, 0], np.pi) if flip else np.eye(3)
        theta = rng.uniform(0, 2 * np.pi)
        tilt_axis = rng.normal(size=2)
        tilt = rng.uniform(0, r.tilt)
        R = _rot_axis([tilt_axis[0], tilt_axis[1], 0.0], tilt) @ rotation("z", theta) @ R0
        rv = v @ R.T
        ext = rv.max(0) - rv.min(0)
        footprint = rng.uniform(*r.footprint)
        relief = rng.uniform(*r.max_relief)
        s = min(footprint / max(ext[0], ext[1]), relief / max(ext[2], 1e-12))
        lift = 0.0
        if r.pedestal_probability > 0 and pedestal_rng is not None and pedestal_rng.random() < r.pedestal_probability:
            lift = pedestal_rng.uniform(*r.pedestal_height)
            shrink = pedestal_rng.uniform(*r.pedestal_shrink)
            # the object keeps its size; pedestal + object stay within the largest relief of the range
            lift = min(lift, r.max_relief[1] - s * ext[2])
            lift = lift if lift >= 0.5 * r.pedestal_height[0] else 0.0
        radius = 0.5 * s * np.hypot(ext[0], ext[1])
        # position: isolated -> reject overlaps of footprint circles; overlapping -> near the previous one
        for attempt in range(50):
            if layout == "overlapping" and circles:
                px, py, pr = circles[-1]
                ang = rng.uniform(0, 2 * np.pi)
                dist = rng.uniform(0.3, 0.8) * (pr + radius)
                cx, cy = px + dist * np.cos(ang), py + dist * np.sin(ang)
                cx, cy = np.clip(cx, xmin, xmax), np.clip(cy, ymin, ymax)
            else:
                cx, cy = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax)
            if layout != "isolated" or all(np.hypot(cx - qx, cy - qy) > qr + radius for qx, qy, qr in circles):
                break
        circles.append((cx, cy, radius))
        lo, hi = rv.min(0) * s, rv.max(0) * s
        offset = np.array([cx - (lo[0] + hi[0]) / 2, cy - (lo[1] + hi[1]) / 2, lift - lo[2]])
        transform = np.eye(4)
        transform[:3, :3] = s * R
        transform[:3, 3] = offset
        # pose: file coordinates x scaled by s -> world: R (A (s x) + s a) + offset
        A, a = asset.canonical[:3, :3], asset.canonical[:3, 3]
        pose = np.eye(4)
        pose[:3, :3] = R @ A
        pose[:3, 3] = s * (R @ a) + offset
        placed.append(PlacedObject(mesh=asset.path, scale=float(s), pose=pose, asset=asset, transform=transform))
        if lift > 0:
            placed.append(_pedestal(rv[:, :2] * s, offset[:2], lift, shrink, len(placed)))
    return Scene(objects=placed, layout=layout)
