"""fppsim.phase.psp: N-step phase shifting, temporal unwrapping, phase -> 3D (analytic geometry, no rendering)."""

import numpy as np
import pytest

from math import erfc

from fppsim.phase import psp, triangulation
from fppsim.phase import wrap
from _helpers import distorted_rig, reference_plane_height, reference_plane_parameters, synthesize_stack
from fppsim.geometry.rig import DEFAULT_PROJECTOR_ROLL, Device, Rig, make_default_rig, make_figshare_like_rig, make_parallel_rig

TWO_PI = 2 * np.pi


def _angle_diff(a, b):
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


# ------------------------------------------------------------------ the theory the decoder is checked against
def phase_noise_std(image_noise_std, modulation, n_steps: int = 4):
    """Standard deviation (rad) of the N-step wrapped phase for additive image noise:
    ``sigma_phi = sqrt(2/N) * sigma_I / B`` (independent Gaussian noise ``sigma_I`` per image, small-noise limit)."""
    return np.sqrt(2.0 / n_steps) * np.asarray(image_noise_std, np.float64) / np.asarray(modulation, np.float64)


def ladder_stability_bound(freqs=psp.DEFAULT_FREQS) -> float:
    """Largest wrapped-phase error (rad) per frequency for which the ladder never picks a wrong order.

    With correct orders up to step ``i-1`` the absolute phase ``Phi_{i-1}`` carries the error ``e_{i-1}`` of
    its wrapped phase, so the rounding argument of step ``i`` is ``k_true + (r_i e_{i-1} - e_i)/(2 pi)`` with
    ``r_i = f_i/f_{i-1}``. Rounding is right while ``|r_i e_{i-1} - e_i| < pi``; with every ``|e| <= eps``
    that holds for all steps iff ``(1 + r_max) eps < pi``. (1, 8, 80): ``pi/11``; (1, 4, 16, 80): ``pi/6``.
    (The lowest frequency also needs ``Phi_0`` farther than ``eps`` from the 0/2pi seam: ``seam_margin``.)"""
    f = np.asarray(freqs, dtype=np.float64)
    return float(np.pi) if f.size < 2 else float(np.pi / (1.0 + np.max(f[1:] / f[:-1])))


def order_error_probability(phase_noise, freqs=psp.DEFAULT_FREQS) -> float:
    """Expected fraction of pixels with a wrong fringe order for Gaussian phase noise of standard deviation
    ``phase_noise`` (rad) per frequency: step ``i`` fails when ``|r_i e_{i-1} - e_i| > pi``, a Gaussian of
    standard deviation ``phase_noise * sqrt(r_i^2 + 1)``, ``p_i = erfc(pi / (sqrt(2) sigma_i))``; the ladder
    fails with ``1 - prod(1 - p_i)`` (seam errors at the projector edges not included)."""
    f = np.asarray(freqs, dtype=np.float64)
    s = float(phase_noise)
    if s <= 0:
        return 0.0
    ok = 1.0
    for r in f[1:] / f[:-1]:
        ok *= 1.0 - erfc(np.pi / (np.sqrt(2.0) * s * np.sqrt(r * r + 1.0)))
    return 1.0 - ok


# ---------------------------------------------------------------------------------------- N-step
@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_wrapped_phase_exact_and_A_B_recovered(n):
    rng = np.random.default_rng(n)
    phi = rng.uniform(-np.pi, np.pi, size=(64, 80))
    A = rng.uniform(20, 200, size=phi.shape)
    B = rng.uniform(1, 1, size=phi.shape) * rng.uniform(5, 19, size=phi.shape)
    stack = synthesize_stack(phi, A, B, n_steps=n)
    assert stack.shape == (n,) + phi.shape
    res = psp.wrapped_phase(stack)
    assert res.phase.dtype == np.float64
    assert np.max(np.abs(_angle_diff(res.phase, phi))) < 1e-6
    assert np.all((res.phase > -np.pi) & (res.phase <= np.pi))
    np.testing.assert_allclose(res.background, A, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.modulation, B, rtol=0, atol=1e-9)
    # the sums give the same phase and B = (2/N) sqrt(S^2 + C^2)
    s, c = psp.phase_sums(stack)
    np.testing.assert_array_equal(psp.phase_from_sums(s, c), res.phase)
    np.testing.assert_allclose(2.0 / n * np.hypot(s, c), B, atol=1e-9)
    # unpacking
    p, a, b = psp.wrapped_phase(stack)
    np.testing.assert_array_equal(p, res.phase)


