"""uhrnet.scoring.phase_residual on a folder (`uhrnet evaluate-phase`): checkpoints on a PSin/PCos/Fringe/iPattern
folder, no height labels."""

import json

import numpy as np
import pytest

from _helpers import scene, train_tiny, write_figshare
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.cli import main

pytestmark = pytest.mark.slow  # trains a tiny model (about 15 s on 2 cores)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ephase")
    write_figshare(tmp / "real", n=8, h=32, w=64, seed=1)
    run = train_tiny(tmp / "unet", "--real", tmp / "real")
    rng = np.random.default_rng(7)
    root = tmp / "phase"
    truth = {}
    for i in range(3):
        img, height, valid = scene(rng, 32, 64)
        xx = np.arange(64)[None, :] * np.ones((32, 1))
        phase = 1.0 + 2 * np.pi * xx / 11.6 - 0.45 * height  # the benchmark's carrier and sign
        save_psp_folder_sample(root, f"{i}", *sums_from_phase(phase, valid, 30.0), img)
        truth[f"{i}"] = (phase, height, valid)
    return tmp, run, root, truth


def test_report(setup, capsys):
    tmp, run, root, truth = setup
    out = tmp / "report"
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "2",
               "--names", "tiny", "--device", "cpu", "--degree", "2"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "Residual RMSE (rad)" in text and "| tiny |" in text
    doc = json.loads((out / "phase_results.json").read_text())
    assert [r["id"] for r in doc["per_image"]] == ["0", "1", "2"]
    assert doc["models"][0]["name"] == "tiny" and doc["degree"] == 2
    row = doc["models"][0]
    assert row["ratio"] == pytest.approx(np.mean([r["models"]["tiny"]["prediction"]["rmse_rad"]
                                                  / r["models"]["tiny"]["flat"]["rmse_rad"] for r in doc["per_image"]]))
    assert np.isfinite(row["plane_ratio"]) and "Plane-pixel plane" in text
    for rec in doc["per_image"]:
        m = rec["models"]["tiny"]
        assert m["flat"]["explained"] == pytest.approx(0.0, abs=1e-9)
        # the flat baseline's residual is the relief left by a degree-2 plane fit of the true phase
        phase, height, valid = truth[rec["id"]]
        assert m["flat"]["relief_rms_rad"] > 1.0
        assert m["prediction"]["rmse_rad"] <= m["flat"]["rmse_rad"] + 1e-9  # h terms can only lower SS
        assert rec["valid_phase_fraction"] == pytest.approx(valid.mean())
        # the second score: the plane fitted on the plane's own pixels, found in the phase (h == 0 there)
        plane = m["plane"]
        assert plane["flat"]["plane_pixels"] > 0 and plane["flat"]["plane_pixels"] <= (valid & (height == 0)).sum() + 5
        assert plane["prediction"]["rmse_rad"] <= plane["flat"]["rmse_rad"] + 1e-9
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["0.png", "1.png"]
    # the predicted-invalid mask option leaves out what the model calls shadow
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp / "r2"), "--figures", "0",
               "--device", "cpu", "--mask-predicted-invalid", "--ids", "1"])
    m = doc["per_image"][1]["models"]["tiny"]
    if rc == 0:
        doc2 = json.loads((tmp / "r2" / "phase_results.json").read_text())
        assert doc2["models"][0]["pixel_fraction"] <= m["pixel_fraction"]
    else:  # this model calls too much shadow to fit anything: a one-line error
        assert "valid pixels" in capsys.readouterr().err
    assert (out / "phase_results.md").read_text().startswith("# Calibration-free phase evaluation")


def test_errors_are_one_line(setup, capsys, tmp_path):
    tmp, run, root, truth = setup
    rc = main(["evaluate-phase", str(run), "--phase-root", str(tmp_path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1
    assert "missing folder(s) PSin, PCos, Fringe, iPattern" in err
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "o"), "--ids", "9"])
    assert rc == 1 and "no such id(s): 9" in capsys.readouterr().err


