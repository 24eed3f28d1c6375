"""Input folders: an entry the readers skip that looks meant as input (a dangling symbolic link, an image in a format
the readers do not take) gets one warning line naming it, once, and the "nothing to read" errors name what was
skipped; unrelated files (README, .json, hidden ones) get no word."""

import os

import numpy as np
import pytest

from _helpers import scene, tiny_psp_root
from fppsim.dataio.encoding import encode_png
from fppsim.dataio.readers import load_fringe_images, open_labelled, open_source, skipped_note
from fppsim.errors import InputError, DatasetError, PSPMatError

OTHER = ("README", "notes.json", ".hidden.webp", "model.mat")  # never mentioned


def _folder(d, usable: bool):
    """``d`` with (when ``usable``) two PNG fringe images, a .webp, a .GIF, a link to a missing .png, a link to a
    missing text file and the unrelated files."""
    d.mkdir(parents=True)
    img = scene(np.random.default_rng(1), 32, 64)[0]
    if usable:
        (d / "a.png").write_bytes(encode_png(img))
        (d / "b.png").write_bytes(encode_png(img))
    (d / "c.webp").write_bytes(b"RIFF\x00\x00\x00\x00WEBPVP8 ")
    (d / "e.GIF").write_bytes(b"GIF89a")
    os.symlink(d.parent / "moved" / "d.png", d / "d.png")
    os.symlink(d.parent / "moved" / "notes.txt", d / "notes.txt")
    for name in OTHER:
        (d / name).write_text("x")
    assert not (d / "d.png").exists() and (d / "d.png").is_symlink()  # the truth: a dangling link
    return d


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning: ")]


def _assert_named_once(lines, d, expected):
    assert sorted(line.split(": ")[1] for line in lines) == sorted(str(d / n) for n in expected), lines
    assert not any(n in line for line in lines for n in OTHER + ("notes.txt", "a.png", "b.png"))


def test_fit_rigs_folder_warns_once_per_skipped_entry_and_names_them_when_nothing_is_left(tmp_path, capsys):
    d = _folder(tmp_path / "imgs", usable=True)
    images, layout = load_fringe_images(d)
    assert [im.name for im in images] == ["a", "b"]  # each image read: the folder listed again per image
    lines = _warnings(capsys.readouterr().err)
    _assert_named_once(lines, d, ["c.webp", "e.GIF", "d.png"])
    assert any("d.png: skipped: a symbolic link to" in line and "does not exist" in line for line in lines)
    assert any("c.webp: skipped: .webp is not a format read here (only .png" in line for line in lines)
    load_fringe_images(d)
    assert _warnings(capsys.readouterr().err) == []  # once per entry
    none = _folder(tmp_path / "none", usable=False)
    with pytest.raises(InputError) as e:
        load_fringe_images(none)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{none}: no fringe images")
    assert "skipped: c.webp (.webp is not a format read here), d.png (a symbolic link to" in msg and "e.GIF" in msg
    assert not any(n in msg.split("skipped:")[1] for n in OTHER + ("notes.txt",))
    assert _warnings(capsys.readouterr().err) == []  # the error says it, no warning besides


def test_predicts_folder_warns_and_its_no_images_error_says_what_was_skipped(tmp_path, capsys):
    from uhrnet.errors import ConfigError
    from uhrnet.inference.prediction import read_inputs

    d = _folder(tmp_path / "imgs", usable=True)
    assert [name for name, _ in read_inputs([d])] == ["a", "b"]
    _assert_named_once(_warnings(capsys.readouterr().err), d, ["c.webp", "e.GIF", "d.png"])
    none = _folder(tmp_path / "none", usable=False)
    with pytest.raises(ConfigError, match=r"no images \(.*\) in this folder; skipped: c\.webp \(\.webp is not a "
                                          r"format read here\), d\.png \(a symbolic link to .*\), e\.GIF"):
        read_inputs([none])
    empty = tmp_path / "empty"
    _folder(empty, usable=False)
    for p in empty.iterdir():
        if p.name not in OTHER:
            p.unlink()
    with pytest.raises(ConfigError) as e:  # only unrelated files: the error as before, nothing skipped to name
        read_inputs([empty])
    assert "skipped" not in str(e.value)



def test_a_phase_shifting_root_names_its_skipped_frames(tmp_path, capsys):
    """What evaluate-phase --phase-root and label-real list (Source.scan_ids): a frame moved away (its links left
    behind) and an iPattern saved as PNG are named, once per entry though the folder is listed again."""
    root = tiny_psp_root(tmp_path / "scans", 2)
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        os.symlink(tmp_path / "moved" / "7.mat", root / sub / "7.mat")
    (root / "iPattern" / "8.png").write_bytes(b"x")
    (root / "iPattern" / "README").write_text("x")
    assert open_source(root).scan_ids() == ["0", "1"]
    assert open_source(root).scan_ids() == ["0", "1"]
    lines = _warnings(capsys.readouterr().err)
    _assert_named_once(lines, root, ["PSin/7.mat", "PCos/7.mat", "Fringe/7.mat", "iPattern/7.mat", "iPattern/8.png"])
    assert any(line.endswith("8.png: skipped: .png is not a format read here (only .mat)") for line in lines)
    for p in (root / "iPattern").glob("[01].mat"):
        p.unlink()
    with pytest.raises(PSPMatError) as e:
        open_source(root).scan_ids()
    assert str(e.value) == (f"{root / 'iPattern'}: no .mat files; skipped: 7.mat (a symbolic link to "
                            f"{tmp_path / 'moved' / '7.mat'}, which does not exist), 8.png (.png is not a format "
                            "read here)")
    # ids that differ because one folder's frame is a dangling link: the error names the link too
    root2 = tiny_psp_root(tmp_path / "scans2", 2)
    (root2 / "Fringe" / "1.mat").unlink()
    os.symlink(tmp_path / "moved" / "1.mat", root2 / "Fringe" / "1.mat")
    with pytest.raises(PSPMatError, match=r"ids differ between folders: Fringe lacks 1; skipped: Fringe/1\.mat \(a "
                                          r"symbolic link to .*, which does not exist\)$"):
        open_source(root2).scan_ids()


