"""pipelines/gpu_check.sh's helpers: which carried wheels install here, and the report built from the steps'
outputs. (The whole script's offline CPU dry run takes minutes: docs/USAGE.md "GPU, offline".)"""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "pipelines"))
import gpu_check  # noqa: E402


def test_wheels_picks_this_interpreters_build_and_the_pure_ones(tmp_path):
    here = f"cp{sys.version_info[0]}{sys.version_info[1]}"
    other = "cp39" if here != "cp39" else "cp310"
    names = [f"zlib_ng-1.1.0-{here}-{here}-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
             f"zlib_ng-1.1.0-{other}-{other}-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
             "trimesh-5.2.0-py3-none-any.whl", "pyglet-2.1.19-py3-none-any.whl",
             "foreign-1.0-py3-none-win_amd64.whl"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    got = sorted(Path(p).name for p in gpu_check.wheels(tmp_path))
    if sys.platform == "linux" and os.uname().machine == "x86_64":
        assert got == sorted([names[0], names[2], names[3]])  # one zlib-ng, no foreign build
    else:
        assert names[1] not in got and "foreign-1.0-py3-none-win_amd64.whl" not in got


def _write(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_report_collects_the_steps(tmp_path):
    out = tmp_path
    _write(out / "step_env.json", {"device": "NVIDIA X", "torch": "2.11", "cuda": "13.0", "python": "3.12.3",
                                   "cpu_cores": 16, "gl_platform": "egl", "budget_s": 600, "tiny_dry_run": False})
    for name, rc, secs in (("forward_fp32", 0, 12.0), ("generate", 0, 20.0), ("train", 0, 70.0), ("ddp", 1, 9.0)):
        _write(out / f"step_{name}.json", {"exit_code": rc, "seconds": secs, "limit_s": 100, "timed_out": False})
    _write(out / "forward_fp32.json", {"results": [{"model": "uhrnet", "forward_ms": 14.0, "parameters": 30330977},
                                                   {"model": "unet", "forward_ms": 4.0, "parameters": 31030593}]})
    syn = out / "work" / "syn"
    syn.mkdir(parents=True)
    np.save(syn / "f1_80.npy", np.zeros((100, 4, 4, 1), np.float32))
    run = out / "work" / "run"
    run.mkdir(parents=True)
    with open(run / "history.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["epoch", "val_rmse_mm", "seconds"])
        w.writeheader()
        w.writerows([{"epoch": 1, "val_rmse_mm": 5.0, "seconds": 30.0}, {"epoch": 2, "val_rmse_mm": 4.0, "seconds": 8.0},
                     {"epoch": 3, "val_rmse_mm": 3.0, "seconds": 12.0}])
    _write(out / "work" / "s2r" / "report.json", {
        "config": {"count": 100, "epochs": 3, "model": "uhrnet"},
        "variants": [{"real": {"object_rmse_mm": 6.5},
                      "rows": [{"real": {"object_median_abs_mm": 3.5},
                                "real_phase": [{"folder": "x/FP1523", "id": "1201", "rmse_rad": 1.7}]}]}]})
    res = gpu_check.report(out)
    assert res["generate"]["samples_per_s"] == pytest.approx(100 / 20.0)
    # 80 % of the samples train; the first epoch (autotuning) is left out of the rate
    assert res["train"]["samples_per_s"] == pytest.approx(80 / 10.0)
    assert res["forward_ms"]["fp32"]["uhrnet"]["forward_ms"] == 14.0
    assert res["ddp"]["exit_code"] == 1 and res["ddp"]["backend"] == "nccl"
    assert res["sim2real"]["pair_object_rmse_mm"] == 6.5
    assert res["sim2real"]["phase_residual_rad"] == {"FP1523/1201": 1.7}
    md = (out / "gpu_check.md").read_text()
    assert "| uhrnet | 14.00 | 22.4 |" in md and "8.0 training samples/s" in md and "6.50 mm" in md
    assert json.loads((out / "gpu_check.json").read_text())["device"] == "NVIDIA X"


@pytest.mark.parametrize("budget", ["abc", "30", "-5", "99999999999999999999999", "86401", "1e3"])
def test_bad_budget_is_one_line_and_exit_2(tmp_path, budget):
    r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(tmp_path / "o")],
                       env={**os.environ, "GPU_CHECK_BUDGET": budget, "PYTHON": sys.executable},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "GPU_CHECK_BUDGET" in r.stderr
    assert "integer expression" not in r.stderr and "too great" not in r.stderr
    assert not (tmp_path / "o").exists()  # nothing made for a refused run


@pytest.mark.parametrize("seeds", ["", "1 x", "-1", "1.5"])
def test_bad_study_seeds_are_one_line_and_exit_2(tmp_path, seeds):
    r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(tmp_path / "o")],
                       env={**os.environ, "GPU_CHECK_STUDY_SEEDS": seeds, "PYTHON": sys.executable},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "GPU_CHECK_STUDY_SEEDS" in r.stderr
    assert not (tmp_path / "o").exists()


def test_bad_tiny_flag_is_one_line_and_exit_2(tmp_path):
    r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(tmp_path / "o")],
                       env={**os.environ, "GPU_CHECK_TINY": "99999999999999999999999", "PYTHON": sys.executable},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "GPU_CHECK_TINY" in r.stderr
    assert not (tmp_path / "o").exists()