def test_four_step_formula_and_integer_input():
    rng = np.random.default_rng(0)
    stack = rng.integers(0, 256, size=(4, 30, 40)).astype(np.uint8)
    I = stack.astype(np.float64)
    res = psp.wrapped_phase(stack)
    np.testing.assert_allclose(res.phase, np.arctan2(I[3] - I[1], I[0] - I[2]), atol=1e-12)
    np.testing.assert_allclose(res.modulation, 0.5 * np.hypot(I[3] - I[1], I[0] - I[2]), atol=1e-12)
    np.testing.assert_allclose(res.background, I.mean(0), atol=1e-12)


def test_sign_convention_of_shifts():
    # I_n = A + B cos(phi + delta_n) with delta_n = 2 pi n / N: phi = 1.0 must come back as +1.0, not -1.0
    stack = synthesize_stack(np.array([1.0]), 100.0, 50.0, n_steps=4)
    np.testing.assert_allclose(stack[:, 0], 100 + 50 * np.cos(1.0 + np.array([0, 0.5, 1, 1.5]) * np.pi))
    assert psp.wrapped_phase(stack).phase[0] == pytest.approx(1.0, abs=1e-12)


def test_non_uniform_shifts_least_squares():
    rng = np.random.default_rng(1)
    phi = rng.uniform(-np.pi, np.pi, size=500)
    shifts = np.array([0.0, 1.3, 2.1, 4.0, 5.5])
    stack = synthesize_stack(phi, 80.0, 30.0, shifts=shifts)
    res = psp.wrapped_phase(stack, shifts=shifts)
    assert np.max(np.abs(_angle_diff(res.phase, phi))) < 1e-9
    np.testing.assert_allclose(res.modulation, 30.0, atol=1e-9)
    np.testing.assert_allclose(res.background, 80.0, atol=1e-9)
    with pytest.raises(ValueError, match="rank"):
        psp.wrapped_phase(np.ones((3, 2)), shifts=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="3 images but 4"):
        psp.wrapped_phase(np.ones((3, 2)), shifts=[0, 1, 2, 3])
    with pytest.raises(ValueError, match=">= 3"):
        psp.phase_shifts(2)


def test_wrap_phase_range():
    w = wrap(np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.5, 7.0, np.nan]))
    np.testing.assert_allclose(w[:6], [np.pi, np.pi, np.pi, np.pi, 0.5, 7.0 - TWO_PI], atol=1e-12)
    assert np.isnan(w[6])
    # exact -pi from atan2 is mapped to +pi
    stack = np.array([[-1.0], [0.0], [1.0], [0.0]])  # I0 - I2 = -2, I3 - I1 = 0
    stack[3] = -0.0
    stack[1] = 0.0
    assert psp.wrapped_phase(stack).phase[0] == np.pi


def test_quality_mask_and_noise_model():
    A = np.array([100.0, 100.0, 100.0, np.nan, 10.0])
    B = np.array([50.0, 5.0, 20.0, 50.0, 9.0])
    np.testing.assert_array_equal(psp.quality_mask(A, B, 10.0), [True, False, True, False, False])
    np.testing.assert_array_equal(psp.quality_mask(A, B, 1.0, min_ratio=0.3), [True, False, False, False, True])
    # sigma_phi = sqrt(2/N) sigma_I / B, checked by Monte Carlo
    rng = np.random.default_rng(2)
    phi = rng.uniform(-np.pi, np.pi, size=100_000)
    stack = synthesize_stack(phi, 100.0, 40.0, n_steps=4) + rng.normal(0, 2.0, size=(4, phi.size))
    err = _angle_diff(psp.wrapped_phase(stack).phase, phi)
    assert np.std(err) == pytest.approx(phase_noise_std(2.0, 40.0, 4), rel=0.03)


# ---------------------------------------------------------------------------------------- unwrapping
def _ladder_phases(u, W, freqs):
    return {f: TWO_PI * f * u / W for f in freqs}


def test_ladder_bound_values_and_bad_ladders():
    assert ladder_stability_bound((1, 8, 80)) == pytest.approx(np.pi / 11)
    assert ladder_stability_bound() == pytest.approx(np.pi / 11)
    assert ladder_stability_bound((1, 4, 16, 80)) == pytest.approx(np.pi / 6)
    assert ladder_stability_bound((1,)) == pytest.approx(np.pi)
    for bad in [(2, 8, 80), (1, 80, 8), (1, 1, 8)]:
        with pytest.raises(ValueError, match="ladder"):
            psp.unwrap_temporal([np.zeros(2)] * 3, freqs=bad)


