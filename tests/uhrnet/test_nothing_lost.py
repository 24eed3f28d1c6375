"""Issue 30: nothing lost, nothing silent, for train --init-from / --head phase, adapt and predict --refine.

Each test is one case of the issue, run as a user would (the command line, one error line, the exit
status) on a tiny model: files the tool did not write survive, a run never writes over the weights it
starts from, a full disk names the file, unusable rigs are refused wherever they enter, and adapt
resumes only what it can continue and sees images as predict does.
"""

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from uhrnet.cli import main

from _helpers import rig_fringe, tiny_rig, train_tiny, write_figshare, write_native_rig

pytestmark = pytest.mark.usefixtures("one_thread")


def _bump(rig, peak=6.0, cx=30.0, cy=15.0, sigma=8.0):
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    return peak * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))


def _images(folder: Path, rig) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    fr = np.stack([rig_fringe(rig, _bump(rig, 6.0)), rig_fringe(rig, _bump(rig, 4.0, cx=40.0))])
    np.save(folder / "f1_80.npy", (fr.astype(np.float32) / 127.5 - 1)[..., None])
    return folder


def _zero_baseline(path: Path) -> Path:
    d = tiny_rig().to_dict()
    d["projector"] = dict(d["camera"])  # the projector where the camera is
    d["projector"]["width"], d["projector"]["height"] = 912, 1140
    path.write_text(json.dumps(d))
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lost")
    torch.set_num_threads(1)
    write_figshare(tmp / "syn", n=6, h=32, w=64, seed=1)
    run = train_tiny(tmp / "run", "--synthetic", tmp / "syn", "--synthetic-split", "train", extra=["--no-augment"])
    rig = tiny_rig()
    rig.save(tmp / "rig.json")
    _images(tmp / "real", rig)
    return tmp, run


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_error(capsys, *needles) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]


def _adapt(tmp, run, out, *extra):
    return main(["adapt", str(run), "--images", str(tmp / "real"), "--rig", str(tmp / "rig.json"), "--out", str(out),
                 "--epochs", "1", "--no-progress", *map(str, extra)])


# ------------------------------------------------------------------------------------------- case 1
@pytest.mark.parametrize("command", ["adapt", "train"])
def test_disk_full_while_saving_a_checkpoint_is_one_line_naming_the_file(setup, tmp_path, monkeypatch, capsys, command):
    """torch.save reports a full disk as RuntimeError('... unexpected pos ...') from the OSError."""
    import uhrnet.checkpoint as cp

    tmp, run = setup
    real_save = torch.save

    def full_disk(obj, f):
        try:
            real_save(obj, f)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        except OSError:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")

    monkeypatch.setattr(cp.torch, "save", full_disk)
    out = tmp_path / "out"
    if command == "adapt":
        rc = _adapt(tmp, run, out)
    else:
        rc = main(["train", "--synthetic", str(tmp / "syn"), "--synthetic-split", "train", "--model", "unet",
                   "--base-channels", "4", "--epochs", "1", "--loss", "l2", "--no-progress", "--out", str(out)])
    assert rc == 1
    _one_error(capsys, str(out / "last.pt"), "No space left on device")
    assert not list(out.glob(".fppsim-tmp-*")) and not (out / "last.pt").exists()


# ------------------------------------------------------------------------------------------- case 2
def test_adapt_pads_images_whose_sides_are_not_multiples_of_16_as_predict_does(setup, tmp_path, capsys):
    tmp, run = setup
    rig = tiny_rig(width=70, height=38)
    rig.save(tmp_path / "odd.json")
    _images(tmp_path / "odd", rig)
    out = tmp_path / "ad"
    assert main(["adapt", str(run), "--images", str(tmp_path / "odd"), "--rig", str(tmp_path / "odd.json"),
                 "--out", str(out), "--epochs", "1", "--no-progress", "--no-figures"]) == 0
    assert main(["predict", str(out), str(tmp_path / "odd"), "--out", str(tmp_path / "p"), "--no-progress",
                 "--no-ply"]) == 0
    assert np.load(tmp_path / "p" / "odd_0000_height.npy").shape == (38, 70)