def test_train_val_phase_picks_best_by_the_real_frames(setup, tmp_path, capsys):
    """``uhrnet train --val-phase``: each epoch's score is what evaluate-phase reports for that epoch's
    weights, and best.pt is the epoch the real frames score lowest, whatever the synthetic validation says."""
    tmp, _, root, truth = setup
    run = train_tiny(tmp_path / "vp", "--real", tmp / "real", epochs=3, extra=["--val-phase", root])
    printed = capsys.readouterr().out
    assert "real phase residual" in printed and "(held-out frames " in printed
    rows = history(run)
    ratios = [float(r["val_phase_ratio"]) for r in rows]
    assert len(ratios) == 3 and all(np.isfinite(ratios))
    import torch

    best = torch.load(run / "best.pt", map_location="cpu", weights_only=False)
    full = [r["val_phase_ratio"] for r in torch.load(run / "last.pt", map_location="cpu", weights_only=False)["history"]]
    assert full == pytest.approx(ratios, rel=1e-5)
    assert best["best"]["metric"] == "val_phase_ratio"
    assert best["epoch"] == 1 + int(np.argmin(full))  # first of equal scores: a later one must be lower
    assert [int(r["best"]) for r in rows][best["epoch"] - 1] == 1
    for ckpt, row in (("best.pt", rows[best["epoch"] - 1]), ("last.pt", rows[-1])):
        out = tmp_path / f"ev_{ckpt}"
        assert main(["evaluate-phase", str(run / ckpt), "--phase-root", str(root), "--out", str(out),
                     "--figures", "0", "--device", "cpu"]) == 0
        doc = json.loads((out / "phase_results.json").read_text())
        per = [r["models"][doc["models"][0]["name"]] for r in doc["per_image"]]
        # QA: scored on the frames that chose it, evaluate-phase says so (last.pt only when it is the best epoch)
        chose = ckpt == "best.pt" or best["epoch"] == 3
        assert list(doc["chosen_on"].values()) == ([["0", "2"]] if chose else [])
        assert ("chosen (train --val-phase) on frame(s) 0, 2" in capsys.readouterr().out) == chose
        # frames 0 and 2 choose best.pt, frame 1 is held out (issue 50: no best.pt chosen on its own score)
        for keys, frames in ((("val_phase_ratio", "val_phase_rad"), [per[0], per[2]]),
                             (("val_phase_heldout_ratio", "val_phase_heldout_rad"), [per[1]])):
            ratio = np.mean([m["prediction"]["rmse_rad"] / m["flat"]["rmse_rad"] for m in frames])
            assert float(row[keys[0]]) == pytest.approx(ratio, rel=1e-4)
            assert float(row[keys[1]]) == pytest.approx(np.mean([m["prediction"]["rmse_rad"] for m in frames]),
                                                        rel=1e-4)
    # the frames that choose best.pt cannot change under a resumed run, nor be dropped from an older one
    rc = main(["train", "--out", str(run), "--resume", "--epochs", "4", "--val-phase", str(tmp_path)])
    assert rc == 1 and "--val-phase" in capsys.readouterr().err
    assert main(["train", "--out", str(run), "--resume", "--epochs", "4", "--no-progress"]) == 0
    assert "val_phase_ratio" in history(run)[-1] and np.isfinite(float(history(run)[-1]["val_phase_ratio"]))


def test_evaluate_phase_recognises_a_copy_of_the_frames_that_chose_best(setup, tmp_path, capsys):
    """A copy of the --val-phase folder under another name (a frame renamed in it too) is scored with the warning
    that the weights were chosen on it; its held-out frame and an unrelated frame are not named."""
    import shutil

    tmp, _, root, truth = setup
    run = train_tiny(tmp_path / "vp", "--real", tmp / "real", extra=["--val-phase", root])
    copy = tmp_path / "moved" / "my_frames"
    shutil.copytree(root, copy)
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        (copy / sub / "2.mat").rename(copy / sub / "b.mat")
    phase, height, valid = truth["0"]
    save_psp_folder_sample(copy, "new", *sums_from_phase(phase + 0.3 * height, valid, 30.0),
                           np.full(phase.shape, 120, np.uint8))  # another scene: not a frame of the run
    capsys.readouterr()
    out = tmp_path / "ev"
    assert main(["evaluate-phase", str(run / "best.pt"), "--phase-root", str(copy), "--out", str(out),
                 "--figures", "0", "--device", "cpu"]) == 0
    doc = json.loads((out / "phase_results.json").read_text())
    assert list(doc["chosen_on"].values()) == [["0", "b"]]  # frames 0 and 2 chose best.pt; 1 was held out
    warn = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning:")]
    assert len(warn) == 1 and f"0, b of {copy} (the same frames as 0, 2 of {root.resolve()})" in warn[0]
    assert "Not held out" in (out / "phase_results.md").read_text()
    assert main(["evaluate-phase", str(run / "best.pt"), "--phase-root", str(copy), "--out", str(tmp_path / "e2"),
                 "--figures", "0", "--device", "cpu", "--ids", "1", "new"]) == 0
    assert json.loads((tmp_path / "e2" / "phase_results.json").read_text())["chosen_on"] == {}
    assert "weights were chosen" not in capsys.readouterr().out