def test_unwrap_noise_free_range_and_order():
    W = 912
    u = np.linspace(0, W, 20001)[:-1]  # [0, W)
    true = _ladder_phases(u, W, (1, 8, 80))
    wrapped = {f: wrap(p) for f, p in true.items()}
    out = psp.unwrap_temporal(wrapped, seam_margin=0.0)
    np.testing.assert_allclose(out.phase, true[80], atol=1e-9)
    assert out.phase.min() >= 0 and out.phase.max() < TWO_PI * 80
    np.testing.assert_allclose(out.phase, wrapped[80] + TWO_PI * out.order, atol=1e-9)
    assert out.order.dtype == np.int64 and out.order.min() == 0 and out.order.max() == 80
    assert out.reliable.all() and out.residual.max() < 1e-9
    # sequence input, default ladder, and another ladder
    seq = psp.unwrap_temporal([wrapped[1], wrapped[8], wrapped[80]], seam_margin=0.0)
    np.testing.assert_array_equal(seq.phase, out.phase)
    t2 = _ladder_phases(u, W, (1, 4, 16, 80))
    out2 = psp.unwrap_temporal({f: wrap(p) for f, p in t2.items()}, seam_margin=0.0)
    np.testing.assert_allclose(out2.phase, t2[80], atol=1e-9)
    assert out2.freqs == (1, 4, 16, 80)
    # a ladder of one frequency: the 1-period phase in [0, 2 pi)
    one = psp.unwrap_temporal({1: wrapped[1]}, seam_margin=0.0)
    np.testing.assert_allclose(one.phase, true[1], atol=1e-12)


@pytest.mark.parametrize("freqs", [(1, 8, 80), (1, 4, 16, 80)])
def test_unwrap_zero_order_errors_below_bound(freqs):
    rng = np.random.default_rng(3)
    W, n = 912, 200_000
    eps = 0.99 * ladder_stability_bound(freqs)
    u = rng.uniform(0, W, n)
    true = _ladder_phases(u, W, freqs)
    away = (true[1] > eps) & (true[1] < TWO_PI - eps)  # the 0/2pi seam of the 1-period phase
    noise = {f: rng.uniform(-eps, eps, n) for f in freqs}  # worst case: bounded noise at the bound
    out = psp.unwrap_temporal({f: wrap(true[f] + noise[f]) for f in freqs})
    fmax = freqs[-1]
    err = out.phase - (true[fmax] + noise[fmax])
    assert np.max(np.abs(err[away])) < 1e-9  # zero order errors
    # Gaussian noise well inside the bound: no errors, and nothing flagged (max_residual = pi/2 sits
    # 6.6 standard deviations of the residual noise sig * sqrt(r^2 + 1) away)
    sig = ladder_stability_bound(freqs) / 12
    noise = {f: rng.normal(0, sig, n) for f in freqs}
    out = psp.unwrap_temporal({f: wrap(true[f] + noise[f]) for f in freqs})
    err = out.phase - (true[fmax] + noise[fmax])
    assert np.max(np.abs(err[away])) < 1e-9
    margin = (np.pi / 2) / freqs[1]  # default seam margin: max_residual / (f_1 / f_0)
    assert out.reliable[(true[1] > margin + 5 * sig) & (true[1] < TWO_PI - margin - 5 * sig)].all()


def test_unwrap_flags_order_errors_above_bound():
    rng = np.random.default_rng(4)
    W, n, freqs = 912, 200_000, (1, 8, 80)
    u = rng.uniform(0.1 * W, 0.9 * W, n)
    true = _ladder_phases(u, W, freqs)
    # bounded noise above the bound pi/11 but below 3 pi / (2 * 11): wrong orders appear, all are flagged
    eps = 0.4
    assert eps > ladder_stability_bound(freqs)
    noise = {f: rng.uniform(-eps, eps, n) for f in freqs}
    out = psp.unwrap_temporal({f: wrap(true[f] + noise[f]) for f in freqs})
    wrong = np.abs(out.phase - (true[80] + noise[80])) > 1.0
    assert wrong.sum() > 100
    assert not out.reliable[wrong].any()
    # Gaussian noise: the wrong-order fraction matches order_error_probability, >= 95% of them flagged
    sig = 0.12
    noise = {f: rng.normal(0, sig, n) for f in freqs}
    out = psp.unwrap_temporal({f: wrap(true[f] + noise[f]) for f in freqs})
    wrong = np.abs(out.phase - (true[80] + noise[80])) > 1.0
    expected = order_error_probability(sig, freqs)
    assert 0.005 < expected < 0.02
    assert wrong.mean() == pytest.approx(expected, rel=0.15)
    assert (~out.reliable[wrong]).mean() > 0.95
    assert order_error_probability(0.0) == 0.0