# ------------------------------------------------------------------------------------------- case 3
def test_phase_head_rig_of_another_camera_size_is_refused_and_the_rerun_then_works(tmp_path, capsys):
    rig = tiny_rig()
    write_native_rig(tmp_path / "syn", rig, n=4)
    tiny_rig(width=32, height=16).save(tmp_path / "small_cam.json")
    rig.save(tmp_path / "rig.json")
    out = tmp_path / "run"
    base = ["train", "--synthetic", str(tmp_path / "syn"), "--synthetic-split", "train", "--head", "phase",
            "--model", "unet", "--base-channels", "4", "--epochs", "1", "--loss", "l2", "--no-progress",
            "--no-augment", "--out", str(out)]
    assert main(base + ["--rig", str(tmp_path / "small_cam.json")]) == 1
    _one_error(capsys, "small_cam.json", "32x16", "64x32")
    assert not out.exists()  # a failed run leaves no folder behind
    out.mkdir()
    assert main(base + ["--rig", str(tmp_path / "small_cam.json")]) == 1
    capsys.readouterr()
    assert main(base + ["--rig", str(tmp_path / "rig.json")]) == 0  # nothing blocks the corrected re-run


# ------------------------------------------------------------------------------------------- case 4
@pytest.mark.parametrize("name", ["config.json", "history.csv", "images.json", "figures/real_0000_adapt.png"])
def test_adapt_never_replaces_files_it_did_not_write(setup, tmp_path, capsys, name):
    tmp, run = setup
    out = tmp_path / "ad"
    (out / name).parent.mkdir(parents=True)
    (out / name).write_text("someone else's")
    assert _adapt(tmp, run, out) == 1
    _one_error(capsys, str(out / name), "not written by uhrnet adapt")
    assert _snapshot(out) == {Path(name): b"someone else's"}


def test_adapt_replaces_its_own_files_on_resume_and_overwrite(setup, tmp_path, capsys):
    tmp, run = setup
    out = tmp_path / "ad"
    assert _adapt(tmp, run, out) == 0
    assert _adapt(tmp, run, out, "--epochs", "2") == 0  # resumes its own run
    assert _adapt(tmp, run, out, "--lr", "1e-3", "--overwrite") == 0
    assert json.loads((out / "config.json").read_text())["lr"] == 1e-3


# ------------------------------------------------------------------------------------------- case 5
def test_adapt_into_the_training_run_is_refused_even_with_overwrite(setup, tmp_path, capsys):
    tmp, run = setup
    before = _snapshot(run)
    for extra in ((), ("--overwrite",)):
        assert _adapt(tmp, run, run, *extra) == 1
        line = _one_error(capsys, str(run), "replace the weights")
        assert "--overwrite" not in line
    assert main(["adapt", str(run / "best.pt"), "--images", str(tmp / "real"), "--rig", str(tmp / "rig.json"),
                 "--out", str(run), "--epochs", "1", "--no-progress", "--overwrite"]) == 1
    capsys.readouterr()
    copy = tmp_path / "copy"  # another folder holding a training run (its ownership record says so)
    shutil.copytree(run, copy)
    assert _adapt(tmp, run, copy, "--overwrite") == 1
    _one_error(capsys, str(copy), "best.pt", "choose another --out")  # a training run's best.pt: refused first
    assert _snapshot(run) == before and _snapshot(copy) == before
    (copy / "best.pt").unlink()  # its other files are still the run's, by its ownership record
    kept = {k: v for k, v in _snapshot(copy).items() if k.name != ".fppsim-owned.json"}
    assert _adapt(tmp, run, copy, "--overwrite") == 1
    _one_error(capsys, "written by uhrnet train, not uhrnet adapt")
    assert {k: v for k, v in _snapshot(copy).items() if k.name != ".fppsim-owned.json"} == kept


