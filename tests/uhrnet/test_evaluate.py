"""uhrnet evaluate: Table 3 (Markdown/CSV/JSON), per-sample metrics and comparison figures."""

import csv
import json
import shutil

import numpy as np
import pytest
import torch

from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.cli import main
from uhrnet.data.datasets import load_sources
from uhrnet.inference.prediction import predict_labels

from _helpers import REAL_SAMPLE, one_line, train_tiny, write_figshare, write_native


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval")
    write_figshare(tmp / "real", n=10, h=32, w=64, seed=1)
    write_native(tmp / "syn", n=10, h=32, w=64, seed=2)
    data = ("--real", tmp / "real", "--synthetic", tmp / "syn")
    a = train_tiny(tmp / "unet", *data, model="unet")
    b = train_tiny(tmp / "uhrnet", *data, model="uhrnet")
    return tmp, a, b


def test_evaluate_two_models(runs, capsys):
    tmp, a, b = runs
    out = tmp / "report"
    rc = main(["evaluate", str(a / "best.pt"), str(b), "--out", str(out), "--timing-repeats", "1",
               "--figures", "2", "--no-progress"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "| Model | RMSE (mm) | SSIM |" in printed and "report:" in printed
    md = (out / "results.md").read_text()
    assert "| unet |" in md and "| uhrnet |" in md and "RMSE real (mm)" in md
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["name"] for r in rows] == ["unet", "uhrnet"]
    summary = json.loads((out / "results.json").read_text())
    assert summary["split"] == "test" and summary["images"] == 2  # 1 real + 1 synthetic test image (10 -> 8/1/1)
    unet = summary["models"][0]
    assert unet["parameters"] == load_checkpoint(a / "best.pt")["n_parameters"]
    assert unet["seconds_per_image"] > 0 and unet["images_real"] == 1 and unet["images_synthetic"] == 1
    with open(out / "per_sample.csv") as f:
        per = list(csv.DictReader(f))
    assert len(per) == 4
    # The reported RMSE is the mean of per-image RMSEs over valid pixels, in mm.
    ckpt = load_checkpoint(a / "best.pt")
    model, transform = model_from_checkpoint(ckpt)
    src = load_sources([tmp / "real"], [tmp / "syn"], transform)
    errs = []
    for i in range(len(src.test)):
        s = src.test[i]
        pred = predict_labels(model, s["fringe"][None])[0, 0].numpy().astype(np.float64)
        m = s["mask"][0].numpy() > 0
        errs.append(np.sqrt(np.mean((pred[m] - s["height"][0].numpy()[m]) ** 2)) / 6)
    assert unet["rmse_mm"] == pytest.approx(np.mean(errs), rel=1e-5)
    figs = sorted(p.name for p in (out / "figures").iterdir())
    assert len(figs) == 2 and all(f.endswith(".png") for f in figs)


def test_evaluate_options_and_errors(runs, capsys):
    tmp, a, b = runs
    out = tmp / "report2"
    rc = main(["evaluate", str(a), str(a), "--synthetic", str(tmp / "syn"), "--real", "--out", str(out),
               "--split", "all", "--samples", "000003", "#0", "--timing-repeats", "0", "--no-progress",
               "--names", "first", "second"])
    assert rc == 0
    summary = json.loads((out / "results.json").read_text())
    assert summary["images"] == 10 and summary["models"][1]["name"] == "second"
    assert summary["models"][0]["seconds_per_image"] is None
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["synthetic_000000.png", "synthetic_000003.png"]
    capsys.readouterr()
    assert main(["evaluate", str(tmp / "nope.pt"), "--out", str(out)]) == 1
    assert "nope.pt: checkpoint not found" in capsys.readouterr().err
    assert main(["evaluate", str(a), "--out", str(out), "--names", "x", "y"]) == 2  # a usage error
    assert "--names: 2 names for 1 checkpoints" in capsys.readouterr().err
    assert main(["evaluate", str(tmp / "nope.pt"), "--out", str(out), "--names", "x", "y"]) == 2  # before reading
    assert "--names: 2 names for 1 checkpoints" in capsys.readouterr().err
    assert main(["evaluate", str(a), "--out", str(out), "--samples", "zzz", "--no-progress"]) == 1
    assert "--samples" in capsys.readouterr().err
    assert main(["evaluate", str(a), "--out", str(tmp / "report3"), "--row", "100000", "--no-progress"]) == 1
    assert "--row 100000" in capsys.readouterr().err and not (tmp / "report3").exists()
    (tmp / "garbage.pt").write_bytes(b"garbage" * 10)
    assert main(["evaluate", str(tmp / "garbage.pt"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "garbage.pt: cannot load checkpoint: not a PyTorch checkpoint" in err and "weights_only" not in err


@pytest.mark.parametrize("content", [b"hello world\n", b"\x80\x02", b"garbage" * 10])
def test_a_file_that_is_no_checkpoint_says_so(tmp_path, content):
    """A text file or a truncated pickle named .pt: torch's own errors were 'KeyError: 104' or an empty EOFError."""
    from uhrnet.checkpoint import load_checkpoint
    from uhrnet.errors import CheckpointError

    (tmp_path / "m.pt").write_bytes(content)
    with pytest.raises(CheckpointError, match=r"m\.pt: cannot load checkpoint: not a PyTorch checkpoint"):
        load_checkpoint(tmp_path / "m.pt")


@pytest.mark.skipif(not (REAL_SAMPLE / "height_map.npy").exists(), reason="../shared/real-sample absent")
def test_evaluate_on_the_real_sample(runs):
    tmp, a, _ = runs
    out = tmp / "real_report"
    rc = main(["evaluate", str(a), "--real", str(REAL_SAMPLE), "--synthetic", "--split", "all", "--out", str(out),
               "--timing-repeats", "1", "--no-progress"])
    assert rc == 0
    summary = json.loads((out / "results.json").read_text())
    assert summary["images"] == 1 and summary["models"][0]["timing_shape"] == [352, 640]
    assert np.isfinite(summary["models"][0]["rmse_mm"])
    assert (out / "figures" / "real_000000.png").exists()


def test_evaluate_writes_only_its_own_files(runs, tmp_path, capsys):
    """evaluate once replaced a user's results.md, per_sample.csv and figures in --out without a word, and wrote
    results.* before failing on a figures/ that is a file: now its names are claimed (.fppsim-owned.json) before
    anything is scored or written, a foreign one refused in one line; its own report, recorded or from before the
    record, is replaced on a re-run."""
    from fppsim.owned import RECORD, owners

    tmp, a, _ = runs
    args = ["evaluate", str(a), "--timing-repeats", "0", "--no-progress", "--figures", "1"]
    own = tmp_path / "own"
    for _ in range(2):  # the second time into its own report
        assert main([*args, "--out", str(own)]) == 0
    capsys.readouterr()
    figure = next((own / "figures").iterdir()).name
    assert owners(own) == {n: "uhrnet evaluate" for n in
                           ["results.md", "results.csv", "results.json", "per_sample.csv", f"figures/{figure}"]}
    (own / RECORD).unlink()  # a report written before evaluate recorded its files is adopted
    assert main([*args, "--out", str(own)]) == 0 and owners(own)["results.md"] == "uhrnet evaluate"
    capsys.readouterr()

    for mine in ("results.md", "per_sample.csv", f"figures/{figure}"):
        user = tmp_path / mine.replace("/", "_")
        (user / "figures").mkdir(parents=True)
        (user / mine).write_text("mine")
        before = sorted(user.rglob("*"))
        assert main([*args, "--out", str(user)]) == 1
        one_line(capsys, f"{user / mine} exists and was not written by uhrnet evaluate")
        assert (user / mine).read_text() == "mine" and sorted(user.rglob("*")) == before  # nothing written
    legacy = tmp_path / "legacy"  # a folder without a record: a results.md that is not evaluate's is not adopted
    shutil.copytree(own, legacy)
    (legacy / RECORD).unlink()
    (legacy / "results.md").write_text("mine")
    assert main([*args, "--out", str(legacy)]) == 1
    one_line(capsys, "results.md exists and was not written by uhrnet evaluate")
    assert (legacy / "results.md").read_text() == "mine" and not (legacy / RECORD).exists()

    (tmp_path / "ef1").mkdir()
    (tmp_path / "ef1" / "figures").write_text("a file")
    assert main([*args, "--out", str(tmp_path / "ef1")]) == 1
    one_line(capsys, f"{tmp_path / 'ef1' / 'figures'}: a file where evaluate writes its figures folder")
    assert sorted(p.name for p in (tmp_path / "ef1").iterdir()) == ["figures"]
    assert main([*args, "--out", str(tmp_path / "ef1"), "--figures", "0"]) == 0  # no figure: no figures folder needed


@pytest.mark.parametrize("command", ["evaluate", "evaluate-phase", "predict"])
def test_every_option_says_what_it_does_and_its_default(command):
    """evaluate's --batch-size, --device and --crop and predict's --device once showed no description or default in
    --help; every option now has one, and one with a default names it in [brackets], as the other options do."""
    import argparse

    from uhrnet.cli import build_parser

    sub = next(a for a in build_parser(command)._actions if isinstance(a, argparse._SubParsersAction))
    options = [a for a in sub.choices[command]._actions if a.option_strings and a.dest != "help"]
    assert [a.dest for a in options if not a.help] == []
    assert [a.dest for a in options if a.default not in (None, False) and "[" not in a.help] == []