def test_train_val_phase_bad_folder_is_one_line(setup, tmp_path, capsys):
    tmp, _, root, truth = setup
    rc = main(["train", "--real", str(tmp / "real"), "--model", "unet", "--base-channels", "4", "--epochs", "1",
               "--out", str(tmp_path / "r"), "--no-progress", "--val-phase", str(tmp_path / "nope")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and err.count("--val-phase") == 1 and "nope" in err
    assert not (tmp_path / "r" / "last.pt").exists()


def test_train_val_phase_frames_of_another_size_are_one_line(setup, tmp_path, capsys):
    """Frames of another size than the training images are of another rig: refused before any training."""
    tmp, _, _, _ = setup
    rng = np.random.default_rng(3)
    img, height, valid = scene(rng, 40, 64)
    phase = 1.0 + 2 * np.pi * np.arange(64)[None, :] * np.ones((40, 1)) / 11.6 - 0.45 * height
    save_psp_folder_sample(tmp_path / "other", "9", *sums_from_phase(phase, valid, 30.0), img)
    rc = main(["train", "--real", str(tmp / "real"), "--model", "unet", "--base-channels", "4", "--epochs", "1",
               "--out", str(tmp_path / "r"), "--no-progress", "--val-phase", str(tmp_path / "other")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1, err
    assert "64 x 40 px" in err and "training images are 64 x 32" in err
    assert not (tmp_path / "r" / "last.pt").exists()


def test_frames_written_another_way_are_read_that_way(setup, tmp_path, capsys):
    """The same frames written as atan2(PSin, PCos) + 2 pi Order, or with PSin negated: --convention auto (the
    default of evaluate-phase and of train's --val-phase-convention) reads them the way they were written, says
    so, and scores them exactly as the public-layout frames; read as the public data they are garbage."""
    import scipy.io

    tmp, run, root, truth = setup
    for sid, (phase, height, valid) in truth.items():
        img = scipy.io.loadmat(root / "iPattern" / f"{sid}.mat")["iPattern"]
        save_psp_folder_sample(tmp_path / "fppsim", sid, *sums_from_phase(phase, valid, 30.0, "fppsim"), img)
        save_psp_folder_sample(tmp_path / "negated", sid, *sums_from_phase(phase, valid, 30.0), img)
        f = tmp_path / "negated" / "PSin" / f"{sid}.mat"
        scipy.io.savemat(f, {"PSin": -scipy.io.loadmat(f)["PSin"]})

    def ratios(folder, *flags):
        out = tmp_path / f"ev_{folder.name}_{len(flags)}"
        assert main(["evaluate-phase", str(run), "--phase-root", str(folder), "--out", str(out), "--figures", "0",
                     "--device", "cpu", *flags]) == 0
        doc = json.loads((out / "phase_results.json").read_text())
        return [m["prediction"]["rmse_rad"] / m["flat"]["rmse_rad"] for r in doc["per_image"] for m in r["models"].values()]

    want = ratios(root)
    assert "written as" not in capsys.readouterr().out
    for name, words in (("fppsim", "written as atan2(PSin, PCos) + 2 pi Order"),
                        ("negated", "with PSin negated")):
        assert ratios(tmp_path / name) == pytest.approx(want, rel=1e-9), name
        text = capsys.readouterr().out
        assert text.count(words) == len(truth), name
    forced = ratios(tmp_path / "fppsim", "--convention", "benchmark")
    assert forced != pytest.approx(want, rel=1e-3)
    # train --val-phase: the same reading, said once per folder, the same score
    scores = {}
    for name in ("phase", "fppsim"):
        folder = root if name == "phase" else tmp_path / name
        r = train_tiny(tmp_path / f"vp_{name}", "--real", tmp / "real", extra=["--val-phase", folder, "--seed", 5])
        text = capsys.readouterr().out
        assert ("--val-phase: " in text and "(--val-phase-convention fppsim)" in text) == (name == "fppsim"), text
        scores[name] = float(history(r)[0]["val_phase_ratio"])
    assert scores["fppsim"] == pytest.approx(scores["phase"], rel=1e-6)
    rc = main(["train", "--real", str(tmp / "real"), "--model", "unet", "--base-channels", "4", "--epochs", "1",
               "--out", str(tmp_path / "r"), "--no-progress", "--val-phase-convention", "fppsim"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "give --val-phase DIR" in err


def history(run):
    import csv

    with open(run / "history.csv") as fh:
        return list(csv.DictReader(fh))


def test_refine_adds_a_row_on_the_same_pixels(setup, tmp_path, capsys):
    """--refine phase scores the heights after the image's own phase beside the network's, on the same pixels; its
    flags without --refine are refused in one line (exit 2)."""
    from _helpers import tiny_rig

    tmp, run, root, truth = setup
    tiny_rig().save(tmp_path / "rig.json")
    out = tmp_path / "refined"
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "0",
                 "--names", "tiny", "--device", "cpu", "--refine", "phase", "--rig", str(tmp_path / "rig.json")]) == 0
    doc = json.loads((out / "phase_results.json").read_text())
    assert [m["name"] for m in doc["models"]] == ["tiny", "tiny +orders"]
    for rec in doc["per_image"]:
        net, ref = rec["models"]["tiny"], rec["models"]["tiny +orders"]
        assert ref["pixel_fraction"] == net["pixel_fraction"]
        assert ref["flat"]["rmse_rad"] == net["flat"]["rmse_rad"]
    # through a rig fitted with no plane in view there is no plane-pixel score (its "plane" would be the objects)
    from fppsim.geometry.rig import Rig

    Rig.from_dict({**tiny_rig().to_dict(), "plane_in_view": False}).save(tmp_path / "np.json")
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "np"), "--figures",
                 "0", "--device", "cpu", "--refine", "phase", "--rig", str(tmp_path / "np.json")]) == 0
    doc = json.loads((tmp_path / "np" / "phase_results.json").read_text())
    assert all(r["plane_pixel_fraction"] == 0 and r["models"]["unet +orders"]["plane"] is None
               for r in doc["per_image"]), doc["per_image"][0]
    # QA: the report says why its plane-pixel columns are empty (null in the JSON)
    assert "No plane in view: no plane-pixel score (0, 1, 2: the --rig records no reference plane" in (
        tmp_path / "np" / "phase_results.md").read_text()
    assert all(m["plane_ratio"] is None for m in doc["models"])
    assert not any(r["plane_in_view"] for r in doc["per_image"])
    capsys.readouterr()
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "x"),
                 "--rig", str(tmp_path / "rig.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--refine phase" in err[0]
    assert not (tmp_path / "x").exists()


def test_a_frame_with_no_plane_in_view_has_no_plane_pixel_score(setup, tmp_path, capsys):
    """Without --rig, a frame whose objects stand on black: the plane-pixel score fitted its 'plane' to pixels found on
    the object (FP672's figurine on black: 0.94 of flat), which the plane's share of the image cannot tell from a real
    plane (FP147's face on black 14 %, with its plane 19 %). A plane reaches beyond the view: the dome on black here
    leaves a 'plane' on the dome that reaches no side of the image, so the frame has no plane-pixel score (null in the
    JSON, a line in the report and on screen); the same dome on its plane keeps it."""
    tmp, run, _, _ = setup
    yy, xx = np.mgrid[0:120, 0:160]
    r2 = ((xx - 80) / 67.0) ** 2 + ((yy - 60) / 54.0) ** 2
    height = np.where(r2 < 1, 40.0 * np.sqrt(np.clip(1 - r2, 0, 1)), 0.0)  # 59 % of the view
    phase = 0.9 * xx + 0.05 * yy - 0.6 * height
    img = np.clip(120 + 90 * np.cos(phase), 1, 255).astype(np.uint8)
    on = height > 0
    root = tmp_path / "frames"
    save_psp_folder_sample(root, "plane", *sums_from_phase(phase, None, 30.0), img)
    save_psp_folder_sample(root, "black", *sums_from_phase(phase, on, 30.0), np.where(on, img, 0))
    out = tmp_path / "report"
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "0",
                 "--device", "cpu", "--degree", "2"]) == 0
    text = capsys.readouterr().out
    doc = json.loads((out / "phase_results.json").read_text())
    rec = {r["id"]: r for r in doc["per_image"]}
    assert rec["plane"]["plane_in_view"] and min(rec["plane"]["plane_sides"]) > 0.9
    assert rec["plane"]["models"]["unet"]["plane"] is not None
    assert not rec["black"]["plane_in_view"] and max(rec["black"]["plane_sides"]) < 0.1
    assert rec["black"]["models"]["unet"]["plane"] is None  # before: fitted on a 'plane' found on the dome
    plane_only = rec["plane"]["models"]["unet"]["plane"]
    assert doc["models"][0]["plane_ratio"] == pytest.approx(plane_only["prediction"]["rmse_rad"]
                                                            / plane_only["flat"]["rmse_rad"])
    line = [x for x in text.splitlines() if x.startswith("black: unet residual")]
    assert len(line) == 1 and "plane-pixel score: no plane in view" in line[0], text
    assert "No plane in view on 1 of the 2 frames" in (out / "phase_results.md").read_text()
    # the frame on black alone: no plane-pixel number at all, null in the JSON and '-' in the table
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "r2"), "--figures",
                 "0", "--device", "cpu", "--degree", "2", "--ids", "black"]) == 0
    text = capsys.readouterr().out
    doc = json.loads((tmp_path / "r2" / "phase_results.json").read_text())
    row = doc["models"][0]
    assert row["plane_ratio"] is None and row["plane_rmse_rad"] is None and row["plane_flat_rmse_rad"] is None
    assert "| - | - | - |" in text
    assert "No plane in view: no plane-pixel score (black: the 'plane' found reaches 0 of" in text


