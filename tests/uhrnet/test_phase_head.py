"""The physics head (uhrnet.models.phase_head): every architecture with head="phase", its phase offset against
analytic truth, PhaseHeadLoss, and a tiny `uhrnet train --head phase` run whose checkpoint the other commands
take unchanged."""

import json
import math

import numpy as np
import pytest
import torch

from uhrnet.cli import main
from uhrnet.models import build_model, list_models, outputs_of
from uhrnet.physics.rig_layer import RigLayer

from _helpers import tiny_rig, wrap_phase, write_figshare, write_native_rig

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def rig():
    return tiny_rig()


@pytest.mark.parametrize("name", list_models())
def test_every_model_takes_the_phase_head_and_rebuilds_from_its_config(name, rig):
    torch.manual_seed(0)
    model = build_model(name, head="phase", rig=rig.to_dict(), base_channels=4)
    assert model.config["head"] == "phase" and model.config["out_channels"] == 3
    x = torch.rand(2, 1, 32, 64) * 2 - 1
    model.train()
    outs = outputs_of(model(x))
    assert len(outs) == (6 if model.config.get("name") == "hnet" else 1)  # hNet: fused + 5 side outputs
    assert all(o.shape == (2, 1, 32, 64) for o in outs)
    assert len(model.last_parts) == len(outs)
    model.eval()
    with torch.no_grad():
        y = model(x)
    assert isinstance(y, torch.Tensor) and y.shape == (2, 1, 32, 64) and torch.isfinite(y).all()
    assert model.last_parts == []
    config = json.loads(json.dumps(model.config))  # what a checkpoint stores
    again = build_model(**config)
    again.load_state_dict(model.state_dict())
    again.eval()
    with torch.no_grad():
        assert torch.equal(again(x), y)
    with pytest.raises(ValueError, match="rig sees 64x32"):
        model(torch.zeros(1, 1, 32, 32))


def test_the_phase_head_needs_a_rig_and_the_rig_needs_the_head():
    with pytest.raises(ValueError, match="needs the rig"):
        build_model("unet", head="phase", base_channels=4)
    with pytest.raises(ValueError, match="belong to the phase head"):
        build_model("unet", rig={}, base_channels=4)
    with pytest.raises(ValueError, match="unknown head"):
        build_model("unet", head="depth", base_channels=4)


def _crafted(rig, origin, coarse_dphi, confidence=1.0):
    """A backbone output for the analytic bump: coarse height whose phase is off by ``coarse_dphi`` (rad), and
    (cos, sin) of ``phase_true + origin`` (fppsim's forward model, not the head's layer) times ``confidence``."""
    from fppsim.fitting.height_sensitivity import surface_phase

    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    h = 12.0 * np.exp(-((xx - 30) ** 2 + (yy - 15) ** 2) / (2 * 9.0 ** 2))
    phase = surface_phase(rig, h)
    layer = RigLayer(rig)
    coarse_mm = layer.height_from_phase(torch.from_numpy(phase + coarse_dphi)).numpy()
    out = np.stack([coarse_mm / 10.0, confidence * np.cos(phase + origin), confidence * np.sin(phase + origin)])
    return h, torch.from_numpy(out[None]).float()


@pytest.mark.parametrize("origin", [0.0, 1.3, -2.6, 72.0])
def test_the_phase_offset_is_removed_and_the_exact_height_recovered(rig, origin):
    """The measured phase counts from another origin (a real projector's pattern phase): the head estimates it
    per image and subtracts it. The coarse height's phase error is a symmetric pattern within half a period,
    so the weighted circular mean of (phi_w - Phi_c) is exactly the origin."""
    head = build_model("unet", head="phase", rig=rig.to_dict(), base_channels=4)
    xx = np.arange(rig.camera.width)[None, :].repeat(rig.camera.height, 0)
    dphi = 0.45 * math.pi * np.sin(2 * np.pi * 2 * xx / xx.shape[1])  # two whole periods: symmetric values
    h, out = _crafted(rig, origin, dphi)
    parts = head._combine(out)
    assert float(parts["offset"]) == pytest.approx(float(wrap_phase(origin)), abs=1e-4)
    height_mm = 10.0 * parts["height"][0, 0].numpy()
    assert np.abs(height_mm - h).max() < 2e-3
    if origin:  # the opposite sign convention would miss by 2 * origin / sensitivity
        wrong = RigLayer(rig).height_from_phase(torch.from_numpy(parts["phase"][0, 0].double().numpy() + 2 * float(
            parts["offset"]))).numpy()
        assert np.abs(wrong - h).mean() > 1.0


def test_untrusted_phase_keeps_the_coarse_height(rig):
    head = build_model("unet", head="phase", rig=rig.to_dict(), base_channels=4, min_confidence=0.3)
    h, out = _crafted(rig, 0.5, 0.3, confidence=0.2)
    parts = head._combine(out)
    np.testing.assert_allclose(parts["height"].numpy(), out[:, :1].numpy(), atol=1e-6)  # (10 c) / 10
    assert float(parts["confidence"].max()) == pytest.approx(0.2)


