"""``uhrnet.scoring.bench.bench(BenchConfig(...))`` (``uhrnet bench``): parameters, forward time, training-step time and peak memory per model.

With ``optimize`` every model is also timed in its deployable forms (batch norms folded; also
channels_last; also torch.compile; the ONNX export under onnxruntime and under OpenVINO), each checked
against the eager output; the fastest torch form is reported as the forward time, the fastest form of
all as ``best_deployable_ms``. The UHRNet / U-Net ratio ``uhrnet_unet_forward_ratio`` is then that of
each model in its fastest deployable form, re-timed in alternating pairs (UHRNet, U-Net, UHRNet, ...)
so that a slow spell of a shared machine falls on both (``uhrnet_unet_torch_ratio``: the torch forms').

For each model at batch 1 (352 x 640 by default): the trainable parameter count, the median forward
time in eval mode without gradient (the paper's "speed"), the median time of one training step (forward,
MSE summed over the model's outputs, backward, Adam step) and the peak memory of each. Finally the
UHRNet / U-Net forward-time ratio, which the paper measured as 0.0224 s / 0.0081 s = 2.77 on an
RTX 2080 Ti. Peak memory is ``torch.cuda.max_memory_allocated`` on CUDA (weights and optimizer state
included) and the growth of the peak resident set size on CPU (roughly: activations and gradients).
"""

from __future__ import annotations

import inspect
import shutil
import tempfile
import gc
import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable
from uhrnet.errors import ConfigError, UsageError
from uhrnet.models import ALIASES, ARCHITECTURES, build_model, count_parameters, list_models, outputs_of, prediction_of
from uhrnet.scoring.timing import peak_memory_bytes, time_call
from uhrnet.inference.deploy import prepare_for_inference
from uhrnet.device import select_device
from fppsim.files import atomic_write_text, check_writable_dir, json_text
from uhrnet.inference.export import export_model, onnx_runner

DEFAULT_MODELS = ("uhrnet", "unet", "model_a", "model_b", "hnet")
REFERENCE_WIDTH = 64  # the default base width of uhrnet and unet, which --base-channels replaces
PAPER_SECONDS = {"uhrnet": 0.0224, "unet": 0.0081}  # RTX 2080 Ti, batch 1, 352 x 640
OPT_VARIANTS = ("fold", "fold_cl", "compile", "onnxruntime", "openvino")
RUNTIME_FORMS = ("onnxruntime", "openvino")  # the ONNX export of fold under each runtime (not torch forms)
OPT_RTOL = 1e-4  # a deployable form must match the eager model within this fraction of the output range
AMP = ("off", "fp16", "bf16")


@dataclass
class BenchConfig:
    """What to measure: model names, input size (multiples of 16), batch, device, timed ``repeats``
    after ``warmup`` calls, autocast dtype (``amp``), memory format, torch.compile, a width override
    (``base_channels``), whether to time a training step, whether to also time the deployable forms
    ``variants`` (``optimize``; see :func:`optimize_variants`), and an optional JSON output path.
    Checks itself: :class:`UsageError` for a value wrong on its own, :class:`ConfigError` for a ``json``
    path it may not write (a folder, or an existing file that is not a report bench wrote)."""

    models: list = field(default_factory=lambda: list(DEFAULT_MODELS))
    height: int = 352
    width: int = 640
    batch_size: int = 1
    device: str = "auto"
    repeats: int = 10
    warmup: int = 3
    amp: str = "off"
    channels_last: bool = False
    compile: bool = False
    base_channels: int | None = None
    train: bool = True
    optimize: bool = False
    variants: list = field(default_factory=lambda: list(OPT_VARIANTS))
    json: str | Path | None = None

    def __post_init__(self):
        unknown = [m for m in self.models if m.lower() not in list_models()]
        if unknown:
            raise UsageError(f"--models {' '.join(unknown)}: unknown; known: {', '.join(list_models())}")
        if self.height % 16 or self.width % 16 or not (16 <= self.height <= 4096 and 16 <= self.width <= 4096):
            raise UsageError(f"--height and --width must be multiples of 16 from 16 to 4096, got "
                             f"{self.height}x{self.width}")
        for flag, value, low in (("--repeats", self.repeats, 1), ("--warmup", self.warmup, 0),
                                 ("--batch-size", self.batch_size, 1)):
            if value < low:
                raise UsageError(f"{flag} must be >= {low}, got {value}")
        if self.base_channels is not None and self.base_channels < 1:
            raise UsageError(f"--base-channels must be >= 1, got {self.base_channels}")
        if self.amp not in AMP:
            raise UsageError(f"--amp {self.amp!r}: choose from {', '.join(AMP)}")
        bad = [v for v in self.variants if v not in OPT_VARIANTS]
        if bad:
            raise UsageError(f"--variants {' '.join(bad)}: choose from {', '.join(OPT_VARIANTS)}")
        if self.compile:
            self.warmup = max(self.warmup, 2)
        if self.json is not None:  # fail now, not after minutes of timing
            path = Path(self.json)
            if path.is_dir():
                raise ConfigError(f"--json {path}: is a folder; give a file name")
            try:
                check_writable_dir(path.parent, "--json")
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
            check_replaceable(path)


