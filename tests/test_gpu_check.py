"""pipelines/gpu_check.sh's helpers: which carried wheels install here, and the report built from the steps'
outputs. (The whole script's offline CPU dry run takes minutes: docs/USAGE.md "GPU, offline".)"""

import csv
import json
import os
import subprocess
import sys
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


@pytest.mark.parametrize("budget", ["abc", "30", "-5"])
def test_bad_budget_is_one_line_and_exit_2(tmp_path, budget):
    r = subprocess.run(["bash", str(ROOT / "pipelines" / "gpu_check.sh"), "run", str(tmp_path / "o")],
                       env={**os.environ, "GPU_CHECK_BUDGET": budget, "PYTHON": sys.executable},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "GPU_CHECK_BUDGET" in r.stderr
    assert not (tmp_path / "o").exists()  # nothing made for a refused run


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