def test_unwrap_seam_nan_and_errors():
    W = 912
    # a pixel seeing u_p slightly left of column 0: the 1-period phase wraps to ~2 pi
    u = np.array([-0.3, 0.2, 40.0, 450.0, 911.4])  # seam margin (pi/2)/8 rad = 28.5 columns
    true = _ladder_phases(u, W, (1, 8, 80))
    wrapped = {f: wrap(p) for f, p in true.items()}
    out = psp.unwrap_temporal(wrapped)
    assert not out.reliable[0] and not out.reliable[1] and not out.reliable[4]  # within the seam margin
    assert out.reliable[2] and out.reliable[3]
    assert out.phase[0] == pytest.approx(true[80][0] + TWO_PI * 80)  # wrong by a whole ladder, but flagged
    shifted = psp.unwrap_temporal(wrapped, phase_origin=-np.pi / W, seam_margin=0.0)
    np.testing.assert_allclose(shifted.phase, true[80], atol=1e-9)
    # non-finite input -> NaN phase, order 0, unreliable
    w = {f: p.copy() for f, p in wrapped.items()}
    w[8][3] = np.nan
    out = psp.unwrap_temporal(w)
    assert np.isnan(out.phase[3]) and out.order[3] == 0 and not out.reliable[3]
    assert np.isfinite(out.phase[[0, 1, 2, 4]]).all()
    with pytest.raises(ValueError, match="no wrapped phase for frequencies"):
        psp.unwrap_temporal({1: wrapped[1], 8: wrapped[8]}, freqs=(1, 8, 80))
    with pytest.raises(ValueError, match="3-frequency ladder"):
        psp.unwrap_temporal([wrapped[1], wrapped[80]])
    with pytest.raises(ValueError, match="differ in shape"):
        psp.unwrap_temporal([wrapped[1], wrapped[8], wrapped[80][:2]])
    with pytest.raises(ValueError, match="start at 1"):
        psp.unwrap_temporal({8: wrapped[8], 80: wrapped[80]})


# ---------------------------------------------------------------------------------------- geometry
def _converging_rig():
    r = make_default_rig()
    a = np.arctan2(180.0, 480.0)  # projector at +x, axis turned onto the scene centre
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    R = Ry @ np.diag([1.0, -1.0, -1.0])
    C = np.array([180.0, 0.0, 480.0])
    K = np.array([[1208.8, 2.0, 455.5], [0, 1210.0, 569.5], [0, 0, 1]])  # with a little skew
    proj = Device(K=K, R=R, t=-R @ C, width=912, height=1140, dist=[0.03, 0, 0, 0, 0])
    return Rig(r.camera, proj, periods=80.0, name="converging")


def _scene_points(rig, pixels):
    """First surface along each camera ray: a tilted plane z = 3 + 0.06 x - 0.04 y plus a sphere."""
    o, d = rig.camera.pixel_rays(pixels)
    a = np.array([0.06, -0.04, -1.0])
    s_plane = -(o @ a + 3.0) / (d @ a)
    c, r = np.array([15.0, -10.0, 10.0]), 45.0
    oc = o - c
    b = np.einsum("...i,i->...", d, oc)
    dd = np.einsum("...i,...i->...", d, d)
    disc = b * b - dd * (oc @ oc - r * r)
    with np.errstate(invalid="ignore"):
        s_sph = (-b - np.sqrt(disc)) / dd
    s = np.where(disc > 0, np.minimum(s_sph, s_plane), s_plane)
    return o + s[..., None] * d, disc > 0


