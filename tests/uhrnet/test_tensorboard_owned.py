"""Issue 36.5: train/adapt --tensorboard remove only the event files they recorded as their own.

A fresh run (or ``--overwrite``) used to delete every ``events.out.tfevents.*`` in ``RUN/tensorboard/``,
a person's or another tool's too, and ``--overwrite`` without ``--tensorboard`` left the replaced run's
curves beside the new history. Now each writer's event file goes into the run's ownership record
(``.fppsim-owned.json``) and only recorded files are removed; a foreign event file is refused in one
line before anything is written, other files there are left alone (uhrnet.training.tb_log).
"""

import json
from pathlib import Path

import pytest

from uhrnet.cli import main

from _helpers import adapt_setup, write_figshare

pytest.importorskip("tensorboard", reason="tensorboard (the optional extra) not installed")

pytestmark = pytest.mark.usefixtures("one_thread")

FOREIGN = "events.out.tfevents.1700000000.elsewhere.1.0"  # another writer's curves
FOREIGN_BYTES = b"not ours"


@pytest.fixture(scope="module")
def figshare(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tbown") / "real"
    write_figshare(folder, n=8, h=32, w=64, seed=1)
    return folder


def _train(run, data, *extra):
    return main(["train", "--real", str(data), "--model", "unet", "--base-channels", "4", "--batch-size", "2",
                 "--epochs", "1", "--lr", "1e-3", "--out", str(run), "--no-progress", *extra])


def _events(run: Path) -> set[str]:
    return {p.name for p in (run / "tensorboard").glob("*tfevents*")}


def _recorded(run: Path, tool: str) -> set[str]:
    files = json.loads((run / ".fppsim-owned.json").read_text())["files"]
    return {n.split("/", 1)[1] for n, t in files.items() if n.startswith("tensorboard/") and t == tool}


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_error(capsys, *parts):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for part in parts:
        assert part in err[0], err[0]


def _foreign(run: Path, name: str = FOREIGN) -> Path:
    (run / "tensorboard").mkdir(parents=True, exist_ok=True)
    path = run / "tensorboard" / name
    path.write_bytes(FOREIGN_BYTES)
    return path


def test_train_fresh_run_refuses_a_foreign_event_file_and_writes_nothing(figshare, tmp_path, capsys):
    run = tmp_path / "run"
    path = _foreign(run)
    (run / "tensorboard" / "notes.txt").write_text("mine")
    before = _snapshot(run)
    assert _train(run, figshare, "--tensorboard") == 1
    _one_error(capsys, str(path), "not written by uhrnet train")
    assert _snapshot(run) == before and not (run / ".fppsim-owned.json").exists()  # nothing written


@pytest.mark.slow
def test_train_overwrite_removes_only_its_own_event_files(figshare, tmp_path, capsys):
    run = tmp_path / "run"
    assert _train(run, figshare, "--tensorboard") == 0
    first = _events(run)
    assert len(first) == 1 and _recorded(run, "uhrnet train") == first  # recorded as its own
    (run / "tensorboard" / "notes.txt").write_text("mine")  # not an event file: never in the way
    (run / "tensorboard" / "other").mkdir()  # TensorBoard shows a subfolder as a run of its own
    (run / "tensorboard" / "other" / FOREIGN).write_bytes(FOREIGN_BYTES)
    assert _train(run, figshare, "--tensorboard", "--overwrite") == 0
    second = _events(run)
    assert len(second) == 1 and second != first  # the replaced run's curves went, only its own
    assert _recorded(run, "uhrnet train") == second
    assert (run / "tensorboard" / "notes.txt").read_text() == "mine"
    assert (run / "tensorboard" / "other" / FOREIGN).read_bytes() == FOREIGN_BYTES
    # a foreign event file beside them: --overwrite is refused, the run as it was
    path = _foreign(run)
    before = _snapshot(run)
    capsys.readouterr()
    assert _train(run, figshare, "--tensorboard", "--overwrite") == 1
    _one_error(capsys, str(path), "not written by uhrnet train")
    assert _snapshot(run) == before


@pytest.mark.slow
def test_train_overwrite_without_tensorboard_removes_the_replaced_runs_curves(figshare, tmp_path):
    run = tmp_path / "run"
    assert _train(run, figshare, "--tensorboard") == 0
    assert len(_events(run)) == 1
    path = _foreign(run)  # not ours: stays (nothing is written there without --tensorboard)
    assert _train(run, figshare, "--overwrite") == 0
    assert _events(run) == {FOREIGN} and path.read_bytes() == FOREIGN_BYTES
    assert _recorded(run, "uhrnet train") == set()


@pytest.mark.slow
def test_train_resume_touches_no_foreign_event_file(figshare, tmp_path):
    run = tmp_path / "run"
    assert _train(run, figshare, "--tensorboard") == 0
    first = _events(run)
    path = _foreign(run)
    assert main(["train", "--real", str(figshare), "--model", "unet", "--base-channels", "4", "--batch-size", "2",
                 "--epochs", "2", "--lr", "1e-3", "--out", str(run), "--no-progress", "--tensorboard",
                 "--resume"]) == 0
    events = _events(run)
    assert first < events and len(events) == 3 and path.read_bytes() == FOREIGN_BYTES
    assert _recorded(run, "uhrnet train") == events - {FOREIGN}  # the resumed session's file is its own too


@pytest.mark.slow
def test_adapt_tensorboard_follows_the_same_rules(tmp_path, capsys):
    source, _, real = adapt_setup(tmp_path)
    out = tmp_path / "ad"
    cmd = ["adapt", str(source), "--images", str(real), "--out", str(out), "--rig", str(tmp_path / "rig.json"),
           "--no-figures", "--no-progress", "--epochs", "1"]
    # a fresh adaptation into a folder holding someone's event file: refused, nothing written
    path = _foreign(out)
    before = _snapshot(out)
    capsys.readouterr()
    assert main(cmd + ["--tensorboard"]) == 1
    _one_error(capsys, str(path), "not written by uhrnet adapt")
    assert _snapshot(out) == before
    path.unlink()
    # its own event files are recorded and replaced by --overwrite; other files stay
    assert main(cmd + ["--tensorboard"]) == 0
    first = _events(out)
    assert len(first) == 1 and _recorded(out, "uhrnet adapt") == first
    (out / "tensorboard" / "notes.txt").write_text("mine")
    assert main(cmd + ["--tensorboard", "--overwrite"]) == 0
    second = _events(out)
    assert len(second) == 1 and second != first and _recorded(out, "uhrnet adapt") == second
    assert (out / "tensorboard" / "notes.txt").read_text() == "mine"
    # --overwrite without --tensorboard: the replaced adaptation's curves go, a foreign event file stays
    path = _foreign(out)
    assert main(cmd + ["--overwrite"]) == 0
    assert _events(out) == {FOREIGN} and path.read_bytes() == FOREIGN_BYTES
    assert _recorded(out, "uhrnet adapt") == set()
