"""Issue 49: the speed options (uhrnet.training.speed), the samples on the device (uhrnet.data.device_data) and
their augmentation there (uhrnet.data.device_augment), checked on a CPU: the CPU's defaults are the old path,
the device path gives the CPU's batches and the CPU augmentation's distribution."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from scipy.ndimage import gaussian_filter

from tests._helpers import scene, write_figshare
from uhrnet.cli import main
from uhrnet.data.augment import AugmentConfig, augment_sample
from uhrnet.data.datasets import MixedSampler, Prepared, load_sources
from uhrnet.data.device_augment import augment_fringes, draw, gaussian_blur
from uhrnet.data.device_data import DeviceLoader, DeviceSet
from uhrnet.training.builders import match_layout
from uhrnet.training.distributed import DistInfo, MetricSums
from uhrnet.training.speed import DeviceSums, LossWatch, resolve_speed
from uhrnet.training.train_config import RunConfig


def test_cpu_defaults_are_the_old_path():
    sp = resolve_speed(RunConfig(amp=True), torch.device("cpu"))
    assert sp.amp_dtype == torch.bfloat16 and not sp.scaler
    assert not (sp.channels_last or sp.epoch_sync or sp.fused_adam or sp.compile) and sp.device_data == "auto"
    asked = resolve_speed(RunConfig(channels_last="on", host_sync="epoch", fused_adam="on"), torch.device("cpu"))
    assert asked.channels_last and asked.epoch_sync and asked.fused_adam


def test_gaussian_blur_is_scipys():
    x = np.random.default_rng(0).uniform(0, 255, (40, 56))
    for sigma in (0.7, 1.2, 6.0):
        got = gaussian_blur(torch.from_numpy(x)[None, None], sigma)[0, 0].numpy()
        assert np.allclose(got, gaussian_filter(x, sigma, mode="nearest"), atol=1e-9)


def _sample(seed=1, h=48, w=96):
    fr, z = write_figshare_arrays(seed, h, w)
    mask = (z > -100).astype(np.float32)
    return {"fringe": torch.from_numpy(fr)[None], "height": torch.from_numpy(z)[None],
            "mask": torch.from_numpy(mask)[None], "source": "synthetic"}


def write_figshare_arrays(seed, h, w):
    f8, hmm, valid = scene(np.random.default_rng(seed), h, w)
    fr = (f8.astype(np.float32) / 127.5 - 1).astype(np.float32)
    fr[~valid] = -1.0
    z = (hmm * 6.0 - 97.0).astype(np.float32)
    z[~valid] = -105.0
    return fr, z


def test_device_augmentation_draws_the_cpus_parameters():
    """Noise off: the device's image is the CPU's up to an 8-bit level (float32 against float64)."""
    cfg = AugmentConfig(noise=(0.0, 0.0), shot=(0.0, 0.0), probability=1.0)
    s = _sample()
    valid = s["mask"][None] > 0.5
    for seed in range(6):
        cpu = augment_sample(s, seed, cfg)["fringe"]
        dev = augment_fringes(s["fringe"][None], valid, [draw(seed, s["fringe"].shape[-2:], cfg)], None)[0]
        levels = ((cpu - dev).abs() * 127.5).round()
        assert levels.max() <= 1 and (levels > 0).float().mean() < 0.02, (seed, float((levels > 0).float().mean()))


def test_device_augmentation_has_the_cpus_distribution():
    """Default draws with noise: the images' statistics over seeds are the CPU's."""
    cfg = AugmentConfig()
    s = _sample(seed=3)
    valid = s["mask"][None] > 0.5
    gen = torch.Generator().manual_seed(0)
    cpu, dev = [], []
    for seed in range(40):
        a = augment_sample(s, seed, cfg)["fringe"]
        b = augment_fringes(s["fringe"][None], valid, [draw(seed, s["fringe"].shape[-2:], cfg)], gen)[0]
        assert torch.equal(a == -1, b == -1) or (valid.sum() > 0)
        cpu.append([float(a.mean()), float(a.std())])
        dev.append([float(b.mean()), float(b.std())])
    cpu, dev = np.array(cpu), np.array(dev)
    assert np.allclose(cpu, dev, atol=0.02), np.abs(cpu - dev).max(0)
    assert np.allclose(cpu.mean(0), dev.mean(0), atol=0.005)


@pytest.mark.parametrize("crop", [None, (24, 40)])
def test_device_loader_gives_the_dataloaders_batches(tmp_path, crop):
    """Augmentation off: the same samples, crops and order as the DataLoader, fringes to float16's precision."""
    write_figshare(tmp_path / "d", n=10, h=32, w=64, seed=2)
    src = load_sources(synthetic=[tmp_path / "d"])
    train = Prepared(src.train, crop, None, random_crop=True)
    sampler = MixedSampler(src.train.n_real, src.train.n_synthetic, None, None, 5)
    loader = DeviceLoader(DeviceSet(train, torch.device("cpu")), sampler, 3)
    host = torch.utils.data.DataLoader(train, batch_size=3, sampler=sampler)
    assert len(loader) == len(host)
    for a, b in zip(loader, host):
        assert torch.equal(a["height"], b["height"]) and torch.equal(a["mask"], b["mask"])
        assert torch.allclose(a["fringe"], b["fringe"], atol=1e-3) and a["source"] == b["source"]


