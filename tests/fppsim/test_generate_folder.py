"""`fppsim generate` / `merge` and the --out folder: never a file it did not write, nothing left by a failed run,
one format and one sample set per folder, the seed range, the help, the manifest's object count (QA, stop 67)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fppsim.cli import main
from fppsim.dataio.formats import manifest_record, read_manifest, reconcile
from fppsim.errors import SampleError, UsageError
from fppsim.owned import RECORD
from _helpers import one_line, unreadable

MESH = Path(__file__).resolve().parents[2] / "assets" / "meshes" / "bust_s0.ply"


def _gen(out, *extra, count=2):
    return main(["generate", "-q", "--meshes", str(MESH), "--out", str(out), "--count", str(count), "--no-psp", *extra])


def _tree(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes (folders as None)."""
    return {p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None) for p in folder.rglob("*")}


# ------------------------------------------------------------------------------------ 1: the user's files
@pytest.mark.parametrize("fmt, mine", [("figshare", "Z.npy"), ("figshare", "preview.png"), ("native", "manifest.jsonl"),
                                       ("figshare", "native/manifest.jsonl"), ("native", "preview.png")])
def test_a_file_generate_did_not_write_is_refused_before_anything_is_written(tmp_path, capsys, fmt, mine):
    out = tmp_path / "g"
    (out / mine).parent.mkdir(parents=True)
    (out / mine).write_text("mine\n")
    before = _tree(out)
    assert _gen(out, "--format", fmt) == 1
    one_line(capsys, f"{out / mine} exists and was not written by fppsim generate")
    assert _tree(out) == before  # not one byte written, not even the ownership record


def test_merge_refuses_a_file_it_did_not_write(tmp_path, capsys):
    shard = tmp_path / "s0"
    assert _gen(shard, "--format", "figshare", "--no-preview", count=1) == 0
    out = tmp_path / "m"
    out.mkdir()
    (out / "Z.npy").write_text("mine\n")
    assert main(["merge", str(out), str(shard)]) == 1
    one_line(capsys, f"{out / 'Z.npy'} exists and was not written by fppsim generate")
    assert (out / "Z.npy").read_text() == "mine\n" and not (out / "native").exists()


def test_its_own_folder_resumes_and_a_merged_one_too(tmp_path):
    out = tmp_path / "g"
    assert _gen(out, "--format", "figshare", count=1) == 0
    assert json.loads((out / RECORD).read_text())["files"] == {
        n: "fppsim generate" for n in ("Z.npy", "f1_80.npy", "native/dataset.json", "native/manifest.jsonl", "preview.png")}
    assert _gen(out, "--format", "figshare", count=2) == 0
    assert np.load(out / "Z.npy").shape[0] == 2 and len(read_manifest(out / "native")) == 2
    merged = tmp_path / "m"
    assert main(["merge", str(merged), str(out)]) == 0
    assert _gen(merged, "--format", "figshare", "--no-preview", count=2) == 0  # merge claims what generate claims


def _users_frames(out: Path, what: str) -> str:
    """``out`` holding the user's own fringe frames (``what``), with a README beside them; the words the refusal
    names them by."""
    out.mkdir(parents=True)
    (out / "README.txt").write_text("my frames\n")
    if what == "images":
        for name in ("frame0.png", "frame1.png", "frame2.TIF"):
            (out / name).write_bytes(b"frame")
        return "3 fringe image(s) (frame0.png, frame1.png, frame2.TIF)"
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        (out / ("scan" if what == "nested" else "") / sub).mkdir(parents=True)
        (out / ("scan" if what == "nested" else "") / sub / "1.mat").write_bytes(b"mat")
    return "1 scan folder(s) one level down (scan/)" if what == "nested" else "a scan in the public layout"


