"""Issue 11: pipelines/gpu_bench.sh must run on an NVIDIA machine that has PyTorch and little else, possibly
offline. Its steps (uhrnet bench, an AMP epoch, torchrun train) are run here with every optional module
blocked (``sys.modules[name] = None``: ``import`` fails, ``importlib.util.find_spec`` says absent)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BLOCKED = ["scipy", "skimage", "yaml", "tqdm", "matplotlib", "trimesh", "pyrender", "cv2", "OpenGL", "onnx",
           "onnxruntime", "openvino", "PIL", "sklearn", "zlib_ng"]

SCRIPT = """
import sys
for name in {blocked!r}:
    sys.modules[name] = None
sys.argv = {argv!r}
import runpy
{run}
"""


def _run(module: str, argv: list[str], tmp_path: Path, env_extra: dict | None = None):
    code = SCRIPT.format(blocked=BLOCKED, argv=[module, *argv], run=f"runpy.run_module({module!r}, run_name='__main__')")
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env_extra or {})}
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow
def test_gpu_bench_steps_need_only_torch_and_numpy(tmp_path):
    r = _run("uhrnet", ["bench", "--models", "uhrnet", "unet", "--height", "32", "--width", "64", "--base-channels",
                        "4", "--repeats", "1", "--warmup", "0", "--no-train", "--device", "cpu"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "UHRNet / U-Net forward time" in r.stdout

    data = tmp_path / "data"
    gpu_bench = str(ROOT / "pipelines" / "gpu_bench.py")
    sub = subprocess.run([sys.executable, gpu_bench, "data", str(data)], env={**os.environ, "GPU_BENCH_TINY": "1"},
                         capture_output=True, text=True, timeout=120)
    assert sub.returncode == 0, sub.stderr[-2000:]
    r = _run("uhrnet", ["train", "--real", str(data), "--model", "uhrnet", "--base-channels", "4", "--epochs", "1",
                        "--batch-size", "2", "--seed", "0", "--out", str(tmp_path / "run"), "--no-progress"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "run" / "best.pt").is_file() and "matplotlib" in r.stdout + r.stderr  # the plot is skipped

    code = SCRIPT.format(blocked=BLOCKED, argv=["gpu_bench.py", "epoch", str(tmp_path / "out")],
                         run=f"runpy.run_path({gpu_bench!r}, run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "GPU_BENCH_TINY": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    step = json.loads((tmp_path / "out" / "step_epoch.json").read_text())
    assert step["all_losses_finite"] and step["weights_finite"]
