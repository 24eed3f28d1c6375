"""uhrnet.models: exact parameter counts, output shapes, registry, and that each model can learn."""

from __future__ import annotations

import pytest
import torch

from uhrnet.models import count_parameters
from uhrnet.models import build_model, list_models

PAPER_COUNTS = {
    ("uhrnet", ()): 30_330_977,
    ("uhrnet", (("fusion", False),)): 26_114_881,
    ("unet", ()): 31_030_593,
    ("unet", (("base_channels", 32),)): 7_759_521,
    ("model_a", ()): 7_759_521,
    ("model_b", ()): 26_114_881,
    ("model_c", ()): 30_330_977,
    ("model_d", ()): 30_330_977,
    ("hnet", ()): 8_632_261,
}


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    """Tiny models on a shared machine run 10-30x faster on one thread than on an oversubscribed pool."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


TINY = {"uhrnet": 4, "unet": 4, "hnet": 2, "model_a": 2, "model_b": 4}


@pytest.mark.parametrize(("name", "options"), list(PAPER_COUNTS), ids=lambda v: str(v))
def test_exact_parameter_counts(name, options):
    assert count_parameters(build_model(name, **dict(options))) == PAPER_COUNTS[(name, options)]


def test_hnet_within_paper_tolerance():
    assert abs(count_parameters(build_model("hnet")) - 8.63e6) <= 0.005 * 8.63e6


def _forward(model, x):
    with torch.no_grad():
        return model(x)


@pytest.mark.parametrize("name", ["uhrnet", "unet", "hnet", "model_b"])
def test_full_width_output_shape_64x96(name):
    model = build_model(name).eval()
    assert _forward(model, torch.randn(1, 1, 64, 96)).shape == (1, 1, 64, 96)


@pytest.mark.parametrize("name", list(TINY))
def test_output_shape_352x640(name):
    model = build_model(name, base_channels=TINY[name]).eval()
    assert _forward(model, torch.randn(1, 1, 352, 640)).shape == (1, 1, 352, 640)


def test_hnet_returns_fused_plus_five_sides_in_training_only():
    model = build_model("hnet", base_channels=2)
    x = torch.randn(2, 1, 32, 48)
    outs = _forward(model.train(), x)
    assert isinstance(outs, tuple) and len(outs) == 6
    assert all(o.shape == (2, 1, 32, 48) for o in outs)
    fused = _forward(model.eval(), x)
    assert torch.is_tensor(fused) and fused.shape == (2, 1, 32, 48)


def test_hnet_guidance_upsampling_starts_bilinear():
    branch = build_model("hnet", base_channels=2).guidance[0]  # bottleneck: x16 transposed conv
    up = branch[-1]
    out = up(torch.ones(1, 1, 4, 6))
    assert out.shape == (1, 1, 64, 96)
    assert torch.allclose(out[..., 8:-8, 8:-8], torch.ones(()))  # exact interpolation away from borders


@pytest.mark.parametrize("name", ["uhrnet", "unet", "hnet"])
def test_rejects_sizes_not_divisible_by_16(name):
    with pytest.raises(ValueError, match="multiples of 16"):
        _forward(build_model(name, base_channels=4).eval(), torch.randn(1, 1, 40, 64))


def test_in_out_channels_and_channels_last():
    model = build_model("uhrnet", base_channels=4, in_channels=3, out_channels=2).eval()
    x = torch.randn(1, 3, 32, 32)
    ref = _forward(model, x)
    assert ref.shape == (1, 2, 32, 32)
    model = model.to(memory_format=torch.channels_last)
    fast = _forward(model, x.contiguous(memory_format=torch.channels_last))
    assert torch.allclose(ref, fast, atol=1e-5)


def test_registry_names_and_errors():
    assert set(list_models()) == {"uhrnet", "unet", "hnet", "model_a", "model_b", "model_c", "model_d"}
    with pytest.raises(ValueError, match="known models: uhrnet, unet, hnet"):
        build_model("resnet")
    with pytest.raises(ValueError, match="fusion"):
        build_model("model_b", fusion=True)
    with pytest.raises(ValueError, match="does not take"):
        build_model("unet", fusion=False)
    with pytest.raises(ValueError, match="divisible by 4"):
        build_model("uhrnet", base_channels=6)
    assert build_model("UHRNet", base_channels=4).config["name"] == "uhrnet"


@pytest.mark.parametrize("name", ["uhrnet", "model_b", "model_a", "hnet", "model_d"])
def test_config_rebuilds_same_architecture(name):
    model = build_model(name, base_channels=4)
    assert model.config["name"] == name and model.config["base_channels"] == 4
    clone = build_model(**model.config)
    clone.load_state_dict(model.state_dict())  # same layers, same shapes
    assert clone.config == model.config


@pytest.mark.parametrize("name", ["uhrnet", "model_b", "unet", "hnet"])
def test_one_adam_step_lowers_loss_on_fixed_batch(name):
    torch.manual_seed(0)
    options = {"dropout": 0.0} if name in ("uhrnet", "model_b", "hnet") else {}
    model = build_model(name, base_channels=4, **options).train()
    x = torch.randn(2, 1, 32, 32)
    target = torch.nn.functional.avg_pool2d(x, 3, 1, 1)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss_value():
        out = model(x)
        outs = out if isinstance(out, (tuple, list)) else (out,)
        return sum(torch.nn.functional.mse_loss(o, target) for o in outs)

    before = loss_value()
    optimizer.zero_grad()
    before.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    optimizer.step()
    with torch.no_grad():
        after = loss_value()
    assert after.item() < before.item()


def test_a_registered_head_takes_its_own_options(monkeypatch):
    """build_model knows no head: a registered head's options reach its wrapper, and no other head takes them."""
    from torch import nn

    from uhrnet.models import heads

    class Scaled(nn.Module):
        def __init__(self, backbone, rig, factor=1.0):
            super().__init__()
            self.backbone, self.factor = backbone, factor
            self.config = {**backbone.config, "head": "scaled", "factor": factor}

        def forward(self, x):
            return self.backbone(x) * self.factor

    monkeypatch.setitem(heads.HEADS, "scaled", heads.Head("scaled", wrap=Scaled, options=("factor",)))
    model = build_model("unet", head="scaled", factor=2.0, base_channels=4)
    assert isinstance(model, Scaled) and model.factor == 2.0
    again = build_model(**model.config)  # the config rebuilds it, as a checkpoint does
    assert isinstance(again, Scaled) and again.factor == 2.0
    with pytest.raises(ValueError, match="factor= belong to the scaled head"):
        build_model("unet", factor=2.0, base_channels=4)
