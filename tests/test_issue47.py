"""Issue 47 (QA: nothing lost, nothing silent): every output path checked up front by one helper
(fppsim.files.check_outputs), the study record a typed object (pipelines/scaling.py --merge), reading
conventions measured wherever phase-shifting files are read, options a mode does not use refused, resource
options bounded by the machine."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from fppsim.cli import main as fppsim_main
from _helpers import write_figshare


def _one_line(capsys, *parts):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for p in parts:
        assert p in err, err
    return err


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
        _one_line(capsys, "--json", "must end in .json")
    else:
        assert fppsim_main([cmd, str(frames), "--out", str(same), "--json", str(same)]) == 2
        _one_line(capsys, f"--json {same}", "is also --out")
    assert not same.exists() and not (tmp_path / out).exists()
    # a file of the input folder, even with --force and the right extension
    theirs = frames / out
    theirs.write_text("the user's")
    assert fppsim_main([cmd, str(frames), "--out", str(theirs), "--force"]) == 2
    _one_line(capsys, "is a file of the input folder")
    assert theirs.read_text() == "the user's"
    # an extension that does not fit what is written
    bad = tmp_path / "rig.mat"
    assert fppsim_main([cmd, str(frames), "--out", str(bad)]) == 2
    _one_line(capsys, f"--out {bad}", "must end in")
    assert not bad.exists()


def test_fit_optics_refuses_its_rig_as_output(frames, tmp_path, capsys):
    rig = tmp_path / "rig.yaml"
    rig.write_text("not read\n")
    assert fppsim_main(["fit-optics", str(frames), "--rig", str(rig), "--out", str(rig), "--force"]) == 2
    _one_line(capsys, "is an input of this command")
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
    _one_line(capsys, f"--json {ro / 'report.json'}", "cannot write in")
    assert not out.exists()


def test_compare_real_json_is_checked_up_front(frames, tmp_path, capsys):
    mine = tmp_path / "notes.json"
    mine.write_text("mine")
    assert fppsim_main(["compare-real", str(frames), str(frames), "--json", str(mine)]) == 1
    _one_line(capsys, f"--json {mine}", "exists; pass --force")
    assert fppsim_main(["compare-real", str(frames), str(frames), "--json", str(frames / "Z.npy"), "--force"]) == 2
    _one_line(capsys, "must end in .json")
    assert mine.read_text() == "mine"