REPORT_KEYS = ("device", "input_shape", "results", "uhrnet_unet_forward_ratio")  # in every report bench wrote
MAX_REPORT_BYTES = 64 * 2**20  # a bench report is kilobytes; a larger file is someone else's


def is_bench_report(path: str | Path) -> bool:
    """Is the file ``path`` a report ``uhrnet bench --json`` wrote (a JSON object with :data:`REPORT_KEYS`,
    ``results`` a list)? Reads a file that does not start with ``{`` no further (a checkpoint, say)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_REPORT_BYTES:
            return False
        with open(path, "rb") as fh:
            if fh.read(64).lstrip()[:1] != b"{":
                return False
            fh.seek(0)
            data = json.loads(fh.read().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and all(k in data for k in REPORT_KEYS) and isinstance(data["results"], list)


def check_replaceable(path: str | Path) -> None:
    """Raise :class:`ConfigError` when ``path`` exists and is anything but a report bench wrote: ``--json``
    never replaces a checkpoint, a notes file or another tool's JSON."""
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not (path.is_file() and is_bench_report(path)):
        raise ConfigError(f"--json {path}: exists and is not a report uhrnet bench wrote; move it away or "
                          f"choose another name (bench replaces only its own reports)")


def build_scaled(name: str, base_channels: int | None):
    """``build_model(name)``, with every width scaled by ``base_channels / 64`` when given."""

    if base_channels is None:
        return build_model(name)
    arch, fixed = ALIASES.get(name.lower(), (name.lower(), {}))
    if arch not in ARCHITECTURES:
        return build_model(name)  # raises the registry's ValueError
    default = fixed.get("base_channels", inspect.signature(ARCHITECTURES[arch]).parameters["base_channels"].default)
    scaled = max(1, round(default * base_channels / REFERENCE_WIDTH))
    return build_model(arch, **{**fixed, "base_channels": scaled})