def test_a_relative_outdir_is_the_callers(tmp_path):
    """OUTDIR relative to the folder the script was started in, not to the checkout."""
    (tmp_path / "results.txt").write_text("mine")
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "a.txt").write_text("a")
    for name, says in (("results.txt", "not a folder"), ("theirs", "did not write")):
        r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", name], cwd=tmp_path,
                           env={**os.environ, "PYTHON": sys.executable}, capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
        assert says in r.stderr and str(tmp_path / name) in r.stderr
    assert not (ROOT / "results.txt").exists() and not (ROOT / "theirs").exists()


def test_an_outdir_holding_someone_elses_files_is_refused_untouched(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "work").mkdir()
    (out / "work" / "notes.txt").write_text("keep")
    (out / "train.log").write_text("keep too")
    r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(out)],
                       env={**os.environ, "PYTHON": sys.executable}, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "did not write" in r.stderr and r.stderr.strip().count("\n") == 0
    assert (out / "work" / "notes.txt").read_text() == "keep" and (out / "train.log").read_text() == "keep too"
    assert not (out / ".gpu_check").exists()


def _report_fixture(out: Path, amp: bool | None) -> None:
    _write(out / "step_env.json", {"device": "cpu (no CUDA device)", "torch": "2.13", "cuda": None, "python": "3.12",
                                   "cpu_cores": 2, "gl_platform": "osmesa", "budget_s": 600, "tiny_dry_run": True})
    _write(out / "step_train.json", {"exit_code": 0, "seconds": 9.0, "limit_s": 100, "timed_out": False})
    syn = out / "work" / "syn"
    syn.mkdir(parents=True)
    np.save(syn / "f1_80.npy", np.zeros((10, 4, 4, 1), np.float32))
    run = out / "work" / "run"
    run.mkdir(parents=True)
    (run / "history.csv").write_text("epoch,val_rmse_mm,seconds\n1,5.0,4.0\n2,4.0,2.0\n")
    if amp is not None:
        _write(run / "config.json", {"model": "uhrnet", "amp": amp})


@pytest.mark.parametrize("amp", [False, True, None])
def test_report_says_amp_only_when_the_run_used_it_and_that_the_rate_includes_validation(tmp_path, amp):
    _report_fixture(tmp_path, amp)
    res = gpu_check.report(tmp_path)
    md = (tmp_path / "gpu_check.md").read_text()
    line = next(x for x in md.splitlines() if x.startswith("Training ("))
    assert line.startswith("Training (UHRNet, AMP):" if amp else "Training (UHRNet):")
    assert "4.0 training samples/s, validation included" in line  # 8 training samples / 2 s (epoch 1 left out)
    assert res["train"]["amp"] is amp and "validation" in res["train"]["samples_per_s_note"]


def _script(out, env=None, **kw):
    return subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(out)],
                          env={**os.environ, "PYTHON": sys.executable, **(env or {})}, capture_output=True, text=True,
                          timeout=kw.get("timeout", 120))