def test_compare_reals_layouts_name_a_dangling_sample_or_pair_file(tmp_path, capsys):
    from _helpers import write_figshare, write_native

    nat = tmp_path / "nat"
    write_native(nat, n=3)
    (nat / "manifest.jsonl").unlink()
    (nat / "dataset.json").exists() or (nat / "dataset.json").write_text("{}")
    os.symlink(tmp_path / "moved", nat / "000009")  # a sample folder linked from where it no longer is
    assert open_labelled(nat).ids() == ["000000", "000001", "000002"]
    _assert_named_once(_warnings(capsys.readouterr().err), nat, ["000009"])
    pair = tmp_path / "pair"
    write_figshare(pair, n=2)
    (pair / "Z.npy").unlink()
    os.symlink(tmp_path / "moved.npy", pair / "Z.npy")
    with pytest.raises(DatasetError, match=r"no dataset found .*; skipped: Z\.npy \(a symbolic link to .*moved\.npy, "
                                           r"which does not exist\)$"):
        open_labelled(pair)
    assert skipped_note(tmp_path / "nowhere", (".png",)) == ""


def test_a_folder_is_looked_through_once_however_often_it_is_listed(tmp_path, monkeypatch, capsys):
    """fit-rig's folder is listed again for every image it reads (Folder.fringe_image): the look for skipped entries
    ran each time too, as long again as the listing itself (a 20,000-image folder: 8.1 s for 20 frames, not 3.9 s)."""
    from fppsim.dataio.readers import listing

    d = _folder(tmp_path / "imgs", usable=True)
    looks = []
    real = listing.skipped_entries
    monkeypatch.setattr(listing, "skipped_entries", lambda *a, **k: looks.append(a) or real(*a, **k))
    images, _ = load_fringe_images(d)
    load_fringe_images(d)
    assert [im.name for im in images] == ["a", "b"] and len(looks) == 1, looks
    _assert_named_once(_warnings(capsys.readouterr().err), d, ["c.webp", "e.GIF", "d.png"])


def test_a_folder_changed_since_is_looked_through_again_and_the_memory_can_be_cleared(tmp_path, capsys):
    """The once-per-process memory could not be reset, so a long-lived process (a notebook, a test session) that
    read a folder again after adding a stray .webp to it was never told. A changed folder (its mtime) is looked
    through again and says what is new, not what it said; forget_skipped() makes it say everything again."""
    from fppsim.dataio.readers.listing import forget_skipped

    d = _folder(tmp_path / "imgs", usable=True)
    load_fringe_images(d)
    _assert_named_once(_warnings(capsys.readouterr().err), d, ["c.webp", "e.GIF", "d.png"])
    load_fringe_images(d)
    assert _warnings(capsys.readouterr().err) == []
    (d / "f.heic").write_bytes(b"x")
    st = os.stat(d)
    os.utime(d, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a coarse clock could leave it unchanged
    load_fringe_images(d)
    _assert_named_once(_warnings(capsys.readouterr().err), d, ["f.heic"])
    forget_skipped()
    load_fringe_images(d)
    _assert_named_once(_warnings(capsys.readouterr().err), d, ["c.webp", "e.GIF", "d.png", "f.heic"])
    load_fringe_images(d)
    assert _warnings(capsys.readouterr().err) == []


def test_under_a_command_the_warning_begins_as_its_other_lines_do(tmp_path, capsys):
    """`fppsim fit-rig: warning: ...`, as the command's error line and the other commands' warnings (`uhrnet predict:
    warning: ...`) begin; a bare `warning:` from library code called outside a command line."""
    from fppsim.cli import main
    from fppsim.files import command_named, warn

    with command_named("uhrnet predict"):
        warn("x")
    warn("y")
    assert capsys.readouterr().err.splitlines() == ["uhrnet predict: warning: x", "warning: y"]
    d = _folder(tmp_path / "imgs", usable=True)
    main(["fit-rig", str(d), "--out", str(tmp_path / "rig.yaml")])  # the fit's own outcome does not matter here
    err = capsys.readouterr().err.splitlines()
    lines = [line for line in err if ": warning: " in line]
    assert sorted(lines) == sorted(f"fppsim fit-rig: warning: {d / n}: skipped: {r}" for n, r in [
        ("c.webp", ".webp is not a format read here (only .png, .tif, .tiff, .bmp, .jpg, .jpeg)"),
        ("e.GIF", ".GIF is not a format read here (only .png, .tif, .tiff, .bmp, .jpg, .jpeg)"),
        ("d.png", f"a symbolic link to {tmp_path / 'moved' / 'd.png'}, which does not exist")]), err
    assert not _warnings("\n".join(err))
