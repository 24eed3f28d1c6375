"""Procedural sculptures (fppsim.rendering.shapes.procedural), rig jitter, and their use in the scene sampler."""

import numpy as np
import pytest

from fppsim.geometry.jitter import RigJitter, jitter_rig
from fppsim.geometry.rig import make_figshare_like_rig as make_default_rig  # the rig with the real trend
from fppsim.rendering.scene import PROCEDURAL_PREFIX, SceneRanges, procedural_asset, sample_scene
from fppsim.rendering.shapes import PROCEDURAL_KINDS, add_detail, make_shape, procedural


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_procedural_shape_is_a_closed_sculpture_and_deterministic(seed):
    kind, m = procedural(seed)
    assert kind in dict(PROCEDURAL_KINDS)
    assert m.is_watertight and m.volume > 0
    assert 60.0 <= m.extents.max() <= 120.0 and np.all(m.extents > 5)
    assert m.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    kind2, m2 = procedural(seed)
    assert kind2 == kind and np.array_equal(m.vertices, m2.vertices) and np.array_equal(m.faces, m2.faces)


def test_procedural_family_varies_kind_and_shape():
    kinds = {procedural(s, detail=False)[0] for s in range(12)}
    assert len(kinds) >= 3
    with pytest.raises(ValueError, match="non-negative"):
        procedural(-1)


def test_detail_adds_multiscale_relief_and_keeps_topology():
    m = make_shape("mask", 0)
    d = add_detail(m, np.random.default_rng(0))
    assert np.array_equal(d.faces, m.faces) and d.is_watertight
    disp = np.linalg.norm(d.vertices - m.vertices, axis=1)
    top = m.vertex_normals[:, 2] > 0.5
    assert 0.1 < np.percentile(disp[top], 90) < 3.0  # sub-mm to mm detail on the face
    assert np.all(disp[m.vertices[:, 2] < 1e-9] < 1e-9)  # the flat base stays on the plane


def test_scene_draws_procedural_objects_by_share():
    rig = make_default_rig()
    only = sample_scene([], rig, np.random.default_rng(0), SceneRanges(procedural_share=1.0, procedural_pool=3))
    assert all(o.mesh.startswith(PROCEDURAL_PREFIX) for o in only.objects)
    asset = procedural_asset(1)
    assert asset.path.startswith(PROCEDURAL_PREFIX) and asset is procedural_asset(1)  # cached
    none = sample_scene([asset], rig, np.random.default_rng(0), SceneRanges(procedural_share=0.0))
    assert all(o.asset is asset for o in none.objects)
    with pytest.raises(ValueError, match="procedural_share"):
        SceneRanges(procedural_share=1.5)


def _half_periods(rig):
    cam = rig.camera
    uv = np.stack(np.meshgrid(np.arange(0, 640, 4.0), [175.0]), -1).reshape(-1, 2)
    X = cam.backproject(uv, cam.plane_depth(uv))
    up = rig.projector.project(X)[0][:, 0]
    period = rig.projector.width / rig.periods / np.abs(np.gradient(up, 4.0))
    return period[:80].mean(), period[80:].mean()


def test_rig_jitter_keeps_the_scene_centred_and_spreads_the_period():
    rig = make_default_rig()
    origin = rig.projector.project(np.zeros(3))[0]
    lefts, rights = [], []
    for s in range(40):
        j = jitter_rig(rig, np.random.default_rng(s), RigJitter())
        np.testing.assert_allclose(j.projector.project(np.zeros(3))[0], origin, atol=1e-9)
        np.testing.assert_allclose(j.projector.center, rig.projector.center, atol=1e-9)
        left, right = _half_periods(j)
        lefts.append(left)
        rights.append(right)
        assert left > right  # the trend keeps its sign
    mid = (np.array(lefts) + np.array(rights)) / 2
    assert mid.min() < 11.5 and mid.max() > 11.9  # covers the held-out real frames' 11.4-11.6 px
    assert np.all((mid > 11.2) & (mid < 12.3))
    a = jitter_rig(rig, np.random.default_rng(9), RigJitter())
    b = jitter_rig(rig, np.random.default_rng(9), RigJitter())
    np.testing.assert_array_equal(a.projector.K, b.projector.K)
    assert jitter_rig(rig, np.random.default_rng(9), RigJitter(0, 0)) is rig
    with pytest.raises(ValueError):
        RigJitter(yaw=-1)