def _loss_setup(rig):
    from fppsim.fitting.height_sensitivity import surface_phase
    from uhrnet.training.losses import L2Loss, PhaseHeadLoss

    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    h = 8.0 * np.exp(-((xx - 30) ** 2 + (yy - 15) ** 2) / (2 * 8.0 ** 2))
    phase = surface_phase(rig, h)
    mask = np.ones(h.shape, np.float32)
    mask[:, 50:54] = 0  # a shadow
    target = torch.from_numpy((6.0 * h - 97.0)[None, None]).float()
    m = torch.from_numpy(mask[None, None])
    ph = torch.from_numpy(phase[None, None]).float()
    perfect = torch.from_numpy(np.stack([h / 10.0, np.cos(phase) * mask, np.sin(phase) * mask])[None]).float()
    loss = PhaseHeadLoss(L2Loss(), scale=60.0, shift=-97.0, mm_per_unit=1 / 6)
    return loss, perfect, target, m, ph


def test_phase_head_loss_is_zero_for_perfect_outputs_and_positive_otherwise(rig):
    head = build_model("unet", head="phase", rig=rig.to_dict(), base_channels=4)
    loss, perfect, target, m, ph = _loss_setup(rig)
    zero = float(loss([head._combine(perfect)], target, m, ph))
    assert zero < 1e-3
    for k, change in enumerate((0.3, 0.3, 0.3)):  # coarse 3 mm off / phase rotated / (cos, sin) in the shadow
        bad = perfect.clone()
        if k == 0:
            bad[:, 0] += change
        elif k == 1:
            c, s = bad[:, 1].clone(), bad[:, 2].clone()
            bad[:, 1], bad[:, 2] = c * math.cos(change) - s * math.sin(change), c * math.sin(change) + s * math.cos(change)
        else:
            bad[:, 1:, :, 50:54] = 0.5
        assert float(loss([head._combine(bad)], target, m, ph)) > 100 * zero + 1e-2
    # without a phase (real samples) the phase term is absent, the rest stays
    assert float(loss([head._combine(perfect)], target, m, None)) < 1e-3


def test_phase_head_loss_descends_to_zero(rig):
    """Gradient descent on the raw backbone output from a perturbed start reaches ~0 (the loss's minimum is
    the perfect output)."""
    head = build_model("unet", head="phase", rig=rig.to_dict(), base_channels=4)
    loss, perfect, target, m, ph = _loss_setup(rig)
    g = torch.Generator().manual_seed(0)
    out = (perfect + 0.1 * torch.randn(perfect.shape, generator=g)).requires_grad_(True)
    opt = torch.optim.Adam([out], lr=0.01)
    first = None
    for _ in range(300):
        value = loss([head._combine(out)], target, m, ph)
        first = float(value.detach()) if first is None else first
        opt.zero_grad()
        value.backward()
        opt.step()
    assert float(value.detach()) < 0.01 * first


@pytest.fixture(scope="module")
def phase_run(tmp_path_factory, rig):
    """One epoch of `uhrnet train --head phase` on 6 native samples of the tiny rig (their meta.json's rig)."""
    tmp = tmp_path_factory.mktemp("phase_head")
    write_native_rig(tmp / "syn", rig, n=6, seed=1)
    torch.set_num_threads(1)
    rc = main(["train", "--synthetic", str(tmp / "syn"), "--synthetic-split", "train", "--head", "phase",
               "--model", "unet", "--base-channels", "4", "--epochs", "1", "--batch-size", "2", "--loss", "l2",
               "--lr", "1e-3", "--out", str(tmp / "run"), "--no-progress", "--no-augment"])
    assert rc == 0
    return tmp


def test_a_phase_head_checkpoint_goes_through_every_command_unchanged(phase_run, rig, tmp_path, capsys):
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint

    run = phase_run / "run"
    ck = load_checkpoint(run / "last.pt")
    assert ck["model"]["config"]["head"] == "phase"
    assert ck["model"]["config"]["rig"]["camera"]["width"] == 64  # the samples' rig, from their meta.json
    model, _ = model_from_checkpoint(ck)
    again = build_model(**ck["model"]["config"])
    again.load_state_dict(ck["state_dict"])  # config round trip through the checkpoint
    capsys.readouterr()
    # predict (rig and image size agree), evaluate, export with its check
    np.save(tmp_path / "x.npy", np.zeros((32, 64), np.float32))
    assert main(["predict", str(run), str(tmp_path / "x.npy"), "--out", str(tmp_path / "p"), "--no-progress",
                 "--no-ply"]) == 0
    assert np.load(tmp_path / "p" / "x_height.npy").shape == (32, 64)
    assert main(["evaluate", str(run / "last.pt"), "--out", str(tmp_path / "e"), "--split", "train"]) == 0
    assert main(["export", str(run / "last.pt"), "--out", str(tmp_path / "m.onnx"), "--check", "--height", "32",
                 "--width", "64"]) == 0
    assert (tmp_path / "m.onnx").stat().st_size > 1000
    # timing, as bench measures models (bench itself builds models by name, not from checkpoints)
    from uhrnet.scoring.timing import inference_seconds

    assert inference_seconds(model, (1, 1, 32, 64), warmup=0, repeats=1) > 0


def test_head_phase_refusals_are_one_line(tmp_path, capsys):
    write_figshare(tmp_path / "fig", n=4, h=32, w=64)
    base = ["train", "--synthetic", str(tmp_path / "fig"), "--head", "phase", "--base-channels", "4", "--epochs", "1",
            "--no-progress"]
    assert main([*base, "--crop", "16x32", "--out", str(tmp_path / "a")]) == 2  # options that never go together
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--head phase needs whole camera images" in err[0] and "--crop" in err[0]
    assert main([*base, "--out", str(tmp_path / "b")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no native/ folder" in err[0] and str(tmp_path / "fig") in err[0]
    assert not (tmp_path / "b" / "last.pt").exists()
