"""pipelines/gpu_speed.py (issue 49), gpu_check.sh's speed step: the report's keys for the settings before and after
the speed options, its dated file, and gpu_check's table of it; the whole step at toy sizes on the CPU."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "pipelines"))
import gpu_check  # noqa: E402
import gpu_speed  # noqa: E402


def _setting(sps, seed_s):
    return {"settings": {"device_data": "auto"}, "uhrnet_train_samples_per_s": sps, "unet_recipe_seed_train_s": seed_s,
            "unet_recipe_samples_per_s": 50.0, "uhrnet_step": {"share": dict.fromkeys(gpu_check.PHASES, 0.25),
                                                                 "step_ms": 80.0}}


def test_report_has_the_keys_before_and_after():
    rec = gpu_speed.report(_setting(30.0, 90.0), _setting(95.0, 25.0), commit="a" * 40, device="NVIDIA H100 80GB HBM3",
                           tiny=False, sizes=dict(gpu_speed.FULL))
    for part in (rec, rec["before"], rec["after"]):
        assert set(gpu_speed.KEYS) <= set(part)
    assert rec["commit"] == "a" * 40 and rec["uhrnet_train_samples_per_s"] == 95.0
    assert rec["before"]["unet_recipe_seed_train_s"] == 90.0 and rec["speedup"]["unet_recipe_seed"] == pytest.approx(3.6)
    assert gpu_speed.bench_name("NVIDIA H100 80GB HBM3", 0.0) == "1970-01-01_nvidia-h100-80gb-hbm3.json"
    table = "\n".join(gpu_check.speed_table(rec))
    assert "| before | 30.0 | 50.0 | 90.0 | 25 | 25 | 25 | 25 | 80.0 |" in table and "| after | 95.0 |" in table


def test_gpu_check_report_carries_the_speed_table(tmp_path):
    rec = gpu_speed.report(_setting(30.0, 90.0), _setting(95.0, 25.0), commit="b" * 40, device="cpu", tiny=True,
                           sizes=dict(gpu_speed.TINY))
    (tmp_path / "speed.json").write_text(json.dumps(rec))
    res = gpu_check.report(tmp_path)
    assert res["speed"]["after"]["uhrnet_train_samples_per_s"] == 95.0
    assert "| after | 95.0 |" in (tmp_path / "gpu_check.md").read_text()


def test_tiny_run_on_the_cpu_writes_both_reports(tmp_path, one_thread):
    assert gpu_speed.main(["--out", str(tmp_path / "w"), "--tiny", "--bench-dir", str(tmp_path / "bench"),
                           "--commit", "c" * 40]) == 0
    rec = json.loads((tmp_path / "w" / "speed.json").read_text())
    files = list((tmp_path / "bench").glob("*_cpu.json"))
    assert len(files) == 1 and json.loads(files[0].read_text()) == rec
    assert rec["commit"] == "c" * 40 and rec["device"] == "cpu" and rec["tiny_dry_run"]
    for name in ("before", "after"):
        r = rec[name]
        assert set(gpu_speed.KEYS) <= set(r) and r["uhrnet_train_samples_per_s"] > 0 and r["unet_recipe_seed_train_s"] > 0
        assert sum(r["uhrnet_step"]["share"].values()) == pytest.approx(1.0)
    assert rec["after"]["settings"]["device_data"] == "on" and rec["before"]["settings"]["device_data"] == "off"