@pytest.mark.parametrize("fmt", ["native", "figshare"])
@pytest.mark.parametrize("what", ["images", "scan", "nested"])
def test_a_folder_of_the_users_frames_is_refused_before_anything_is_written(tmp_path, capsys, fmt, what):
    """QA: `generate --out DIR` beside the user's own frames (plain images, or a scan in the public layout) wrote its
    dataset among them; `fit-rig DIR` then read generate's samples instead of the frames. Refused up front."""
    out = tmp_path / "frames"
    found = _users_frames(out, what)
    before = _tree(out)
    assert _gen(out, "--format", fmt) == 1
    one_line(capsys, f"--out {out} already holds {found}", "that fppsim generate did not write: choose another folder")
    assert _tree(out) == before  # not one byte written, not even the ownership record


def test_a_readme_is_no_frame_and_its_own_preview_is_no_users_image(tmp_path, capsys):
    """Files that are no frames (a README, a .json) stay as they were and generate writes beside them, as before;
    generate's own preview.png, recorded or from before the record, never blocks a re-run, with --no-preview too."""
    out = tmp_path / "g"
    out.mkdir()
    (out / "README.txt").write_text("notes\n")
    (out / "notes.json").write_text("{}")
    assert _gen(out, count=1) == 0
    assert (out / "README.txt").read_text() == "notes\n" and (out / "preview.png").is_file()
    assert _gen(out, "--no-preview", count=2) == 0 and len(read_manifest(out)) == 2
    _as_before_the_record(out)
    assert _gen(out, "--no-preview", count=2) == 0  # the legacy preview is recognised by its form
    (out / "mine.png").write_bytes(b"frame")
    assert _gen(out, count=2) == 1
    one_line(capsys, f"--out {out} already holds 1 fringe image(s) (mine.png)")


def test_a_folder_it_cannot_look_into_is_no_frames(tmp_path, capsys, monkeypatch):
    """Review: `generate --out DIR` beside a folder it may not look into (`lost+found` on a disk's root) was refused
    with `DIR/lost+found/arrays.npz: Permission denied` by the look for the user's frames; it was written before.
    Such a folder holds no frame a reader could take: the dataset is written, and merge's OUT is taken too; a scan
    beside it is still refused."""
    out = tmp_path / "disk"
    (out / "lost+found").mkdir(parents=True)
    unreadable(monkeypatch, out / "lost+found")
    assert _gen(out, "--no-preview", count=1) == 0 and len(read_manifest(out)) == 1
    merged = tmp_path / "disk2"
    (merged / "lost+found").mkdir(parents=True)
    unreadable(monkeypatch, merged / "lost+found")
    assert main(["merge", str(merged), str(out)]) == 0 and len(read_manifest(merged)) == 1
    capsys.readouterr()
    scans = tmp_path / "scans"
    _users_frames(scans, "nested")
    (scans / "lost+found").mkdir()
    unreadable(monkeypatch, scans / "lost+found")
    assert _gen(scans, count=1) == 1
    one_line(capsys, f"--out {scans} already holds 1 scan folder(s) one level down (scan/)")


def _as_before_the_record(out: Path, sub: str = "") -> None:
    """What fppsim wrote before the ownership record: no record, manifest lines without ``pedestals``."""
    (out / RECORD).unlink()
    recs = [{k: v for k, v in r.items() if k != "pedestals"} for r in read_manifest(out / sub)]
    (out / sub / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))


@pytest.mark.parametrize("fmt", ["native", "figshare"])
def test_a_dataset_written_before_the_record_is_adopted(tmp_path, fmt):
    out, sub = tmp_path / "g", ("native" if fmt == "figshare" else "")
    assert _gen(out, "--format", fmt, count=1) == 0
    _as_before_the_record(out, sub)
    assert _gen(out, "--format", fmt, count=2) == 0
    assert [r["id"] for r in read_manifest(out / sub)] == ["000000", "000001"]
    assert all("pedestals" in r for r in read_manifest(out / sub))  # old records rebuilt, not mixed
    assert "preview.png" in json.loads((out / RECORD).read_text())["files"]


