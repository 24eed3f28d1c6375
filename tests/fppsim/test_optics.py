"""Image-formation model: pattern profile, parameter sampling, noise, saturation, gamma."""

import re

import numpy as np
import pytest

from fppsim.rendering.optics import Optics, OpticsRanges, form_image, pattern_profile, projector_radiance


def test_pattern_profile_phase_period_and_quantisation():
    sharp = Optics(projector_blur=0.0, pixelated=True, pattern_bits=8, projector_gamma=1.0)
    u, p = pattern_profile(912, 80, 0.0, sharp)
    assert u[0] == pytest.approx(-0.5 + 0.5 / 8) and u[-1] == pytest.approx(911.5 - 0.5 / 8)
    assert p.min() >= 0 and p.max() <= 1
    assert np.allclose(np.unique(np.rint(p * 255)) / 255, np.unique(p))  # 8-bit DMD levels
    # DMD column c shows cos(2 pi f c / W) for its whole width
    cols = np.arange(912)
    np.testing.assert_allclose(projector_radiance(cols.astype(float), 912, 80, 0.0, sharp),
                               np.rint(255 * (0.5 + 0.5 * np.cos(2 * np.pi * 80 * cols / 912))) / 255, atol=1e-12)
    # continuous, unquantised, defocused: still a cosine of the right phase (amplitude reduced by the blur)
    smooth = Optics(projector_blur=1.0, pixelated=False, pattern_bits=0)
    x = np.linspace(100, 800, 2001)
    v = projector_radiance(x, 912, 80, 0.3, smooth)
    k = 2 * np.pi * 80 / 912
    design = np.stack([np.ones_like(x), np.cos(k * x + 0.3), np.sin(k * x + 0.3)], 1)
    c, *_ = np.linalg.lstsq(design, v, rcond=None)
    assert c[0] == pytest.approx(0.5, abs=1e-3) and abs(c[2]) < 1e-3
    assert c[1] == pytest.approx(0.5 * np.exp(-0.5 * k ** 2), rel=1e-2)  # Gaussian MTF at the fringe frequency


def test_projector_gamma_bends_the_pattern():
    g = Optics(projector_blur=0.0, pixelated=False, pattern_bits=0, projector_gamma=2.2)
    assert projector_radiance(np.array([912 / 80 / 4]), 912, 80, 0.0, g)[0] == pytest.approx(0.5 ** 2.2, rel=3e-3)  # linear interpolation of the 1/8-px profile


def test_ranges_sample_deterministic_and_fixed():
    r = OpticsRanges()
    a, b = r.sample(np.random.default_rng(3)), r.sample(np.random.default_rng(3))
    assert a == b
    assert r.gain[0] <= a.gain <= r.gain[1]
    fixed = OpticsRanges.fixed(a)
    assert fixed.sample(np.random.default_rng(99)) == a
    assert OpticsRanges.from_dict({"noise_sigma": 0}).noise_sigma == (0.0, 0.0)
    with pytest.raises(ValueError, match="unknown optics parameter"):
        OpticsRanges.from_dict({"gian": [1, 2]})
    with pytest.raises(ValueError, match="lo <= hi"):
        OpticsRanges.from_dict({"gain": [3, 1]})


def test_form_image_noise_saturation_gamma():
    H, W = 200, 300
    base = np.full((H, W), 50.0, np.float32)
    mod = np.full((H, W), 100.0, np.float32)
    pat = np.full((H, W), 0.5, np.float32)  # E = 100 gray levels
    o = Optics(camera_blur=0.0, noise_sigma=2.0, shot_noise=0.1)
    img = form_image((base, mod), pat, o, np.random.default_rng(0))
    assert img.dtype == np.uint8
    assert img.mean() == pytest.approx(100, abs=0.1)
    assert img.std() == pytest.approx(np.sqrt(2.0 ** 2 + 0.1 * 100 + 1 / 12), rel=0.03)
    assert np.array_equal(img, form_image((base, mod), pat, o, np.random.default_rng(0)))  # seeded
    assert np.all(form_image((base * 10, mod), pat, Optics(camera_blur=0), None) == 255)  # saturation
    gam = form_image((base, mod), pat, Optics(camera_blur=0, camera_gamma=2.0), None)
    assert gam[0, 0] == round(255 * (100 / 255) ** 0.5)
    # supersampled blocks are averaged
    ss = form_image((np.zeros((6, 9), np.float32), np.ones((6, 9), np.float32) * 90),
                    np.tile(np.array([0, 1, 2], np.float32), (6, 3)), Optics(camera_blur=0), None, scale=3)
    assert ss.shape == (2, 3) and np.all(ss == 90)