def test_device_sums_and_loss_watch():
    host, dev = MetricSums(["a"]), DeviceSums(["a"], torch.device("cpu"))
    for v in ([1.0, float("nan"), 2.5], [4.0]):
        host.add("a", torch.tensor(v))
        dev.add("a", torch.tensor(v))
    assert host.reduce(DistInfo(), "cpu") == dev.reduce(DistInfo(), "cpu")
    w = LossWatch(torch.device("cpu"))
    w.note(torch.tensor(1.0), 0)
    assert w.first_bad(DistInfo(), "cpu") is None
    w.note(torch.tensor(float("inf")), 3)
    w.note(torch.tensor(float("nan")), 4)
    assert w.first_bad(DistInfo(), "cpu") == (3, float("inf"), True)


def test_the_device_path_trains_on_a_cpu(tmp_path):
    """Every speed option that runs on a CPU, asked for: the run trains and records them."""
    write_figshare(tmp_path / "d", n=10, h=32, w=64, seed=4)
    out = tmp_path / "run"
    assert main(["train", "--synthetic", str(tmp_path / "d"), "--out", str(out), "--model", "unet", "--base-channels",
                 "4", "--epochs", "2", "--batch-size", "2", "--crop", "24x48", "--device", "cpu", "--threads", "1",
                 "--device-data", "on", "--host-sync", "epoch", "--channels-last", "on", "--fused-adam", "off",
                 "--amp", "--no-progress"]) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["device_data"] == "on" and cfg["host_sync"] == "epoch" and cfg["channels_last"] == "on"
    rows = torch.load(out / "last.pt", weights_only=False)["history"]
    assert len(rows) == 2 and all(np.isfinite(r["train_loss"]) and np.isfinite(r["val_rmse_mm"]) for r in rows)


def test_resumed_optimizer_state_takes_the_weights_layout():
    """--channels-last: moments loaded from a checkpoint are strided as their weights (builders.match_layout)."""
    conv = torch.nn.Conv2d(3, 4, 3)
    opt = torch.optim.Adam(conv.parameters())
    conv(torch.randn(1, 3, 8, 8)).sum().backward()
    opt.step()
    saved = opt.state_dict()
    conv = conv.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(conv.parameters())
    opt.load_state_dict(saved)
    w = conv.weight
    before = opt.state[w]["exp_avg"].clone()
    assert opt.state[w]["exp_avg"].stride() != w.stride()
    match_layout(opt)
    assert opt.state[w]["exp_avg"].stride() == w.stride() and torch.equal(opt.state[w]["exp_avg"], before)


def test_cpu_auto_is_every_option_off_bit_for_bit(tmp_path):
    """On a CPU the speed options' defaults are the path runs took before them: a seeded run with them equals,
    tensor for tensor, one with each asked off (and the float16 type, which a CPU never uses)."""
    write_figshare(tmp_path / "d", n=8, h=32, w=64, seed=4)
    common = ["train", "--synthetic", str(tmp_path / "d"), "--model", "unet", "--base-channels", "4", "--epochs", "2",
              "--batch-size", "2", "--device", "cpu", "--seed", "3", "--threads", "1", "--amp", "--ema", "0.9",
              "--no-progress"]
    off = ["--amp-dtype", "fp16", "--channels-last", "off", "--device-data", "off", "--host-sync", "step",
           "--fused-adam", "off"]
    assert main([*common, "--out", str(tmp_path / "auto")]) == 0
    assert main([*common, *off, "--out", str(tmp_path / "off")]) == 0
    a, b = (torch.load(tmp_path / r / "last.pt", weights_only=False) for r in ("auto", "off"))
    for key in ("state_dict", "train_state_dict"):
        assert a[key].keys() == b[key].keys() and all(torch.equal(a[key][k], b[key][k]) for k in a[key])
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    assert all(torch.equal(sa[i][k], sb[i][k]) for i in sa for k in sa[i])
    assert [r["train_loss"] for r in a["history"]] == [r["train_loss"] for r in b["history"]]