def test_a_refused_resume_writes_not_even_the_record(tmp_path, capsys):
    """Review: a dataset from before the record, resumed with another seed, was refused after its files were
    claimed, leaving a new ownership record behind; the same for merge."""
    out = tmp_path / "g"
    assert _gen(out, count=1) == 0
    _as_before_the_record(out)
    before = _tree(out)
    assert _gen(out, "--seed", "5", count=2) == 1
    one_line(capsys, "holds a dataset made with different seed")
    assert _tree(out) == before
    other = tmp_path / "o"
    assert _gen(other, "--seed", "5", count=1) == 0
    assert main(["merge", str(out), str(other)]) == 1
    one_line(capsys, "cannot merge these shards into it")
    assert _tree(out) == before


def test_a_legacy_folder_adopts_only_what_it_can_show_is_fppsims(tmp_path, capsys):
    import cv2

    out = tmp_path / "g"
    assert _gen(out, "--no-preview", count=1) == 0
    _as_before_the_record(out)
    cv2.imwrite(str(out / "preview.png"), np.zeros((10, 10), np.uint8))  # a PNG, but not a preview of generate's
    before = (out / "preview.png").read_bytes()
    assert _gen(out, count=1) == 1
    one_line(capsys, f"{out / 'preview.png'} exists and was not written by fppsim generate")
    assert (out / "preview.png").read_bytes() == before


# ------------------------------------------------------------------------------------ 2: failed runs
def test_a_run_that_fails_up_front_leaves_nothing(tmp_path, capsys):
    assert main(["generate", "--meshes", str(tmp_path / "nonexistent"), "--out", str(tmp_path / "e"), "--count", "2"]) == 1
    one_line(capsys, "not found")
    (tmp_path / "empty").mkdir()
    assert main(["generate", "--meshes", str(tmp_path / "empty"), "--out", str(tmp_path / "e"), "--count", "2"]) == 1
    one_line(capsys, "no usable mesh")
    assert not (tmp_path / "e").exists()
    out = tmp_path / "gst"
    (out / "000001").mkdir(parents=True)
    assert _gen(out) == 1
    one_line(capsys, "000001 exists but is not a finished fppsim sample")
    assert sorted(p.name for p in out.iterdir()) == ["000001"]


def test_a_run_without_a_single_sample_leaves_nothing(tmp_path, capsys, monkeypatch):
    import fppsim.generation as generation

    def fail(index, *a, **k):
        raise SampleError(f"sample {index}: nothing in view")

    monkeypatch.setattr(generation, "synthesize", fail)
    out = tmp_path / "g"
    assert _gen(out, "--format", "figshare") == 1
    one_line(capsys, "nothing could be generated")
    assert not out.exists()
    out.mkdir()
    assert _gen(out) == 1
    capsys.readouterr()
    assert list(out.iterdir()) == []


def test_settings_beside_no_sample_do_not_block_the_corrected_run(tmp_path):
    out = tmp_path / "g"
    assert _gen(out, "--seed", "5", count=1) == 0
    shutil.rmtree(out / "000000")  # as an earlier version's failed run left it: settings, no sample
    assert _gen(out, "--seed", "6", count=1) == 0
    assert json.loads((out / "dataset.json").read_text())["seed"] == 6


