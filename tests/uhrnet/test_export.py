"""BN folding, UHRNet block merging and `uhrnet export` (ONNX via onnxruntime, TorchScript) on tiny models."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from uhrnet.checkpoint import FORMAT, VERSION
from uhrnet.errors import ExportError
from uhrnet.cli import main
from fppsim.dataio.formats import LabelTransform
from uhrnet.models import build_model, list_models
from uhrnet.inference.deploy import fold_batchnorm, fold_conv_bn, prepare_for_inference

TINY = {"uhrnet": 8, "unet": 4, "hnet": 2, "model_a": 2, "model_b": 8, "model_c": 8, "model_d": 8}


@pytest.fixture(autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def randomise_bn(model: nn.Module, seed: int = 0) -> nn.Module:
    """Non-trivial running statistics and affine parameters (fresh BNs are the identity in eval mode)."""
    g = torch.Generator().manual_seed(seed)
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            n = m.num_features
            m.running_mean.copy_(torch.rand(n, generator=g) - 0.5)
            m.running_var.copy_(torch.rand(n, generator=g) * 1.5 + 0.5)
            m.weight.data.copy_(torch.rand(n, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(n, generator=g) * 0.4 - 0.2)
    return model.eval()


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / (b.max() - b.min()))


@pytest.mark.parametrize("transpose", [False, True])
@pytest.mark.parametrize("groups", [1, 2])
def test_fold_conv_bn_matches_conv_then_bn(transpose, groups):
    torch.manual_seed(0)
    conv = (nn.ConvTranspose2d(4, 6, 3, stride=2, padding=1, output_padding=1, groups=groups) if transpose
            else nn.Conv2d(4, 6, 3, padding=2, dilation=2, groups=groups))
    bn = randomise_bn(nn.BatchNorm2d(6))
    x = torch.randn(2, 4, 9, 11)
    with torch.no_grad():
        expected = bn(conv(x))
        got = fold_conv_bn(conv, bn)(x)
    assert rel_err(got, expected) < 1e-5


def test_fold_conv_bn_without_bias_and_refuses_batch_statistics():
    conv = nn.Conv2d(3, 5, 1, bias=False)
    bn = randomise_bn(nn.BatchNorm2d(5))
    x = torch.randn(1, 3, 4, 4)
    with torch.no_grad():
        assert rel_err(fold_conv_bn(conv, bn)(x), bn(conv(x))) < 1e-5
    with pytest.raises(ValueError, match="running statistics"):
        fold_conv_bn(conv, nn.BatchNorm2d(5, track_running_stats=False))


@pytest.mark.parametrize("name", list_models())
def test_folded_models_equal_the_original(name):
    torch.manual_seed(1)
    model = randomise_bn(build_model(name, base_channels=TINY[name]))
    x = torch.randn(2, 1, 32, 48)
    with torch.no_grad():
        expected = model(x)
        folded = fold_batchnorm(model)
        assert not any(isinstance(m, nn.BatchNorm2d) for m in folded.modules())
        assert rel_err(folded(x), expected) < 1e-5
        fast = prepare_for_inference(model, channels_last=True)
        assert rel_err(fast(x.contiguous(memory_format=torch.channels_last)), expected) < 1e-5
    # the original is untouched (copies by default)
    assert any(isinstance(m, nn.BatchNorm2d) for m in model.modules()) == (name not in ("unet", "hnet", "model_a"))


def write_checkpoint(path, name: str, seed: int = 0):
    torch.manual_seed(seed)
    net = randomise_bn(build_model(name, base_channels=TINY[name]), seed)
    torch.save({
        "format": FORMAT, "version": VERSION,
        "model": {"name": net.config["name"], "config": dict(net.config)},
        "state_dict": net.state_dict(),
        "output": {"scale": 6.0, "shift": -90.0},
        "label_transform": LabelTransform().to_dict(),
        "epoch": 1,
    }, path)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("name", ["uhrnet", "unet", "hnet", "model_a", "model_b", "model_c", "model_d"])
def test_export_onnx_round_trip_every_model(tmp_path, name, capsys):
    pytest.importorskip("onnxruntime")
    ckpt = write_checkpoint(tmp_path / "m.pt", name)
    out = tmp_path / f"{name}.onnx"
    assert main(["export", str(ckpt), "--out", str(out), "--check", "--height", "32", "--width", "48"]) == 0
    assert "check passed" in capsys.readouterr().out


@pytest.mark.slow
def test_export_dynamic_onnx_matches_torch_at_other_sizes(tmp_path):
    import onnxruntime as ort

    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint

    ckpt = write_checkpoint(tmp_path / "m.pt", "uhrnet")
    out = tmp_path / "u.onnx"
    assert main(["export", str(ckpt), "--out", str(out), "--height", "32", "--width", "32", "--dynamic"]) == 0
    model, _ = model_from_checkpoint(load_checkpoint(ckpt))
    x = torch.rand(2, 1, 48, 64) * 2 - 1
    with torch.no_grad():
        expected = model(x)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = torch.from_numpy(session.run(None, {"fringe": x.numpy()})[0])
    assert rel_err(got, expected) < 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("name", ["uhrnet", "hnet"])
def test_export_torchscript_round_trip(tmp_path, name, capsys):
    ckpt = write_checkpoint(tmp_path / "m.pt", name)
    out = tmp_path / "m.ts"
    assert main(["export", str(ckpt), "--format", "torchscript", "--out", str(out), "--check",
                 "--height", "32", "--width", "48"]) == 0
    loaded = torch.jit.load(str(out))
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint

    model, _ = model_from_checkpoint(load_checkpoint(ckpt))
    x = torch.rand(1, 1, 64, 32) * 2 - 1  # another size than the trace's
    with torch.no_grad():
        assert rel_err(loaded(x), model(x)) < 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["onnx", "torchscript"])
def test_check_fails_on_a_tampered_export(tmp_path, fmt, capsys):
    """An export of other weights must fail the check against the checkpoint: exit 1, one line."""
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.inference.export import check_export, export_model

    ckpt = write_checkpoint(tmp_path / "m.pt", "uhrnet")
    model, _ = model_from_checkpoint(load_checkpoint(ckpt))
    tampered, _ = model_from_checkpoint(load_checkpoint(ckpt))
    with torch.no_grad():  # a small change of one weight
        conv = tampered.net.head
        conv.weight[0, 0, 0, 0] += 0.05 * conv.weight.abs().max()
    out = tmp_path / "m.bin"
    export_model(tampered, out, fmt, (1, 1, 32, 48))
    result = check_export(out, fmt, model, (1, 1, 32, 48))
    assert not result["passed"] and result["max_abs_diff"] > result["tolerance"] > 0
    assert check_export(out, fmt, tampered, (1, 1, 32, 48))["passed"]


def test_export_cli_check_failure_exit_code(tmp_path, capsys, monkeypatch):
    import uhrnet.inference.export as export

    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    real = export.run_exported
    monkeypatch.setattr(export, "run_exported", lambda *a: real(*a) + 1.0)  # a broken runtime
    assert main(["export", str(ckpt), "--out", str(tmp_path / "u.ts"), "--check", "--height", "16",
                 "--width", "16", "--format", "torchscript"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "check failed" in err[0]


def test_export_user_errors(tmp_path, capsys):
    assert main(["export", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "x.onnx")]) == 1
    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    assert main(["export", str(ckpt), "--out", str(tmp_path / "x.onnx"), "--height", "30"]) == 2  # a bad value: usage
    for opset in ("5", "99"):
        assert main(["export", str(ckpt), "--out", str(tmp_path / "x.onnx"), "--opset", opset]) == 2
    captured = capsys.readouterr()
    assert "checkpoint not found" in captured.err and "multiples of 16" in captured.err
    assert captured.err.count("--opset must be between") == 2 and not captured.out  # no exporter dump
    assert not (tmp_path / "x.onnx").exists()


def test_failed_check_leaves_the_output_as_it_was(tmp_path, capsys, monkeypatch):
    """The export is checked under a staging name and moved onto --out only when it passes: a failed or
    impossible check leaves the user's file untouched and no staging file behind."""
    import uhrnet.inference.export as export

    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    out = tmp_path / "keep.onnx"
    assert main(["export", str(ckpt), "--out", str(out), "--height", "16", "--width", "16"]) == 0  # export's own file
    kept = out.read_bytes()
    listing = sorted(p.name for p in tmp_path.iterdir())
    assert listing == [".fppsim-owned.json", "keep.onnx", "m.pt"]
    real = export.run_exported
    monkeypatch.setattr(export, "run_exported", lambda *a: real(*a) + 1.0)  # a broken runtime
    capsys.readouterr()
    assert main(["export", str(ckpt), "--out", str(out), "--check", "--height", "32", "--width", "32"]) == 1
    assert "check failed, nothing written" in capsys.readouterr().err
    assert out.read_bytes() == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    monkeypatch.setattr(export, "run_exported", real)
    assert main(["export", str(ckpt), "--out", str(out), "--check", "--height", "32", "--width", "32"]) == 0
    assert out.read_bytes() != kept
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    # a file export did not write is never replaced, whatever the check would say
    (tmp_path / "mine.onnx").write_bytes(b"the user's file")
    assert main(["export", str(ckpt), "--out", str(tmp_path / "mine.onnx"), "--height", "16", "--width", "16"]) == 1
    assert "was not written by uhrnet export" in capsys.readouterr().err
    assert (tmp_path / "mine.onnx").read_bytes() == b"the user's file"