def test_an_outdir_that_is_a_file_is_one_line_and_exit_2(tmp_path):
    f = tmp_path / "results.txt"
    f.write_text("mine")
    r = _script(f)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0
    assert str(f) in r.stderr and "not a folder" in r.stderr and f.read_text() == "mine"


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="the refusal of a machine without CUDA")
def test_no_cuda_is_refused_before_anything_is_written(tmp_path):
    r = _script(tmp_path / "o")  # not TINY: the real sizes need a GPU
    assert r.returncode == 2 and "no CUDA device" in r.stderr and r.stderr.strip().count("\n") == 0
    assert not (tmp_path / "o").exists()
    (tmp_path / "e").mkdir()  # an existing empty OUTDIR stays empty
    assert _script(tmp_path / "e").returncode == 2 and not any((tmp_path / "e").iterdir())


def _fake_python(tmp_path) -> Path:
    """An interpreter for the script whose steps (``PY -m ...``, ``PY pipelines/scaling.py``/``gpu_speed.py``) each write one file
    named by their process into their --out folder, as the real tools would, and fail at once; everything else
    is this Python."""
    fake = tmp_path / "fakepy"
    fake.write_text(f"""#!/bin/bash
if [ "$1" = -m ] || [ "$1" = pipelines/scaling.py ] || [ "$1" = pipelines/gpu_speed.py ]; then
  prev=""; for a in "$@"; do [ "$prev" = --out ] && mkdir -p "$a" && echo x > "$a/made-$$.txt"; prev=$a; done
  exit 1
fi
exec {sys.executable} "$@"
""")
    fake.chmod(0o755)
    return fake


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_a_rerun_replaces_only_its_own_files(tmp_path):
    """Two TINY runs whose steps fail at once (about 20 s): the second removes the first one's step files and
    work folders, keeps the user's files at any depth, and refuses a foreign file where a step writes."""
    out = tmp_path / "o"
    env = {"GPU_CHECK_TINY": "1", "PYTHON": str(_fake_python(tmp_path))}
    assert _script(out, env).returncode == 0
    first = {n for n in _files(out) if n.startswith("work/")}
    # the study step runs (and writes its tiny arms file itself) only where prepare copied the real data
    assert ("work/study/arms.yaml" in first) == (ROOT / ".gpu_data" / "real-sample").is_dir()
    assert all("made-" in n for n in first - {"work/study/arms.yaml"}) and (out / "gpu_check.md").is_file()
    mine = {"my_notes.log": "notes", "work/keep.txt": "keep", "work/mine/a.txt": "a", "gpu_check.md.bak": "b"}
    for name, text in mine.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
    r = _script(out, env)
    assert r.returncode == 0, r.stderr
    assert all((out / n).read_text() == t for n, t in mine.items())
    second = {n for n in _files(out) if n.startswith("work/")} - set(mine)
    assert second and not (second & first) - {"work/study/arms.yaml"}  # the earlier run's went (arms.yaml rewritten)
    assert gpu_check.settle(out)  # the record lists what the run wrote, nothing of the user's
    rec = json.loads((out / ".fppsim-owned.json").read_text())["files"]
    assert second <= set(rec) and not set(mine) & set(rec)
    # a file of someone else's where a step writes: refused, naming it, before anything is removed
    (out / "work" / "run" / "notes.txt").write_text("theirs")
    before = _files(out)
    r = _script(out, env)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "work/run/notes.txt" in r.stderr
    assert _files(out) == before