def test_every_parameter_is_declared_once_and_the_classes_derive_from_the_declarations():
    from dataclasses import fields
    from pathlib import Path

    from fppsim.rendering import optics
    from fppsim.rendering.optics import EFFECTS, MODEL, OPTICS_LIMITS, OPTICS_UNITS, SITES
    from fppsim.rendering.optics.model import interval

    declared = [p for e in EFFECTS for p in e.params]
    names = [p.name for p in declared]
    assert len(names) == len(set(names))
    assert [f.name for f in fields(Optics)] == names == [f.name for f in fields(OpticsRanges)]
    assert all(e.site in SITES for e in EFFECTS)
    numbers = [p for p in declared if p.sample is not None]
    assert list(OPTICS_LIMITS) == OpticsRanges.range_names() == [p.name for p in numbers]
    assert OPTICS_LIMITS == {p.name: interval(p.limits) for p in numbers}
    assert OPTICS_UNITS == {p.name: p.unit for p in numbers if p.unit}
    assert Optics() == Optics(**{p.name: p.default for p in declared})
    r = OpticsRanges()
    for p in declared:
        assert getattr(r, p.name) == (tuple(p.sample) if p.sample is not None else p.default)
    assert Optics.model is MODEL and OpticsRanges.model is MODEL
    # the reach of the blurs (the camera blur's 4 sigma) sets the margin a sample renders
    assert OpticsRanges().render_margin() == 4 and OpticsRanges(camera_blur=(0.3, 1.1)).render_margin() == 5
    # the stage and the sample code name no effect: they run whatever the model declares
    root = Path(optics.__file__).parents[1]
    for module in (root / "optics" / "stage.py", root / "synth.py"):
        text = module.read_text()
        assert not [n for n in names if re.search(rf"\.{n}\b|['\"]{n}['\"]", text)], module


def test_limits_refuse_values_outside_and_name_the_parameter():
    with pytest.raises(ValueError, match=r"optics 'dirt' must be in \[0, 1\], got 1.5"):
        Optics(dirt=1.5)
    with pytest.raises(ValueError, match=r"optics 'vignetting' must be in \[0, 1\), got 1"):
        OpticsRanges.from_dict({"vignetting": [0.0, 1.0]})
    with pytest.raises(ValueError, match="optics 'pixelated' must be true or false"):
        Optics(pixelated="yes")
    assert Optics().noise_free().noise_sigma == 0.0 and Optics().noise_free().shot_noise == 0.0


def _toy_effect():
    """A fringe-contrast knob on the pattern the camera sees: P -> 0.5 + c (P - 0.5); c = 1 is off."""
    from fppsim.rendering.optics import Effect, Param

    def apply(pattern, optics, ctx):
        return (0.5 + optics.fringe_contrast * (pattern - 0.5)).astype(pattern.dtype)

    return Effect("fringe contrast", "camera_pattern",
                  (Param("fringe_contrast", 1.0, (0.2, 0.4), "[0, 1]", off=1.0, doc="toy."),), apply)


def test_a_new_effect_is_one_declaration_end_to_end():
    from fppsim.rendering.optics import EFFECTS, OpticsModel, form_images
    from fppsim.rendering.render import plane_geometry
    from fppsim.geometry.rig import Rig

    toy = OpticsModel(EFFECTS + (_toy_effect(),))
    # derived: a field, a default range, limits, the --optics names
    assert toy.Optics().fringe_contrast == 1.0 and toy.OpticsRanges().fringe_contrast == (0.2, 0.4)
    assert toy.limits["fringe_contrast"] == (0.0, True, 1.0, True)
    assert toy.OpticsRanges.range_names()[-1] == "fringe_contrast"
    with pytest.raises(ValueError, match="optics 'fringe_contrast' must be in"):
        toy.OpticsRanges.from_dict({"fringe_contrast": 2})
    # appended at the end: the earlier parameters keep their random draws
    a = OpticsRanges().sample(np.random.default_rng(7)).to_dict()
    b = toy.OpticsRanges().sample(np.random.default_rng(7)).to_dict()
    assert 0.2 <= b.pop("fringe_contrast") <= 0.4 and a == b
    # the stage runs it: off gives the very images of the default model, 0 removes the fringes
    rig = Rig.default()
    geom = plane_geometry(rig)
    shifts = [(80.0, 0.0), (80.0, np.pi)]
    plain = form_images(geom, rig, Optics(), shifts, None)
    same = form_images(geom, rig, toy.Optics(), shifts, None)
    flat = form_images(geom, rig, toy.Optics(fringe_contrast=0.0), shifts, None)
    assert all(np.array_equal(x, y) for x, y in zip(plain, same))
    assert np.abs(plain[0].astype(int) - plain[1]).mean() > 20
    assert np.abs(flat[0].astype(int) - flat[1]).max() <= 1


def test_declarations_are_checked():
    from fppsim.rendering.optics import Effect, OpticsModel, Param
    from fppsim.rendering.optics.shading import SHADING

    with pytest.raises(ValueError, match="unknown site 'lens'"):
        Effect("x", "lens", (), lambda v, o, c: v)
    with pytest.raises(ValueError, match="'gain' is declared twice"):
        OpticsModel((SHADING, SHADING))
    with pytest.raises(ValueError, match="must declare sample"):
        Param("half", 0.5, (0.0, 1.0))


def test_optics_classes_pickle_by_their_published_name():
    """Spawned generator workers receive OpticsRanges by pickle: the derived classes must be found where
    fppsim.rendering.optics publishes them (Python 3.12's make_dataclass had set __module__ to fppsim.rendering.optics.model,
    which broke `generate --workers 2` there)."""
    import pickle

    from fppsim.rendering.optics import Optics, OpticsRanges

    for cls in (Optics, OpticsRanges):
        assert cls.__module__ == "fppsim.rendering.optics"
        obj = cls()
        assert pickle.loads(pickle.dumps(obj)) == obj
