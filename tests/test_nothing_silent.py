"""Issue 36's second QA pass: values that cannot give a valid result are one line and a non-zero exit, and
no tool replaces a file it did not write, even at a name it once wrote."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fppsim.cli import main as fppsim_main
from tests._helpers import one_line, write_figshare
from uhrnet.cli import main


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    write_figshare(d / "real", n=6, h=32, w=64, seed=1)
    assert main(["train", "--real", str(d / "real"), "--out", str(d / "run"), "--model", "unet", "--base-channels",
                 "4", "--epochs", "1", "--batch-size", "2", "--device", "cpu", "--no-progress", "--threads", "1"]) == 0
    return d


def test_export_refuses_a_file_changed_since_it_wrote_it(run, tmp_path, capsys):
    out = tmp_path / "model.pt"
    args = ["export", str(run / "run"), "--format", "torchscript", "--out", str(out), "--height", "32", "--width", "64"]
    assert main(args) == 0
    assert main(args) == 0  # its own file, unchanged: replaced
    out.write_text("the user's own file now")
    capsys.readouterr()
    assert main(args) == 1
    one_line(capsys, "was changed since uhrnet export wrote it")
    assert out.read_text() == "the user's own file now"


@pytest.mark.parametrize("cmd", [["export", "RUN", "--out", "x.onnx", "--height", "160000", "--width", "160000"],
                                 ["bench", "--models", "unet", "--height", "160000", "--width", "160000"]])
def test_huge_sizes_are_usage_errors(run, tmp_path, capsys, cmd):
    cmd = [str(run / "run") if c == "RUN" else str(tmp_path / c) if c.endswith(".onnx") else c for c in cmd]
    assert main(cmd) == 2
    one_line(capsys, "--height and --width must be multiples of 16 from 16 to 4096")


def test_huge_counts_epochs_and_rates_are_usage_errors(run, tmp_path, capsys):
    assert fppsim_main(["generate", "--count", "100000000000000000000", "--meshes", "assets/meshes",
                        "--out", str(tmp_path / "g")]) == 2
    one_line(capsys, "--count must be from 1 to 10,000,000")
    assert not (tmp_path / "g").exists()
    base = ["train", "--real", str(run / "real"), "--model", "unet", "--base-channels", "4", "--device", "cpu"]
    assert main(base + ["--lr", "1e300", "--out", str(tmp_path / "t")]) == 2
    one_line(capsys, "--lr must be a finite rate up to 10")
    assert main(base + ["--epochs", "1" + "0" * 30, "--out", str(tmp_path / "t")]) == 2
    one_line(capsys, "--epochs must be at most 1,000,000")
    assert not (tmp_path / "t").exists()


def test_import_weights_refuses_nan_weights(tmp_path, capsys):
    from tests.uhrnet.test_reference_weights import random_reference_state, save_reference

    state = random_reference_state(64)
    key = next(k for k, v in state.items() if v.is_floating_point())
    state[key] = state[key].clone().fill_(float("nan"))
    path = save_reference(tmp_path / "w.pth", state)
    assert main(["import-weights", str(path), "--out", str(tmp_path / "o")]) == 1
    one_line(capsys, "holds NaN or inf values")
    assert not (tmp_path / "o" / "best.pt").exists()


def test_predict_into_its_input_folder_twice_and_duplicate_inputs(run, tmp_path, capsys):
    import cv2

    folder = tmp_path / "inout"
    folder.mkdir()
    cv2.imwrite(str(folder / "img.png"), np.full((32, 64), 90, np.uint8))
    args = ["predict", str(run / "run"), str(folder), "--out", str(folder), "--no-ply", "--device", "cpu",
            "--no-progress"]
    assert main(args) == 0
    assert main(args) == 0  # its own outputs are not read back as inputs
    capsys.readouterr()
    assert main(["predict", str(run / "run"), str(folder / "img.png"), str(folder / "img.png"), "--out",
                 str(tmp_path / "d"), "--no-ply", "--device", "cpu", "--no-progress"]) == 0
    assert sorted(p.name for p in (tmp_path / "d").glob("*_height.npy")) == ["img_height.npy"]
    (tmp_path / "afile").write_text("x")
    capsys.readouterr()
    assert main(["predict", str(run / "run"), str(folder / "img.png"), "--out", str(tmp_path / "afile"),
                 "--no-ply", "--device", "cpu", "--no-progress"]) == 1
    one_line(capsys, "is a file, not a folder")


def test_tensorboard_path_that_is_a_file(run, tmp_path, capsys):
    pytest.importorskip("tensorboard")
    out = tmp_path / "tb"
    out.mkdir()
    (out / "tensorboard").write_text("not a folder")
    assert main(["train", "--real", str(run / "real"), "--out", str(out), "--model", "unet", "--base-channels", "4",
                 "--epochs", "1", "--device", "cpu", "--no-progress", "--tensorboard"]) == 1
    one_line(capsys, "exists and is not a folder")
    assert sorted(p.name for p in out.iterdir()) == ["tensorboard"]