# ------------------------------------------------------------------------------------ 3: one dataset per folder
def test_switching_format_is_refused(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _gen(a, "--no-preview", count=1) == 0
    before = _tree(a)
    assert _gen(a, "--format", "figshare", count=1) == 1
    one_line(capsys, "generated with --format native", str(a / "dataset.json"))
    assert _tree(a) == before
    assert _gen(b, "--format", "figshare", "--no-preview", count=1) == 0
    before = _tree(b)
    assert _gen(b, count=1) == 1
    one_line(capsys, "generated with --format figshare", str(b / "native" / "dataset.json"))
    assert _tree(b) == before


def test_a_smaller_count_on_a_figshare_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "f"
    assert _gen(out, "--format", "figshare", "--no-preview", count=2) == 0
    before = _tree(out)
    assert _gen(out, "--format", "figshare", "--no-preview", count=1) == 1
    one_line(capsys, "holds 2 samples", "--count 2 or more")
    assert _tree(out) == before  # Z.npy and native/ still hold the same 2 samples
    # a native folder holds its samples and nothing else to disagree with them: a smaller --count reads it
    n = tmp_path / "n"
    assert _gen(n, "--no-preview", count=2) == 0
    assert _gen(n, "--no-preview", count=1) == 0 and len(read_manifest(n)) == 2


# ------------------------------------------------------------------------------------ 4: the seed
def test_a_negative_seed_is_a_usage_error_before_anything_is_written(tmp_path, capsys):
    for cmd in (["generate", "--meshes", str(MESH), "--count", "2"], ["validate-psp", "--meshes", str(MESH), "--count", "1"]):
        with pytest.raises(SystemExit) as e:
            main([*cmd, "--out", str(tmp_path / "gs"), "--seed", "-1"])
        assert e.value.code == 2
        assert "--seed: expected an integer >= 0, got -1" in capsys.readouterr().err
    assert not (tmp_path / "gs").exists()
    from fppsim.generation import GenerateConfig, generate_dataset

    with pytest.raises(UsageError, match="--seed must be an integer >= 0"):
        GenerateConfig(meshes=[str(MESH)], out=tmp_path / "gs", count=1, seed=-1)
    with pytest.raises(ValueError, match="--seed must be an integer >= 0"):
        generate_dataset([str(MESH)], tmp_path / "gs", 1, seed=-1)
    assert not (tmp_path / "gs").exists()
    # numpy's SeedSequence takes any integer >= 0, however large
    assert GenerateConfig(meshes=[str(MESH)], out=tmp_path / "gs", count=1, seed=10 ** 20).seed == 10 ** 20


# ------------------------------------------------------------------------------------ 5: help
def test_help_states_the_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "pixel centres; default 1)" in text and "(default -100, the reference code's)" in text


# ------------------------------------------------------------------------------------ 6: the manifest's counts
def test_manifest_counts_objects_and_pedestals_apart(tmp_path):
    meta = {"index": 0, "seed": 0, "stats": {"valid_fraction": 0.5},
            "objects": [{"mesh": "a.ply"}, {"mesh": "pedestal:1"}, {"mesh": "procedural:bust:3"}]}
    rec = manifest_record("000000", meta)
    assert (rec["objects"], rec["pedestals"]) == (2, 1)
    # a manifest written before the split is rebuilt from meta.json, never left mixed
    (tmp_path / "000000").mkdir()
    (tmp_path / "000000" / "meta.json").write_text(json.dumps(meta))
    (tmp_path / "manifest.jsonl").write_text(json.dumps({"id": "000000", "index": 0, "seed": 0, "objects": 3}) + "\n")
    assert [(r["objects"], r["pedestals"]) for r in reconcile(tmp_path)] == [(2, 1)]


def test_generated_manifest_objects_follow_objects_flag(tmp_path):
    out = tmp_path / "g"
    assert _gen(out, "--objects", "2", "--pedestal", "1", "--no-preview", count=1) == 0
    rec = read_manifest(out)[0]
    meta = json.loads((out / "000000" / "meta.json").read_text())
    assert rec["objects"] == 2 and rec["objects"] + rec["pedestals"] == len(meta["objects"])


def test_merge_refuses_a_shard_as_out_and_a_damaged_sample(tmp_path, capsys):
    """QA L5: `merge S0 S0 S1` turned the shard into the merged set; a sample without arrays.npz was merged."""
    s0, s1 = tmp_path / "s0", tmp_path / "s1"
    assert _gen(s0, "--shard", "0/2", "--no-preview") == 0 and _gen(s1, "--shard", "1/2", "--no-preview") == 0
    before = _tree(s0)
    assert main(["merge", str(s0), str(s0), str(s1)]) == 2
    one_line(capsys, f"OUT {s0} is the shard {s0}")
    assert _tree(s0) == before
    (s1 / "000001" / "arrays.npz").unlink()
    out = tmp_path / "m"
    assert main(["merge", str(out), str(s0), str(s1)]) == 1
    one_line(capsys, "000001: damaged sample (no arrays.npz)")
    assert not out.exists()
