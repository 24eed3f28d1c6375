"""Issue 47 (QA: nothing lost, nothing silent): every output path checked up front by one helper
(fppsim.files.check_outputs), the study record a typed object (pipelines/scaling.py --merge), reading
conventions measured wherever phase-shifting files are read, options a mode does not use refused, resource
options bounded by the machine."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from fppsim.cli import main as fppsim_main
from _helpers import one_line, write_figshare


@pytest.fixture
def frames(tmp_path):
    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=1)
    return tmp_path / "real"


# ------------------------------------------------------------------------------------- item 2 and 8: outputs
@pytest.mark.parametrize("cmd", ["fit-rig", "fit-optics"])
def test_an_output_that_is_another_output_or_an_input_is_refused_before_any_work(cmd, frames, tmp_path, capsys):
    out = "o.yaml" if cmd == "fit-optics" else "r.json"
    same = tmp_path / "same.json"
    if cmd == "fit-optics":
        assert fppsim_main([cmd, str(frames), "--out", str(tmp_path / out), "--json", str(tmp_path / out)]) == 2
        one_line(capsys, "--json", "must end in .json")
    else:
        assert fppsim_main([cmd, str(frames), "--out", str(same), "--json", str(same)]) == 2
        one_line(capsys, f"--json {same}", "is also --out")
    assert not same.exists() and not (tmp_path / out).exists()
    # a file of the input folder, even with --force and the right extension
    theirs = frames / out
    theirs.write_text("the user's")
    assert fppsim_main([cmd, str(frames), "--out", str(theirs), "--force"]) == 2
    one_line(capsys, "is a file of the input folder")
    assert theirs.read_text() == "the user's"
    # an extension that does not fit what is written
    bad = tmp_path / "rig.mat"
    assert fppsim_main([cmd, str(frames), "--out", str(bad)]) == 2
    one_line(capsys, f"--out {bad}", "must end in")
    assert not bad.exists()


def test_fit_optics_refuses_its_rig_as_output(frames, tmp_path, capsys):
    rig = tmp_path / "rig.yaml"
    rig.write_text("not read\n")
    assert fppsim_main(["fit-optics", str(frames), "--rig", str(rig), "--out", str(rig), "--force"]) == 2
    one_line(capsys, "is an input of this command")
    assert rig.read_text() == "not read\n"


@pytest.mark.parametrize("cmd", ["fit-rig", "fit-optics"])
def test_an_unwritable_output_folder_is_refused_before_any_work(cmd, frames, tmp_path, capsys, monkeypatch):
    """Root ignores permissions: the file system's refusal is simulated on the probe the check writes."""
    import fppsim.files as files

    ro = tmp_path / "ro"
    ro.mkdir()
    real_tmp = files.tmp_path

    def tmp(final, pid=None):
        if Path(final).parent == ro:
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_tmp(final, pid)
    monkeypatch.setattr(files, "tmp_path", tmp)
    out = tmp_path / ("o.yaml" if cmd == "fit-optics" else "r.json")
    assert fppsim_main([cmd, str(frames), "--out", str(out), "--json", str(ro / "report.json")]) == 1
    one_line(capsys, f"--json {ro / 'report.json'}", "cannot write in")
    assert not out.exists()


def test_compare_real_json_is_checked_up_front(frames, tmp_path, capsys):
    mine = tmp_path / "notes.json"
    mine.write_text("mine")
    assert fppsim_main(["compare-real", str(frames), str(frames), "--json", str(mine)]) == 1
    one_line(capsys, f"--json {mine}", "exists; pass --force")
    assert fppsim_main(["compare-real", str(frames), str(frames), "--json", str(frames / "Z.npy"), "--force"]) == 2
    one_line(capsys, "must end in .json")
    assert mine.read_text() == "mine"


# ------------------------------------------------------------------------------------- item 1: the study record
ARMS = """
arms:
  - name: n400
    series: [samples]
    count: 400
"""


def _record(count=400, epochs=10, lr=5e-4, seeds=((0, 5.0), (1, 6.0)), device="cuda", name="n400"):
    return {"arms": [{"name": name, "resize": None, "device": device, "count": count, "epochs": epochs, "lr": lr,
                      "steps": 1600, "generate": [], "train": [],
                      "seeds": [{"seed": s, "pair_object_rmse_mm": v} for s, v in seeds]}]}


@pytest.fixture
def study(tmp_path):
    import json

    from _helpers import load_pipeline

    scaling = load_pipeline("scaling")
    (tmp_path / "arms.yaml").write_text(ARMS)
    ledger = tmp_path / "study.json"
    ledger.write_text(json.dumps(_record()))

    def merge(*paths):
        return scaling.main(["--arms-file", str(tmp_path / "arms.yaml"), "--ledger", str(ledger), "--merge",
                             *map(str, paths)])
    return tmp_path, ledger, merge


