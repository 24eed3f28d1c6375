"""`uhrnet train --threads N` (issue 35.2): a seeded run repeats bit for bit at the same CPU thread count, the
count is recorded, the process's own count is restored, and a bad count is a usage error."""

from __future__ import annotations

import json

import pytest
import torch

from tests._helpers import write_figshare
from uhrnet.cli import main


def _run(tmp_path, name, threads):
    out = tmp_path / name
    assert main(["train", "--synthetic", str(tmp_path / "data"), "--out", str(out), "--model", "unet",
                 "--base-channels", "4", "--epochs", "2", "--batch-size", "2", "--resize", "32x64", "--device", "cpu",
                 "--seed", "3", "--threads", str(threads), "--no-progress"]) == 0
    return out


def test_threads_pinned_repeat_and_are_recorded(tmp_path):
    write_figshare(tmp_path / "data", n=8, h=32, w=64, seed=4)
    before = torch.get_num_threads()
    a, b = _run(tmp_path, "a", 1), _run(tmp_path, "b", 1)
    assert torch.get_num_threads() == before
    assert json.loads((a / "config.json").read_text())["torch_threads"] == 1
    wa, wb = (torch.load(r / "last.pt", weights_only=False)["state_dict"] for r in (a, b))
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.parametrize("value", ["0", "-2", "5000"])
def test_bad_thread_count_is_a_usage_error(tmp_path, value, capsys):
    write_figshare(tmp_path / "data", n=8, h=32, w=64, seed=4)
    assert main(["train", "--synthetic", str(tmp_path / "data"), "--out", str(tmp_path / "o"), "--threads", value,
                 "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "--threads must be a number of CPU threads from 1 to 1024" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


_STEP = """
import sys, torch
from uhrnet.device import keep_freed_memory
from uhrnet.models import build_model
applied = keep_freed_memory() if sys.argv[1] == "1" else None
torch.manual_seed(0); torch.set_num_threads(1)
m = build_model("unet", base_channels=4)
x = torch.randn(2, 1, 96, 128)
((m(x) - x) ** 2).mean().backward()
print(applied, float(sum(p.grad.double().abs().sum() for p in m.parameters())).hex())
"""


def test_keeping_freed_memory_changes_no_number():
    """uhrnet.device.keep_freed_memory (what CPU training and adapt call: glibc keeps large freed blocks instead
    of unmapping them) changes where memory comes from, never a computed bit; it applies on Linux with glibc."""
    import platform
    import subprocess
    import sys

    runs = [subprocess.run([sys.executable, "-c", _STEP, flag], capture_output=True, text=True, check=True,
                           timeout=120).stdout.split() for flag in ("0", "1")]
    assert runs[0][1] == runs[1][1]
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert runs[1][0] == "True"