def measure(name: str, args, device, runners: dict | None = None) -> dict:
    """Build one model and measure it; returns a JSON-ready dict. With ``optimize`` and a ``runners``
    dict, the callable of the fastest deployable form is left in it (``{form: callable}``)."""
    import torch


    model = build_scaled(name, args.base_channels).to(device)
    params = count_parameters(model)
    memory_format = torch.channels_last if args.channels_last else torch.contiguous_format
    model = model.to(memory_format=memory_format)
    shape = (args.batch_size, model.config["in_channels"], args.height, args.width)
    x = torch.randn(shape, device=device).contiguous(memory_format=memory_format)
    target = torch.randn((args.batch_size, 1, args.height, args.width), device=device)
    net = torch.compile(model) if args.compile else model
    amp = args.amp

    def autocast():
        if amp == "off":
            return torch.autocast(device.type, enabled=False)
        return torch.autocast(device.type, dtype=torch.float16 if amp == "fp16" else torch.bfloat16)

    def forward():
        with torch.no_grad(), autocast():
            net(x)

    model.eval()
    fwd = time_call(forward, device, args.warmup, args.repeats)
    fwd_peak = peak_memory_bytes(forward, device)
    result = {
        "model": name,
        "base_channels": model.config["base_channels"],
        "parameters": params,
        "forward_ms": 1000 * statistics.median(fwd),
        "forward_peak_bytes": fwd_peak,
        "train_step_ms": None,
        "train_peak_bytes": None,
    }
    if args.optimize:
        with torch.no_grad():
            reference = model(x)
        result["eager_forward_ms"] = result["forward_ms"]
        result["optimized"] = optimize_variants(model, x, reference, args, device, runners)
        torch_forms = {k: v for k, v in result["optimized"].items() if k not in RUNTIME_FORMS and v.get("ok")}
        best = min(torch_forms, key=lambda k: torch_forms[k]["forward_ms"], default=None)
        if best is not None and torch_forms[best]["forward_ms"] < result["forward_ms"]:
            result["forward_ms"] = torch_forms[best]["forward_ms"]
            result["best_form"] = best
        else:
            result["best_form"] = "eager"
        for form in RUNTIME_FORMS:
            v = result["optimized"].get(form, {})
            result[f"{form}_ms"] = v.get("forward_ms") if v.get("ok") else None
        ok = {k: v["forward_ms"] for k, v in result["optimized"].items() if v.get("ok")}
        ok["eager"] = result["eager_forward_ms"]
        result["best_deployable_form"] = min(ok, key=ok.get)
        result["best_deployable_ms"] = ok[result["best_deployable_form"]]
        model = model.to(memory_format=memory_format)
    if args.train:
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)

        def train_step():
            optimizer.zero_grad(set_to_none=True)
            with autocast():
                out = net(x)
                loss = sum(torch.nn.functional.mse_loss(o.float(), target) for o in outputs_of(out))
            loss.backward()
            optimizer.step()

        model.train()
        step = time_call(train_step, device, args.warmup, args.repeats)
        result["train_step_ms"] = 1000 * statistics.median(step)
        result["train_peak_bytes"] = peak_memory_bytes(train_step, device)
        model.eval()
        model.zero_grad(set_to_none=True)
        del optimizer
    if runners is not None and args.optimize:
        # only the fastest form is re-timed (bench's pairs): let the others go now
        best = result["best_deployable_form"]
        kept = forward if best == "eager" else runners[best]  # (every form that passed is in runners)
        runners.clear()
        runners[best] = kept
    return result


def _rel_diff(out, reference) -> float:
    import torch


    out, ref = prediction_of(out), prediction_of(reference)
    span = float(ref.max() - ref.min())
    return float((torch.as_tensor(out).float() - ref.float()).abs().max()) / max(span, 1e-12)