def test_val_phase_holds_out_every_second_frame_and_says_when_it_cannot(setup, tmp_path):
    """Issue 50: with several frames every second one is held out of the choice of best.pt; with one frame the
    run is told that best.pt is chosen on the frame it is scored on."""
    from uhrnet.scoring.phase_residual import PhaseValidation

    tmp, _, root, truth = setup
    pv = PhaseValidation([root], max_frames=8)
    assert [f["held_out"] for f in pv.frames] == [False, True, False] and not pv.notes
    phase, height, valid = truth["0"]
    one = tmp_path / "one"
    save_psp_folder_sample(one, "7", *sums_from_phase(phase, valid, 30.0), np.full(phase.shape, 120, np.uint8))
    pv = PhaseValidation([one], max_frames=8)
    assert [f["held_out"] for f in pv.frames] == [False]
    assert len(pv.notes) == 1 and "chosen on the frame it is scored on" in pv.notes[0]
    # QA: the same folder given twice (or a copy of it) held out the frame that chose best.pt
    import shutil

    shutil.copytree(one, tmp_path / "copy")
    for roots in ([one, one], [one, tmp_path / "copy"], [one, tmp_path / "one" / ".." / "one"]):
        pv = PhaseValidation(roots, max_frames=8)
        assert [f["held_out"] for f in pv.frames] == [False], roots
        assert "chosen on the frame it is scored on" in pv.notes[0]
    pv = PhaseValidation([root, tmp_path / "copy", root], max_frames=8)
    assert [f["held_out"] for f in pv.frames] == [False, True, False, True]
    assert not any("chosen on the frame" in n for n in pv.notes)