def test_phase_direction_against_projector_projection():
    rig = make_default_rig()
    proj = rig.projector
    X = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 20.0]])
    uv, z = proj.project(X)
    assert np.all(z > 0)
    assert uv[0, 0] == pytest.approx((proj.width - 1) / 2)  # default rig: scene centre mid-projector
    assert uv[1, 0] > uv[0, 0]  # projector columns (and phase) increase with world x
    # the default projector is rolled by DEFAULT_PROJECTOR_ROLL (the real fringes lean): 10 mm along
    # world y moves the projector column by about 10 mm * f / 500 mm * sin(roll), not 0
    assert uv[2, 0] - uv[0, 0] == pytest.approx(
        10.0 * proj.K[0, 0] / 523.3 * np.sin(DEFAULT_PROJECTOR_ROLL), rel=0.05)
    assert uv[3, 0] < uv[0, 0]  # a raised point shifts towards smaller u_p (projector at +x)
    phase = rig.phase_of_column(uv[:, 0])
    np.testing.assert_allclose(phase, TWO_PI * 80 * uv[:, 0] / proj.width)
    # the camera pixels of these points, triangulated from their phase, give the points back
    pix, _ = rig.camera.project(X)
    tri = triangulation.triangulate(rig, phase, pixels=pix)
    np.testing.assert_allclose(tri.points, X, atol=1e-9)
    np.testing.assert_allclose(tri.column, uv[:, 0], atol=1e-9)
    np.testing.assert_allclose(tri.row, uv[:, 1], atol=1e-9)


@pytest.mark.parametrize("rig_factory", [make_default_rig, distorted_rig, _converging_rig])
def test_full_chain_round_trip(rig_factory):
    """Known 3D points -> projector columns -> phase-shifted stacks at (1, 8, 80) -> N-step phase ->
    temporal unwrapping -> triangulation: recovers the points (checks every sign convention at once)."""
    rig = rig_factory()
    pixels = rig.camera.pixel_grid()[::4, ::4]
    X, on_sphere = _scene_points(rig, pixels)
    assert on_sphere.mean() > 0.1
    uv, _ = rig.projector.project(X)
    assert np.all((uv[..., 0] > 0) & (uv[..., 0] < rig.projector.width - 1))
    wrapped = {}
    for f in (1, 8, 80):
        stack = synthesize_stack(rig.phase_of_column(uv[..., 0], f), 90.0, 60.0, n_steps=4)
        wrapped[f] = psp.wrapped_phase(stack).phase
    un = psp.unwrap_temporal(wrapped)
    assert un.reliable.all()
    np.testing.assert_allclose(un.phase, rig.phase_of_column(uv[..., 0]), atol=1e-9)
    tri = triangulation.triangulate(rig, un.phase, pixels=pixels)
    assert tri.valid.all()
    assert np.max(np.abs(tri.points - X)) < 1e-6  # mm
    np.testing.assert_array_equal(tri.height, tri.points[..., 2])
    assert np.max(np.abs(tri.height - X[..., 2])) < 1e-6


def test_triangulate_full_grid_mask_and_height_from_phase():
    rig = make_default_rig()
    pixels = rig.camera.pixel_grid()
    X, _ = _scene_points(rig, pixels)
    phase = rig.phase_of_column(rig.projector.project(X)[0][..., 0])
    phase[0, 0] = np.nan
    mask = np.ones(phase.shape, bool)
    mask[5, 7] = False
    tri = triangulation.triangulate(rig, phase, mask=mask)
    assert tri.points.shape == (352, 640, 3) and tri.height.shape == (352, 640)
    assert not tri.valid[0, 0] and not tri.valid[5, 7] and tri.valid.sum() == 352 * 640 - 2
    assert np.isnan(tri.points[0, 0]).all() and np.isnan(tri.height[5, 7])
    np.testing.assert_allclose(tri.points[tri.valid], X[tri.valid], atol=1e-6)
    h = triangulation.height_from_phase(rig, phase, mask=mask)
    np.testing.assert_array_equal(h, tri.height)
    # the camera depth: X = C + depth * ray
    np.testing.assert_allclose(tri.depth[tri.valid], (rig.camera.world_to_device(X))[..., 2][tri.valid], atol=1e-6)
    # phase of another frequency
    h8 = triangulation.height_from_phase(rig, phase * 8 / 80, periods=8)
    np.testing.assert_allclose(h8[tri.valid], h[tri.valid], atol=1e-6)
    with pytest.raises(ValueError, match="camera is 352 x 640"):
        triangulation.triangulate(rig, phase[:10])
    with pytest.raises(ValueError, match="mask has shape"):
        triangulation.triangulate(rig, phase, mask=mask[:10])


