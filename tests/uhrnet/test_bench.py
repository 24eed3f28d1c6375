"""`uhrnet bench` end to end on tiny models and inputs."""

from __future__ import annotations

import json

import pytest
import torch

from uhrnet.cli import main


@pytest.fixture(autouse=True)
def single_thread(one_thread):
    """Tiny models on a shared machine run 10-30x faster on one thread than on an oversubscribed pool."""


def test_bench_runs_all_default_models(tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["bench", "--height", "32", "--width", "64", "--base-channels", "4", "--repeats", "1", "--warmup", "0"]
    assert main([*argv, "--device", "cpu", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "UHRNet / U-Net forward time" in text and "2.77" in text
    report = json.loads(out.read_text())
    results = {r["model"]: r for r in report["results"]}
    assert list(results) == ["uhrnet", "unet", "model_a", "model_b", "hnet"]
    assert results["model_a"]["base_channels"] == 2 and results["uhrnet"]["base_channels"] == 4
    for r in results.values():
        assert r["parameters"] > 0 and r["forward_ms"] > 0 and r["train_step_ms"] > 0
    assert report["uhrnet_unet_forward_ratio"] == pytest.approx(
        results["uhrnet"]["forward_ms"] / results["unet"]["forward_ms"]
    )


def test_bench_channels_last_without_training(capsys):
    argv = ["bench", "--models", "hnet", "--height", "32", "--width", "32", "--base-channels", "4"]
    assert main([*argv, "--repeats", "1", "--warmup", "0", "--channels-last", "--no-train"]) == 0
    assert "hnet" in capsys.readouterr().out


def test_bench_user_errors(capsys):
    assert main(["bench", "--models", "resnet"]) == 2
    assert main(["bench", "--height", "40"]) == 2
    if not torch.cuda.is_available():
        assert main(["bench", "--device", "cuda"]) == 1
    assert "error" in capsys.readouterr().err


def test_bench_json_destination_is_checked_before_timing(tmp_path, capsys):
    """A --json that cannot be written fails at once (before minutes of timing), one line, exit 1."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["bench", "--models", "unet", "--json", str(tmp_path)]) == 1
    assert main(["bench", "--models", "unet", "--json", str(blocker / "out.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "is a folder" in err[0] and "is a file, not a folder" in err[1] and str(blocker) in err[1]
    assert blocker.read_text() == "x"


TINY = ["bench", "--models", "unet", "--height", "16", "--width", "16", "--base-channels", "4", "--repeats", "1",
        "--warmup", "0", "--no-train", "--device", "cpu"]


@pytest.mark.parametrize("flags, flag", [(["--repeats", "0"], "--repeats"), (["--warmup", "-1"], "--warmup"),
                                         (["--batch-size", "0"], "--batch-size"), (["--models", "bogus"], "--models"),
                                         (["--base-channels", "0"], "--base-channels"),
                                         (["--base-channels", "-4"], "--base-channels"),
                                         (["--variants", "fold"], "--variants")])
def test_bench_bad_values_are_usage_errors(tmp_path, capsys, flags, flag):
    """A value wrong on its own (or --variants without --optimize, which it only steers): one line naming the
    flag, exit 2, nothing timed or written (--base-channels 0 measured a width-1 model until stop 67)."""
    out = tmp_path / "b.json"
    assert main([*TINY, *flags, "--json", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and flag in err[0] and not captured.out and not out.exists()


def test_bench_json_replaces_only_its_own_report(tmp_path, capsys):
    """--json never replaces a file bench did not write (a checkpoint, notes, another tool's JSON): one line
    naming it, exit 1, the file as it was; a report of an earlier bench is replaced."""
    ckpt = tmp_path / "best.pt"
    torch.save({"state_dict": {"w": torch.zeros(3)}}, ckpt)
    notes = tmp_path / "mine.json"
    notes.write_text('{"device": "mine", "results": "not a list"}')
    for path in (ckpt, notes):
        before = path.read_bytes()
        assert main([*TINY, "--json", str(path)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(path) in err[0] and "not a report uhrnet bench wrote" in err[0]
        assert path.read_bytes() == before
    out = tmp_path / "bench.json"
    assert main([*TINY, "--json", str(out)]) == 0
    first = out.read_text()
    assert main([*TINY, "--repeats", "2", "--json", str(out)]) == 0  # its own report: replaced
    assert json.loads(out.read_text())["repeats"] == 2 and json.loads(first)["repeats"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bench.json", "best.pt", "mine.json"]  # no temp file left


def test_bench_json_refuses_a_file_that_appears_during_timing(tmp_path, monkeypatch):
    """The check is made again just before writing: a file put there while bench timed is kept."""
    import uhrnet.scoring.bench as bench_module

    out = tmp_path / "late.json"
    real = bench_module._measure_models

    def measure_then_drop_a_file(*a):
        out.write_text("written meanwhile")
        return real(*a)

    monkeypatch.setattr(bench_module, "_measure_models", measure_then_drop_a_file)
    assert main([*TINY, "--json", str(out)]) == 1
    assert out.read_text() == "written meanwhile"


def test_bench_optimize_json_keys(tmp_path, capsys):
    pytest.importorskip("onnxruntime")
    out = tmp_path / "opt.json"
    argv = ["bench", "--models", "uhrnet", "unet", "--height", "16", "--width", "32", "--base-channels", "4",
            "--repeats", "1", "--warmup", "0", "--no-train", "--optimize", "--variants", "fold_cl", "onnxruntime"]
    assert main([*argv, "--device", "cpu", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["optimize"] is True
    for r in report["results"]:
        assert set(r["optimized"]) == {"fold_cl", "onnxruntime"}
        for form in r["optimized"].values():
            assert form["ok"] and form["max_rel_diff"] <= 1e-4 and form["forward_ms"] > 0
        assert r["best_form"] in ("eager", "fold_cl")
        assert r["forward_ms"] <= r["eager_forward_ms"] and r["onnxruntime_ms"] > 0
    by = {r["model"]: r for r in report["results"]}
    assert report["uhrnet_unet_torch_ratio"] == pytest.approx(by["uhrnet"]["forward_ms"] / by["unet"]["forward_ms"])
    # the headline ratio: each model's fastest form of all, re-timed in alternating pairs
    pairs = report["best_deployable_pairs"]
    assert len(pairs["pair_ratios"]) == 1 and pairs["a_ms"] > 0 and pairs["b_ms"] > 0
    assert report["uhrnet_unet_forward_ratio"] == report["uhrnet_unet_best_deployable_ratio"] == pytest.approx(
        pairs["a_ms"] / pairs["b_ms"])
    assert report["uhrnet_unet_onnxruntime_ratio"] == pytest.approx(
        by["uhrnet"]["onnxruntime_ms"] / by["unet"]["onnxruntime_ms"])
    assert "deployable forms" in capsys.readouterr().out


def test_bench_openvino_form_and_best_deployable_ratio(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("openvino")
    out = tmp_path / "ov.json"
    argv = ["bench", "--models", "uhrnet", "unet", "--height", "16", "--width", "32", "--base-channels", "4",
            "--repeats", "1", "--warmup", "0", "--no-train", "--optimize", "--variants", "fold", "onnxruntime",
            "openvino", "--device", "cpu", "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    for r in report["results"]:
        ov = r["optimized"]["openvino"]
        assert ov["ok"] and ov["max_rel_diff"] <= 1e-4 and r["openvino_ms"] == ov["forward_ms"]
        forms = {k: v["forward_ms"] for k, v in r["optimized"].items()} | {"eager": r["eager_forward_ms"]}
        assert r["best_deployable_ms"] == min(forms.values())
        assert forms[r["best_deployable_form"]] == r["best_deployable_ms"]
        assert r["best_form"] in ("eager", "fold")  # torch forms only
    by = {r["model"]: r for r in report["results"]}
    assert report["uhrnet_unet_openvino_ratio"] == pytest.approx(by["uhrnet"]["openvino_ms"] / by["unet"]["openvino_ms"])
    pairs = report["best_deployable_pairs"]
    assert report["uhrnet_unet_best_deployable_ratio"] == pytest.approx(pairs["a_ms"] / pairs["b_ms"])


def test_paired_times_alternate_the_two_calls():
    """Warm-up of each, then a, b, a, b, ...; medians and per-pair ratios from the same calls."""
    from uhrnet.scoring.bench import paired_times

    calls = []
    out = paired_times(lambda: calls.append("a"), lambda: calls.append("b"), "cpu", warmup=2, repeats=3)
    assert calls == ["a"] * 3 + ["b"] * 3 + ["a", "b"] * 3  # warm-ups (each time_call also times one), then pairs
    assert len(out["pair_ratios"]) == 3 and out["ratio"] == pytest.approx(out["a_ms"] / out["b_ms"])


def test_optimize_variants_keeps_each_forms_own_runner(tmp_path):
    """The runner kept for each ONNX runtime is that runtime's (not the last one the loop built)."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("openvino")
    from uhrnet.scoring.bench import BenchConfig, optimize_variants
    from uhrnet.models import build_model

    torch.manual_seed(0)
    model = build_model("unet", base_channels=4).eval()
    x = torch.randn(1, 1, 16, 32)
    with torch.no_grad():
        ref = model(x)
    args = BenchConfig(models=["unet"], height=16, width=32, repeats=1, warmup=0, variants=["onnxruntime", "openvino"])
    runners = {}
    out = optimize_variants(model, x, ref, args, torch.device("cpu"), runners)
    assert out["onnxruntime"]["ok"] and out["openvino"]["ok"] and set(runners) == {"onnxruntime", "openvino"}
    bound = {form: fn.__defaults__[0] for form, fn in runners.items()}  # each lambda's own run
    assert bound["onnxruntime"] is not bound["openvino"]
