"""uhrnet train --init-from CKPT [--freeze PART]: transfer learning from a checkpoint's weights."""

import hashlib
import json
from pathlib import Path

import pytest
import torch

from uhrnet.checkpoint import load_checkpoint
from uhrnet.cli import main
from uhrnet.training.distributed import DistInfo
from uhrnet.errors import CheckpointError, ConfigError, UsageError
from uhrnet.models import build_model, list_models
from uhrnet.models.freeze import FREEZE_CHOICES, parts_of
from uhrnet.training.train_config import TrainConfig, resolve_config
from uhrnet.training.trainer import Trainer

from _helpers import write_figshare

FLAGS = ["--loss", "l2", "--lr", "1e-2", "--crop", "16x32", "--batch-size", "2", "--no-progress"]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """Real data and two tiny pretrained runs: a U-Net with --ema (its average differs from its
    optimised weights) and a UHRNet (batch norms)."""
    root = tmp_path_factory.mktemp("init_from")
    write_figshare(root / "real", n=8, h=32, w=64, seed=3)
    torch.set_num_threads(1)
    for name, model in (("unet", "unet"), ("uhrnet", "uhrnet")):
        extra = ["--ema", "0.5"] if model == "unet" else []
        rc = main(["train", "--real", str(root / "real"), "--model", model, "--base-channels", "4", "--epochs", "1",
                   "--out", str(root / name), *FLAGS, *extra])
        assert rc == 0
    return root


def _config(source, out, **kw):
    base = dict(out=out, real=[source / "real"], model="unet", base_channels=4, epochs=1, loss="l2",
                crop="16x32", batch_size=2, progress=False)
    return TrainConfig(**{**base, **kw})


def test_every_registered_model_declares_encoder_and_decoder():
    """--freeze works for every name of the registry: its parts split all of its parameters."""
    for name in list_models():
        net = build_model(name, base_channels=4)
        parts = parts_of(net)
        assert set(parts) == set(FREEZE_CHOICES) - {"none"}, name
        ids = {part: {id(p) for m in mods for p in m.parameters()} for part, mods in parts.items()}
        assert all(ids.values()), (name, {k: len(v) for k, v in ids.items()})
        assert not ids["encoder"] & ids["decoder"], name
        assert ids["encoder"] | ids["decoder"] == {id(p) for p in net.parameters()}, name
        assert {n.split(".")[0] for n, p in net.named_parameters() if id(p) in ids["encoder"]} == \
            {"encoder", "bottleneck"}, name


def test_init_copies_the_weights_with_a_fresh_optimizer(source, tmp_path):
    ckpt = load_checkpoint(source / "unet")  # a run folder reads as best.pt, like predict / evaluate
    assert ckpt["path"].endswith("best.pt")
    trainer = Trainer(_config(source, tmp_path / "ft", init_from=source / "unet", seed=5), DistInfo())
    state = trainer.net.state_dict()
    assert state.keys() == ckpt["state_dict"].keys()
    for k, v in ckpt["state_dict"].items():  # the moving average (--ema), not the optimised weights
        assert torch.equal(state[k], v), k
    assert any(not torch.equal(v, ckpt["train_state_dict"][k]) for k, v in ckpt["state_dict"].items())
    assert trainer.optimizer.state_dict()["state"] == {}  # no Adam step count or moments
    assert trainer.start_epoch == 0 and trainer.history == [] and trainer.best["epoch"] == 0
    assert trainer.lr_at(0, 0) == pytest.approx(1e-4)  # the schedule starts from its beginning
    assert trainer.network.ema is None  # this run's own options: no average
    record = trainer.cfg.init_from_checkpoint
    best = (source / "unet" / "best.pt").resolve()
    assert trainer.cfg.init_from == record["path"] == str(best)
    assert record["sha256"] == hashlib.sha256(best.read_bytes()).hexdigest()
    assert record["epoch"] == 1 and record["weights"] == "ema" and record["model"] == "unet"


