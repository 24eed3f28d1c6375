"""``uhrnet export``: a checkpoint's model as ONNX or TorchScript, batch norms folded, checked.

The exported model is the checkpoint's network in eval mode, batch norms folded into the convolutions
(:mod:`uhrnet.inference.deploy`), with the label head: input ``fringe`` ``(N, in_channels, H, W)`` float32,
the fringe normalised to [-1, 1] as in training; output ``label`` ``(N, out_channels, H, W)`` float32
in label units (what ``uhrnet predict`` converts to millimetres). H and W must be multiples of 16;
with ``dynamic=True`` the ONNX batch, height and width are free (TorchScript traces are always
shape-generic for these models).

Check (``check=True``): both the exported file (for ONNX: onnxruntime, or OpenVINO with
``runtime="openvino"``; ``torch.jit.load`` for TorchScript) and the checkpoint's unmodified model run a
seeded input (uniform in [-1, 1], seed 0,
batch 1 at the export size); the export passes when ``max |exported - reference| <= CHECK_RTOL *
(max - min of the reference output)``, with ``CHECK_RTOL = 1e-4`` (a floor of 1e-6 on the range).
:func:`export_checkpoint` checks the file under a staging name next to ``out`` and moves it onto
``out`` only when it passes, so a failed check leaves an existing ``out`` as it was.

``format="reference"`` writes the weights for the authors' reference code instead
(:func:`uhrnet.inference.reference_weights.export_reference`: ``{'state_dict': ...}`` for their ``UHRNet()``).
"""

from __future__ import annotations

import ctypes
import io
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fppsim.files import atomic_path, tmp_path, unlink_quietly
from fppsim.owned import claim, output_folder, stamp

from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.inference.deploy import prepare_for_inference
from uhrnet.errors import CheckpointError, ExportError, UsageError
from uhrnet.inference.export_check import CHECK_RTOL, check_input, compare_outputs
from uhrnet.models import prediction_of
from uhrnet.inference.reference_weights import export_reference

FORMATS = ("onnx", "torchscript")
WEIGHT_FORMATS = ("reference",)  # weights for another code base (uhrnet.inference.reference_weights), not a traced graph
EXPORT_FORMATS = FORMATS + WEIGHT_FORMATS
RUNTIMES = ("onnxruntime", "openvino")  # what runs an ONNX file
DEFAULT_OPSET = 17
# torch's TorchScript-based ONNX exporter writes opsets 7-20; each gave the eager output under both
# runtimes for every model here (torch 2.13). Below 7 it writes files onnxruntime rejects.
OPSET_RANGE = (7, 20)
SUFFIXES = {"onnx": ".onnx", "torchscript": ".pt"}
# the file suffixes each --format writes under; a suffix of another format only (x.onnx with torchscript, x.pt
# with onnx) is refused, any other name (m.bin, a name without suffix) is the user's choice
FORMAT_SUFFIXES = {"onnx": (".onnx",), "torchscript": (".pt", ".pth", ".ts", ".zip"), "reference": (".pth", ".pt")}
EXPORT_TOOL = "uhrnet export"
MAX_SIDE = 4096  # px: a check input larger than a camera is a typo (and memory a machine lacks)


@dataclass
class ExportConfig:
    checkpoint: Path
    out: Path
    format: str = "onnx"
    height: int = 352
    width: int = 640
    opset: int = DEFAULT_OPSET
    dynamic: bool = False
    check: bool = False
    optimize: bool = True
    runtime: str = "onnxruntime"

    def __post_init__(self):
        h, w = self.height, self.width
        if h % 16 or w % 16 or not (16 <= h <= MAX_SIDE and 16 <= w <= MAX_SIDE):
            raise UsageError(f"--height and --width must be multiples of 16 from 16 to {MAX_SIDE}, got {h}x{w}")
        lo, hi = OPSET_RANGE
        if self.format == "onnx" and not lo <= self.opset <= hi:
            raise UsageError(f"--opset must be between {lo} and {hi}, got {self.opset}")
        if self.format not in EXPORT_FORMATS:
            raise ExportError(f"unknown format {self.format!r}; choose from {', '.join(EXPORT_FORMATS)}")
        if self.runtime not in RUNTIMES:
            raise ExportError(f"unknown runtime {self.runtime!r}; choose from {', '.join(RUNTIMES)}")
        if self.runtime != "onnxruntime" and self.format != "onnx":
            raise UsageError(f"--runtime {self.runtime} runs ONNX files; it does not apply to --format {self.format}")
        if self.dynamic and self.format != "onnx":
            raise UsageError(f"--dynamic frees the batch, height and width axes of an ONNX file; it has no effect on "
                             f"--format {self.format}: leave it out")
        suffix = Path(self.out).suffix.lower()
        others = {s for f, ss in FORMAT_SUFFIXES.items() if f != self.format for s in ss}
        if suffix in others and suffix not in FORMAT_SUFFIXES[self.format]:
            raise UsageError(f"--out {self.out}: a {suffix} name for --format {self.format}; name it "
                             f"{' or '.join(FORMAT_SUFFIXES[self.format])} (or give the --format that writes {suffix})")


