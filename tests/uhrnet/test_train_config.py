"""The training options: declared once on :class:`RunConfig`'s fields, read by the trainer as attributes."""

import ast
import dataclasses
from pathlib import Path

import pytest

from uhrnet.training.train_config import (DEFAULTS, LEGACY, LEGACY_LOCKED, LOCKED, RunConfig, TrainConfig,
                                          resolve_config)

ROOT = Path(__file__).resolve().parents[2]
TRAINING = ROOT / "uhrnet" / "training"


def test_defaults_locked_and_legacy_are_read_off_the_fields():
    options = [f for f in dataclasses.fields(RunConfig) if f.name != "init_from_checkpoint"]
    assert list(DEFAULTS) == [f.name for f in options]
    assert DEFAULTS["epochs"] == 200 and DEFAULTS["lr"] == 1e-4 and DEFAULTS["real"] == []
    assert RunConfig().lr == DEFAULTS["lr"] and RunConfig().real is not RunConfig().real  # no shared list
    assert "seed" in LOCKED and "epochs" not in LOCKED and "lr" not in LOCKED
    assert LEGACY["augment"] == "off" and LEGACY["lr_schedule"] == "constant" and "ema" not in LEGACY
    assert set(LEGACY_LOCKED) <= set(LEGACY) <= set(LOCKED)


def test_every_option_is_a_flag_of_train_config_given_as_none():
    given = {f.name: f for f in dataclasses.fields(TrainConfig)}
    assert all(given[name].default is None for name in DEFAULTS)


def test_resolved_config_is_frozen_and_records_as_before():
    cfg = RunConfig(**resolve_config(TrainConfig(out="r", synthetic=["s"], epochs=3)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.epochs = 4
    record = cfg.to_dict()
    assert list(record) == list(DEFAULTS) and record["epochs"] == 3  # no init_from_checkpoint key: none made
    made = dataclasses.replace(cfg, init_from_checkpoint={"path": "x"}).to_dict()
    assert list(made) == list(DEFAULTS) + ["init_from_checkpoint"]
    assert RunConfig(**made) == dataclasses.replace(cfg, init_from_checkpoint={"path": "x"})


def test_trainer_reads_no_option_by_its_name_as_a_string():
    """``cfg["lr"]`` / ``cfg.get("lr")`` would let a typo through until that line runs; attributes fail on load."""
    options = {"cfg", "self.cfg", "config", "self.config", "args", "self.args"}  # (self.net.config: the model's)
    reads = []
    for node in ast.walk(ast.parse((TRAINING / "trainer.py").read_text())):
        if (isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant)
                and isinstance(node.slice.value, str) and ast.unparse(node.value) in options):
            reads.append(f"{node.lineno}: {ast.unparse(node)}")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
                and ast.unparse(node.func.value) in options):
            reads.append(f"{node.lineno}: {ast.unparse(node)}")
    assert not reads, reads