# ------------------------------------------------------------------------------------------- case 6
def test_init_from_its_own_out_is_refused_even_with_overwrite(setup, tmp_path, capsys):
    tmp, run = setup
    mine = tmp_path / "pre"
    shutil.copytree(run, mine)
    before = _snapshot(mine)
    for init in (mine, mine / "best.pt"):
        assert main(["train", "--synthetic", str(tmp / "syn"), "--synthetic-split", "train", "--model", "unet",
                     "--base-channels", "4", "--epochs", "1", "--loss", "l2", "--no-progress", "--init-from", str(init),
                     "--out", str(mine), "--overwrite"]) == 1
        _one_error(capsys, "--init-from", "replace the weights")
    assert _snapshot(mine) == before


def test_train_never_replaces_foreign_files_even_with_overwrite(setup, tmp_path, capsys):
    tmp, run = setup
    out = tmp_path / "run"
    out.mkdir()
    (out / "history.png").write_text("a figure of mine")
    assert main(["train", "--synthetic", str(tmp / "syn"), "--synthetic-split", "train", "--model", "unet",
                 "--base-channels", "4", "--epochs", "1", "--loss", "l2", "--no-progress", "--out", str(out),
                 "--overwrite"]) == 1
    _one_error(capsys, str(out / "history.png"), "not written by uhrnet train")
    assert _snapshot(out) == {Path("history.png"): b"a figure of mine"}


# ------------------------------------------------------------------------------------------- case 7
def test_a_rig_that_cannot_measure_is_refused_wherever_it_enters(setup, tmp_path, capsys):
    tmp, run = setup
    zero = _zero_baseline(tmp_path / "zerobase.json")
    assert main(["predict", str(run), str(tmp / "real"), "--out", str(tmp_path / "p"), "--refine", "phase",
                 "--rig", str(zero), "--no-progress", "--no-ply"]) == 1
    _one_error(capsys, "zerobase.json", "fringes do not move with height")
    assert not list((tmp_path / "p").glob("*_height.npy")) if (tmp_path / "p").exists() else True
    assert main(["adapt", str(run), "--images", str(tmp / "real"), "--rig", str(zero), "--out", str(tmp_path / "a"),
                 "--epochs", "1", "--no-progress"]) == 1
    _one_error(capsys, "zerobase.json", "fringes do not move with height")
    assert not (tmp_path / "a").exists()
    write_native_rig(tmp_path / "syn", tiny_rig(), n=2)
    assert main(["train", "--synthetic", str(tmp_path / "syn"), "--synthetic-split", "train", "--head", "phase",
                 "--rig", str(zero), "--model", "unet", "--base-channels", "4", "--epochs", "1", "--no-progress",
                 "--out", str(tmp_path / "t")]) == 1
    _one_error(capsys, "zerobase.json", "fringes do not move with height")


# ------------------------------------------------------------------------------------------- case 8
def test_adapt_resume_refuses_a_changed_source_keeps_its_epochs_and_names_the_option(setup, tmp_path, capsys):
    tmp, run = setup
    src = tmp_path / "src"
    shutil.copytree(run, src)
    out = tmp_path / "ad"
    assert _adapt(tmp, src, out, "--epochs", "2") == 0
    assert _adapt(tmp, src, out, "--epochs", "1") == 0  # fewer epochs: nothing to do, the record says 2
    assert json.loads((out / "config.json").read_text())["epochs"] == 2
    assert _adapt(tmp, src, out, "--epochs", "3", "--lr", "1e-3") == 1
    _one_error(capsys, "--lr 0.001", "0.0003")
    before = _snapshot(out)
    ck = torch.load(src / "best.pt", weights_only=True)  # the source retrained meanwhile
    ck["state_dict"] = {k: v + 0.01 if v.is_floating_point() else v for k, v in ck["state_dict"].items()}
    torch.save(ck, src / "best.pt")
    assert _adapt(tmp, src, out, "--epochs", "3") == 1
    _one_error(capsys, str(src / "best.pt"), "changed since")
    assert _snapshot(out) == before


