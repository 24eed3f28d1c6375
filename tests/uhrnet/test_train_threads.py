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