def test_mismatched_checkpoint_is_one_line_error(source, tmp_path, capsys):
    data = ["--real", str(source / "real"), *FLAGS, "--epochs", "1"]
    ck = str((source / "unet" / "best.pt"))
    cases = [
        (["--model", "unet", "--base-channels", "8"], "model unet (base_channels=4) does not match this run's unet "
                                                      "(base_channels=8)"),
        (["--model", "hnet", "--base-channels", "4"], "model unet does not match this run's hnet"),
        (["--model", "unet", "--base-channels", "4", "--raw-output"], "--raw-output or the label transform differs"),
    ]
    for i, (flags, expected) in enumerate(cases):
        assert main(["train", *data, *flags, "--init-from", str(source / "unet"), "--out", str(tmp_path / f"r{i}")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"init-from {ck}: " in err[0] and expected in err[0], err
        assert not (tmp_path / f"r{i}" / "config.json").exists()
    # an ablation alias is its architecture: model_b and uhrnet without fusion hold the same weights
    with pytest.raises(CheckpointError, match="does not match"):
        Trainer(_config(source, tmp_path / "m", model="model_b", init_from=source / "uhrnet"), DistInfo())
    assert main(["train", *data, "--model", "unet", "--base-channels", "4", "--init-from", str(tmp_path / "none.pt"),
                 "--out", str(tmp_path / "r9")]) == 1
    assert "none.pt: checkpoint not found" in capsys.readouterr().err
    # --freeze: a value wrong on its own exits 2, without --init-from it does not fit (exit 1)
    with pytest.raises(UsageError, match="--freeze"):
        TrainConfig(out="r", freeze="everything")
    with pytest.raises(SystemExit) as exc:
        main(["train", *data, "--freeze", "everything", "--out", str(tmp_path / "r8")])
    assert exc.value.code == 2
    capsys.readouterr()
    assert main(["train", *data, "--model", "unet", "--base-channels", "4", "--freeze", "encoder",
                 "--out", str(tmp_path / "r7")]) == 1
    assert "--freeze encoder needs --init-from" in capsys.readouterr().err


def test_fine_tune_records_its_start_and_resume_continues(source, tmp_path, capsys):
    run = tmp_path / "ft"
    base = ["train", "--real", str(source / "real"), "--model", "unet", "--base-channels", "4", *FLAGS,
            "--out", str(run)]
    assert main(base + ["--epochs", "1", "--init-from", str(source / "unet" / "last.pt")]) == 0
    out = capsys.readouterr().out
    assert "init-from " in out and "moving-average (--ema) weights of its epoch 1" in out
    last = (source / "unet" / "last.pt").resolve()
    config = json.loads((run / "config.json").read_text())
    assert config["init_from"] == str(last) and config["freeze"] == "none"
    assert config["init_from_checkpoint"]["sha256"] == hashlib.sha256(last.read_bytes()).hexdigest()
    first = load_checkpoint(run / "last.pt")
    assert first["epoch"] == 1 and first["args"]["init_from_checkpoint"] == config["init_from_checkpoint"]

    # a resume continues the run from its own last.pt; the init checkpoint is not read again
    trainer = Trainer(TrainConfig(out=run, resume="auto", epochs=2, progress=False), DistInfo())
    assert trainer.start_epoch == 1 and trainer.optimizer.state_dict()["state"]
    for k, v in first["state_dict"].items():
        assert torch.equal(trainer.net.state_dict()[k], v), k
    assert trainer.cfg.init_from_checkpoint == config["init_from_checkpoint"]
    del trainer
    assert main(["train", "--out", str(run), "--resume", "--epochs", "2", "--init-from", str(last),
                 "--no-progress"]) == 0  # the same --init-from is allowed and ignored
    assert "resuming after epoch 1" in capsys.readouterr().out
    assert load_checkpoint(run / "last.pt")["epoch"] == 2
    assert json.loads((run / "config.json").read_text())["init_from_checkpoint"] == config["init_from_checkpoint"]

    # another --init-from, or another --freeze, is refused on resume like every locked option
    assert main(["train", "--out", str(run), "--resume", "--init-from", str(source / "uhrnet"), "--no-progress"]) == 1
    assert "--init-from" in (err := capsys.readouterr().err) and "differs from the checkpoint's" in err
    assert main(["train", "--out", str(run), "--resume", "--freeze", "encoder", "--no-progress"]) == 1
    assert "--freeze encoder differs" in capsys.readouterr().err
    # a run made before these options (no init_from in its args) refuses them too
    older = {"real": [], "synthetic": []}
    assert resolve_config(TrainConfig(out="r"), older)["init_from"] is None
    with pytest.raises(ConfigError, match="--init-from .* differs"):
        resolve_config(TrainConfig(out="r", init_from=str(last)), older)
    with pytest.raises(ConfigError, match="--freeze decoder differs"):
        resolve_config(TrainConfig(out="r", freeze="decoder"), older)


def _frozen_and_trained(before: dict, after: dict, prefixes) -> tuple[list, list]:
    same, moved = [], []
    for k, v in before.items():
        (same if torch.equal(after[k], v) else moved).append(k)
    frozen = [k for k in before if k.split(".")[0] in prefixes]
    return [k for k in frozen if k in moved], [k for k in before if k not in frozen and k in same]


def test_freeze_keeps_the_frozen_part_bit_identical(source, tmp_path):
    """UHRNet (batch norms) with its encoder frozen, a U-Net with its decoder frozen: two epochs of
    training leave every frozen weight and batch-norm statistic as the checkpoint had it and move the rest."""
    cases = (("uhrnet", "encoder", ("encoder", "bottleneck")), ("unet", "decoder", ("decoder", "head")))
    for model, part, prefixes in cases:
        start = load_checkpoint(source / model)["state_dict"]
        run = tmp_path / f"{model}-{part}"
        assert main(["train", "--real", str(source / "real"), "--model", model, "--base-channels", "4", *FLAGS,
                     "--epochs", "2", "--init-from", str(source / model), "--freeze", part, "--out", str(run)]) == 0
        ck = load_checkpoint(run / "last.pt")
        moved_frozen, still_trainable = _frozen_and_trained(start, ck["state_dict"], prefixes)
        assert moved_frozen == [], (model, part)
        assert not [k for k in still_trainable if k.endswith("weight")], (model, part)  # every trainable weight moved
        assert ck["args"]["freeze"] == part
        weights = [k for k in start if "running_" not in k and "num_batches" not in k]  # parameters, not buffers
        n_optimised = sum(len(g["params"]) for g in ck["optimizer"]["param_groups"])
        assert n_optimised == sum(1 for k in weights if k.split(".")[0] not in prefixes), (model, part)