def test_the_trainer_stays_short():
    """The loop apart from its builders: the Trainer class under 250 lines, no training function over 100."""
    long = []
    for path in sorted(TRAINING.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            size = getattr(node, "end_lineno", 0) - getattr(node, "lineno", 0) + 1
            if isinstance(node, ast.ClassDef) and node.name == "Trainer" and size >= 250:
                long.append(f"{path.name} {node.name} {size}")
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and size > 100 and path.name != "adapt.py":
                long.append(f"{path.name} {node.name} {size}")
    assert not long, long


# ---------------------------------------------------------------------------- s67: option values wrong on their own
BAD_VALUES = [
    (["--seed", "-1"], "--seed"), (["--seed", "99999999999999999999"], "--seed"), (["--seed", str(2**32)], "--seed"),
    (["--samples-per-epoch", "-3"], "--samples-per-epoch"), (["--samples-per-epoch", "0"], "--samples-per-epoch"),
    (["--workers", "-1"], "--workers"), (["--resize", "0x0"], "--resize"), (["--resize", "abc"], "--resize"),
    (["--crop", "0x8"], "--crop"), (["--epochs", "0"], "--epochs"), (["--batch-size", "0"], "--batch-size"),
    (["--lr", "nan"], "--lr"), (["--lr", "-1"], "--lr"), (["--synthetic-ratio", "1.5"], "--synthetic-ratio"),
    (["--base-channels", "0"], "--base-channels"), (["--model-option", "foo=1"], "--model-option"),
    (["--model-option", "foo"], "--model-option"), (["--model-option", "min_confidence=0.5"], "--model-option"),
    (["--label-transform", "plane_offset=-90", "invalid_threshold=-80"], "the plane would count as invalid"),
    (["--resume", "--overwrite"], "--overwrite"),
]


@pytest.mark.parametrize("flags, culprit", BAD_VALUES, ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_option_values_wrong_on_their_own_are_usage_errors_before_anything_is_written(tmp_path, capsys, flags, culprit):
    """Exit 2, one line naming the flag, no run folder: checked by the config, before any data is read (the
    --synthetic folder does not even exist) or training starts; they were numpy / DataLoader / torch tracebacks
    in the first epoch, exit 1, or (--samples-per-epoch 0, --resume --overwrite, a plane below the invalid
    threshold) accepted."""
    from uhrnet.cli import main

    out = tmp_path / "run"
    rc = main(["train", "--synthetic", str(tmp_path / "nothing"), "--model", "unet", "--epochs", "1", "--no-progress",
               "--out", str(out), *flags])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err and culprit in err, err
    assert not out.exists()


def test_seed_range_and_model_options_in_the_library():
    from uhrnet.errors import UsageError
    from uhrnet.models import check_model_options
    from uhrnet.training.train_config import MAX_SEED

    assert TrainConfig(out="r", synthetic=["s"], seed=MAX_SEED).seed == 2**32 - 1
    for bad in (-1, MAX_SEED + 1, 1.5, True):
        with pytest.raises(UsageError, match="--seed"):
            TrainConfig(out="r", synthetic=["s"], seed=bad)
    with pytest.raises(UsageError, match="--samples-per-epoch"):
        TrainConfig(out="r", synthetic=["s"], samples_per_epoch=0)
    assert TrainConfig(out="r", synthetic=["s"], workers=0, samples_per_epoch=None).workers == 0
    check_model_options("uhrnet", {"fusion": False})  # nothing is built
    check_model_options("unet", {"min_confidence": 0.5}, head="phase")
    for name, options, head, match in (("unet", {"fusion": True}, "height", "does not take"),
                                       ("model_b", {"fusion": True}, "height", "model_b is uhrnet with fusion"),
                                       ("unet", {"min_confidence": 0.5}, "height", "phase head"),
                                       ("nope", {}, "height", "unknown model"), ("unet", {}, "nope", "unknown head")):
        with pytest.raises(ValueError, match=match):
            check_model_options(name, options, head=head)
    # a resume is checked against the checkpoint's model and head, not the defaults (no --model given here)
    TrainConfig(out="r", resume="auto", model_option=["min_confidence=0.5"])
    # review: a run recorded with --samples-per-epoch 0 (all samples, before stop 67) still resumes
    from uhrnet.training.train_config import resolve_config

    previous = resolve_config(TrainConfig(out="r", synthetic=["s"]))
    assert resolve_config(TrainConfig(out="r", resume="auto"), {**previous, "samples_per_epoch": 0})[
        "samples_per_epoch"] is None


def test_folders_of_different_image_sizes_are_refused_before_training(tmp_path, capsys):
    """Stacking a batch failed in the first epoch (torch.stack: 'expects each tensor to be equal size'); now one
    line naming both folders and sizes, and --resize (or --crop) trains on them together."""
    from _helpers import write_figshare
    from uhrnet.cli import main

    write_figshare(tmp_path / "small", n=8, h=32, w=64)
    write_figshare(tmp_path / "large", n=8, h=48, w=96, seed=1)
    base = ["train", "--model", "unet", "--base-channels", "4", "--epochs", "1", "--batch-size", "2", "--threads", "1",
            "--no-progress", "--synthetic", str(tmp_path / "small"), "--real", str(tmp_path / "large"), "--real-split",
            "train"]
    assert main(base + ["--out", str(tmp_path / "r1")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for part in ("32x64", "48x96", str(tmp_path / "small"), str(tmp_path / "large"), "--resize"):
        assert part in err, err
    assert not (tmp_path / "r1").exists()
    assert main(base + ["--out", str(tmp_path / "r2"), "--resize", "32x64"]) == 0
    assert main(base + ["--out", str(tmp_path / "r3"), "--crop", "32x32"]) == 0
    # review: one image per batch on a CPU trained before (and such a run must still resume)
    one = [a if a != "2" else "1" for a in base]
    assert main(one + ["--out", str(tmp_path / "r4")]) == 0
    assert main(one + ["--out", str(tmp_path / "r4"), "--resume", "--epochs", "2"]) == 0
