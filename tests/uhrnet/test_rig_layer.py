"""uhrnet.physics.rig_layer.RigLayer: the differentiable phase <-> height layer equals fppsim's triangulation."""

import json

import numpy as np
import pytest
import torch

from _helpers import distorted_rig, reference_plane_height, reference_plane_parameters
from fppsim.fitting.height_sensitivity import centre_sensitivity, surface_phase
from fppsim.geometry.rig import Rig, data_path, make_default_rig
from fppsim import phase as np_phase
from fppsim.phase.triangulation import height_from_phase, triangulate
from uhrnet.physics.rig_layer import RigLayer, circular_mean, wrap

pytestmark = pytest.mark.usefixtures("one_thread")


RIGS = {
    "default": make_default_rig,
    "parallel": lambda: Rig.load(data_path("parallel_rig.json")),
    "figshare_like": lambda: Rig.load(data_path("figshare_like_rig.json")),
    "distorted": distorted_rig,
}


def _surface(cam, peak=35.0):
    """(H, W) float64 height map, mm: a bump on the plane plus ripples and a dent below it."""
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    r2 = ((xx - cam.width * 0.55) ** 2 + (yy - cam.height * 0.45) ** 2) / (0.18 * cam.width) ** 2
    return peak * np.exp(-r2) + 4.0 * np.sin(xx / 23.0) * np.cos(yy / 31.0) - 6.0 * (xx < 40)


@pytest.fixture(scope="module", params=list(RIGS))
def case(request):
    rig = RIGS[request.param]()
    h = _surface(rig.camera)
    return request.param, rig, RigLayer(rig), h, surface_phase(rig, h)


def test_height_from_phase_equals_fppsim(case):
    name, rig, layer, h, phase = case
    ref = height_from_phase(rig, phase)
    out, ok = layer.height_from_phase(torch.from_numpy(phase)[None, None], return_valid=True)
    out, ok = out[0, 0].numpy(), ok[0, 0].numpy()
    assert out.dtype == np.float64
    assert np.array_equal(ok, np.isfinite(ref)) and ok.all()
    assert np.abs(out - ref).max() < 1e-9, name  # measured ~4e-13 (1.6e-11 distorted)
    assert np.abs(out - h).max() < 1e-9
    # float32 phase in, float64 arithmetic inside: only the input's rounding (~3e-5 mm)
    out32 = layer.height_from_phase(torch.from_numpy(phase).float())
    assert out32.dtype == torch.float32
    assert np.abs(out32.numpy() - ref).max() < 1e-4
    # float32 arithmetic throughout
    lay32 = RigLayer(rig, compute_dtype=torch.float32)
    assert np.abs(lay32.height_from_phase(torch.from_numpy(phase).float()).numpy() - ref).max() < 5e-4


def test_phase_from_height_equals_fppsim_and_round_trips(case):
    name, rig, layer, h, phase = case
    th = torch.from_numpy(h)
    ph = layer.phase_from_height(th).numpy()
    assert np.abs(ph - phase).max() < 1e-9
    back = layer.phase_from_height(layer.height_from_phase(torch.from_numpy(phase))).numpy()
    assert np.abs(back - phase).max() < 1e-9
    assert np.abs(layer.height_from_phase(layer.phase_from_height(th)).numpy() - h).max() < 1e-9


def test_validity_matches_fppsim_over_a_wide_range():
    """Random phases reaching far outside any plausible scene: the same valid pixels as fppsim."""
    rng = np.random.default_rng(1)
    every = (slice(None, None, 3), slice(None, None, 3))  # a strided grid keeps it fast
    for rig, span in ((make_default_rig(), (-800.0, 400.0)), (distorted_rig(), (-300.0, 120.0))):
        layer = RigLayer(rig, pixels=every)
        uv = rig.camera.pixel_grid()[every]
        phase = layer.plane_phase().numpy() + rng.uniform(*span, layer.grid_shape)
        phase[::7, ::5] = np.nan
        ref = triangulate(rig, phase, pixels=uv).height
        out, ok = layer.height_from_phase(torch.from_numpy(phase), return_valid=True)
        assert np.array_equal(ok.numpy(), np.isfinite(ref))
        assert np.isnan(out.numpy()[~ok.numpy()]).all()
        assert np.nanmax(np.abs(out.numpy() - ref)) < 1e-8


