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
