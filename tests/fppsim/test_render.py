"""Rendered geometry against analytic truth: tilted plane, sphere, shadow of a box."""

import numpy as np
import pytest
import trimesh

from fppsim.rendering.render import DepthRenderer, Instance, scene_geometry
from fppsim.geometry.rig import Rig


@pytest.fixture(scope="module")
def rig():
    return Rig.default()


@pytest.fixture(scope="module")
def renderer():
    r = DepthRenderer()
    yield r
    r.close()


def _camera_rays(rig):
    origin, d = rig.camera.pixel_rays(rig.camera.pixel_grid())
    return origin, d


def _analytic_phase(rig, X):
    return rig.phase_of_column(rig.projector.project(X)[0][..., 0])


def _tilted_square(rig, renderer, normal, p0, half):
    """Render a square (2 x ``half`` mm) through ``p0`` with ``normal``; return the geometry, the
    analytic intersection of every camera ray with its plane, and the unit normal."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0, 1, 0]); e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    corners = np.array([p0 + half * (a * e1 + b * e2) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    g = scene_geometry(rig, [Instance.world(corners, [[0, 1, 2], [0, 2, 3]])], renderer)
    origin, d = _camera_rays(rig)
    s = (p0 - origin) @ n / (d @ n)
    return g, origin + s[..., None] * d, n


def test_tilted_plane(rig, renderer):
    # tilted 20 deg about y and 10 deg about x, a 300 mm square
    g, X, n = _tilted_square(rig, renderer, [np.sin(np.deg2rad(20)), np.sin(np.deg2rad(10)), 1.0],
                             np.array([0.0, 0.0, 30.0]), 150)
    on = g.on_object & (X[..., 2] > 0)
    assert on.mean() > 0.5
    err = np.abs(g.points[..., 2] - X[..., 2])[on]
    assert np.median(err) < 0.05 and np.percentile(err, 99) < 0.1
    perr = np.abs(np.asarray(g.u_p) - rig.projector.project(X)[0][..., 0])[on & g.lit]
    assert np.median(perr) < 0.05  # projector columns
    # normals of the plane are recovered
    assert np.median(np.abs(g.normals[on] @ n - 1)) < 1e-4


def test_sphere_height_phase_and_mask(rig, renderer):
    c, r = np.array([10.0, 5.0, 20.0]), 30.0
    s = trimesh.creation.icosphere(6, radius=r)
    g = scene_geometry(rig, [Instance.world(s.vertices + c, s.faces)], renderer)
    origin, d = _camera_rays(rig)
    oc = origin - c
    b = d @ oc
    a = np.sum(d * d, -1)
    disc = b * b - a * (oc @ oc - r * r)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a
    X = origin + t[..., None] * d
    hit = (disc > 0) & (X[..., 2] > 0)
    # the plane is exact where the sphere is not hit
    plane = ~hit & g.seen
    assert np.all(g.height[plane & ~g.on_object] == 0.0)
    inner = hit & g.on_object
    err = np.abs(g.height - X[..., 2])[inner]
    assert inner.sum() > 10000
    assert np.median(err) < 0.05
    phase_err = np.abs(rig.phase_of_column(g.u_p) - _analytic_phase(rig, X))[inner & g.lit]
    assert np.median(phase_err) < 0.01  # rad
    # sphere silhouette agrees with the analytic disc to within one pixel ring
    assert np.sum(hit != g.on_object) < 0.02 * hit.sum()
    # the projector lights the sphere side facing +x (the projector) and not the far side
    lit_obj = g.lit & g.on_object
    assert lit_obj.sum() > 0.7 * inner.sum()


def test_box_shadow_width(rig, renderer):
    """A tall box casts a shadow on the plane towards -x whose width follows from similar triangles."""
    h, x1 = 40.0, -20.0
    box = trimesh.creation.box(extents=[40.0, 40.0, h])
    v = box.vertices + [x1 + 20.0, 0.0, h / 2]
    g = scene_geometry(rig, [Instance.world(v, box.faces)], renderer)
    C = rig.projector.center
    s = C[2] / (C[2] - h)  # projector ray over the box's top edge at x1 reaches the plane here
    x_shadow = C[0] + s * (x1 - C[0])
    row = 175  # image row through y ~ 0
    xs = g.points[row, :, 0]
    shadow = g.seen[row] & ~g.lit[row] & ~g.on_object[row]
    measured = xs[shadow]
    assert measured.size > 0
    mm_per_px = 500.0 / 1230.0
    assert abs(measured.min() - x_shadow) < 2 * mm_per_px
    # the camera (at x = 0) sees the plane only beyond the box top edge's occlusion
    Cc = rig.camera.center
    x_visible = Cc[0] + Cc[2] / (Cc[2] - h) * (x1 - Cc[0])
    assert abs(measured.max() - x_visible) < 2 * mm_per_px


def test_renderer_reuses_keyed_meshes(rig, renderer):
    s = trimesh.creation.icosphere(3, radius=20.0)
    T = np.eye(4); T[:3, 3] = [0, 0, 20]
    inst = Instance(s.vertices, s.faces, T, key="sphere")
    d1 = renderer.depth(rig.camera, [inst])
    T2 = T.copy(); T2[0, 3] = 40
    d2 = renderer.depth(rig.camera, [Instance(s.vertices, s.faces, T2, key="sphere")])
    d3 = renderer.depth(rig.camera, [inst])
    assert np.array_equal(d1, d3) and not np.array_equal(d1, d2)
    assert np.isfinite(d1).sum() == np.isfinite(d2).sum() or abs(np.isfinite(d1).sum() - np.isfinite(d2).sum()) < 200


def test_distorted_camera_tilted_plane(rig, renderer):
    """With lens distortion the rendered geometry still matches the analytic plane, corners included."""
    from fppsim.geometry.rig import Device, Rig

    cam = rig.camera
    dcam = Device(K=cam.K, R=cam.R, t=cam.t, width=cam.width, height=cam.height, dist=[-0.25, 0.08, 0.001, -0.001, 0.0])
    drig = Rig(camera=dcam, projector=rig.projector, periods=rig.periods)
    g, X, _ = _tilted_square(drig, renderer, [np.sin(np.deg2rad(15)), 0.0, 1.0], np.array([0.0, 0.0, 25.0]), 400)
    on = g.on_object & (X[..., 2] > 0)
    assert on[0, 0] and on[-1, 0] and on.mean() > 0.6  # the distorted (left) corners see the plane too
    err = np.abs(g.points[..., 2] - X[..., 2])[on]
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.05