def test_export_refuses_to_overwrite_a_checkpoint(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    ckpt = write_checkpoint(run / "best.pt", "unet")
    other = write_checkpoint(tmp_path / "other.pt", "unet")
    before = ckpt.read_bytes(), other.read_bytes()
    assert main(["export", str(run), "--out", str(ckpt), "--format", "torchscript", "--height", "16", "--width", "16"]) == 1
    assert main(["export", str(run), "--out", str(other), "--format", "torchscript", "--height", "16", "--width", "16"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "is the checkpoint being exported" in err[0] and "is a uhrnet checkpoint" in err[1]
    assert (ckpt.read_bytes(), other.read_bytes()) == before


@pytest.mark.parametrize("fmt, name, flags, says", [
    ("torchscript", "x.onnx", [], "a .onnx name for --format torchscript"),
    ("onnx", "x.pt", [], "a .pt name for --format onnx"),
    ("onnx", "x.ts", [], "a .ts name for --format onnx"),
    ("reference", "x.onnx", [], "a .onnx name for --format reference"),
    ("torchscript", "x.ts", ["--dynamic"], "--dynamic frees the batch, height and width axes of an ONNX file"),
    ("reference", "x.pth", ["--dynamic"], "it has no effect on --format reference"),
])
def test_export_contradictory_flags_are_usage_errors(tmp_path, capsys, fmt, name, flags, says):
    """A suffix of another format (TorchScript under x.onnx, ONNX under x.pt) or --dynamic where it means nothing:
    one line naming the flag, exit 2, nothing read or written (until stop 67 both were written without a word)."""
    out = tmp_path / name
    assert main(["export", str(tmp_path / "not-read.pt"), "--format", fmt, "--out", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and not out.exists()


def test_export_free_suffixes_are_the_users_choice(tmp_path, capsys):
    """A name of no format's suffix (m.bin) is written as asked."""
    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    for name, fmt in (("m.bin", "onnx"), ("t.bin", "torchscript")):
        assert main(["export", str(ckpt), "--format", fmt, "--out", str(tmp_path / name), "--height", "16",
                     "--width", "16"]) == 0
        assert (tmp_path / name).stat().st_size > 1000


@pytest.mark.parametrize("check", [[], ["--check"]])
def test_export_torchscript_to_a_name_without_suffix(tmp_path, capsys, check):
    """A suffix-less --out (``model``) is written and loads to the checkpoint's outputs; torch once named the
    archive after the temporary name up to its first dot and refused it."""
    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    out = tmp_path / "model"
    assert main(["export", str(ckpt), "--format", "torchscript", "--out", str(out), "--height", "16",
                 "--width", "16", *check]) == 0, capsys.readouterr().err
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.models import prediction_of
    net, _ = model_from_checkpoint(load_checkpoint(ckpt))
    x = torch.rand(1, 1, 16, 16, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        want = prediction_of(net.eval()(x))
        got = torch.jit.load(str(out))(x)
    assert torch.allclose(prediction_of(got), want, atol=1e-4)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".fppsim")) == ["m.pt", "model"]


def test_onnx_runner_errors_name_the_cause(tmp_path):
    from uhrnet.inference.export import export_model, onnx_runner

    with pytest.raises(ExportError, match="no such ONNX file"):
        onnx_runner(tmp_path / "missing.onnx")
    model = build_model("unet", base_channels=4).eval()
    path = export_model(model, tmp_path / "m.onnx", "onnx", (1, 1, 16, 16))
    for bad in (0, -2, 2.5, "two", True):
        with pytest.raises(ExportError, match="threads must be a positive integer"):
            onnx_runner(path, threads=bad)
    pytest.importorskip("openvino")
    from uhrnet.inference.export import run_exported

    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(ExportError) as info:
        run_exported(bad, "onnx", torch.zeros(1, 1, 16, 16), runtime="openvino")
    assert "openvino cannot load it" in str(info.value) and not str(info.value).rstrip().endswith(":)")


@pytest.mark.parametrize("name", ["uhrnet", "unet"])
def test_export_check_under_openvino_agrees_with_onnxruntime(tmp_path, name, capsys):
    """OpenVINO runs the same ONNX file as onnxruntime (an independent runtime) in float32: both agree
    with the checkpoint within the check tolerance (bfloat16 inference, OpenVINO's default on CPUs with
    AVX512-BF16, would not)."""
    pytest.importorskip("openvino")
    pytest.importorskip("onnxruntime")
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.inference.export import onnx_runner

    ckpt = write_checkpoint(tmp_path / "m.pt", name)
    out = tmp_path / f"{name}.onnx"
    assert main(["export", str(ckpt), "--out", str(out), "--check", "--runtime", "openvino",
                 "--height", "32", "--width", "48"]) == 0
    assert "check passed (openvino)" in capsys.readouterr().out
    model, _ = model_from_checkpoint(load_checkpoint(ckpt))
    x = torch.rand(1, 1, 32, 48, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.no_grad():
        expected = model(x)
    ov = torch.from_numpy(onnx_runner(out, "openvino", threads=1)(x.numpy()))
    ort = torch.from_numpy(onnx_runner(out, "onnxruntime", threads=1)(x.numpy()))
    assert rel_err(ov, expected) < 1e-4 and rel_err(ov, ort) < 1e-4


def test_openvino_check_fails_on_a_tampered_export(tmp_path):
    pytest.importorskip("openvino")
    from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
    from uhrnet.inference.export import check_export, export_model

    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    model, _ = model_from_checkpoint(load_checkpoint(ckpt))
    tampered, _ = model_from_checkpoint(load_checkpoint(ckpt))
    with torch.no_grad():
        tampered.net.head.weight[0, 0, 0, 0] += 0.05 * tampered.net.head.weight.abs().max()
    out = export_model(tampered, tmp_path / "t.onnx", "onnx", (1, 1, 32, 32))
    assert not check_export(out, "onnx", model, (1, 1, 32, 32), runtime="openvino")["passed"]
    assert check_export(out, "onnx", tampered, (1, 1, 32, 32), runtime="openvino")["passed"]


def test_export_runtime_user_errors(tmp_path, capsys):
    ckpt = write_checkpoint(tmp_path / "m.pt", "unet")
    out = tmp_path / "m.ts"
    assert main(["export", str(ckpt), "--out", str(out), "--format", "torchscript", "--runtime", "openvino",
                 "--check"]) == 2  # contradictory flags: a usage error (exit 1 until stop 67)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--runtime openvino" in err[0] and not out.exists()
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(ckpt), "--out", str(out), "--runtime", "tensorrt"])
    assert exit_info.value.code == 2


def test_openvino_leaves_the_callers_signal_stack_alone(tmp_path):
    """OpenVINO's CPU plugin installs an alternate signal stack of its own on the compiling thread and may
    free it later: a signal Python then catches (SA_ONSTACK) was delivered onto freed memory and the
    test run died with SIGSEGV. onnx_runner gives the thread its own stack back."""
    pytest.importorskip("openvino")
    import ctypes

    from uhrnet.inference.export import _SignalStack, export_model, keep_signal_stack, onnx_runner

    try:
        sigaltstack = ctypes.CDLL(None, use_errno=True).sigaltstack
    except (OSError, AttributeError):
        pytest.skip("no sigaltstack in this libc")

    def current():
        s = _SignalStack()
        assert sigaltstack(None, ctypes.byref(s)) == 0
        return s.ss_sp, s.ss_flags, s.ss_size

    from uhrnet.models import build_model

    path = export_model(build_model("unet", base_channels=4).eval(), tmp_path / "m.onnx", "onnx", (1, 1, 16, 16))
    mine = ctypes.create_string_buffer(16880)  # faulthandler's size: one the plugin replaces (not just "none")
    before = current()
    try:
        assert sigaltstack(ctypes.byref(_SignalStack(ctypes.addressof(mine), 0, len(mine))), None) == 0
        ours = current()
        run = onnx_runner(path, "openvino")  # the plugin's default threads: it replaced the stack then
        assert current() == ours
        run(np.zeros((1, 1, 16, 16), np.float32))
        assert current() == ours
        with keep_signal_stack():  # what the plugin does, without it: the thread's stack replaced
            other = ctypes.create_string_buffer(1 << 16)
            sigaltstack(ctypes.byref(_SignalStack(ctypes.addressof(other), 0, len(other))), None)
            assert current() != ours
        assert current() == ours
    finally:
        sigaltstack(ctypes.byref(_SignalStack(before[0], before[1], before[2])), None)
    assert current() == before