def deployable(model: nn.Module) -> nn.Module:
    """``model`` (e.g. a LabelHead) with batch norms folded, eval mode.

    UHRNet's blocks are not merged (the removed ``MergedMultiLevelConvBlock``): onnxruntime runs
    convolutions in a blocked channel layout (NCHWc) and fuses a following residual add and LeakyReLU
    into them, but the merged block's channel splits force a layout conversion around every
    convolution (97 reorder nodes in UHRNet against 34 unmerged); torch runs them slower too.
    """

    return prepare_for_inference(model)


def export_model(
    model: nn.Module,
    out: str | Path,
    format: str = "onnx",
    input_shape: tuple[int, int, int, int] = (1, 1, 352, 640),
    opset: int = DEFAULT_OPSET,
    dynamic: bool = False,
    optimize: bool = True,
) -> Path:
    """Write ``model`` (eval mode, single-tensor output) to ``out`` as ONNX or TorchScript.

    ``optimize``: fold batch norms first (same function). The file is written
    next to ``out`` under a temporary name and renamed, so an existing file is replaced only by a
    complete export. Returns ``out``.
    """
    if format not in FORMATS:
        raise ExportError(f"unknown format {format!r}; choose from {', '.join(FORMATS)}")
    n, c, h, w = input_shape
    if h % 16 or w % 16 or h < 16 or w < 16:
        raise ExportError(f"height and width must be positive multiples of 16, got {h}x{w}")
    model = model.eval()
    net = deployable(model) if optimize else model
    x = check_input(c, h, w).expand(n, c, h, w).contiguous()
    param = next(net.parameters(), None)
    if param is not None:  # trace on the model's device (uhrnet bench --device cuda --optimize)
        x = x.to(param.device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(out) as tmp, warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # tracer notes on the shape check, legacy-exporter notice
            if format == "onnx":
                axes = {"fringe": {0: "batch", 2: "height", 3: "width"},
                        "label": {0: "batch", 2: "height", 3: "width"}} if dynamic else None
                torch.onnx.export(net, (x,), str(tmp), dynamo=False, opset_version=opset,
                                  input_names=["fringe"], output_names=["label"], dynamic_axes=axes,
                                  do_constant_folding=True)
            else:
                traced = torch.jit.trace(net, (x,), check_trace=False)
                traced = torch.jit.freeze(traced)
                # through memory: torch names the archive's records after the file name up to its last dot,
                # which for the temporary name of a suffix-less --out (.fppsim-tmp-PID-model) is empty
                buffer = io.BytesIO()
                torch.jit.save(traced, buffer)
                tmp.write_bytes(buffer.getvalue())
    except ExportError:
        raise
    except Exception as exc:
        raise ExportError(f"{out}: {format} export failed ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
    return out


def _threads(threads) -> int | None:
    if threads is None:
        return None
    try:
        n = int(threads)
        whole = not isinstance(threads, bool) and float(threads) == n
    except (TypeError, ValueError):
        n, whole = 0, False
    if n < 1 or not whole:
        raise ExportError(f"threads must be a positive integer, got {threads!r}")
    return n


def _last_line(exc: Exception) -> str:
    """OpenVINO puts the source location first and the cause last: keep the last non-empty line."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[-1][:200] if lines else "no details"


class _SignalStack(ctypes.Structure):
    _fields_ = [("ss_sp", ctypes.c_void_p), ("ss_flags", ctypes.c_int), ("ss_size", ctypes.c_size_t)]


@contextmanager
def keep_signal_stack():
    """Restore the calling thread's alternate signal stack (``sigaltstack``) on leaving.

    OpenVINO's CPU plugin (2026.4) installs an alternate signal stack of its own on the thread that
    compiles a model, in memory it may later release. Python installs its signal handlers with
    ``SA_ONSTACK``, so a signal caught after that (torch's DataLoader catches SIGCHLD, for instance) could
    be delivered onto freed memory and the kernel kills the process with SIGSEGV; this thread keeps its
    own stack instead (faulthandler's, or none). A no-op where libc has no ``sigaltstack``.
    """
    try:
        sigaltstack = ctypes.CDLL(None, use_errno=True).sigaltstack
    except (OSError, AttributeError, TypeError):  # TypeError: Windows' CDLL wants a name
        yield
        return
    old = _SignalStack()
    saved = sigaltstack(None, ctypes.byref(old)) == 0
    try:
        yield
    finally:
        if saved and sigaltstack(ctypes.byref(old), None) != 0:
            warnings.warn(f"could not restore this thread's signal stack after OpenVINO "
                          f"(errno {ctypes.get_errno()}): a later signal may crash the process", RuntimeWarning,
                          stacklevel=3)


def onnx_runner(path: str | Path, runtime: str = "onnxruntime", threads: int | None = None):
    """A function ``run(x: np.ndarray float32 (N, C, H, W)) -> np.ndarray`` that runs the ONNX file
    ``path`` on the CPU under ``runtime``: ``"onnxruntime"`` or ``"openvino"`` (its CPU plugin, in
    float32: on CPUs with AVX512-BF16 or AMX OpenVINO would otherwise compute in bfloat16, a different
    function; latency mode, one stream). ``threads``: intra-op threads (default: the runtime's own).
    Raises :class:`ExportError` when the runtime is not installed or cannot load the file."""
    path = Path(path)
    if runtime not in RUNTIMES:
        raise ExportError(f"unknown runtime {runtime!r}; choose from {', '.join(RUNTIMES)}")
    threads = _threads(threads)
    if not path.is_file():
        raise ExportError(f"{path}: no such ONNX file")
    if runtime == "onnxruntime":
        try:
            import onnxruntime as ort
        except ImportError:
            raise ExportError("running an ONNX export needs onnxruntime (pip install onnxruntime)") from None
        try:
            opts = ort.SessionOptions()
            if threads:
                opts.intra_op_num_threads = threads
            session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:
            raise ExportError(f"{path}: onnxruntime cannot load it ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
        name = session.get_inputs()[0].name
        return lambda x: session.run(None, {name: np.ascontiguousarray(x, dtype=np.float32)})[0]
    try:
        import openvino as ov
    except ImportError:
        raise ExportError("running an ONNX export under OpenVINO needs openvino (pip install openvino)") from None
    config = {"INFERENCE_PRECISION_HINT": "f32", "PERFORMANCE_HINT": "LATENCY"}
    if threads:
        config["INFERENCE_NUM_THREADS"] = str(threads)
    try:
        with keep_signal_stack():
            request = ov.Core().compile_model(str(path), "CPU", config).create_infer_request()
    except Exception as exc:
        raise ExportError(f"{path}: openvino cannot load it ({type(exc).__name__}: {_last_line(exc)})") from None

    def run(x):
        request.infer({0: np.ascontiguousarray(x, dtype=np.float32)})
        return request.get_output_tensor(0).data.copy()

    return run


def run_exported(path: str | Path, format: str, x: torch.Tensor, runtime: str = "onnxruntime") -> np.ndarray:
    """Run an exported file on ``x`` (ONNX: :func:`onnx_runner` with ``runtime``; TorchScript: ``torch.jit.load``)."""
    path = Path(path)
    if format == "onnx":
        run = onnx_runner(path, runtime)
        try:
            return run(x.numpy())
        except Exception as exc:
            raise ExportError(f"{path}: {runtime} cannot run it ({type(exc).__name__}: {_last_line(exc)})") from None
    try:
        module = torch.jit.load(str(path), map_location="cpu")
        with torch.no_grad():
            return module(x).numpy()
    except Exception as exc:
        raise ExportError(f"{path}: torch.jit.load cannot run it ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None


def check_export(path: str | Path, format: str, reference: nn.Module, input_shape: tuple[int, int, int, int],
                 rtol: float = CHECK_RTOL, runtime: str = "onnxruntime") -> dict:
    """Compare the exported file (an ONNX file run under ``runtime``) with ``reference`` on the seeded
    check input.

    Returns ``{"max_abs_diff", "output_range", "tolerance", "passed"}``; tolerance is
    ``rtol * max(output range, 1e-6)``.
    """
    n, c, h, w = input_shape
    x = check_input(c, h, w).expand(n, c, h, w).contiguous()
    with torch.no_grad():
        ref = reference.eval()(x)
    ref = prediction_of(ref).float().numpy()
    got = run_exported(path, format, x, runtime)
    if got.shape != ref.shape:
        return {"max_abs_diff": float("inf"), "output_range": float(np.ptp(ref)), "tolerance": 0.0, "passed": False,
                "shape": list(got.shape)}
    return compare_outputs(got, ref, rtol)


def export_checkpoint(config: ExportConfig) -> dict:
    """Export a checkpoint (file or run folder) as ``config`` says; with ``config.check``, raise
    :class:`ExportError` when the export differs from the checkpoint's model beyond the tolerance.
    Returns a summary dict (path, format, check result)."""

    ckpt = load_checkpoint(config.checkpoint)
    out = Path(config.out)
    if out.is_dir():
        raise ExportError(f"--out {out}: is a folder; give the file to write (e.g. {out / ('model' + SUFFIXES.get(config.format, '.pth'))})")
    if out.exists() and out.resolve() == Path(ckpt["path"]).resolve():
        raise ExportError(f"{out}: is the checkpoint being exported; choose another --out")
    if out.is_file() and _is_checkpoint(out):
        raise ExportError(f"{out}: is a uhrnet checkpoint; choose another --out (an export would replace it)")
    # the folder is locked and --out claimed for export before anything is written: an existing file is
    # replaced only when an earlier export wrote it (fppsim.owned), never someone's weights or notes
    with output_folder(out.parent, EXPORT_TOOL, error=ExportError):
        claim(out.parent, EXPORT_TOOL, [out.name], hint="choose another --out (export never replaces a file it "
                                                         "did not write)")
        summary = _export(ckpt, out, config)
        stamp(out.parent, [out.name])  # a later export refuses the file if someone changes it meanwhile
        return summary


def _export(ckpt: dict, out: Path, config: ExportConfig) -> dict:
    if config.format in WEIGHT_FORMATS:
        return export_reference(ckpt, out, config.check, (1, 1, config.height, config.width))
    model, _ = model_from_checkpoint(ckpt)
    in_channels = int(ckpt["model"]["config"].get("in_channels", 1))
    shape = (1, in_channels, config.height, config.width)
    summary = {"path": str(out), "format": config.format, "model": ckpt["model"]["config"].get("name"),
               "input_shape": list(shape), "check": None, "runtime": config.runtime if config.format == "onnx" else None}
    if not config.check:
        export_model(model, out, config.format, shape, config.opset, config.dynamic, config.optimize)
        return summary
    # Export to this process's temporary sibling of --out, named with the format's suffix (OpenVINO picks
    # its reader by it), check that file, and only then move it onto --out: a failed check leaves --out
    # as it was.
    stage = tmp_path(out.with_suffix(SUFFIXES[config.format]))
    try:
        export_model(model, stage, config.format, shape, config.opset, config.dynamic, config.optimize)
        result = check_export(stage, config.format, model, shape, runtime=config.runtime)
        summary["check"] = result
        if not result["passed"]:
            raise ExportError(
                f"{out}: check failed, nothing written: max |exported - checkpoint| = {result['max_abs_diff']:.3g} > "
                f"{result['tolerance']:.3g} (= {CHECK_RTOL:g} x output range {result['output_range']:.3g})"
            )
        stage.replace(out)
    finally:
        unlink_quietly(stage)
    return summary


def _is_checkpoint(path: Path) -> bool:

    if path.suffix.lower() == ".onnx":
        return False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's note on TorchScript archives
            load_checkpoint(path)
    except (CheckpointError, OSError):
        return False
    return True


# --------------------------------------------------------------------------------------------------
# CLI