def test_begin_and_settle_own_exactly_what_the_run_wrote(tmp_path):
    out = tmp_path / "o"
    gpu_check.begin(out)  # a new folder: marker and record, nothing else
    assert sorted(p.name for p in out.iterdir()) == [".fppsim-owned.json", ".gpu_check", "work"]
    (out / "train.log").write_text("run 1")
    (out / "work" / "syn" / "sub").mkdir(parents=True)
    (out / "work" / "syn" / "sub" / "a.npy").write_text("x")
    (out / "work" / "s2r").mkdir()
    (out / "work" / "s2r" / "link").symlink_to(out / "work" / "syn")  # a link is removed, never followed
    # killed before settle: the folders it was writing are its own entirely, the user's files are not
    (out / "my_notes.log").write_text("keep")
    (out / "work" / "keep.txt").write_text("keep")
    gpu_check.heartbeat(out)  # the run was alive after writing them (its steps' guard)
    gpu_check.begin(out)
    assert _files(out) == {".fppsim-owned.json", ".gpu_check", "my_notes.log", "work/keep.txt"}
    (out / "work" / "syn").mkdir()
    (out / "work" / "syn" / "b.npy").write_text("y")
    rec = gpu_check.settle(out)
    assert rec["work/syn/b.npy"] == gpu_check.TOOL and "work/run" not in rec and "train.log" not in rec
    (out / "work" / "syn" / "c.txt").write_text("after the run")  # someone's, in the run's folder
    with pytest.raises(gpu_check.Refused, match="c.txt exists and was not written"):
        gpu_check.begin(out)
    assert (out / "work" / "syn" / "b.npy").exists()  # refused before anything was removed
    (out / "work" / "syn" / "c.txt").unlink()
    (out / "step_train.json").mkdir()  # a folder where the run writes a file
    with pytest.raises(gpu_check.Refused, match="step_train.json exists and was not written"):
        gpu_check.begin(out)


def test_after_an_unclean_stop_a_file_added_later_is_refused_not_deleted(tmp_path):
    out = tmp_path / "o"
    gpu_check.begin(out)
    (out / "work" / "syn").mkdir()
    (out / "work" / "syn" / "a.npy").write_text("the run's")
    os.utime(out / ".gpu_check")  # the run's last sign of life, then it was killed with -9 (no settle)
    time.sleep(0.05)
    (out / "work" / "syn" / "user.txt").write_text("added after the run")
    with pytest.raises(gpu_check.Refused, match="user.txt changed after the stopped run"):
        gpu_check.begin(out)
    assert (out / "work" / "syn" / "user.txt").read_text() == "added after the run"
    assert (out / "work" / "syn" / "a.npy").exists()  # refused before anything was removed
    (out / "work" / "syn" / "user.txt").unlink()
    gpu_check.begin(out)  # only the run's file left: removed
    assert not (out / "work" / "syn").exists()


def test_after_an_unclean_stop_of_unknown_times_the_folder_is_refused(tmp_path):
    out = tmp_path / "o"
    gpu_check.begin(out)
    (out / ".gpu_check").write_text("")  # an earlier version's marker: when the run ran is unknown
    (out / "work" / "run").mkdir()
    (out / "work" / "run" / "notes.txt").write_text("someone's?")
    with pytest.raises(gpu_check.Refused, match=r"work/run: a stopped run was writing it"):
        gpu_check.begin(out)
    assert (out / "work" / "run" / "notes.txt").read_text() == "someone's?"