def test_merge_refuses_an_arm_of_another_definition_under_the_same_name(study, capsys):
    import json

    tmp_path, ledger, merge = study
    other = tmp_path / "other.json"
    other.write_text(json.dumps(_record(count=50, epochs=2, lr=1e-2, seeds=((2, 40.0),))))
    before = ledger.read_text()
    assert merge(other) == 2
    one_line(capsys, "n400 [cuda]", "count 50 vs 400", "epochs 2 vs 10", "lr 0.01 vs 0.0005")
    assert ledger.read_text() == before and not (tmp_path / "study_table.md").exists()


def test_merge_refuses_non_finite_numbers_and_names_the_merge_input(study, capsys):
    tmp_path, ledger, merge = study
    before = ledger.read_text()
    nan = tmp_path / "nan.json"
    nan.write_text('{"arms": [{"name": "elsewhere", "seeds": [{"seed": 0, "pair_object_rmse_mm": NaN}]}]}')
    assert merge(nan) == 2
    one_line(capsys, f"--merge {nan}", "non-finite")
    cut = tmp_path / "cut.json"
    cut.write_text(before[: len(before) // 2])
    assert merge(cut) == 2
    err = one_line(capsys, f"--merge {cut}", "not a readable scaling.json")
    assert "--ledger" not in err
    foreign = tmp_path / "foreign.json"
    foreign.write_text('{"mine": 1}')
    assert merge(foreign) == 2
    err = one_line(capsys, f"--merge {foreign}", "not a scaling study record")
    assert "name another --ledger" not in err
    assert ledger.read_text() == before


def test_merge_counts_what_it_added_and_keeps_figures_it_did_not_write(study, capsys):
    import json

    tmp_path, ledger, merge = study
    new = tmp_path / "new.json"
    new.write_text(json.dumps(_record(seeds=((2, 7.0),))))
    assert merge(new, new) == 0
    out = capsys.readouterr().out
    assert "1 seed result(s) merged (1 new, 0 replacing" in out and "1 already recorded" in out, out
    assert [s["seed"] for s in json.loads(ledger.read_text())["arms"][0]["seeds"]] == [0, 1, 2]
    assert merge(new) == 0
    assert "0 seed result(s) merged" in capsys.readouterr().out
    # a user's figure beside another ledger is never replaced
    other = tmp_path / "mine"
    other.mkdir()
    (other / "study.json").write_text(json.dumps(_record()))
    (other / "study_samples.png").write_bytes(b"the user's figure")
    from _helpers import load_pipeline

    scaling = load_pipeline("scaling")
    assert scaling.main(["--arms-file", str(tmp_path / "arms.yaml"), "--ledger", str(other / "study.json"),
                         "--merge", str(new)]) == 2
    one_line(capsys, "study_samples.png", "not written by pipelines/scaling.py")
    assert (other / "study_samples.png").read_bytes() == b"the user's figure"
    assert json.loads((other / "study.json").read_text()) == _record()


# ------------------------------------------------------------------------------------- items 3 and 9: readings
def _scan_folder(root):
    import numpy as np

    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
    from fppsim.fitting.height_sensitivity import surface_phase
    from _helpers import rig_fringe, tiny_rig

    rig = tiny_rig()
    yy, xx = np.mgrid[0:32, 0:64].astype(float)
    h = 6.0 * np.exp(-((xx - 25.0) ** 2 + (yy - 15.0) ** 2) / 98.0)
    save_psp_folder_sample(root, "1201", *sums_from_phase(surface_phase(rig, h) + 72.0), rig_fringe(rig, h))
    return rig


@pytest.mark.parametrize("convention,negate", [("fppsim", False), ("benchmark", True), ("auto", True)])
def test_a_reading_that_does_not_fit_the_files_is_said_whether_given_or_detected(tmp_path, convention, negate):
    """The files are written the public way; a reading given another way (or --negate-sin with auto, which
    auto no longer overrides: docs/own_rig.md section 4) is kept but measured and named in one line."""
    from fppsim.dataio.readers import load_psp_folder_sample, reading_note

    _scan_folder(tmp_path / "F")
    s = load_psp_folder_sample(tmp_path / "F", "1201", convention=convention, negate_sin=negate)
    assert s.meta["negate_sin"] is negate and s.meta["jump_share"] > 0.05
    note = reading_note(s.meta)
    assert note and "1201" in note and "the phase read is WRONG" in note and "--convention benchmark" in note
    fine = load_psp_folder_sample(tmp_path / "F", "1201", convention="benchmark")
    assert fine.meta["jump_share"] < 0.01 and reading_note(fine.meta) is None


def test_label_real_counts_a_misread_scan_as_not_fitting(tmp_path, capsys):
    import json

    rig = _scan_folder(tmp_path / "F")
    rig.save(tmp_path / "rig.json")
    args = ["label-real", str(tmp_path / "F"), "--rig", str(tmp_path / "rig.json"), "--convention", "fppsim", "--out",
            str(tmp_path / "lab"), "--quiet", "--no-preview"]
    assert fppsim_main(args) == 1  # labels it knows are wrong: refused, nothing written (QA M4)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "1201" in err[0] and "convention" in err[0] and "--keep-unfit" in err[0]
    assert not (tmp_path / "lab" / "Z.npy").exists()
    assert fppsim_main(args + ["--keep-unfit"]) == 0
    assert "the phase read is WRONG" in capsys.readouterr().err
    report = json.loads((tmp_path / "lab" / "label_real.json").read_text())
    assert report["summary"]["scans_not_fitting"] == 1


@pytest.mark.parametrize("cmd", ["fit-rig", "fit-optics", "label-real"])
def test_an_incomplete_scan_folder_is_named_not_read_as_plain_images(tmp_path, cmd, capsys):
    import shutil

    _scan_folder(tmp_path / "F")
    shutil.rmtree(tmp_path / "F" / "PCos")
    out = tmp_path / ("o.yaml" if cmd == "fit-optics" else "lab" if cmd == "label-real" else "r.json")
    assert fppsim_main([cmd, str(tmp_path / "F"), "--out", str(out)]) == 1
    one_line(capsys, "PCos")
    assert not out.exists()


# ------------------------------------------------------------------------------------- item 5: resources
def test_threads_and_workers_beyond_the_cores_are_refused(tmp_path, capsys, monkeypatch):
    import fppsim.threads as threads
    from uhrnet.cli import main as uhrnet_main

    monkeypatch.setattr(threads, "machine_cores", lambda: 2)
    write_figshare(tmp_path / "real", n=4, h=32, w=64, seed=1)
    assert uhrnet_main(["train", "--real", str(tmp_path / "real"), "--out", str(tmp_path / "run"), "--model", "unet",
                        "--base-channels", "4", "--device", "cpu", "--threads", "1000"]) == 2
    one_line(capsys, "--threads 1000", "2 CPU core(s)")
    assert not (tmp_path / "run").exists()
    assert fppsim_main(["generate", "--count", "2", "--meshes", "assets/meshes", "--workers", "64",
                        "--out", str(tmp_path / "g")]) == 2
    one_line(capsys, "--workers 64", "2 CPU core(s)")
    assert not (tmp_path / "g").exists()


# ------------------------------------------------------------------------------------- item 4: scaling_job.sh
def test_scaling_job_refuses_an_unknown_arm_before_creating_anything_and_fails_non_zero(tmp_path):
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PY": sys.executable, "WORKTREE": str(tmp_path / "wt")}
    r = subprocess.run(["bash", str(root / "pipelines" / "scaling_job.sh"), "nosucharm:0"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "nosucharm" in r.stderr and not (tmp_path / "wt").exists(), r.stderr
    # a seed that fails: exit 1, and the line names the log that exists
    fake = tmp_path / "py"
    fake.write_text(f'#!/bin/sh\ncase "$*" in *--list*) exec {sys.executable} "$@";; esac\necho boom; exit 1\n')
    fake.chmod(0o755)
    (tmp_path / "wt").mkdir()
    r = subprocess.run(["bash", str(root / "pipelines" / "scaling_job.sh"), "n100:0"],
                       env={**env, "PY": str(fake)}, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, (r.stdout, r.stderr)
    log = tmp_path / "wt" / "runs" / "scaling" / "job.log"
    assert "n100 seed 0 failed" in r.stdout and str(log) in r.stdout and "boom" in log.read_text()


# ------------------------------------------------------------------------------------- item 7: unused options
@pytest.mark.parametrize("extra", [["--params", "yaw"], ["--col-bands", "6"], ["--sensitivity", "off"],
                                   ["--params", "yaw,roll,periods,distance"]])
def test_fit_rig_without_base_refuses_label_fit_options_it_would_not_use(tmp_path, extra, capsys):
    _scan_folder(tmp_path / "F")
    out = tmp_path / "r.json"
    assert fppsim_main(["fit-rig", str(tmp_path / "F"), "--out", str(out), *extra]) == 2
    one_line(capsys, extra[0], "needs height labels")
    assert not out.exists() and capsys.readouterr().out == ""


# ------------------------------------------------------------------------------------- item 6: fitted periods
@pytest.mark.parametrize("periods,ladder,ok", [(13.9999999999, "1,4,14", True), (12.37, "1,4,12.37", True),
                                               (12.37, "1,8,80", False)])
def test_generate_makes_psp_data_for_a_rig_with_fitted_periods(tmp_path, capsys, periods, ladder, ok):
    from fppsim.dataio.readers import read_native_psp
    from fppsim.fitting.fit_periods import adjust_rig
    from _helpers import tiny_rig

    rig = adjust_rig(tiny_rig(), periods=periods)
    rig.save(tmp_path / "rig.json")
    root = Path(__file__).resolve().parents[1]
    argv = ["generate", "-q", "--no-preview", "--meshes", str(root / "assets" / "meshes"), "--count", "1",
            "--rig", str(tmp_path / "rig.json"), "--psp-freqs", ladder, "--out", str(tmp_path / "g")]
    if not ok:
        assert fppsim_main(argv) != 0
        one_line(capsys, "12.37", "got 80", "--psp-freqs 1,")
        return
    assert fppsim_main(argv) == 0, capsys.readouterr().err
    sample = next(p for p in (tmp_path / "g").iterdir() if p.is_dir() and p.name.isdigit())
    _, stacks, _, meta = read_native_psp(sample)
    assert len(stacks) == 3 and max(stacks) == pytest.approx(periods)
