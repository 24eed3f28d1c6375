"""pipelines/bench_report.py collects benchmark JSON files into one Markdown page."""

from __future__ import annotations

import json
from pathlib import Path

from _helpers import load_pipeline

ROOT = Path(__file__).resolve().parents[1]


def load_report():
    return load_pipeline("bench_report")


def test_report_collects_uhrnet_generate_and_gpu_json(tmp_path):
    bench = {"device": "cpu, 2 threads", "input_shape": [1, 1, 352, 640], "uhrnet_unet_forward_ratio": 1.234,
             "uhrnet_unet_best_deployable_ratio": 1.515,
             "results": [
                 {"model": "uhrnet", "base_channels": 64, "parameters": 30330977, "forward_ms": 900.0,
                  "eager_forward_ms": 1500.0, "best_form": "fold_cl", "onnxruntime_ms": 800.0, "openvino_ms": 700.0,
                  "best_deployable_ms": 700.0, "best_deployable_form": "openvino", "train_step_ms": None},
                 {"model": "unet", "base_channels": 64, "parameters": 31030593, "forward_ms": 729.3,
                  "train_step_ms": 2000.0}]}
    (tmp_path / "uhrnet.json").write_text(json.dumps(bench))
    # a newer bench: forward ratio = best forms re-timed in pairs, the torch forms' ratio on its own key
    newer = {**bench, "uhrnet_unet_forward_ratio": 1.47, "uhrnet_unet_best_deployable_ratio": 1.47,
             "uhrnet_unet_torch_ratio": 1.96}
    (tmp_path / "uhrnet_newer.json").write_text(json.dumps(newer))
    (tmp_path / "generate.json").write_text(json.dumps(
        {"mesh": "/x/ogre.obj", "psp": True, "write": True, "sample_s_median": 0.5, "samples_per_s": 2.0,
         "cost_over_floor": 4.5}))
    (tmp_path / "gpu.json").write_text(json.dumps({"kind": "gpu_bench", "device": "NVIDIA X", "steps": {"fp32": {"uhrnet_ms": 20}}}))
    (tmp_path / "broken.json").write_text("{")
    out = tmp_path / "BENCH.md"
    report = load_report()
    assert report.main([str(tmp_path), "--out", str(out)]) == 0
    page = out.read_text()
    assert "30,330,977" in page and "**1.23**" in page and "fold_cl" in page and "1500.0" in page
    assert "700.0 (openvino)" in page and "**1.51**" in page
    assert "**1.96**" in page and "**1.47**" in page
    assert "| generate | ogre.obj | True | True | 500.0 | 2.00 | 4.50 |" in page
    assert "NVIDIA X" in page and "torch" in page and "logical cores" in page


def test_report_without_gpu_json_says_not_run(tmp_path, capsys):
    report = load_report()
    assert report.main([str(tmp_path)]) == 0
    assert "Not run: no GPU" in capsys.readouterr().out
    assert report.main([str(tmp_path / "missing")]) == 2
