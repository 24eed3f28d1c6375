"""A built wheel works anywhere: installed alone (no checkout on the path), `fppsim generate` runs from
another directory with the packaged default rig and meshes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_installed_alone_generates_with_the_default_rig(tmp_path):
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    # build from a clean copy: an in-tree build would leave build/ behind, whose stale files (modules
    # deleted since) setuptools would put into later wheels
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("fppsim", "uhrnet"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    res = subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "dist"), str(src)],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    wheel = next((tmp_path / "dist").glob("fppsim_uhrnet-*.whl"))
    import zipfile

    names = zipfile.ZipFile(wheel).namelist()
    for needed in ("fppsim/py.typed", "uhrnet/py.typed", "fppsim/data/default_rig.json",
                   "fppsim/data/figshare_like_rig.json", "fppsim/data/parallel_rig.json", "fppsim/data/meshes/bust_s0.ply"):
        assert needed in names, needed
    # A fresh environment: the wheel alone in its own folder, the dependencies from this interpreter's
    # site-packages (no .pth files processed there, so the editable checkout is NOT importable).
    site = tmp_path / "site"
    res = subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    deps = sysconfig.get_paths()["purelib"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(PYTHONPATH=os.pathsep.join([str(site), deps]), PYOPENGL_PLATFORM="osmesa")
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = subprocess.run([sys.executable, "-S", "-c", "import fppsim, sys; print(fppsim.__file__)"],
                           env=env, cwd=work, capture_output=True, text=True, timeout=120)
    assert where.stdout.strip().startswith(str(site)), (where.stdout, where.stderr[-1000:])
    meshes = site / "fppsim" / "data" / "meshes"
    cmd = [sys.executable, "-S", "-m", "fppsim.cli", "generate", "--meshes", str(meshes), "--out", "out",
           "--count", "1", "--no-psp", "--no-preview", "-q"]
    res = subprocess.run(cmd, env=env, cwd=work, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    with np.load(work / "out" / "000000" / "arrays.npz") as z:
        assert z["height"].shape == (352, 640) and z["mask"].mean() > 0.5
