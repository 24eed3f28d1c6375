"""train/adapt --tensorboard: the logs read back through TensorBoard's own reader equal history.csv and
the loss formulas, resumed runs continue them without duplicate steps, and a missing tensorboard
package is one line and exit 2 before anything runs."""

import csv
import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from uhrnet.cli import main

from _helpers import adapt_setup, write_figshare

pytest.importorskip("tensorboard", reason="tensorboard (the optional extra) not installed")
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

STEPS = 3  # 6 training images of the 8 (reference split), batch 2


def _read(folder) -> EventAccumulator:
    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    acc.Reload()
    return acc


def _scalars(acc, tag) -> tuple[list[int], list[float]]:
    events = acc.Scalars(tag)
    return [e.step for e in events], [e.value for e in events]


def _history(run) -> list[dict]:
    with open(run / "history.csv") as f:
        return list(csv.DictReader(f))


def _raw_steps(folder, tag) -> tuple[list[int], list[int]]:
    """Steps of ``tag`` in every event file as written (purged events included), and the steps of the
    writers' session starts (their purge_step)."""
    steps, starts = [], []
    for path in sorted(folder.glob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            steps += [event.step for v in event.summary.value if v.tag == tag]
            if event.HasField("session_log") and event.session_log.status == event.session_log.START:
                starts.append(event.step)
    return steps, starts


def _train(run, data, epochs, *extra):
    return main(["train", "--real", str(data), "--model", "unet", "--base-channels", "4", "--batch-size", "2",
                 "--epochs", str(epochs), "--lr", "1e-3", "--out", str(run), "--no-progress", "--tensorboard",
                 *extra])


@pytest.fixture(scope="module")
def figshare(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tb") / "real"
    write_figshare(folder, n=8, h=32, w=64, seed=1)
    return folder


@pytest.mark.slow
def test_train_logs_every_step_and_epoch_and_a_validation_image(figshare, tmp_path, capsys):
    run = tmp_path / "run"
    assert _train(run, figshare, 2) == 0
    assert f"tensorboard --logdir {run / 'tensorboard'}" in capsys.readouterr().out
    acc = _read(run / "tensorboard")
    rows = _history(run)
    # per step: the loss, its compound parts (total = chunked L2 + 1000 * SSIM loss) and the rate
    steps, loss = _scalars(acc, "train/loss")
    assert steps == list(range(1, 2 * STEPS + 1))
    _, chunked = _scalars(acc, "train/loss_terms/chunked")
    _, ssim = _scalars(acc, "train/loss_terms/ssim")
    np.testing.assert_allclose(loss, np.add(chunked, 1000.0 * np.asarray(ssim)), rtol=1e-4)
    assert np.mean(loss[:STEPS]) == pytest.approx(float(rows[0]["train_loss"]), rel=1e-4)
    steps, lr = _scalars(acc, "train/lr")
    assert lr[0] == pytest.approx(1e-3) and lr[-1] == pytest.approx(1e-3 * 0.05)  # the cosine's ends
    # per epoch, at the epoch's last step: history.csv's columns
    for column in ("train_loss", "train_rmse_mm", "train_ssim", "val_rmse_mm", "val_ssim", "lr"):
        steps, values = _scalars(acc, f"epoch/{column}")
        assert steps == [STEPS, 2 * STEPS], column
        np.testing.assert_allclose(values, [float(r[column]) for r in rows], rtol=1e-5, err_msg=column)
    assert _scalars(acc, "epoch") == ([STEPS, 2 * STEPS], [1.0, 2.0])
    # the first validation sample (image 7 of the reference split): prediction, target, error per epoch
    from fppsim.dataio.formats import PRESETS
    from uhrnet.data.datasets import load_sources

    sample = load_sources(real=[figshare], transform=PRESETS["figshare"]).val[0]
    height = PRESETS["figshare"].height_mm(sample["height"][0].numpy())[sample["mask"][0].numpy() > 0]
    for tag in ("prediction", "target", "error"):
        images = acc.Images(f"val_image/{tag}")
        assert [im.step for im in images] == [STEPS, 2 * STEPS] and (images[0].width, images[0].height) == (64, 32)
    from PIL import Image

    target = np.asarray(Image.open(io.BytesIO(acc.Images("val_image/target")[0].encoded_image_string)).convert("L"))
    assert target.max() == 255 and target[sample["mask"][0].numpy() == 0].max() == 0  # the scale: min..max
    text = acc.Tensors("val_image/ranges/text_summary")[-1].tensor_proto.string_val[0].decode()
    lo, hi = map(float, re.search(r"target: black (\S+) mm \.\. white (\S+) mm", text).groups())
    assert lo == pytest.approx(height.min(), abs=1e-3) and hi == pytest.approx(height.max(), rel=1e-3)
    assert text.startswith(f"{sample['id']}: ")


@pytest.mark.slow
def test_resume_continues_the_log_without_duplicate_steps(figshare, tmp_path, capsys):
    run = tmp_path / "run"
    assert _train(run, figshare, 1) == 0
    shutil.copy(run / "last.pt", tmp_path / "epoch1.pt")
    assert _train(run, figshare, 2, "--resume") == 0
    # killed after epoch 2's log was flushed but before its checkpoint: the resume redoes epoch 2
    shutil.copy(tmp_path / "epoch1.pt", run / "last.pt")
    assert _train(run, figshare, 2, "--resume") == 0
    folder = run / "tensorboard"
    steps, starts = _raw_steps(folder, "train/loss")
    assert sorted(steps) == sorted([*range(1, 2 * STEPS + 1), *range(STEPS + 1, 2 * STEPS + 1)])  # epoch 2 twice
    assert starts == [1, STEPS + 1, STEPS + 1]  # each resume starts after the checkpoint's last step
    acc = _read(folder)  # TensorBoard hides the redone epoch's first copy (purge_step)
    steps, loss = _scalars(acc, "train/loss")
    assert steps == list(range(1, 2 * STEPS + 1))
    steps, values = _scalars(acc, "epoch/val_rmse_mm")
    assert steps == [STEPS, 2 * STEPS]
    np.testing.assert_allclose(values, [float(r["val_rmse_mm"]) for r in _history(run)], rtol=1e-5)
    # --overwrite starts the log afresh too
    assert _train(run, figshare, 1, "--overwrite") == 0
    assert len(list(folder.glob("events.out.tfevents.*"))) == 1
    assert _scalars(_read(folder), "train/loss")[0] == list(range(1, STEPS + 1))


@pytest.mark.slow
def test_ddp_only_rank_0_writes_the_log(figshare, tmp_path):
    run = tmp_path / "run"
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m", "uhrnet",
           "train", "--real", str(figshare), "--model", "unet", "--base-channels", "4", "--epochs", "2",
           "--batch-size", "2", "--device", "cpu", "--out", str(run), "--no-progress", "--tensorboard"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("tensorboard --logdir") == 1
    assert len(list((run / "tensorboard").glob("events.out.tfevents.*"))) == 1
    acc = _read(run / "tensorboard")
    per = 2  # 6 training images over 2 processes, batch 2
    assert _scalars(acc, "train/loss")[0] == list(range(1, 2 * per + 1))
    steps, values = _scalars(acc, "epoch/val_rmse_mm")
    assert steps == [per, 2 * per]
    np.testing.assert_allclose(values, [float(r["val_rmse_mm"]) for r in _history(run)], rtol=1e-5)


def test_missing_tensorboard_is_one_line_and_exit_2_before_anything_runs(figshare, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # as if the package were not installed
    run = tmp_path / "run"
    assert _train(run, figshare, 1) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--tensorboard needs the 'tensorboard' package" in err[0] and "pip install" in err[0], err
    assert not run.exists()  # nothing trained, nothing written
    assert main(["adapt", str(tmp_path / "no.pt"), "--images", str(figshare), "--out", str(tmp_path / "ad"),
                 "--tensorboard"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install" in err[0] and not (tmp_path / "ad").exists()
    from uhrnet.training.adapt import AdaptConfig
    from uhrnet.errors import UsageError
    from uhrnet.training.train_config import TrainConfig

    with pytest.raises(UsageError, match="tensorboard"):
        TrainConfig(out=run, real=[figshare], tensorboard=True)
    with pytest.raises(UsageError, match="tensorboard"):
        AdaptConfig(checkpoint=tmp_path / "no.pt", images=[figshare], out=tmp_path / "ad", tensorboard=True)
    TrainConfig(out=run, real=[figshare])  # without the flag nothing needs it


@pytest.mark.slow
def test_adapt_logs_its_loss_terms_and_resumes_the_log(tmp_path, capsys):
    source, _, real = adapt_setup(tmp_path)
    out = tmp_path / "ad"
    cmd = ["adapt", str(source), "--images", str(real), "--out", str(out), "--rig", str(tmp_path / "rig.json"),
           "--no-figures", "--no-progress", "--tensorboard"]  # w_drift 0.5 (default)
    assert main(cmd + ["--epochs", "2"]) == 0
    assert main(cmd + ["--epochs", "3"]) == 0  # re-running with more epochs resumes
    capsys.readouterr()
    acc = _read(out / "tensorboard")
    steps, loss = _scalars(acc, "train/loss")
    assert steps == list(range(1, 7))  # 2 images a epoch, 3 epochs, each step once
    terms = {t: np.asarray(_scalars(acc, f"train/loss_terms/{t}")[1]) for t in ("grad", "drift")}
    np.testing.assert_allclose(loss, terms["grad"] + 0.5 * terms["drift"], rtol=1e-5)
    assert _scalars(acc, "train/lr")[1] == pytest.approx([3e-4] * 6)
    rows = _history(out)
    for column in ("loss", "grad", "drift"):
        steps, values = _scalars(acc, f"epoch/{column}")
        assert steps == [2, 4, 6], column
        np.testing.assert_allclose(values, [float(r[column]) for r in rows], rtol=1e-5, err_msg=column)
    for tag in ("prediction", "source", "change"):
        assert [im.step for im in acc.Images(f"adapt_image/{tag}")] == [2, 4, 6], tag
    text = acc.Tensors("adapt_image/ranges/text_summary")[0].tensor_proto.string_val[0].decode()
    assert text.startswith("real_0000: ") and "change: black" in text