def optimize_variants(model, x, reference, args, device, runners: dict | None = None) -> dict:
    """Time the deployable forms of ``model`` (eval mode) named in ``args.variants`` on ``x``.

    Returns ``{form: {"forward_ms", "max_rel_diff", "ok"}}`` (``max_rel_diff``: max |form - eager| /
    range of the eager output; ``ok`` when within :data:`OPT_RTOL`), or ``{"error": ...}`` for a form
    that cannot be made here (no C++ compiler for torch.compile, no onnxruntime ...). The timed
    callable of each form that passes goes into ``runners`` when given.
    """
    import torch


    out = {}
    for form in args.variants:
        try:
            if form in RUNTIME_FORMS:
                with tempfile.TemporaryDirectory() as tmp:
                    path = export_model(model, f"{tmp}/m.onnx", "onnx", tuple(x.shape))
                    run = onnx_runner(path, form, threads=torch.get_num_threads())
                feed = x.detach().cpu().contiguous().numpy()
                y = torch.from_numpy(run(feed))
                fn = lambda run=run, feed=feed: run(feed)  # noqa: E731  (bound now: the loop rebinds run)
                times = time_call(fn, "cpu", args.warmup, args.repeats)
            else:
                cl = form in ("fold_cl", "compile")
                net = prepare_for_inference(model, channels_last=cl).to(device)
                xin = x.contiguous(memory_format=torch.channels_last if cl else torch.contiguous_format)
                if form == "compile":
                    net = torch.compile(net)

                def fn(net=net, xin=xin):
                    with torch.inference_mode():
                        return net(xin)

                y = fn()
                times = time_call(fn, device, max(args.warmup, 1 if form == "compile" else 0), args.repeats)
            diff = _rel_diff(y.to(reference.device) if hasattr(y, "to") else y, reference)
            out[form] = {"forward_ms": 1000 * statistics.median(times), "max_rel_diff": diff, "ok": diff <= OPT_RTOL}
            if runners is not None and out[form]["ok"]:
                runners[form] = fn
        except Exception as exc:  # a form that cannot be built here is reported, not fatal
            out[form] = {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"}
    return out


def paired_times(a: Callable[[], object], b: Callable[[], object], device, warmup: int = 3, repeats: int = 10) -> dict:
    """Time ``a`` and ``b`` in ``repeats`` alternating pairs (``a, b, a, b, ...``, after ``warmup`` calls
    of each), so that a slow spell of a shared machine slows both alike.

    Returns ``{"a_ms", "b_ms", "ratio", "pair_ratios"}``: the median ms of each, ``a_ms / b_ms`` and the
    ratio within every pair (their spread shows how steady the machine was).
    """
    for fn in (a, b):
        time_call(fn, device, warmup, 1)
    ta, tb = [], []
    for _ in range(repeats):
        ta += time_call(a, device, 0, 1)
        tb += time_call(b, device, 0, 1)
    a_ms, b_ms = 1000 * statistics.median(ta), 1000 * statistics.median(tb)
    return {"a_ms": a_ms, "b_ms": b_ms, "ratio": a_ms / b_ms, "pair_ratios": [x / y for x, y in zip(ta, tb)]}


def _mib(value: int | None) -> str:
    return "n/a" if value is None else f"{value / 2**20:.0f}"


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def format_table(results: list[dict]) -> str:
    header = ("model", "base", "parameters", "forward ms", "train-step ms", "fwd peak MiB", "train peak MiB")
    rows = [
        (
            r["model"],
            str(r["base_channels"]),
            f"{r['parameters']:,}",
            _ms(r["forward_ms"]),
            _ms(r["train_step_ms"]),
            _mib(r["forward_peak_bytes"]),
            _mib(r["train_peak_bytes"]),
        )
        for r in results
    ]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))) for row in [header, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_optimized(results: list[dict]) -> str:
    """One line per model: eager and each deployable form's forward ms (x: failed its check)."""
    lines = ["deployable forms (forward ms; the best torch form is reported above):"]
    for r in results:
        parts = [f"eager {_ms(r.get('eager_forward_ms'))}"]
        for form, v in r.get("optimized", {}).items():
            if "error" in v:
                parts.append(f"{form} n/a ({v['error'][:60]})")
            else:
                parts.append(f"{form} {_ms(v['forward_ms'])}{'' if v['ok'] else ' (x: differs)'}")
        lines.append(f"  {r['model']}: " + ", ".join(parts) + f" -> torch: {r.get('best_form')}, "
                     f"any: {r.get('best_deployable_form')}")
    return "\n".join(lines)


def bench(args: BenchConfig, echo: Callable[[str], None] = print) -> dict:
    """Measure every model of ``args``; ``echo`` gets the progress lines and the final table.
    Returns the report (also written to ``args.json`` when given)."""
    import torch

    device, where = _bench_device(args)
    echo(
        f"uhrnet bench: {where}; input {args.batch_size}x{args.height}x{args.width}; "
        f"median of {args.repeats} after {args.warmup} warm-up; channels_last {'on' if args.channels_last else 'off'}; "
        f"torch.compile {'on' if args.compile else 'off'}"
        + (f"; --optimize: {' '.join(args.variants)}" if args.optimize else ""),
    )
    results, paired = _measure_models(args, device, echo)
    echo(format_table(results))
    if args.optimize:
        echo(format_optimized(results))
    ratio, torch_ratio, best_ratio, runtime_ratios = _forward_ratios(args, results, paired, echo)
    memory_note = (
        "peak memory: torch.cuda.max_memory_allocated (weights, optimizer state and activations)"
        if device.type == "cuda"
        else "peak memory: growth of the process's peak RSS during one call (n/a where /proc does not allow it)"
    )
    echo(memory_note)
    report = {
        "device": where,
        "input_shape": [args.batch_size, 1, args.height, args.width],
        "repeats": args.repeats,
        "warmup": args.warmup,
        "channels_last": args.channels_last,
        "amp": args.amp,
        "batch_size": args.batch_size,
        "compile": args.compile,
        "torch": torch.__version__,
        "results": results,
        "optimize": bool(args.optimize),
        "uhrnet_unet_forward_ratio": ratio,
        "uhrnet_unet_torch_ratio": torch_ratio if args.optimize else ratio,
        "uhrnet_unet_onnxruntime_ratio": runtime_ratios.get("onnxruntime"),
        "uhrnet_unet_openvino_ratio": runtime_ratios.get("openvino"),
        "uhrnet_unet_best_deployable_ratio": best_ratio,
        "best_deployable_pairs": paired,
        "memory": memory_note,
    }
    if args.json is not None:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        check_replaceable(path)  # again: the file may have appeared during the timing
        atomic_write_text(path, json_text(report, indent=2) + "\n")
        echo(f"wrote {path}")
    return report


def _bench_device(args: BenchConfig):
    """The device and its description; drops the compile variant on a CPU without a C++ compiler (inductor
    needs one) and lets cuDNN pick its fastest kernels on CUDA."""
    import torch

    device = select_device(args.device)
    if args.optimize and "compile" in args.variants and device.type == "cpu":
        if shutil.which("g++") is None and shutil.which("c++") is None:
            args.variants = [v for v in args.variants if v != "compile"]  # inductor needs a C++ compiler on CPU
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        where = torch.cuda.get_device_name(device)
    else:
        where = f"cpu, {torch.get_num_threads()} threads"
    return device, where


def _measure_models(args: BenchConfig, device, echo: Callable[[str], None]) -> tuple[list[dict], dict | None]:
    """:func:`measure` of every model in turn (a line each), and with ``optimize`` the UHRNet / U-Net pairs of
    their fastest forms, timed as soon as both exist: before the other models' memory is measured."""
    import torch

    results, runners, paired = [], {}, None
    for name in args.models:
        keep = {} if args.optimize and name.lower() in ("uhrnet", "unet") else None
        if keep is not None:
            runners[name.lower()] = keep
        try:
            results.append(measure(name, args, device, keep))
        except ValueError as exc:
            raise ConfigError(f"{name}: {exc}") from exc
        r = results[-1]
        echo(f"  {name}: forward {_ms(r['forward_ms'])} ms, train step {_ms(r['train_step_ms'])} ms")
        if runners.get("uhrnet") and runners.get("unet"):
            (a,), (b,) = runners["uhrnet"].values(), runners["unet"].values()
            paired = paired_times(a, b, device, args.warmup, args.repeats)
            runners.clear()
        gc.collect()
        if device.type == "cuda":
            torch.cuda.empty_cache()
    runners.clear()
    return results, paired


def _forward_ratios(args: BenchConfig, results: list[dict], paired: dict | None, echo: Callable[[str], None]):
    """The UHRNet / U-Net forward-time ratios, each echoed: (the reported one, the torch forms', the fastest
    deployable forms', {runtime: ratio}). None / empty without both models; without ``optimize`` only the
    first (the torch forms') is set."""
    by_name = {r["model"].lower(): r for r in results}
    ratio = None
    if "uhrnet" in by_name and "unet" in by_name:
        ratio = by_name["uhrnet"]["forward_ms"] / by_name["unet"]["forward_ms"]
        paper = PAPER_SECONDS["uhrnet"] / PAPER_SECONDS["unet"]
        echo(
            f"UHRNet / U-Net forward time{' (fastest torch forms)' if args.optimize else ''}: {ratio:.2f} "
            f"(paper: {PAPER_SECONDS['uhrnet']} s / "
            f"{PAPER_SECONDS['unet']} s = {paper:.2f} on an RTX 2080 Ti)"
        )
    runtime_ratios, best_ratio, torch_ratio = {}, None, None
    if args.optimize and "uhrnet" in by_name and "unet" in by_name:
        u, n = by_name["uhrnet"], by_name["unet"]
        for form in RUNTIME_FORMS:
            a, b = u.get(f"{form}_ms"), n.get(f"{form}_ms")
            runtime_ratios[form] = a / b if a and b else None
            if runtime_ratios[form] is not None:
                echo(f"UHRNet / U-Net forward time under {form}: {runtime_ratios[form]:.2f}")
        torch_ratio = ratio
        best_ratio = ratio = paired["ratio"]  # (timed as soon as both models were measured)
        echo(f"UHRNet / U-Net forward time, each in its fastest deployable form ({u['best_deployable_form']} / "
             f"{n['best_deployable_form']}; {args.repeats} alternating pairs: {paired['a_ms']:.1f} / "
             f"{paired['b_ms']:.1f} ms): {best_ratio:.2f}")
    return ratio, torch_ratio, best_ratio, runtime_ratios
