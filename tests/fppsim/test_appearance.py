"""fppsim.rendering.optics appearance effects: each one changes the rendered image the way it should."""

import numpy as np
import pytest

pytest.importorskip("pyrender")

from fppsim.rendering.optics import Optics, OpticsRanges  # noqa: E402
from fppsim.geometry.rig import make_default_rig  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    import trimesh

    from fppsim.rendering.render import DepthRenderer, Instance, scene_geometry

    rig = make_default_rig()
    m = trimesh.creation.icosphere(4, radius=30.0)
    T = np.eye(4)
    T[2, 3] = 0.0  # a hemisphere-like dome 30 mm tall at the origin
    geom = scene_geometry(rig, [Instance(np.asarray(m.vertices), np.asarray(m.faces, np.int32), T)], DepthRenderer())
    return rig, geom


def _render(scene, seed=0, **kw):
    from fppsim.rendering.optics import form_images

    rig, geom = scene
    opt = Optics(noise_sigma=0.0, shot_noise=0.0, **kw)
    return form_images(geom, rig, opt, [(80.0, 0.0), (80.0, np.pi)], None, 1, np.random.default_rng(seed))


def _background(imgs):
    """A + B cos + A - B cos: twice the fringe-free image."""
    return imgs[0].astype(float) + imgs[1].astype(float)


def _modulation(imgs):
    return np.abs(imgs[0].astype(float) - imgs[1].astype(float))


def test_defaults_are_off_and_ranges_do_not_draw_them():
    o = Optics()
    assert (o.albedo_texture, o.dirt, o.specular, o.subsurface, o.vignetting) == (0, 0, 0, 0, 0)
    a = OpticsRanges().sample(np.random.default_rng(1))
    b = OpticsRanges(dirt=(0.1, 0.2)).sample(np.random.default_rng(1))
    assert a.gain == b.gain and 0.1 <= b.dirt <= 0.2 and a.dirt == 0


def test_albedo_texture_varies_the_plane_brightness_seeded(scene):
    rig, geom = scene
    plane = ~geom.on_object & geom.lit
    ref = _background(_render(scene))
    tex = _background(_render(scene, albedo_texture=0.3))
    ratio = tex[plane] / np.maximum(ref[plane], 1)
    assert 0.15 < ratio.std() < 0.45  # about the requested relative std
    np.testing.assert_array_equal(_render(scene, 3, albedo_texture=0.3)[0], _render(scene, 3, albedo_texture=0.3)[0])
    assert not np.array_equal(_render(scene, 3, albedo_texture=0.3)[0], _render(scene, 4, albedo_texture=0.3)[0])


def test_dirt_darkens_about_the_requested_fraction(scene):
    rig, geom = scene
    ok = geom.lit
    ref = _background(_render(scene))
    dirty = _background(_render(scene, dirt=0.2))
    darker = (dirty[ok] < 0.9 * ref[ok]).mean()
    assert 0.08 < darker < 0.25
    assert np.all(dirty[ok] <= ref[ok] + 2)  # stains only darken


def test_vignetting_falls_off_towards_the_corners(scene):
    ref = _background(_render(scene))
    vig = _background(_render(scene, vignetting=0.3))
    h, w = ref.shape
    corner = vig[:20, :20].mean() / ref[:20, :20].mean()
    centre_col = vig[h // 2 - 5:h // 2 + 5, 5:25].mean() / ref[h // 2 - 5:h // 2 + 5, 5:25].mean()
    assert corner == pytest.approx(0.7, abs=0.05)
    assert centre_col > corner  # the middle of the left edge is less attenuated than the corner


def test_specular_brightens_the_object_where_the_lobe_points(scene):
    from fppsim.rendering.optics.specular import specular_term

    rig, geom = scene
    obj = geom.on_object & geom.lit
    ref = _background(_render(scene))
    spec = _background(_render(scene, specular=0.5))
    lobe = specular_term(geom.points, geom.normals, rig.camera.center, rig.projector.center)
    peak = obj & (lobe > 0.8)
    assert peak.any()
    assert (spec[peak] / np.maximum(ref[peak], 1)).mean() > 1.2
    low = obj & (lobe < 1e-4)
    gain_low = (spec[low] / np.maximum(ref[low], 1)).mean() - 1
    gain_peak = (spec[peak] / np.maximum(ref[peak], 1)).mean() - 1
    assert gain_low < 0.5 * gain_peak


def test_subsurface_blurs_the_fringes_on_plaster_only(scene):
    rig, geom = scene
    obj = geom.on_object & geom.lit
    plane = ~geom.on_object & geom.lit
    ref, sub = _modulation(_render(scene)), _modulation(_render(scene, subsurface=2.0))
    assert sub[obj].mean() < 0.8 * ref[obj].mean()
    from scipy.ndimage import binary_erosion

    far = plane & binary_erosion(~geom.on_object, iterations=10)
    np.testing.assert_array_equal(sub[far], ref[far])