def test_a_users_report_a_black_frame_and_a_rig_of_another_size(setup, tmp_path, capsys):
    """evaluate-phase never replaces a file it did not write (it once overwrote a user's phase_results.md), and
    re-runs into its own report; a frame with nothing to fit (black) is skipped with a warning while the others
    are scored (a frame the reader cannot read stays an error); a rig of another camera size is refused in one line naming the frame and the rig."""
    import shutil

    from _helpers import tiny_rig

    tmp, run, root, truth = setup
    out = tmp_path / "mine"
    out.mkdir()
    (out / "phase_results.md").write_text("mine")
    args = [str(run), "--figures", "1", "--device", "cpu"]
    assert main(["evaluate-phase", *args, "--phase-root", str(root), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "phase_results.md exists and was not written by uhrnet evaluate-phase" in err[0]
    for bad, said in ((["--degree", "-1"], "--degree"), (["--limit", "0"], "--limit"), (["--figures", "-1"], "--figures"),
                      (["--names", "a", "b"], "--names")):  # option values wrong on their own: exit 2, nothing read
        assert main(["evaluate-phase", *args, "--phase-root", str(root), "--out", str(tmp_path / "u"), *bad]) == 2
        assert said in capsys.readouterr().err and not (tmp_path / "u").exists()
    assert (out / "phase_results.md").read_text() == "mine"
    both = tmp_path / "both"
    shutil.copytree(root, both)
    phase, height, valid = truth["0"]  # its phase, but a black image: no pixel is lit
    save_psp_folder_sample(both, "9", *sums_from_phase(phase, valid, 30.0), np.zeros((32, 64), np.uint8))
    # a lit frame whose every pixel carries the invalid marker (PSin = PCos = 0): nothing to fit either; it once
    # stopped the run after the frames before it were scored, with no report
    save_psp_folder_sample(both, "3", *sums_from_phase(phase, np.zeros_like(valid), 30.0),
                           np.full((32, 64), 120, np.uint8))
    report = tmp_path / "report"
    for _ in range(2):  # the second time into its own report
        assert main(["evaluate-phase", *args, "--phase-root", str(both), "--out", str(report)]) == 0
        printed = capsys.readouterr().out
        assert "9: warning:" in printed and "3: warning:" in printed and "no pixel has a phase" in printed
        doc = json.loads((report / "phase_results.json").read_text())
        assert [r["id"] for r in doc["per_image"]] == ["0", "1", "2"] and doc["skipped"] == ["3", "9"]
    # under --refine phase, a lit frame without readable fringes keeps the network's heights in the +orders row, and
    # the JSON says so
    save_psp_folder_sample(both, "8", *sums_from_phase(phase, valid, 30.0), np.full((32, 64), 128, np.uint8))
    tiny_rig().save(tmp_path / "rig.json")
    assert main(["evaluate-phase", *args, "--phase-root", str(both), "--out", str(tmp_path / "grey"), "--refine",
                 "phase", "--rig", str(tmp_path / "rig.json")]) == 0
    assert "8: warning: no fringe phase to refine with" in capsys.readouterr().out
    rec = {r["id"]: r for r in json.loads((tmp_path / "grey" / "phase_results.json").read_text())["per_image"]}
    assert list(rec["8"]["not_refined"]) == ["unet"] and "not_refined" not in rec["0"]
    assert rec["8"]["models"]["unet +orders"]["prediction"] == rec["8"]["models"]["unet"]["prediction"]
    tiny_rig(width=48).save(tmp_path / "rig48.json")
    assert main(["evaluate-phase", *args, "--phase-root", str(root), "--out", str(tmp_path / "r48"), "--refine",
                 "phase", "--rig", str(tmp_path / "rig48.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "0.mat: image is 64x32 but the rig used by --refine" in err[0] and "rig48.json" in err[0]
    # the failed run leaves no claim behind (nor the folder it made): a user's report put there later is refused
    assert not (tmp_path / "r48" / "phase_results.md").exists()
    (tmp_path / "r48").mkdir(exist_ok=True)
    (tmp_path / "r48" / "phase_results.md").write_text("mine")
    assert main(["evaluate-phase", *args, "--phase-root", str(root), "--out", str(tmp_path / "r48")]) == 1
    assert (tmp_path / "r48" / "phase_results.md").read_text() == "mine"


def test_refine_without_rig_names_the_rig_it_took_and_asks_for_rig(setup, tmp_path, capsys):
    """QA: --refine phase without --rig, from a run trained without one, took fppsim's default rig and refused the
    frames as '(the checkpoint or default rig)', neither saying which nor what to give; now it names the rig it
    took and asks for --rig, in one line."""
    _, run, root, _ = setup
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "ev"), "--refine",
                 "phase", "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "(fppsim's default rig) sees 640x352" in err[0] and "give --rig" in err[0], err
    # predict says it the same way
    assert main(["predict", str(run / "best.pt"), str(root), "--out", str(tmp_path / "pred"), "--refine", "phase",
                 "--device", "cpu", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "(fppsim's default rig) sees 640x352" in err[0] and "give --rig" in err[0], err


def test_refine_says_which_regions_it_could_not_decide(setup, tmp_path, capsys, monkeypatch):
    """QA: under --refine phase a frame whose path left regions undecided (their pixels keep the network's heights)
    was scored without a word, where predict warns; now a warning line per frame and model, and ``undecided`` in
    the frame's JSON record."""
    from _helpers import tiny_rig
    import uhrnet.scoring.phase_residual as pr

    tmp, run, root, truth = setup
    tiny_rig().save(tmp_path / "rig.json")
    real = pr.refine_with_phase

    def undecided_in_frame_1(height, fringe, rig, method, network_mm=None, name="image"):
        refined, stats = real(height, fringe, rig, method, network_mm=network_mm, name=name)
        if "/1.mat" in name:
            stats = {**stats, "undecided_regions": 2, "undecided_fraction": 0.25}
        return refined, stats

    monkeypatch.setattr(pr, "refine_with_phase", undecided_in_frame_1)
    out = tmp_path / "und"
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "0",
                 "--names", "tiny", "--device", "cpu", "--refine", "phase", "--rig", str(tmp_path / "rig.json")]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if "no fringe order the path can decide" in line]
    assert said == ["1: warning: tiny: 2 phase region(s), 25.0% of the pixels, have no fringe order the path can "
                    "decide: the network's heights stay there"]
    rec = {r["id"]: r for r in json.loads((out / "phase_results.json").read_text())["per_image"]}
    assert rec["1"]["undecided"] == {"tiny": {"regions": 2, "fraction": 0.25}} and "undecided" not in rec["0"]


def test_the_report_is_strict_json_with_null_where_a_number_cannot_be_computed(setup, tmp_path):
    """The flat baseline (h = 0) has no height term, so its mm equivalent (residual / |a|) is undefined, and a rig
    with no plane in view leaves every plane-pixel score unmeasured: null in phase_results.json, never the bare NaN
    Python writes, which a strict parser refuses (every report held NaN until the report became strict JSON)."""
    from _helpers import tiny_rig
    from fppsim.geometry.rig import Rig

    tmp, run, root, truth = setup
    Rig.from_dict({**tiny_rig().to_dict(), "plane_in_view": False}).save(tmp_path / "np.json")
    out = tmp_path / "np"
    assert main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "0",
                 "--device", "cpu", "--refine", "phase", "--rig", str(tmp_path / "np.json")]) == 0
    text = (out / "phase_results.json").read_text()
    doc = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    assert "NaN" not in text and "Infinity" not in text
    for rec in doc["per_image"]:
        for m in rec["models"].values():
            assert m["flat"]["a_rad_per_mm"] == 0 and m["flat"]["rmse_mm_equiv"] is None
            assert m["prediction"]["rmse_mm_equiv"] == pytest.approx(m["prediction"]["rmse_rad"]
                                                                     / abs(m["prediction"]["a_rad_per_mm"]))
            assert m["plane"] is None
    for row in doc["models"]:
        assert all(row[k] is None for k in ("plane_rmse_rad", "plane_flat_rmse_rad", "plane_ratio")), row
        assert row["ratio"] > 0 and row["rmse_rad"] > 0


def test_a_reference_whose_order_slipped_is_said_and_scored_without_it(setup, tmp_path, capsys):
    """A patch of the reference's temporal orders 3 periods off (its wrapped phase right): every score still counts
    it; evaluate-phase names it in one line and scores each model and flat again without those pixels."""
    tmp, run, root, truth = setup
    phase, height, valid = truth["0"]
    yy, xx = np.mgrid[:32, :64]
    plane = valid & (height == 0)
    cy, cx = next((y, x) for y in range(4, 28) for x in range(4, 60) if plane[y - 3:y + 4, x - 3:x + 4].all())
    blob = (yy - cy) ** 2 + (xx - cx) ** 2 <= 6
    psin, pcos, order = sums_from_phase(phase, valid, 30.0)
    slipped = tmp_path / "slipped"
    save_psp_folder_sample(slipped, "0", psin, pcos, order + 3 * blob.astype(np.int32),
                           _image(root, "0"))
    save_psp_folder_sample(slipped, "1", *sums_from_phase(*truth["1"][::2], 30.0), _image(root, "1"))
    out = tmp_path / "out"
    assert main(["evaluate-phase", str(run), "--phase-root", str(slipped), "--out", str(out), "--figures", "0",
                 "--names", "tiny", "--device", "cpu", "--degree", "2"]) == 0
    text = capsys.readouterr().out
    notes = [line for line in text.splitlines() if "note: the reference" in line]
    doc = json.loads((out / "phase_results.json").read_text())
    first, second = doc["per_image"]
    assert len(notes) == 1 and notes[0].startswith("0: note:") and "(-3)" in notes[0]
    assert first["reference_slips"]["patches"][0]["pixels"] == int(blob.sum())  # the scored ones counted in the line
    assert f"{first['reference_slips']['pixels']} px" in notes[0] and 0 < first["reference_slips"]["pixels"] <= blob.sum()
    assert first["reference_slips"]["patches"][0]["shift_periods"] == -3
    assert "reference_slips" not in second and "without_slips" not in second["models"]["tiny"]
    m = first["models"]["tiny"]
    # the pixels 3 periods off weigh on the score with them, not without them
    assert m["without_slips"]["flat"] < m["flat"]["rmse_rad"]
    assert m["without_slips"]["prediction"] < m["prediction"]["rmse_rad"]
    assert "| 0 | " in (out / "phase_results.md").read_text().split("Reference order slips")[1]


def test_a_slipped_patch_no_score_counts_is_not_listed(setup, tmp_path):
    """Two slipped patches, the image black on one of them (not scored): the record lists the scored one, with its
    scored pixels, and counts only those."""
    tmp, run, root, truth = setup
    phase, height, valid = truth["0"]
    yy, xx = np.mgrid[:32, :64]
    plane = valid & (height == 0)
    spots = [(y, x) for y in range(4, 28) for x in range(4, 60) if plane[y - 3:y + 4, x - 3:x + 4].all()]
    (ay, ax), (by, bx) = spots[0], next(p for p in spots if abs(p[0] - spots[0][0]) + abs(p[1] - spots[0][1]) > 12)
    seen, dark = ((yy - ay) ** 2 + (xx - ax) ** 2 <= 6), ((yy - by) ** 2 + (xx - bx) ** 2 <= 6)
    psin, pcos, order = sums_from_phase(phase, valid, 30.0)
    image = _image(root, "0").copy()
    image[dark] = 0
    folder = tmp_path / "slipped"
    save_psp_folder_sample(folder, "0", psin, pcos, order + 3 * (seen | dark).astype(np.int32), image)
    out = tmp_path / "out"
    assert main(["evaluate-phase", str(run), "--phase-root", str(folder), "--out", str(out), "--figures", "0",
                 "--names", "tiny", "--device", "cpu", "--degree", "2"]) == 0
    record = json.loads((out / "phase_results.json").read_text())["per_image"][0]["reference_slips"]
    assert len(record["patches"]) == 1 and record["patches"][0]["pixels"] == int(seen.sum())
    scored = (image > 0) & seen  # the fringe's own dark pixels are not scored either
    assert record["patches"][0]["scored_pixels"] == record["pixels"] == int(scored.sum()) > 0


def _image(root, sid):
    from fppsim.dataio.readers.psp_mat import load_ipattern
    return load_ipattern(root / "iPattern" / f"{sid}.mat")


def test_the_slip_line_names_a_model_whose_fit_without_the_slips_failed():
    """One model scored without the slipped pixels, another with too few left: the line names both."""
    from uhrnet.scoring.reference_slips import slip_line
    record = {"pixels": 2, "fraction": 0.4, "patches": [{"pixels": 2, "shift_periods": -3}]}
    models = {"a": {"without_slips": None}, "b": {"without_slips": {"prediction": 1.0, "flat": 2.0}}}
    line = slip_line("x", record, models)
    assert line.endswith("without them: a: too few pixels left to fit, b 1.000 rad (flat 2.000)")
    alone = slip_line("x", record, {"a": {"without_slips": None}})
    assert alone.endswith("without them: a: too few pixels left to fit")


def test_a_frame_of_another_size_under_refine_is_refused_before_anything_is_written(setup, tmp_path, capsys):
    """QA (stop 74): under --refine phase a folder whose third frame is another size than the rig's camera was
    scored frame by frame, so the first frames' figures were written before the one-line refusal, and no report.
    Every frame's size is now checked first: the refusal names the frame (and how many others), nothing is written."""
    import shutil

    from _helpers import tiny_rig

    tmp, run, root, truth = setup
    mixed = tmp_path / "mixed"
    shutil.copytree(root, mixed)
    phase, height, valid = truth["0"]
    save_psp_folder_sample(mixed, "7", *sums_from_phase(phase[:, :48], valid[:, :48], 30.0),
                           np.full((32, 48), 120, np.uint8))
    tiny_rig().save(tmp_path / "rig.json")
    out = tmp_path / "ev"
    assert main(["evaluate-phase", str(run), "--phase-root", str(mixed), "--out", str(out), "--refine", "phase",
                 "--rig", str(tmp_path / "rig.json"), "--figures", "8", "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "7.mat: image is 48x32 but the rig used by --refine" in err[0], err
    assert not out.exists() or not any(out.rglob("*.png")), sorted(out.rglob("*"))
