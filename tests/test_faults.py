"""Issue 9 fault injection: nothing already written is lost, nothing half-written is left behind.

Faults: foreign files in the output folder (item 1), disk full (a real tmpfs when this user may mount
one, else a patched writer; item 4), kill -9 at seeded random points of `generate` and `train`
followed by a re-run that must give exactly the uninterrupted result, two runs on one --out, and
SIGTERM/SIGINT with worker processes (item 9).
"""

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from fppsim.files import FolderBusy, clean_stale_tmp, folder_lock, tmp_path as own_tmp
from fppsim.cli import main as fppsim_main
from fppsim.dataio.formats import DatasetError, LabelTransform, read_manifest, reconcile
from fppsim.dataio.writers import export_figshare

from _helpers import write_figshare

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYOPENGL_PLATFORM": "osmesa", "OMP_NUM_THREADS": "1",
       "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    d = tmp_path_factory.mktemp("fault_meshes")
    trimesh.creation.capsule(height=60.0, radius=18.0, count=[16, 16]).export(d / "capsule.ply")
    return d


def dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` -> its bytes (what must survive)."""
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def gen_args(meshes, out, count, *extra):
    return ["generate", "-q", "--no-preview", "--meshes", str(meshes), "--out", str(out), "--count", str(count),
            "--seed", "5", "--no-psp", *map(str, extra)]


def same_bytes(a: Path, b: Path, ids):
    for sid in ids:
        for name in ("fringe.png", "arrays.npz", "meta.json"):
            assert (a / sid / name).read_bytes() == (b / sid / name).read_bytes(), (sid, name)


# ------------------------------------------------------------------------------------------- item 1
def test_foreign_files_are_never_deleted_nor_counted(tmp_path, meshes, capsys):
    o = tmp_path / "o"
    (o / "000001").mkdir(parents=True)
    (o / ".tmp").mkdir()
    (o / "000001" / "meta.json").write_text('{"a": 1}')
    (o / "000001" / "data.txt").write_text("x")
    (o / ".tmp" / "notes.txt").write_text("mine")
    (o / ".cache.tmp").write_text("someone else's")
    stale = own_tmp(o / "000000", pid=dead_pid())  # ours, from a killed run: may go
    stale.mkdir()
    (stale / "fringe.png").write_bytes(b"half")
    before = {k: v for k, v in snapshot(o).items() if not str(k).startswith(".fppsim-tmp-")}
    assert fppsim_main(gen_args(meshes, o, 2)) == 1
    err = capsys.readouterr().err
    assert "000001 exists but is not a finished fppsim sample" in err and len(err.strip().splitlines()) == 1
    after = snapshot(o)
    for k, v in before.items():
        assert after[k] == v, k  # every foreign file kept, byte for byte
    assert not stale.exists()
    # a stray 000000 without meta.json is not counted as written, and kept
    o2 = tmp_path / "o2"
    (o2 / "000000").mkdir(parents=True)
    (o2 / "000000" / "x.bin").write_bytes(b"1")
    assert fppsim_main(gen_args(meshes, o2, 1)) == 1
    assert "000000 exists" in capsys.readouterr().err
    assert (o2 / "000000" / "x.bin").read_bytes() == b"1"
    assert read_manifest(o2, strict=False) == []


def test_reconcile_and_cleanup_touch_only_our_dead_temp_files(tmp_path):
    root = tmp_path / "ds"
    root.mkdir()
    live = own_tmp(root / "000003", pid=os.getppid())  # a live process's temp folder: in use, kept
    dead = own_tmp(root / "000004", pid=dead_pid())
    legacy = root / f".f1_80.npy.{dead_pid()}.tmp"  # the old naming, also ours
    for p in (live, dead):
        p.mkdir()
    legacy.write_bytes(b"x")
    foreign = [root / ".tmp", root / ".x.tmp", root / "notes", root / "000009"]
    foreign[0].mkdir(), foreign[1].write_text("f"), foreign[2].write_text("n"), foreign[3].mkdir()
    (foreign[3] / "meta.json").write_text("not json")
    assert reconcile(root) == []
    assert live.exists() and not dead.exists() and not legacy.exists()
    assert all(p.exists() for p in foreign)
    assert clean_stale_tmp(root) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="zombie state is read from /proc")
def test_a_zombie_writer_counts_as_dead(tmp_path):
    """A worker orphaned by kill -9 stays a zombie until PID 1 reaps it (seconds in containers); kill(0)
    still succeeds on it, yet its temporary folders are stale and a re-run must remove them."""
    from fppsim.files import pid_alive

    p = subprocess.Popen(["sleep", "30"])
    try:
        assert pid_alive(p.pid)
        p.kill()
        deadline = time.time() + 10
        while time.time() < deadline and b") Z" not in Path(f"/proc/{p.pid}/stat").read_bytes():
            time.sleep(0.01)  # not waited for: a zombie
        os.kill(p.pid, 0)  # what the old check relied on: succeeds on a zombie
        assert not pid_alive(p.pid)
        stale = own_tmp(tmp_path / "000003").parent / f".fppsim-tmp-{p.pid}-000003"
        stale.mkdir()
        assert clean_stale_tmp(tmp_path) == [stale] and not stale.exists()
    finally:
        p.wait()
    assert not pid_alive(p.pid)


def test_folder_lock_refuses_a_second_holder(tmp_path):
    with folder_lock(tmp_path):
        with pytest.raises(FolderBusy, match="in use by another"):
            with folder_lock(tmp_path):
                pass
    with folder_lock(tmp_path):  # released on exit
        pass


# ------------------------------------------------------------------------------------------- item 4
@pytest.fixture(scope="module")
def native_ds(tmp_path_factory, meshes):
    out = tmp_path_factory.mktemp("native") / "ds"
    assert fppsim_main(gen_args(meshes, out, 2)) == 0
    return out


def test_disk_full_in_figshare_export_patched_writer(tmp_path, native_ds, monkeypatch):
    import fppsim.dataio.writers as ds

    out = tmp_path / "fig"
    out.mkdir()
    (out / "f1_80.npy").write_bytes(b"an earlier export")
    calls = {"n": 0}
    real = ds.write_fully

    def full_after_one(fh, data):
        calls["n"] += 1
        if calls["n"] > 2:  # the first sample of each array fits, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fh, data)

    monkeypatch.setattr(ds, "write_fully", full_after_one)
    with pytest.raises(DatasetError, match="No space left on device"):
        export_figshare(native_ds, out, LabelTransform())
    assert sorted(p.name for p in out.iterdir()) == ["f1_80.npy"]  # no temp files, no half arrays
    assert (out / "f1_80.npy").read_bytes() == b"an earlier export"


def _mount_tmpfs(where: Path, size: str) -> bool:
    if os.geteuid() != 0:
        return False
    where.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                          capture_output=True).returncode == 0


def test_disk_full_on_a_real_small_filesystem(tmp_path, native_ds):
    """A 1 MiB tmpfs: the 2 x 1.8 MB figshare arrays do not fit. The CLI must give one line, not SIGBUS."""
    small = tmp_path / "small"
    if not _mount_tmpfs(small, "1m"):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        script = ("import sys; from fppsim.dataio.formats import LabelTransform; from fppsim.dataio.writers import export_figshare\n"
                  "try:\n    export_figshare(sys.argv[1], sys.argv[2], LabelTransform())\n"
                  "except Exception as e:\n    print(type(e).__name__, e, file=sys.stderr); sys.exit(1)\n")
        res = subprocess.run([sys.executable, "-c", script, str(native_ds), str(small)], env=ENV,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 1, (res.returncode, res.stderr)  # not -7 (SIGBUS)
        assert "DatasetError" in res.stderr and "No space left on device" in res.stderr
        assert list(small.iterdir()) == []  # the temp files are gone: the space is free again
    finally:
        subprocess.run(["umount", str(small)], check=False)


def test_disk_full_during_training_keeps_the_last_checkpoint(tmp_path, monkeypatch, capsys):
    import uhrnet.checkpoint as cp
    from uhrnet.cli import main as uhrnet_main

    write_figshare(tmp_path / "real", n=8, h=32, w=64)
    base = ["train", "--real", str(tmp_path / "real"), "--model", "unet", "--base-channels", "4", "--loss", "l2",
            "--no-progress", "--out", str(tmp_path / "run")]
    assert uhrnet_main(base + ["--epochs", "1"]) == 0
    before = snapshot(tmp_path / "run")
    capsys.readouterr()
    real_save = torch.save

    def full_disk(obj, f):
        real_save(obj, f)  # the bytes go to the temp file ...
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # ... and the flush finds the disk full

    monkeypatch.setattr(cp.torch, "save", full_disk)
    assert uhrnet_main(base + ["--epochs", "2", "--resume"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0], err
    monkeypatch.undo()
    run = tmp_path / "run"
    assert not list(run.glob(".fppsim-tmp-*")) and not list(run.glob(".*.tmp*"))
    assert cp.load_checkpoint(run / "last.pt")["epoch"] == 1
    for name in ("last.pt", "best.pt"):
        assert (run / name).read_bytes() == before[Path(name)]


# ------------------------------------------------------------------------------------------- kill -9
def _count_samples(out: Path) -> int:
    return sum(1 for p in out.glob("0*") if (p / "meta.json").is_file()) if out.exists() else 0


@pytest.mark.slow
def test_kill9_generate_at_random_points_then_rerun_is_exact(tmp_path, meshes):
    rng = np.random.default_rng(9)
    count = 5
    ref = tmp_path / "ref"
    assert fppsim_main(gen_args(meshes, ref, count)) == 0
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "fppsim.cli", *gen_args(meshes, out, count, "--workers", "2")]
    kills = 0
    for _ in range(3):
        have = _count_samples(out)
        target = have + int(rng.integers(1, 3))  # kill after 1-2 more samples, plus a random delay
        extra = float(rng.uniform(0.0, 0.4))
        proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        deadline = time.time() + 180
        while proc.poll() is None and _count_samples(out) < target and time.time() < deadline:
            time.sleep(0.02)
        time.sleep(extra)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            kills += 1
        proc.wait()
        before = {p.name: snapshot(p) for p in out.glob("0*") if (p / "meta.json").is_file()}
        if len(before) == count:
            break
    assert kills >= 1, "every run finished before it could be killed"
    res = subprocess.run(cmd, env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    for sid, files in before.items():  # nothing already finished is lost or rewritten by the re-run
        assert snapshot(out / sid) == files, sid  # finished samples untouched by the re-run
    ids = [f"{i:06d}" for i in range(count)]
    assert [r["id"] for r in read_manifest(out)] == ids
    same_bytes(out, ref, ids)  # byte-identical to the uninterrupted run (arrays.npz included)
    assert not list(out.glob(".fppsim-tmp-*"))


@pytest.mark.slow
def test_kill9_during_figshare_export_then_rerun_is_exact(tmp_path, meshes):
    ref = tmp_path / "ref"
    assert fppsim_main(gen_args(meshes, ref, 2, "--format", "figshare")) == 0
    out = tmp_path / "out"
    assert fppsim_main(gen_args(meshes, out, 2, "--format", "figshare")) == 0
    for name in ("f1_80.npy", "Z.npy"):
        (out / name).unlink()
    # an export that writes slowly, killed while its temp files exist
    script = ("import sys, time\nimport fppsim.dataio.writers as d\nfrom fppsim.dataio.formats import LabelTransform\n"
              "real = d.write_fully\ndef slow(fh, b):\n    real(fh, b); fh.flush(); time.sleep(0.3)\n"
              "d.write_fully = slow\nd.export_figshare(sys.argv[1] + '/native', sys.argv[1], LabelTransform())\n")
    proc = subprocess.Popen([sys.executable, "-c", script, str(out)], env=ENV)
    deadline = time.time() + 120
    while not list(out.glob(".fppsim-tmp-*-Z.npy")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert list(out.glob(".fppsim-tmp-*")), "the export finished before it could be killed"
    assert not (out / "f1_80.npy").exists()  # nothing half-written under the final name
    assert fppsim_main(gen_args(meshes, out, 2, "--format", "figshare")) == 0  # the re-run cleans and completes
    assert not list(out.glob(".fppsim-tmp-*"))
    for name in ("f1_80.npy", "Z.npy"):
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name


def _history_rows(run):
    import csv

    with open(run / "history.csv") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r.pop("seconds")
    return rows


@pytest.mark.slow
def test_kill9_train_at_random_points_then_resume_is_exact(tmp_path):
    write_figshare(tmp_path / "real", n=8, h=32, w=64, seed=3)
    epochs = 4

    def cmd(out, *extra):
        return [sys.executable, "-m", "uhrnet", "train", "--real", str(tmp_path / "real"), "--model", "unet",
                "--base-channels", "4", "--loss", "l2", "--lr", "1e-3", "--batch-size", "2", "--epochs", str(epochs),
                "--seed", "2", "--no-progress", "--device", "cpu", "--out", str(out), *extra]

    ref, out = tmp_path / "ref", tmp_path / "killed"
    res = subprocess.run(cmd(ref), env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    rng = np.random.default_rng(4)
    kills = 0
    for _ in range(2):  # the second round only runs when the first process was not killed in time
        done = len(_history_rows(out)) if (out / "history.csv").exists() else 0
        target, extra = done + int(rng.integers(1, 3)), float(rng.uniform(0.0, 0.5))
        proc = subprocess.Popen(cmd(out, "--resume"), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 180
        while proc.poll() is None and time.time() < deadline and (
                not (out / "history.csv").exists() or len(_history_rows(out)) < target):
            time.sleep(0.02)
        time.sleep(extra)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            kills += 1
        proc.wait()
        if kills:
            break
    assert kills >= 1
    res = subprocess.run(cmd(out, "--resume"), env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    from uhrnet.checkpoint import load_checkpoint

    a, b = load_checkpoint(ref / "last.pt"), load_checkpoint(out / "last.pt")
    assert a["epoch"] == b["epoch"] == epochs
    for k, v in a["state_dict"].items():
        assert torch.equal(v, b["state_dict"][k]), k
    assert _history_rows(ref) == _history_rows(out)
    assert not list(out.glob(".fppsim-tmp-*"))


# ------------------------------------------------------------------------------------------- item 9
@pytest.mark.slow
def test_two_generate_runs_on_one_out(tmp_path, meshes):
    out, ref = tmp_path / "out", tmp_path / "ref"
    cmd = [sys.executable, "-m", "fppsim.cli", *gen_args(meshes, out, 3)]
    first = subprocess.Popen(cmd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / "dataset.json").exists() and first.poll() is None and time.time() < deadline:
        time.sleep(0.02)  # dataset.json is written while the lock is held
    second = subprocess.run(cmd, env=ENV, capture_output=True, text=True, timeout=300)
    _, err1 = first.communicate(timeout=300)
    assert first.returncode == 0, err1[-2000:]
    if second.returncode != 0:  # it overlapped: refused with one line, nothing of the first run destroyed
        assert second.returncode == 1
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "in use by another fppsim generate run" in lines[0], second.stderr
    assert fppsim_main(gen_args(meshes, ref, 3)) == 0
    ids = [f"{i:06d}" for i in range(3)]
    assert [r["id"] for r in read_manifest(out)] == ids
    same_bytes(out, ref, ids)


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signals_stop_generate_workers_cleanly(tmp_path, meshes, signum):
    if not Path("/proc/self/stat").exists():
        pytest.skip("needs /proc to find worker processes")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "fppsim.cli", *gen_args(meshes, out, 40, "--workers", "2")]
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 180
    while _count_samples(out) < 1 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    workers = _children(proc.pid)
    assert proc.poll() is None and workers, "generate ended before the signal"
    proc.send_signal(signum)  # to the parent only, as Slurm's scancel/timeout does
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, (proc.returncode, err[-2000:])
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "re-run the same command to resume" in lines[0], err[-2000:]
    assert "Traceback" not in err and "BrokenPipeError" not in err
    deadline = time.time() + 10
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.time() < deadline:
        time.sleep(0.05)
    alive = [w for w in workers if Path(f"/proc/{w}").exists()
             and "Z" not in Path(f"/proc/{w}/stat").read_text().rsplit(")", 1)[1].split()[0]]
    assert not alive, f"orphaned workers {alive}"
    finished = {r["id"] for r in reconcile(out)}
    assert finished and not list(out.glob(".fppsim-tmp-*"))