# ------------------------------------------------------------------------------------------- case 9
def test_adapt_runs_the_network_at_the_training_runs_resize_as_predict_does(tmp_path, monkeypatch, capsys):
    import uhrnet.checkpoint as cp

    write_figshare(tmp_path / "syn", n=4, h=32, w=64, seed=1)
    run = train_tiny(tmp_path / "run", "--synthetic", tmp_path / "syn", "--synthetic-split", "train",
                     extra=["--no-augment", "--resize", "16x32"])
    rig = tiny_rig()
    rig.save(tmp_path / "rig.json")
    _images(tmp_path / "real", rig)
    seen = []
    real = cp.model_from_checkpoint

    def spy(*a, **k):
        model, transform = real(*a, **k)
        model.register_forward_pre_hook(lambda mod, args: seen.append(tuple(args[0].shape[-2:])))
        return model, transform

    import uhrnet.training.adapt as adapt_module

    monkeypatch.setattr(adapt_module, "model_from_checkpoint", spy)  # where adapt looks it up
    assert main(["adapt", str(run), "--images", str(tmp_path / "real"), "--rig", str(tmp_path / "rig.json"),
                 "--out", str(tmp_path / "ad"), "--epochs", "1", "--no-progress", "--no-figures"]) == 0
    assert seen and set(seen) == {(16, 32)}


# ------------------------------------------------------------------------------------------- case 10
@pytest.mark.parametrize("flag,value", [("--min-reliability", "2"), ("--min-reliability", "1"), ("--max-step", "0")])
def test_adapt_ranges_that_adapt_nothing_are_usage_errors(setup, tmp_path, capsys, flag, value):
    tmp, run = setup
    assert _adapt(tmp, run, tmp_path / "ad", flag, value) == 2
    _one_error(capsys, flag)
    assert not (tmp_path / "ad").exists()


# ------------------------------------------------------------------------------------------- smaller
def test_failed_runs_leave_no_empty_out_folder(setup, tmp_path, capsys):
    tmp, run = setup
    out = tmp_path / "new" / "ad"
    assert main(["adapt", str(run), "--images", str(tmp / "real"), "--out", str(out), "--epochs", "1",
                 "--no-progress"]) == 1  # fppsim's default rig: 640 x 352, not these images' size
    _one_error(capsys, "rig's camera")
    assert not out.exists() and not out.parent.exists()


def test_phase_head_with_resize_is_a_usage_error(tmp_path, capsys):
    assert main(["train", "--synthetic", str(tmp_path), "--head", "phase", "--resize", "96x160",
                 "--out", str(tmp_path / "run")]) == 2
    _one_error(capsys, "--head phase", "--resize")


def test_a_full_disk_names_the_file_whatever_writes_it(tmp_path, monkeypatch):
    import fppsim.files as files

    def full(fh, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as write_fully reports a short write

    monkeypatch.setattr(files, "write_fully", full)
    with pytest.raises(OSError) as exc:
        files.atomic_write_text(tmp_path / "history.csv", "epoch\n")
    assert exc.value.filename == str(tmp_path / "history.csv") and exc.value.errno == errno.ENOSPC
    assert not list(tmp_path.iterdir())


def test_adapt_reads_a_scan_folder_that_holds_only_ipattern(setup, tmp_path, capsys):
    from fppsim.dataio.writers import save_psp_folder_sample

    tmp, run = setup
    rig = tiny_rig()
    scan = tmp_path / "scan"
    f8 = rig_fringe(rig, _bump(rig, 5.0))
    save_psp_folder_sample(scan, "1201", np.zeros(f8.shape), np.ones(f8.shape), np.zeros(f8.shape), f8)
    for sub in ("PSin", "PCos", "Fringe"):
        shutil.rmtree(scan / sub)
    assert main(["adapt", str(run), "--images", str(scan), "--rig", str(tmp / "rig.json"), "--out",
                 str(tmp_path / "ad"), "--epochs", "1", "--no-progress", "--no-figures"]) == 0
    assert [im["name"] for im in json.loads((tmp_path / "ad" / "images.json").read_text())] == ["scan_1201"]


@pytest.mark.parametrize("count,needle", [("0", "--count must be from 1"), ("4", "needs at least 6 samples")])
def test_sim2real_counts_it_cannot_use_are_usage_errors_before_generating(tmp_path, capsys, count, needle):
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(tmp_path / "o"), "--count", count]) == 2
    _one_error(capsys, needle)
    assert not (tmp_path / "o").exists()


