"""Pedestals under objects (fppsim.rendering.scene): prism geometry, scene draws, rendered heights."""

import numpy as np
import pytest
import trimesh

from fppsim.geometry.rig import Rig
from fppsim.rendering.scene import PEDESTAL_PREFIX, SceneRanges, asset_from_arrays, pedestal_prism, sample_scene


def test_prism_is_closed_outward_and_has_the_analytic_volume():
    # regular hexagon of circumradius 20 mm, 15 mm high: volume = (3 sqrt(3) / 2) r^2 h
    a = np.linspace(0, 2 * np.pi, 7)[:-1]
    v, f = pedestal_prism(np.c_[20 * np.cos(a), 20 * np.sin(a)], 15.0)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(1.5 * np.sqrt(3) * 400 * 15, rel=1e-9)  # positive: normals point out
    assert v[:, 2].min() == 0.0 and v[:, 2].max() == 15.0


def _assets():
    box = trimesh.creation.box(extents=(60.0, 40.0, 20.0))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=25.0)
    return [asset_from_arrays(box.vertices, box.faces, "box"), asset_from_arrays(ball.vertices, ball.faces, "ball")]


def test_no_pedestal_draws_leave_scenes_unchanged():
    rig = Rig.default()
    assert SceneRanges().pedestal_probability == 0.5  # the default
    for seed in range(5):
        a = sample_scene(_assets(), rig, np.random.default_rng(seed), SceneRanges(pedestal_probability=0.0))
        b = sample_scene(_assets(), rig, np.random.default_rng(seed), SceneRanges(pedestal_probability=0.0),
                         pedestal_rng=np.random.default_rng(99))
        c = sample_scene(_assets(), rig, np.random.default_rng(seed), SceneRanges(pedestal_probability=1.0),
                         pedestal_rng=np.random.default_rng(99))
        assert [o.to_dict() for o in a.objects] == [o.to_dict() for o in b.objects]
        # pedestals move objects up but draw nothing else from the scene generator
        assert [o.scale for o in a.objects] == [o.scale for o in c.objects if not o.mesh.startswith(PEDESTAL_PREFIX)]


def test_pedestals_lift_objects_and_stay_under_them():
    rig = Rig.default()
    ranges = SceneRanges(pedestal_probability=1.0, objects=(1, 1))
    lifted = 0
    for seed in range(20):
        sc = sample_scene(_assets(), rig, np.random.default_rng(seed), ranges, pedestal_rng=np.random.default_rng(seed))
        obj = sc.objects[0]
        if len(sc.objects) == 1:  # the object alone already reaches the top of the relief range
            assert obj.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
            continue
        lifted += 1
        ped = sc.objects[1]
        assert ped.mesh.startswith(PEDESTAL_PREFIX)
        top = ped.vertices[:, 2].max()
        assert ranges.pedestal_height[0] / 2 <= top <= ranges.pedestal_height[1]
        assert obj.vertices[:, 2].min() == pytest.approx(top, abs=1e-9)  # the object rests on it
        assert obj.vertices[:, 2].max() <= ranges.max_relief[1] + 1e-9
        # the pedestal's outline lies inside the object's (convex) outline
        from matplotlib.path import Path as MPath
        from scipy.spatial import ConvexHull

        xy = obj.vertices[:, :2]
        hull = MPath(xy[ConvexHull(xy).vertices])
        assert hull.contains_points(ped.vertices[:, :2], radius=1e-6).all()
    assert lifted >= 10


@pytest.mark.parametrize("bad", [dict(pedestal_probability=1.5), dict(pedestal_height=(0.0, 5.0)),
                                 dict(pedestal_height=(20.0, 10.0)), dict(pedestal_shrink=(0.5, 1.2))])
def test_bad_pedestal_ranges_are_refused(bad):
    with pytest.raises(ValueError, match="pedestal"):
        SceneRanges(**bad)


def test_rendered_pedestal_top_and_shadow(tmp_path):
    """A flat box on a 25 mm pedestal rendered through the whole generator: its top face is exactly
    25 mm above the same box drawn without a pedestal (same seed: same pose and size), and the raised
    box casts a larger projector shadow."""
    from fppsim.generation import generate_dataset as generate
    from fppsim.rendering.synth import SynthConfig

    box = trimesh.creation.box(extents=(50.0, 40.0, 10.0))
    path = tmp_path / "box.stl"
    box.export(path)
    tops, invalid = {}, {}
    for name, p in (("plane", 0.0), ("raised", 1.0)):
        scene = SceneRanges(objects=(1, 1), footprint=(60.0, 60.0), max_relief=(55.0, 55.0), tilt=0.0,
                            view_margin=0.35, flip_probability=0.0, pedestal_probability=p,
                            pedestal_height=(25.0, 25.0), pedestal_shrink=(0.8, 0.8))
        generate([str(path)], tmp_path / name, 1, seed=1, config=SynthConfig(rig=Rig.default(), scene=scene, psp_freqs=()),
                 progress=False, noise_free=True)
        a = np.load(tmp_path / name / "000000" / "arrays.npz")
        h = a["height"][a["height"] > 1.0]
        vals, counts = np.unique(np.round(h, 2), return_counts=True)
        tops[name] = vals[np.argmax(counts)]  # the flat top face
        invalid[name] = int((a["mask"] == 0).sum())
    assert tops["plane"] > 5.0
    assert tops["raised"] - tops["plane"] == pytest.approx(25.0, abs=0.02)
    assert invalid["raised"] > 1.5 * invalid["plane"]
