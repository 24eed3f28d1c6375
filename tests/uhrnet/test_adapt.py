"""uhrnet.training.adapt: label-free fine-tuning on tiny images of a tiny rig (run folder, resume, refusals, labels never
read) and the adaptation loss against analytic truth through the rig layer."""

import csv
import json
import math

import numpy as np
import pytest
import torch

from uhrnet.training.adapt import AdaptConfig, adapt, adapt_loss
from uhrnet.cli import main
from uhrnet.errors import ConfigError
from uhrnet.physics.rig_layer import RigLayer

from _helpers import rig_fringe, tiny_rig, train_tiny, write_figshare

pytestmark = pytest.mark.usefixtures("one_thread")


def _bump(rig, peak=6.0, cx=30.0, cy=15.0, sigma=8.0):
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    return peak * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A tiny height-head run (32 x 64 figshare data), the tiny rig as a file, and an unlabelled real-like folder
    of 2 images of that rig whose Z.npy is garbage (adaptation must never read it)."""
    tmp = tmp_path_factory.mktemp("adapt")
    torch.set_num_threads(1)
    write_figshare(tmp / "syn", n=6, h=32, w=64, seed=1)
    run = train_tiny(tmp / "run", "--synthetic", tmp / "syn", "--synthetic-split", "train", extra=["--no-augment"])
    rig = tiny_rig()
    rig.save(tmp / "rig.json")
    real = tmp / "real"
    real.mkdir()
    fr = np.stack([rig_fringe(rig, _bump(rig, 6.0)), rig_fringe(rig, _bump(rig, 4.0, cx=40.0))])
    np.save(real / "f1_80.npy", (fr.astype(np.float32) / 127.5 - 1)[..., None])
    (real / "Z.npy").write_bytes(b"not a label file")
    return tmp, run, rig


def _cfg(tmp, run, out, **kw):
    base = dict(checkpoint=run, images=[tmp / "real"], out=out, rig=tmp / "rig.json", epochs=2, progress=False)
    return AdaptConfig(**{**base, **kw})


def _history(out):
    return list(csv.DictReader((out / "history.csv").open()))


def test_adapt_writes_its_run_folder_never_reads_labels_and_resumes(setup, tmp_path, monkeypatch, capsys):
    tmp, run, rig = setup
    opened = []
    real_load = np.load

    def spy(file, *a, **k):
        opened.append(str(file))
        return real_load(file, *a, **k)

    monkeypatch.setattr(np, "load", spy)
    out = tmp_path / "ad"
    result = adapt(_cfg(tmp, run, out), log=lambda line: None)
    assert not [p for p in opened if p.endswith("Z.npy")]  # the label file is never opened
    assert any(p.endswith("f1_80.npy") for p in opened)
    for name in ("last.pt", "history.csv", "images.json", "config.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "figures").glob("*_adapt.png"))) == 2
    rows = _history(out)
    assert [int(r["epoch"]) for r in rows] == [1, 2] and all(math.isfinite(float(r["loss"])) for r in rows)
    images = json.loads((out / "images.json").read_text())
    assert [im["name"] for im in images] == ["real_0000", "real_0001"]
    assert all({"before_rad", "after_rad", "mean_change_mm"} <= set(im) for im in images)
    assert result.epochs == 2 and len(result.history) == 2
    # predict takes the adaptation's folder as a checkpoint
    monkeypatch.setattr(np, "load", real_load)
    capsys.readouterr()
    assert main(["predict", str(out), str(tmp / "real"), "--out", str(tmp_path / "p"), "--no-progress",
                 "--no-ply"]) == 0
    assert np.load(tmp_path / "p" / "real_0001_height.npy").shape == (32, 64)
    # resume: the same options with more epochs continue the history
    adapt(_cfg(tmp, run, out, epochs=3), log=lambda line: None)
    again = _history(out)
    assert [int(r["epoch"]) for r in again] == [1, 2, 3]
    assert again[:2] == rows
    # the same folder with other options is refused (one line, names the folder)
    with pytest.raises(ConfigError, match="other options") as exc:
        adapt(_cfg(tmp, run, out, epochs=3, lr=1e-3), log=lambda line: None)
    assert str(out) in str(exc.value) and "\n" not in str(exc.value)
    assert len(_history(out)) == 3


def test_adapt_refuses_a_training_run_folder_and_a_rig_of_another_size(setup, tmp_path):
    tmp, run, rig = setup
    with pytest.raises(ConfigError, match="would replace the weights this run starts from"):
        adapt(_cfg(tmp, run, run), log=lambda line: None)
    with pytest.raises(ConfigError, match="rig's camera"):
        adapt(_cfg(tmp, run, tmp_path / "x", rig=None), log=lambda line: None)  # fppsim's default rig: 640 x 352


def test_adapt_loss_is_zero_where_the_height_explains_the_image_and_its_gradient_points_back():
    rig = tiny_rig()
    layer = RigLayer(rig)
    h = torch.from_numpy(_bump(rig, 6.0))[None, None]
    origin = 1.7  # the image counts phase from another origin: only wrapped differences matter
    with torch.no_grad():
        wrapped = torch.remainder(layer.phase_from_height(h) + origin + math.pi, 2 * math.pi) - math.pi
    rel = torch.ones_like(h)
    total, terms = adapt_loss(h, h, wrapped, rel, layer)
    assert float(total) < 1e-9 and all(abs(v) < 1e-9 for v in terms.values())
    # a wrong relief (within half a period) costs, and gradient descent moves it back towards h
    err = torch.from_numpy(_bump(rig, 1.5, cx=20.0, sigma=5.0))[None, None]
    x = (h + err).clone().requires_grad_(True)
    total, terms = adapt_loss(x, (h + err), wrapped, rel, layer, w_drift=0.0)
    assert float(total.detach()) > 1e-3 and terms["grad"] > 0 and set(terms) == {"grad", "drift"}
    total.backward()
    assert float((x.grad * err).sum()) > 0  # the gradient points along the error
    y = (h + err).clone().requires_grad_(True)
    opt = torch.optim.Adam([y], lr=0.05)
    for _ in range(300):  # the gradient term alone (0.55 of the error left after 100 steps, 0.08 after 300)
        loss, _ = adapt_loss(y, h + err, wrapped, rel, layer, w_drift=0.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    # (the phase term sees the relief, not a constant: it compares phase steps, blind to the image's origin)
    relief = lambda d: float((d - d.median()).abs().mean())  # noqa: E731
    assert relief(y.detach() - h) < 0.3 * relief(err)
    # the drift term alone pulls to the source prediction
    z = (h + err).clone().requires_grad_(True)
    loss, terms = adapt_loss(z, h, wrapped, torch.zeros_like(rel) + 1e-3, layer, w_grad=0.0)
    assert terms["drift"] == pytest.approx(float(err.abs().mean()) / 10.0, rel=1e-6)


def test_adapt_says_when_a_float_frame_looks_scaled_to_0_1(setup, tmp_path):
    """A float .npy with no value below 0 is read as the encoding (a [0, 1] image reads about 21 mm off): adapt
    says so for that frame, as predict does (it once read it without a word)."""
    tmp, run, rig = setup
    (tmp_path / "unit").mkdir()
    fr = rig_fringe(rig, _bump(rig, 6.0)).astype(np.float32) / 255.0
    np.save(tmp_path / "unit" / "f.npy", fr)
    lines = []
    try:
        adapt(_cfg(tmp, run, tmp_path / "out", images=[tmp_path / "unit"], epochs=1), log=lines.append)
    except ConfigError:  # the image misread may leave nothing to adapt to: the warning came first
        pass
    said = [line for line in lines if "values span" in line]
    assert len(said) == 1 and said[0].startswith("adapt: warning: ") and "f.npy (f)" in said[0]


def test_adapt_resumed_equals_uninterrupted_bit_for_bit(setup, tmp_path):
    """The image order of an epoch depends on the seed and the epoch only: 1 epoch then a resume to 2 gives the
    weights of a straight 2-epoch run (the shuffle once restarted on every invocation, QA M1)."""
    tmp, run, rig = setup
    g = torch.Generator().manual_seed(0)
    assert torch.randperm(2, generator=g).tolist() != torch.randperm(2, generator=g).tolist()  # orders differ
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    adapt(_cfg(tmp, run, straight, epochs=2, figures=False, seed=0), log=lambda line: None)
    adapt(_cfg(tmp, run, resumed, epochs=1, figures=False, seed=0), log=lambda line: None)
    lines = []
    adapt(_cfg(tmp, run, resumed, epochs=2, figures=False, seed=0), log=lines.append)
    assert any("resuming" in line for line in lines)
    a = torch.load(straight / "last.pt", weights_only=True)["state_dict"]
    b = torch.load(resumed / "last.pt", weights_only=True)["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert _history(straight)[1]["loss"] == _history(resumed)[1]["loss"]
    # a smaller --epochs has nothing to do and says only that
    lines = []
    adapt(_cfg(tmp, run, resumed, epochs=1, figures=False, seed=0), log=lines.append)
    assert not any("resuming" in line for line in lines) and any("nothing to do" in line for line in lines)
    # other options: the message says which value resumes (RUN is required, it cannot be dropped)
    with pytest.raises(ConfigError, match=r"give --lr 0.0003 to resume"):
        adapt(_cfg(tmp, run, resumed, epochs=2, figures=False, lr=1e-3), log=lambda line: None)
    # review: an option the run was started without is left out to resume ("give --rig None" was no command)
    ck = torch.load(resumed / "last.pt", weights_only=False)
    ck["adapt"]["config"]["rig"] = None  # as a run started without --rig records it
    torch.save(ck, resumed / "last.pt")
    with pytest.raises(ConfigError, match=r"--rig \S+ differs from its None; leave --rig out to resume"):
        adapt(_cfg(tmp, run, resumed, epochs=3, figures=False, seed=0), log=lambda line: None)


def test_adapt_refuses_an_out_holding_a_best_pt_it_did_not_write(setup, tmp_path, capsys):
    """A RUN folder stands for its best.pt first: adapt (which writes only last.pt) beside another model's best.pt
    made predict of that folder silently use the other, un-adapted model (QA H3). Refused, nothing written."""
    tmp, run, rig = setup
    out = tmp_path / "someone"
    out.mkdir()
    (out / "best.pt").write_bytes((run / "best.pt").read_bytes())
    rc = main(["adapt", str(run), "--images", str(tmp / "real"), "--out", str(out), "--rig", str(tmp / "rig.json"),
               "--epochs", "1", "--no-progress", "--no-figures"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "best.pt" in err and "\n" not in err
    assert sorted(p.name for p in out.iterdir()) == ["best.pt"]


def test_adapt_refuses_a_negative_seed(setup, tmp_path, capsys):
    tmp, run, rig = setup
    assert main(["adapt", str(run), "--images", str(tmp / "real"), "--out", str(tmp_path / "o"), "--seed", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--seed" in err and "\n" not in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("seed", [True, 1.5, "3", 3.0, None, 2**64])
def test_adapt_refuses_a_seed_that_is_no_torch_seed(setup, tmp_path, seed):
    """adapt's seed is one torch.Generator's: a whole number from 0 to 2**64 - 1 (the check generate's configs use);
    True, 3.0, None were taken or failed as a TypeError, 2**64 a ValueError traceback after config.json was written."""
    tmp, run, rig = setup
    if isinstance(seed, int) and not isinstance(seed, bool):  # the truth: torch refuses it, and takes one less
        with pytest.raises((ValueError, RuntimeError)):
            torch.Generator().manual_seed(seed)
        torch.Generator().manual_seed(seed - 1)
    with pytest.raises(ConfigError, match=r"^--seed must be an integer from 0 to 18446744073709551615, got "):
        _cfg(tmp, run, tmp_path / "o", seed=seed)
    assert AdaptConfig(checkpoint=run, images=[tmp / "real"], out=tmp_path / "o", seed=2**64 - 1).seed == 2**64 - 1


def test_adapt_refuses_a_seed_above_torchs_before_writing(setup, tmp_path, capsys):
    tmp, run, rig = setup
    assert main(["adapt", str(run), "--images", str(tmp / "real"), "--out", str(tmp_path / "o"),
                 "--seed", str(2**64)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("uhrnet adapt: error: --seed must be an integer from 0 to") and "\n" not in err
    assert not (tmp_path / "o").exists()