def test_an_existing_outdir_that_cannot_be_written_says_so(tmp_path, monkeypatch, capsys):
    out = tmp_path / "ro"
    out.mkdir()
    real_mkdir = Path.mkdir

    def mkdir(self, *a, **kw):  # a read-only folder (root, running these tests, may write anywhere)
        if self == out / "work":
            raise PermissionError(13, "Permission denied", str(self))
        return real_mkdir(self, *a, **kw)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    assert gpu_check.main(["begin", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "cannot write there" in err and "cannot create" not in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes in a read-only folder")
def test_a_read_only_outdir_says_cannot_write_there(tmp_path, capsys):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    try:
        assert gpu_check.main(["begin", str(out)]) == 2
    finally:
        out.chmod(0o755)
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "cannot write there" in err and not any(out.iterdir())


def _sleepy_python(tmp_path) -> Path:
    """An interpreter for a TINY run that needs no torch: ``-c`` answers "no CUDA", ``env`` writes nothing, a
    step with --out writes a file there, notes its pid in tmp_path/pids and sleeps $FAKE_SLEEP s; a step
    without --out fails at once; everything else is this Python."""
    fake = tmp_path / "sleepypy"
    fake.write_text(f"""#!/bin/bash
[ "$1" = -c ] && {{ echo 0; exit 0; }}
[ "$1" = pipelines/gpu_check.py ] && [ "$2" = env ] && exit 0
if [ "$1" = -m ]; then
  prev=""; for a in "$@"; do
    if [ "$prev" = --out ]; then
      mkdir -p "$a" && echo x > "$a/made-$$.txt" && echo $$ >> {tmp_path}/pids && exec sleep "${{FAKE_SLEEP:-0}}"
    fi
    prev=$a
  done
  exit 1
fi
exec {sys.executable} "$@"
""")
    fake.chmod(0o755)
    return fake


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _ppid(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def _until(cond, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return cond()


def _start_until_generating(tmp_path, out_arg: str, **kw) -> tuple[subprocess.Popen, int]:
    # the generate step first: the study (where a checkout holds prepare's .gpu_data/) and the forward step
    # (torch's import and three models) before it took over the 60 s below on the 2 loaded cores
    env = {**os.environ, "GPU_CHECK_TINY": "1", "PYTHON": str(_sleepy_python(tmp_path)), "FAKE_SLEEP": "60",
           "GPU_CHECK_STEPS": "generate train"}
    p = subprocess.Popen(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", out_arg], env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **kw)
    pids = tmp_path / "pids"
    assert _until(lambda: pids.is_file() and pids.read_text().strip(), 60), "the generate step never started"
    return p, int(pids.read_text().split()[0])


def _cleanup(p: subprocess.Popen, tmp_path) -> None:
    """Stop what a failed test left running: the script and the step processes it noted (by their pids)."""
    if p.poll() is None:
        p.kill()
        p.wait()
    pids = tmp_path / "pids"
    for pid in (pids.read_text().split() if pids.is_file() else []):
        if _alive(int(pid)):
            os.kill(int(pid), signal.SIGKILL)


def _as_from_a_terminal() -> None:
    """A shell started from a terminal has Ctrl-C at its default; one started with SIGINT ignored cannot even
    trap it (ignored signals survive exec, and bash keeps them). A test run started in the background of a
    non-interactive shell (``pytest ... &``, as long runs often are) has SIGINT ignored, and so had the script:
    the Ctrl-C below was lost and the wait ran out. The test process's own disposition is not handed down."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_stops_the_running_step_and_the_run_with_130(tmp_path):
    out = tmp_path / "o"
    p, step = _start_until_generating(tmp_path, str(out), start_new_session=True, preexec_fn=_as_from_a_terminal)
    try:
        os.killpg(p.pid, signal.SIGINT)  # Ctrl-C: the whole foreground process group
        try:
            assert p.wait(timeout=120) == 130
        except subprocess.TimeoutExpired:
            pytest.fail(f"Ctrl-C did not stop the script in 120 s (pytest's SIGINT: {signal.getsignal(signal.SIGINT)})")
        assert _until(lambda: not _alive(step), 5), "the step outlived Ctrl-C"
        rec = json.loads((out / ".fppsim-owned.json").read_text())["files"]
        assert gpu_check.WRITING not in rec.values()  # settled: the record lists what the run wrote
        assert any(n.startswith("work/syn/made-") for n in rec)
    finally:
        _cleanup(p, tmp_path)


def test_kill_9_stops_the_step_and_a_rerun_keeps_files_added_later(tmp_path):
    p, step = _start_until_generating(tmp_path, "o", cwd=tmp_path)  # a relative OUTDIR: the caller's folder
    out = tmp_path / "o"
    try:
        assert (out / "work" / "syn").is_dir() and not (ROOT / "o").exists()
        guard = _ppid(step)
        p.kill()  # kill -9 of the script
        p.wait()
        assert _until(lambda: not _alive(step) and not _alive(guard), 20), "the step outlived the script"
        time.sleep(0.05)
        (out / "work" / "syn" / "user.txt").write_text("mine")
        (out / "work" / "run").mkdir(exist_ok=True)
        (out / "work" / "run" / "notes.txt").write_text("mine too")
        r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(out)],
                           env={**os.environ, "GPU_CHECK_TINY": "1", "PYTHON": str(_sleepy_python(tmp_path)),
                                "FAKE_SLEEP": "0"}, capture_output=True, text=True, timeout=120)
        assert (out / "work" / "syn" / "user.txt").read_text() == "mine"
        assert (out / "work" / "run" / "notes.txt").read_text() == "mine too"
        assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "work/" in r.stderr, r.stderr
    finally:
        _cleanup(p, tmp_path)
