"""uhrnet train --init: N(0, 2/fan_in) convolutions (the U-Net paper), or PyTorch's default."""

import math

import pytest
import torch
from torch import nn

from uhrnet.cli import main
from uhrnet.checkpoint import load_checkpoint
from uhrnet.models import build_model
from uhrnet.models.init import init_weights

from _helpers import write_native


def test_he_weights_have_the_papers_standard_deviation():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(64, 96, 3), nn.Conv2d(96, 48, 1, groups=2),
                        nn.ConvTranspose2d(128, 64, 2, stride=2), nn.ConvTranspose2d(64, 32, 3, stride=4))
    init_weights(net, "he")
    # incoming values of one output: in/groups * kh * kw, divided by the stride area for a transposed conv
    fan_ins = [64 * 9, 48 * 1, 128 * 4 / 4, 64 * 9 / 16]
    for layer, n in zip(net, fan_ins):
        w = layer.weight.double()
        assert abs(w.mean().item()) < 4 * math.sqrt(2 / n) / math.sqrt(w.numel())
        assert w.std().item() == pytest.approx(math.sqrt(2 / n), rel=0.05), (layer, n)
        assert torch.count_nonzero(layer.bias) == 0


def test_convolutions_before_a_batch_norm_keep_torchs_initialisation():
    torch.manual_seed(1)
    built = build_model("uhrnet", base_channels=4)
    torch.manual_seed(1)
    net = init_weights(build_model("uhrnet", base_channels=4), "he")
    before_bn = net.encoder.blocks[0].branches[3][1][0]  # conv of a ConvBNAct
    assert torch.equal(before_bn.weight, built.encoder.blocks[0].branches[3][1][0].weight)
    assert not torch.equal(net.head.weight, built.head.weight)  # no batch norm after the head
    assert not torch.equal(net.decoder.stages[0].up.weight, built.decoder.stages[0].up.weight)


def test_auto_is_he_without_batch_norm_and_torch_with_it():
    for name, same_as in (("unet", "he"), ("hnet", "he"), ("uhrnet", "torch"), ("model_b", "torch")):
        nets = []
        for scheme in ("auto", same_as):
            torch.manual_seed(4)
            nets.append(init_weights(build_model(name, base_channels=4), scheme))
        for (k, a), b in zip(nets[0].state_dict().items(), nets[1].state_dict().values()):
            assert torch.equal(a, b), (name, k)


def test_hnets_bilinear_upsamplers_survive_every_scheme():
    from uhrnet.models.hnet import bilinear_kernel_

    for scheme in ("auto", "he", "torch"):
        torch.manual_seed(0)
        net = init_weights(build_model("hnet", base_channels=4), scheme)
        ups = [m for m in net.modules() if isinstance(m, nn.ConvTranspose2d) and getattr(m, "keep_init", False)]
        assert ups, "hnet has guidance upsamplers"
        for up in ups:
            expected = bilinear_kernel_(torch.empty_like(up.weight), up.stride[0])
            assert torch.equal(up.weight, expected), scheme


def test_he_keeps_a_relu_unet_alive_where_torchs_default_fades():
    """The point of the option: without normalisation PyTorch's default shrinks the signal about
    six-fold in variance per ReLU layer, so the bottleneck of a U-Net is nearly silent."""
    x = torch.rand(1, 1, 64, 64) * 2 - 1
    stds = {}
    for scheme in ("he", "torch"):
        torch.manual_seed(0)
        net = init_weights(build_model("unet", base_channels=8), scheme).eval()
        seen = []
        hook = net.bottleneck.register_forward_hook(lambda m, i, o: seen.append(o.std().item()))
        with torch.no_grad():
            net(x)
        hook.remove()
        stds[scheme] = seen[0] / x.std().item()
    assert 0.2 < stds["he"] < 5, stds
    assert stds["torch"] < 0.1, stds


def test_torch_scheme_is_the_model_as_built_and_he_is_seeded():
    torch.manual_seed(3)
    built = build_model("hnet", base_channels=4)
    torch.manual_seed(3)
    kept = init_weights(build_model("hnet", base_channels=4), "torch")
    for (k, a), b in zip(built.state_dict().items(), kept.state_dict().values()):
        assert torch.equal(a, b), k
    nets = []
    for _ in range(2):
        torch.manual_seed(5)
        nets.append(init_weights(build_model("uhrnet", base_channels=4), "he"))
    for (k, a), b in zip(nets[0].state_dict().items(), nets[1].state_dict().values()):
        assert torch.equal(a, b), k
    with pytest.raises(ValueError, match="unknown init 'xavier'"):
        init_weights(built, "xavier")


def _train(tmp_path, name, extra):
    return main(["train", "--synthetic", str(tmp_path / "syn"), "--model", "unet", "--base-channels", "4",
                 "--epochs", "1", "--batch-size", "2", "--seed", "2", "--out", str(tmp_path / name),
                 "--no-progress", *extra])


@pytest.mark.slow  # two trainings
def test_train_records_init_and_rejects_an_unknown_one(tmp_path, one_thread, capsys):
    write_native(tmp_path / "syn", n=6, h=32, w=64, seed=1)
    assert _train(tmp_path, "he", []) == 0
    assert _train(tmp_path, "torch", ["--init", "torch"]) == 0
    he, old = (load_checkpoint(tmp_path / n / "last.pt") for n in ("he", "torch"))
    assert he["args"]["init"] == "auto" and old["args"]["init"] == "torch"
    assert not torch.equal(he["state_dict"]["head.weight"], old["state_dict"]["head.weight"])
    with pytest.raises(SystemExit) as exit_:
        _train(tmp_path, "bad", ["--init", "xavier"])
    assert exit_.value.code == 2
    assert "--init" in capsys.readouterr().err
