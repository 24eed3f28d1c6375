"""Single-shot phase (fppsim.phase.single_shot.single_shot_phase): analytic truth, masks, intensity invariance, the
reliability ranking the error, a rendered fppsim sample against its exact phase_true, the real frame."""

from __future__ import annotations

import numpy as np
import pytest

from _helpers import SHARED, figurine_on_black
from fppsim.phase.single_shot import SINGLE_SHOT_METHODS, SingleShotPhase, single_shot_phase
from fppsim.phase import wrap as wrap_phase

REAL_PHASE = SHARED / "real-phase" / "FP1523"


def _analytic(h=128, w=256, noise=1.0, seed=0, bump=3.0):
    """(image float64, phi rad) of ``A + B cos(phi)``: a carrier whose period drifts 12.06 -> 11.40 px left to
    right, fringe lines leaning -1.34 deg (like the real rig), plus a smooth phase bump of ``bump`` rad;
    smooth background and amplitude, Gaussian noise (grey levels)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    p0, p1 = 12.06, 11.40
    f = 1.0 / p0 + (1.0 / p1 - 1.0 / p0) * xx / (w - 1)  # local frequency along rows (cycles/px)
    carrier = 2 * np.pi * (xx / p0 + 0.5 * (1.0 / p1 - 1.0 / p0) * xx ** 2 / (w - 1))
    tilt = np.tan(np.deg2rad(-1.34))
    phi = carrier - 2 * np.pi * f * tilt * yy  # lines u = u0 + tan(tilt) v: lean left going down
    phi += bump * np.exp(-((xx - 0.55 * w) ** 2 + (yy - 0.5 * h) ** 2) / (2 * (0.12 * w) ** 2))
    a = 60 + 20 * xx / w + 10 * np.sin(yy / h * np.pi)
    b = 45 + 10 * np.cos(xx / w * np.pi)
    img = a + b * np.cos(phi) + np.random.default_rng(seed).normal(0, noise, (h, w))
    return img, phi


def _inner(shape, margin):
    m = np.zeros(shape, bool)
    m[margin:-margin, margin:-margin] = True
    return m


def test_analytic_truth_recovered_without_offset():
    img, phi = _analytic()
    for method in SINGLE_SHOT_METHODS:
        r = single_shot_phase(img, method=method)
        assert isinstance(r, SingleShotPhase) and r.method == method
        assert r.wrapped.dtype == np.float32 and r.wrapped.shape == img.shape
        assert r.wrapped.min() > -np.pi - 1e-6 and r.wrapped.max() <= np.pi + 1e-6
        err = np.abs(wrap_phase(r.wrapped - phi))[_inner(img.shape, 24)]
        assert np.median(err) < 0.05, (method, np.median(err))  # measured 0.005 (ftp), 0.007 (rows)
        assert np.percentile(err, 99) < 0.15, (method, np.percentile(err, 99))
    r = single_shot_phase(img)
    assert 11.4 < r.period < 12.1 and -2.0 < r.tilt < -0.7 and r.carrier[0] > 0
    assert r.valid.all() and r.reliability.min() >= 0 and r.reliability.max() <= 1
    # the modulation is the amplitude B (35..55 grey levels here)
    assert 30 < np.median(r.modulation) < 60


def test_direction_conjugates_and_period_hint():
    img, phi = _analytic(noise=0.5)
    r = single_shot_phase(img)
    rm = single_shot_phase(img, direction=-1)
    np.testing.assert_allclose(rm.wrapped, -r.wrapped, atol=1e-5)
    rh = single_shot_phase(img, period=11.7)
    assert abs(rh.period - r.period) < 0.05
    assert np.median(np.abs(wrap_phase(rh.wrapped - phi))[_inner(img.shape, 24)]) < 0.05


def test_masked_and_dark_regions_get_zero_reliability():
    img, phi = _analytic()
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    shadow = (yy - 64) ** 2 + (xx - 80) ** 2 < 18 ** 2  # a projector shadow: intensity 0, as in iPattern
    img[shadow] = 0.0
    user = np.ones((h, w), bool)
    user[10:30, 180:230] = False  # a user mask over perfectly good fringes
    img[5, 5] = np.nan
    r = single_shot_phase(img, mask=user)
    for region in (shadow, ~user):
        assert not r.valid[region].any()
        assert np.all(r.reliability[region] == 0) and np.all(r.modulation[region] == 0)
        assert np.all(r.error[region] == np.float32(np.pi))
    assert r.reliability[5, 5] == 0 and np.isfinite(r.wrapped).all()
    # the rest is still measured: away from the holes and the border the error stays small
    from scipy.ndimage import binary_dilation

    far = _inner(img.shape, 24) & ~binary_dilation(shadow | ~user, iterations=12)
    assert np.median(np.abs(wrap_phase(r.wrapped - phi))[far]) < 0.05
    # pixels next to the holes are less reliable than those far from them
    near = binary_dilation(shadow, iterations=3) & ~shadow
    assert np.median(r.reliability[near]) < np.median(r.reliability[far])


def test_invariant_to_brightness_scaling_and_the_figshare_encoding():
    img, _ = _analytic()
    img8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    img8[40:60, 100:140] = 0  # a shadow, which becomes -1 in the figshare encoding
    ref = single_shot_phase(img8)
    for other in (img8.astype(np.float32) * 0.37 + 5.0, img8.astype(np.float32) / 127.5 - 1.0,
                  (img8.astype(np.float32) / 127.5 - 1.0)[..., None]):
        r = single_shot_phase(other)
        assert np.array_equal(r.valid, ref.valid)
        assert np.abs(wrap_phase(r.wrapped - ref.wrapped)).max() < 1e-4
        np.testing.assert_allclose(r.reliability, ref.reliability, atol=1e-4)
    assert not ref.valid[40:60, 100:140].any()


def test_reliability_ranks_the_error():
    """A phase cliff, a dark low-modulation patch and a noisy patch: the reliability orders the pixels by error."""
    img, phi = _analytic(noise=1.5)
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    step = (xx > 150) & (yy > 70)
    phi2 = phi + 2.0 * step  # a height step: the phase jumps by 2 rad
    a, b = 60.0, 45.0
    lowmod = (xx < 60) & (yy < 50)
    bb = np.where(lowmod, 6.0, b)
    img = a + bb * np.cos(phi2) + np.random.default_rng(3).normal(0, 1.5, (h, w))
    r = single_shot_phase(img)
    err = np.abs(wrap_phase(r.wrapped - phi2))
    rel = r.reliability[r.valid]
    e = err[r.valid]
    lo, hi = np.quantile(rel, [0.2, 0.8])
    assert np.median(e[rel >= hi]) < 0.5 * np.median(e[rel <= lo])
    assert np.mean(e[rel >= hi]) < 0.5 * np.mean(e[rel <= lo])
    # the step and the dim patch are flagged
    near_step = (np.abs(xx - 150) <= 2) & (yy > 72) | (np.abs(yy - 70) <= 2) & (xx > 152)
    assert np.median(r.reliability[near_step]) < 0.5 < np.median(r.reliability[_inner((h, w), 24) & ~step & ~lowmod])
    assert np.median(r.error[lowmod & _inner((h, w), 12)]) > 2 * np.median(r.error[_inner((h, w), 24) & ~step & ~lowmod])


def test_bad_inputs_raise_value_errors():
    img, _ = _analytic(h=32, w=64)
    with pytest.raises(ValueError, match="2-D"):
        single_shot_phase(np.zeros((2, 32, 64)))
    with pytest.raises(ValueError, match="too small"):
        single_shot_phase(np.zeros((8, 64)))
    with pytest.raises(ValueError, match="method"):
        single_shot_phase(img, method="magic")
    with pytest.raises(ValueError, match="direction"):
        single_shot_phase(img, direction=0)
    with pytest.raises(ValueError, match="mask shape"):
        single_shot_phase(img, mask=np.ones((3, 3), bool))
    with pytest.raises(ValueError):
        single_shot_phase(np.full((32, 64), 7.0))  # no fringes at all
    with pytest.raises(ValueError, match="finite"):
        single_shot_phase(np.full((32, 64), np.nan))


def test_rendered_sample_matches_phase_true(tmp_path):
    """One rendered fppsim sample (a box on the plane, default rig and optics): the single-shot phase of
    fringe.png is wrap(phase_true) with no offset (the single-shot pattern has phase shift 0)."""
    import trimesh
    from scipy.ndimage import binary_dilation

    from fppsim.rendering import synth
    from fppsim.generation import load_assets
    from fppsim.rendering.render import DepthRenderer
    from fppsim.geometry.rig import Rig

    trimesh.creation.box(extents=(60.0, 40.0, 25.0)).export(tmp_path / "box.ply")
    assets, _ = load_assets([str(tmp_path / "box.ply")])
    config = synth.SynthConfig(rig=Rig.default(), psp_freqs=(), min_object_fraction=0.0)
    r = DepthRenderer()
    try:
        images, arrays, _ = synth.synthesize(0, 5, assets, config, r)
    finally:
        r.close()
    res = single_shot_phase(images["fringe.png"])
    mask = arrays["mask"] > 0
    hgt = arrays["height"]
    steps = np.zeros_like(mask)
    steps[:, 1:] |= np.abs(np.diff(hgt, axis=1)) > 2.0
    steps[1:, :] |= np.abs(np.diff(hgt, axis=0)) > 2.0
    edge = binary_dilation(steps | ~mask, iterations=3) | ~_inner(mask.shape, 3)
    err = wrap_phase(res.wrapped - arrays["phase_true"])
    good = mask & ~edge
    assert abs(np.median(err[good])) < 0.01  # no offset
    e = np.abs(err[good])
    assert np.median(e) < 0.03 and np.percentile(e, 90) < 0.1  # measured 0.008 / 0.021
    assert np.median(res.reliability[~mask]) < 0.05
    ev, rv = np.abs(err[mask]), res.reliability[mask]
    lo, hi = np.quantile(rv, [0.2, 0.8])
    assert np.median(ev[rv >= hi]) < np.median(ev[rv <= lo])


@pytest.mark.skipif(not (REAL_PHASE / "iPattern").is_dir(), reason="../shared/real-phase absent")
def test_real_frame_against_its_psp_phase():
    """FP1523/1201: iPattern's single-shot phase equals the public absolute phase
    atan2(-PSin, -PCos) + pi + 2 pi Order, wrapped, with the same sign and an offset of about 0."""
    from fppsim.dataio.readers import load_psp_folder_sample

    s = load_psp_folder_sample(REAL_PHASE, "1201")
    r = single_shot_phase(s.image)
    assert 11.4 < r.period < 12.0 and -2.0 < r.tilt < -0.8  # the rig's fringes: about 11.7 px, -1.34 deg
    v = s.valid & r.valid
    assert (s.valid != r.valid).mean() < 0.01  # the dark-run rule finds the benchmark's invalid pixels
    d = wrap_phase(r.wrapped - s.phase)
    off = float(np.angle(np.mean(np.exp(1j * d[v]))))
    assert abs(off) < 0.05  # measured -0.011 rad
    e = np.abs(wrap_phase(d - off))
    assert np.median(e[v]) < 0.04 and np.percentile(e[v], 90) < 0.25  # measured 0.028 / 0.18
    hi = v & (r.reliability > 0.5)
    assert hi.sum() > 0.6 * v.sum() and np.median(e[hi]) < np.median(e[v]) and np.percentile(e[hi], 90) < 0.1


@pytest.mark.parametrize("period, angle_deg", [(11.7, 0.0), (22.0, 90.0), (9.0, -35.0), (15.0, 60.0), (2.6, 0.0), (3.0, 90.0)])
def test_local_carrier_reads_period_and_axis_from_the_wrapped_steps_with_objects_on_black(period, angle_deg):
    """A carrier of known period and direction, half the frame black (no phase) and a bump on the lit half: the
    period and the gradient's axis (sign-free) come back from the wrapped phase's steps; too few reliable pixels
    give NaN and 0 votes."""
    from fppsim.phase.fringe_axis import local_carrier

    yy, xx = np.mgrid[0:200, 0:300].astype(float)
    a = np.radians(angle_deg)
    phase = 2 * np.pi * (xx * np.cos(a) + yy * np.sin(a)) / period
    phase += 3.0 * np.exp(-((xx - 220) ** 2 + (yy - 100) ** 2) / (2 * 25.0 ** 2))  # an object's relief
    wrapped = np.angle(np.exp(1j * phase))
    rel = np.where(xx > 150, 1.0, 0.0)
    wrapped[xx <= 150] = np.nan
    got_period, got_axis, votes = local_carrier(wrapped, rel)
    assert votes > 0.4 * wrapped.size
    assert got_period == pytest.approx(period, rel=0.05)
    assert abs((np.degrees(got_axis) - angle_deg + 90) % 180 - 90) < 2.0  # the same axis either sign
    assert local_carrier(wrapped, np.zeros_like(rel))[2] == 0
    assert np.isnan(local_carrier(wrapped, np.zeros_like(rel))[0])


@pytest.mark.parametrize("period, noise, across", [(8.0, 0.0, False), (10.5, 2.0, False), (14.0, 0.0, True),
                                                   (20.0, 2.0, True)])
def test_fringe_carrier_reads_a_figurines_fringes_not_its_outline(period, noise, across):
    """A figurine on black as FP672/541 without its plane shows it (a bright side with fringes, a dim side, slow
    shading, exact or noisy black): the plain spectrum's peak, where the single-shot phase demodulates when no period
    is given, is the outline's and shading's (34-65 px here; 34-56 px on FP672, whose plane's fringes are 10.5 px), so
    fit-rig refused the plane's period there. fringe_carrier (the spectrum weighted by the frequency squared) gives
    the lit side's fringes, in either direction (``across``: the image transposed, horizontal fringes)."""
    from fppsim.errors import InputError
    from fppsim.phase.fringe_axis import fringe_carrier, oriented_single_shot_phase

    img, _, _, truth = figurine_on_black(period, noise)
    img = img.T if across else img
    fx, fy = fringe_carrier(img, img > 0)
    assert 1.0 / np.hypot(fx, fy) == pytest.approx(truth, rel=0.04)  # measured 0.1-2.6 % off
    along, other = (fy, fx) if across else (fx, fy)
    assert abs(other) < 0.1 * abs(along)  # the fringes' direction (sign-free), within 6 deg (measured 0.1-3.0)
    plain = oriented_single_shot_phase(img.astype(np.float64), "horizontal" if across else "vertical", mask=img > 0)
    assert plain.period > 2.5 * truth  # what made the image hard
    with pytest.raises(InputError):
        fringe_carrier(np.zeros((64, 64)), np.zeros((64, 64), bool))


def test_fringe_carrier_says_in_one_line_where_there_are_no_fringes_to_read():
    """A blank or saturated image has nothing to read, but the round-off of its local mean did: a carrier of 63 px
    on a constant 3, 200 or 255 and 2.8 px on a saturated disc on black (0 and 128 happened to round to nothing). An
    image too small or not 2-D (8 x 8, three channels) read a carrier or failed in numpy. Each is now one InputError."""
    from fppsim.errors import InputError
    from fppsim.phase.fringe_axis import fringe_carrier

    rr, cc = np.mgrid[0:352, 0:640]
    disc = np.where(((cc - 320) / 120.0) ** 2 + ((rr - 176) / 100.0) ** 2 < 1, 255.0, 0.0)
    for img, valid in [(np.full((352, 640), v), None) for v in (0.0, 3.0, 128.0, 200.0, 255.0)] + [(disc, disc > 0)]:
        with pytest.raises(InputError, match="no fringes found"):
            fringe_carrier(img, valid)  # before: (4.5e-07, -0.0158) on the constants, 2.8 px on the disc
    fringes = 120 + 100 * np.cos(2 * np.pi * cc / 11.7)
    for img, valid in [(fringes[:8, :8], None), (np.dstack([fringes] * 3), None), (fringes, np.ones((10, 10), bool))]:
        with pytest.raises(InputError, match="2-D image of 16 px a side"):
            fringe_carrier(img, valid)
    assert 1 / np.hypot(*fringe_carrier(np.clip(fringes + 100, 0, 255))) == pytest.approx(11.7, rel=0.01)  # half lit
