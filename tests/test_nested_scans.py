"""A folder whose sub-folders are each one scan, given where one scan folder is needed (`fit-rig`, `fit-optics`,
`label-real`, `evaluate-phase --phase-root`, `train --val-phase`): refused in one line that names the scan folders
one level down (QA: it said "no fringe images" / "missing folder(s) PSin, ..." without a word of them). Never read
as if they were one scan: each command reads one scan folder at a time."""

import shutil

import pytest

from _helpers import SHARED, one_line, tiny_psp_root, unreadable, write_figshare
from fppsim.dataio.readers import load_fringe_images, open_source
from fppsim.errors import InputError, PSPMatError

FP1523 = SHARED / "real-phase" / "FP1523"



def _root(tmp_path):
    root = tmp_path / "scans"
    for name in ("b", "a"):
        tiny_psp_root(root / name)
    (root / "README.txt").write_text("two sessions\n")
    return root


def _clause(root) -> str:
    return f"; it holds 2 scan folder(s) one level down (a/, b/): give one of them, e.g. {root / 'a'}"


def _tree(folder):
    return {p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None) for p in folder.rglob("*")}


def test_the_clause_has_one_owner_and_says_nothing_without_scan_folders(tmp_path):
    from fppsim.dataio.readers import scan_folders_note

    root = _root(tmp_path)
    assert scan_folders_note(root, open_source(root).scan_folders()) == _clause(root)
    assert open_source(root).scan_folders(phase_shifting=True) == ["a", "b"]
    assert scan_folders_note(root, []) == ""
    # review: generate's refusal of such a folder named them in words of its own; now in the clause's words
    from fppsim.dataio.dataset_folder import check_no_frames
    from fppsim.dataio.readers import scan_folders_words
    from fppsim.errors import GenerateError
    with pytest.raises(GenerateError) as e:
        check_no_frames(root, [])
    assert scan_folders_words(["a", "b"]) == "2 scan folder(s) one level down (a/, b/)"
    assert f"already holds {scan_folders_words(['a', 'b'])} that" in str(e.value)
    many = [f"s{k}" for k in range(6)]
    assert scan_folders_note(root, many).startswith(
        "; it holds 6 scan folder(s) one level down (s0/, s1/, s2/, s3/, ...): give one of them, e.g. ")


def test_the_readers_name_the_scan_folders_one_level_down(tmp_path):
    root = _root(tmp_path)
    with pytest.raises(InputError) as e:  # fit-rig, fit-optics
        load_fringe_images(root)
    assert str(e.value).startswith(f"{root}: no fringe images (") and str(e.value).endswith(_clause(root))
    with pytest.raises(PSPMatError) as e:  # evaluate-phase --phase-root, train --val-phase
        open_source(root).scan_ids()
    assert str(e.value).startswith(f"{root}: missing folder(s) PSin, PCos, Fringe, iPattern (found: a, b)")
    assert str(e.value).endswith(_clause(root)) and "\n" not in str(e.value)
    # one scan folder, or a folder with no scan folders in it: the errors as before
    assert open_source(root / "a").scan_ids() == ["0"]
    shutil.rmtree(root / "a"), shutil.rmtree(root / "b")
    with pytest.raises(PSPMatError) as e:
        open_source(root).scan_ids()
    assert "one level down" not in str(e.value)


def _error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_every_command_that_needs_one_scan_folder_names_them(tmp_path, capsys):
    from fppsim.cli import main as fppsim_main
    from uhrnet.cli import main as uhrnet_main

    root = _root(tmp_path)
    before = _tree(root)
    out = tmp_path / "out"
    out.mkdir()
    for cmd in (["fit-rig", root, "--out", out / "rig.json"],
                ["fit-rig", root, "--out", out / "rig.json", "--base", "default"],
                ["fit-optics", root, "--out", out / "optics.yaml"],
                ["label-real", root, "--out", out / "labels", "-q"]):
        assert fppsim_main(list(map(str, cmd))) == 1
        line = _error_line(capsys)
        assert line.startswith(f"fppsim {cmd[0]}: error: {root}: ") and line.endswith(_clause(root)), line
    # (the folder is listed before any checkpoint is loaded: none is needed to reach the error)
    assert uhrnet_main(["evaluate-phase", str(tmp_path / "none.pt"), "--phase-root", str(root),
                        "--out", str(out / "ev")]) == 1
    line = _error_line(capsys)
    assert line.startswith(f"uhrnet evaluate-phase: error: {root}: missing folder(s)") and line.endswith(_clause(root))
    data = tmp_path / "data"
    write_figshare(data, n=6)
    rc = uhrnet_main(["train", "--real", str(data), "--val-phase", str(root), "--epochs", "1", "--base-channels", "4",
                      "--model", "unet", "--out", str(out / "run"), "--no-progress"])
    assert rc == 1
    line = _error_line(capsys)
    assert line.startswith(f"uhrnet train: error: --val-phase: {root}: missing folder(s)")
    assert line.endswith(_clause(root))
    assert _tree(root) == before  # nothing written there, nothing read as one scan


def test_a_folder_it_may_not_look_into_beside_them(tmp_path, capsys, monkeypatch):
    """Review: a folder it may not look into beside the scan folders (`lost+found`) turned every command's error into
    `ROOT/lost+found/arrays.npz: Permission denied`; it holds no scan anyone could read: the scan folders are named."""
    from fppsim.cli import main

    root = _root(tmp_path)
    (root / "lost+found").mkdir()
    unreadable(monkeypatch, root / "lost+found")
    assert main(["fit-rig", str(root), "--out", str(tmp_path / "rig.json")]) == 1
    one_line(capsys, f"{root}: no fringe images (", _clause(root))
    with pytest.raises(PSPMatError, match="one level down"):
        open_source(root).scan_ids()


def test_hundreds_of_sub_folders_keep_the_line_short(tmp_path):
    """Review: `evaluate-phase --phase-root ROOT` (and `--val-phase`) listed every sub-folder of ROOT in its error's
    "found:" (300 scan folders: a line of 3,000 characters)."""
    root = tmp_path / "many"
    tiny_psp_root(root / "s000")
    for k in range(1, 300):
        (root / f"s{k:03d}").symlink_to(root / "s000")
    with pytest.raises(PSPMatError) as e:
        open_source(root).scan_ids()
    assert "(found: s000, s001, s002, s003, s004, s005, s006, s007, ... (300 in all))" in str(e.value)
    assert str(e.value).endswith(f"300 scan folder(s) one level down (s000/, s001/, s002/, s003/, ...): give one of "
                                 f"them, e.g. {root / 's000'}") and len(str(e.value).replace(str(root), "R")) < 300


@pytest.mark.skipif(not FP1523.is_dir(), reason="needs ../shared/real-phase/FP1523")
def test_the_public_scan_copied_twice_into_one_folder(tmp_path, capsys):
    from fppsim.cli import main

    root = tmp_path / "sessions"
    for name in ("a", "b"):
        shutil.copytree(FP1523, root / name)
    assert main(["fit-rig", str(root), "--out", str(tmp_path / "rig.json")]) == 1
    assert _error_line(capsys).endswith(_clause(root))
    assert main(["label-real", str(root), "--out", str(tmp_path / "labels"), "-q"]) == 1
    assert _error_line(capsys).endswith(_clause(root))