def test_adapt_defaults_like_train_and_states_its_ranges(capsys):
    from uhrnet.training.adapt import AdaptConfig
    from uhrnet.training.train_config import DEFAULTS

    assert AdaptConfig.__dataclass_fields__["device"].default == DEFAULTS["device"] == "auto"
    with pytest.raises(SystemExit):
        main(["adapt", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "reliability (0 to 1) is below this (in [0, 1))" in text and "(rad, > 0)" in text


def test_predict_never_replaces_files_it_did_not_write(setup, tmp_path, capsys):
    tmp, run = setup
    out = tmp_path / "p"
    out.mkdir()
    (out / "real_0001_height_network.npy").write_text("mine")
    args = ["predict", str(run), str(tmp / "real"), "--out", str(out), "--no-progress", "--no-ply"]
    assert main(args) == 0  # without --refine that name is not written
    assert main(args + ["--refine", "phase", "--rig", str(tmp / "rig.json")]) == 1
    _one_error(capsys, str(out / "real_0001_height_network.npy"), "not written by uhrnet predict")
    assert (out / "real_0001_height_network.npy").read_text() == "mine"
    (out / "real_0001_height_network.npy").unlink()
    assert main(args + ["--refine", "phase", "--rig", str(tmp / "rig.json")]) == 0
    assert main(args + ["--refine", "phase", "--rig", str(tmp / "rig.json")]) == 0  # its own files: replaced


def test_sim2real_refuses_an_unusable_rig_before_generating(tmp_path, capsys):
    zero = _zero_baseline(tmp_path / "zerobase.json")
    write_figshare(tmp_path / "real", n=2, h=32, w=64)
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(tmp_path / "o"), "--rig", str(zero)]) == 1
    _one_error(capsys, "zerobase.json", "fringes do not move with height")
    assert not (tmp_path / "o").exists()


def test_sim2real_never_replaces_a_report_it_did_not_write(tmp_path, capsys):
    write_figshare(tmp_path / "real", n=2, h=32, w=64)
    out = tmp_path / "o"
    out.mkdir()
    (out / "report.md").write_text("my report")
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--count", "6"]) == 1
    _one_error(capsys, str(out / "report.md"), "not written by uhrnet sim2real")
    assert (out / "report.md").read_text() == "my report" and not (out / "data").exists()


def test_predict_checks_every_size_before_writing(setup, tmp_path, capsys):
    tmp, run = setup
    tiny_rig(width=70, height=38).save(tmp_path / "odd.json")
    out = tmp_path / "p"
    assert main(["predict", str(run), str(tmp / "real"), "--out", str(out), "--refine", "phase", "--rig",
                 str(tmp_path / "odd.json"), "--no-ply", "--no-progress"]) == 1
    _one_error(capsys, "odd.json", "70x38")
    assert not out.exists()


def test_train_resume_with_fewer_epochs_keeps_the_epochs_the_weights_hold(setup, tmp_path, capsys):
    tmp, run = setup
    mine = tmp_path / "run"
    shutil.copytree(run, mine)
    assert main(["train", "--resume", "--epochs", "1", "--out", str(mine), "--no-progress"]) == 0
    assert json.loads((mine / "config.json").read_text())["epochs"] == 1
    ck = torch.load(mine / "last.pt", weights_only=True)
    ck["epoch"] = 3  # as if trained for 3 epochs
    torch.save(ck, mine / "last.pt")
    assert main(["train", "--resume", "--epochs", "1", "--out", str(mine), "--no-progress"]) == 0
    assert "nothing to do" in capsys.readouterr().out
    assert json.loads((mine / "config.json").read_text())["epochs"] == 3