@pytest.mark.parametrize("h", [0.0, 5.0, 20.0, 50.0])
def test_reference_plane_formula_matches_triangulation(h):
    """The classic formula is exact for the default parallel-axis rig (same-height centres, axes normal
    to the plane); float64 agreement to 1e-9 mm."""
    rig = make_parallel_rig()
    L, d, f0 = reference_plane_parameters(rig)
    assert (L, d) == (500.0, 180.0)
    assert f0 == pytest.approx(80 * 1208.8 / (912 * 500))
    pixels = rig.camera.pixel_grid()[::8, ::8]
    ref = rig.camera.backproject(pixels, rig.camera.plane_depth(pixels, 0.0))
    obj = rig.camera.backproject(pixels, rig.camera.plane_depth(pixels, h))
    phi_ref = rig.phase_of_column(rig.projector.project(ref)[0][..., 0])
    phi_obj = rig.phase_of_column(rig.projector.project(obj)[0][..., 0])
    dphi = phi_ref - phi_obj
    assert np.all(dphi >= -1e-9)  # heights above the plane: positive dphi with this sign
    h_formula = reference_plane_height(dphi, L, d, f0)
    h_tri = triangulation.height_from_phase(rig, phi_obj, pixels=pixels)
    np.testing.assert_allclose(h_formula, h, atol=1e-9)
    np.testing.assert_allclose(h_tri, h, atol=1e-9)


def test_reference_plane_formula_on_curved_surface_and_other_rigs():
    rig = make_parallel_rig()
    pixels = rig.camera.pixel_grid()[::8, ::8]
    X, _ = _scene_points(rig, pixels)
    ref = rig.camera.backproject(pixels, rig.camera.plane_depth(pixels, 0.0))
    dphi = rig.phase_of_column(rig.projector.project(ref)[0][..., 0]) - \
        rig.phase_of_column(rig.projector.project(X)[0][..., 0])
    np.testing.assert_allclose(reference_plane_height(dphi, *reference_plane_parameters(rig)),
                               X[..., 2], atol=1e-9)
    with pytest.raises(ValueError, match="perpendicular"):
        reference_plane_parameters(_converging_rig())
    with pytest.raises(ValueError, match="perpendicular"):  # the figshare-like rig's projector is yawed
        reference_plane_parameters(make_figshare_like_rig())
    # closed form on numbers: dphi = 2 pi f0 d h / (L - h)
    L, d, f0, hh = 400.0, 150.0, 0.1, 25.0
    assert reference_plane_height(TWO_PI * f0 * d * hh / (L - hh), L, d, f0) == pytest.approx(hh)


def test_order_consistency_flags_isolated_order_errors_and_keeps_edges():
    from fppsim.phase.psp import order_consistency

    H, W = 20, 30
    u = np.tile(np.arange(W, dtype=float), (H, 1))
    phase = 2 * np.pi * 80 * u / 912 + 0.0
    phase[:, 15:] += 4 * np.pi  # a genuine depth edge: 2 periods jump between two surfaces
    wrong = phase.copy()
    wrong[5, 5] += 2 * np.pi  # isolated wrong fringe order
    wrong[10, 20] -= 20 * np.pi
    valid = np.ones((H, W), bool)
    valid[0, :] = False
    ok = order_consistency(wrong, valid)
    assert not ok[5, 5] and not ok[10, 20]
    assert ok[1:, :].sum() == (H - 1) * W - 2  # every other valid pixel, including both edge columns
    assert not ok[0].any()  # invalid stays invalid


def test_decode_stacks_full_chain():
    from fppsim.phase.psp import decode_stacks
    from fppsim.geometry.rig import Rig

    rig = Rig.default()
    cam = rig.camera
    uv = cam.pixel_grid()
    X = cam.backproject(uv, cam.plane_depth(uv, plane_z=12.5))  # a plane 12.5 mm above the reference
    u_p = rig.projector.project(X)[0][..., 0]
    stacks = {f: np.rint(synthesize_stack(2 * np.pi * f * u_p / 912, 120.0, 100.0)).astype(np.uint8)
              for f in (1, 8, 80)}
    d = decode_stacks(stacks, rig)
    assert d.valid.mean() > 0.99
    assert np.nanmax(np.abs(d.height - 12.5)) < 0.02
    assert decode_stacks(stacks, None).height is None