def test_parallel_rig_closed_form():
    rig = Rig.load(data_path("parallel_rig.json"))
    layer = RigLayer(rig)
    L, d, f0 = reference_plane_parameters(rig)
    h = _surface(rig.camera)
    phase = layer.phase_from_height(torch.from_numpy(h))
    dphi = (layer.plane_phase() - phase).numpy()
    assert np.abs(reference_plane_height(dphi, L, d, f0) - h).max() < 1e-9
    out = layer.height_from_phase(phase).numpy()
    assert np.abs(out - reference_plane_height(dphi, L, d, f0)).max() < 1e-9


def test_windows_and_resized_grids_match_fppsim_pixels():
    rig = distorted_rig()
    cam = rig.camera
    rows, cols = slice(100, 140), slice(300, 380, 2)
    crop = RigLayer(rig, pixels=(rows, cols))
    full = RigLayer(rig)
    h = _surface(cam)
    phase = surface_phase(rig, h)
    assert crop.grid_shape == (40, 40)
    assert np.abs(crop.height_from_phase(torch.from_numpy(phase[rows, cols])).numpy() - h[rows, cols]).max() < 1e-9
    assert torch.equal(crop.plane_phase(), full.plane_phase()[rows, cols])
    # a half-size image: its pixel (i, j) is camera pixel (2 j + 0.5, 2 i + 0.5)
    half = RigLayer(rig, height=cam.height // 2, width=cam.width // 2)
    vv, uu = np.mgrid[0:cam.height // 2, 0:cam.width // 2] * 2.0 + 0.5
    uv = np.stack([uu, vv], axis=-1)
    ph = np.random.default_rng(0).uniform(-20, 20, uu.shape) + half.plane_phase().numpy()
    ref = triangulate(rig, ph, pixels=uv).height
    assert np.abs(half.height_from_phase(torch.from_numpy(ph)).numpy() - ref).max() < 1e-9
    explicit = RigLayer(rig, pixels=uv[:5, :7])
    assert np.abs(explicit.height_from_phase(torch.from_numpy(ph[:5, :7])).numpy() - ref[:5, :7]).max() < 1e-9
    with pytest.raises(ValueError, match="grid"):
        half.height_from_phase(torch.zeros(cam.height, cam.width))


@pytest.mark.parametrize("rig_factory", [make_default_rig, distorted_rig])
def test_gradcheck(rig_factory):
    rig = rig_factory()
    layer = RigLayer(rig, pixels=(slice(170, 173), slice(310, 314)))
    g = torch.Generator().manual_seed(0)
    h = (torch.rand((2, 1, 3, 4), generator=g, dtype=torch.float64) * 60 - 10).requires_grad_()
    assert torch.autograd.gradcheck(layer.phase_from_height, (h,))
    phase = layer.phase_from_height(h.detach()).requires_grad_()
    assert torch.autograd.gradcheck(layer.height_from_phase, (phase,))
    assert torch.autograd.gradcheck(layer.sensitivity, (h,))


def test_sensitivity_is_the_derivative(case):
    name, rig, layer, h, phase = case
    th = torch.from_numpy(h)
    s = layer.sensitivity(th)
    fd = (layer.phase_from_height(th + 1e-4) - layer.phase_from_height(th - 1e-4)) / 2e-4
    assert torch.allclose(s, fd, rtol=1e-6, atol=0)
    cam = rig.camera
    centre = layer.sensitivity(0.0)[cam.height // 2, cam.width // 2].item()
    assert centre == pytest.approx(centre_sensitivity(rig, dh=1e-4), rel=1e-5)
    if name in ("default", "figshare_like"):
        assert centre == pytest.approx(-0.87, abs=0.02)  # DESIGN.md: -0.87 rad per mm at the centre


def test_invalid_pixels_are_nan_with_zero_gradient():
    layer = RigLayer(make_default_rig(), pixels=(slice(0, 4), slice(0, 4)))
    phase = layer.plane_phase().clone()
    phase[0, 0] = float("nan")
    phase[1, 1] = -1e6  # the intersection lies behind the camera
    phase.requires_grad_()
    h, ok = layer.height_from_phase(phase, return_valid=True)
    assert not ok[0, 0] and not ok[1, 1] and ok.sum() == 14
    assert torch.isnan(h[~ok]).all()
    torch.where(ok, h, torch.zeros_like(h)).sum().backward()
    assert torch.isfinite(phase.grad).all() and phase.grad[0, 0] == 0 and phase.grad[1, 1] == 0


def test_layer_is_the_torch_twin_of_the_rig_forward_model(case):
    """RigLayer.phase_from_height / sensitivity equal fppsim.geometry.rig.Rig.phase_at_height / sensitivity (the one
    numpy ray cut, Device.ray_cut) on every pixel."""
    name, rig, layer, h, phase = case
    np.testing.assert_allclose(layer.phase_from_height(torch.from_numpy(h)).numpy(), rig.phase_at_height(h),
                               rtol=0, atol=1e-9)
    grid = rig.camera.pixel_grid()
    s = layer.sensitivity(torch.full(layer.grid_shape, 5.0, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(s, rig.sensitivity(5.0 - 1e-4, 5.0 + 1e-4, grid), rtol=1e-5, atol=1e-7)


def test_torch_phase_helpers_equal_fppsim_phase():
    """uhrnet.physics.rig_layer.wrap / circular_mean are the torch twins of fppsim.phase.wrap / circular_mean."""
    rng = np.random.default_rng(3)
    edges = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.0, -0.0, np.nextafter(-np.pi, 0), 1e-300, np.nan])
    for p in (rng.uniform(-np.pi, np.pi, 4000), rng.uniform(-40, 40, 4000), edges):
        got, ref = wrap(torch.from_numpy(p)).numpy(), np_phase.wrap(p)
        assert np.array_equal(got, ref, equal_nan=True)
    x = torch.tensor([3 * np.pi, 0.5], requires_grad=True)
    wrap(x).sum().backward()
    assert torch.equal(x.grad, torch.ones(2))
    p, w = rng.uniform(-9, 9, (2, 1, 5, 7)), rng.uniform(0, 1, (2, 1, 5, 7))
    got = circular_mean(torch.from_numpy(p), torch.from_numpy(w))
    assert got.shape == (2, 1, 1, 1)
    for i in range(2):
        assert got[i].item() == pytest.approx(np_phase.circular_mean(p[i], weights=w[i]), abs=1e-12)


def test_dtype_device_and_serialisation():
    rig = distorted_rig()
    layer = RigLayer(rig, pixels=(slice(10, 20), slice(30, 50)))
    assert layer.state_dict() == {}  # the geometry follows from the rig, not from checkpoints
    layer.float()
    layer.half()
    layer.to("cpu", torch.bfloat16)
    assert layer.A.dtype == torch.float64 and layer.ray_ok.dtype == torch.bool
    phase = layer.plane_phase() - 3.0
    ref = layer.height_from_phase(phase)
    for d in (layer.to_dict(), json.loads(json.dumps(layer.to_dict()))):
        again = RigLayer.from_dict(d)
        assert again.grid_shape == layer.grid_shape
        assert torch.equal(again.height_from_phase(phase), ref)
    bare = RigLayer.from_dict(rig.to_dict())  # a checkpoint's config["rig"]
    assert bare.grid_shape == (rig.camera.height, rig.camera.width)
    assert torch.equal(bare.plane_phase()[10:20, 30:50], layer.plane_phase())
    with pytest.raises(ValueError, match="explicit"):
        RigLayer(rig, pixels=np.zeros((2, 2, 2))).to_dict()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    rig = distorted_rig()
    layer = RigLayer(rig)
    h = torch.from_numpy(_surface(rig.camera))[None, None]
    cpu = layer.height_from_phase(layer.phase_from_height(h))
    gpu = layer.to("cuda").height_from_phase(layer.phase_from_height(h.cuda()))
    assert layer.A.is_cuda and layer.A.dtype == torch.float64
    assert (gpu.cpu() - cpu).abs().max() < 1e-9
    g32 = layer.height_from_phase(layer.phase_from_height(h.cuda().float()))
    assert g32.dtype == torch.float32 and (g32.cpu().double() - h).abs().max() < 1e-4
