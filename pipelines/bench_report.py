#!/usr/bin/env python
"""Collect benchmark JSON files from a folder into one Markdown page.

Reads every ``*.json`` in FOLDER (written by ``uhrnet bench --json``, ``pipelines/bench_uhrnet.py``,
``pipelines/bench_generate.py --json`` and ``pipelines/gpu_bench.sh``) and writes a page with the
machine (CPU model, cores, torch version), the date and one table per kind of benchmark.

    python pipelines/bench_report.py FOLDER [--out docs/BENCHMARKS.md] [--note "free text"]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import sys
from pathlib import Path


def machine() -> dict:
    """CPU model, logical cores, Python and torch versions of this machine."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import torch

        torch_version = torch.__version__
    except ImportError:
        torch_version = "not installed"
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "torch": torch_version}


def _f(v, fmt="{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def kind(data: dict) -> str:
    if isinstance(data.get("results"), list) and "uhrnet_unet_forward_ratio" in data:
        return "uhrnet_bench"
    if "cost_over_floor" in data:
        return "generate"
    if data.get("kind") == "gpu_bench":
        return "gpu"
    return "other"


def uhrnet_rows(name: str, data: dict) -> list[str]:
    rows = []
    shape = "x".join(str(s) for s in data.get("input_shape", []))
    for r in data["results"]:
        rows.append(
            f"| {name} | {data.get('device', '?')} | {shape} | {r['model']} | {r['base_channels']} | "
            f"{r['parameters']:,} | {_f(r.get('eager_forward_ms', r['forward_ms']))} | {_f(r['forward_ms'])} | "
            f"{r.get('best_form', 'eager')} | {_f(r.get('onnxruntime_ms'))} | {_f(r.get('openvino_ms'))} | "
            f"{_f(r.get('best_deployable_ms'))} ({r.get('best_deployable_form', '-')}) | {_f(r.get('train_step_ms'))} |"
        )
    # the torch forms' ratio (older files: the forward ratio, which was that); the best column is the
    # ratio of the fastest forms of all, re-timed in alternating pairs by newer benches
    ratio = data.get("uhrnet_unet_torch_ratio", data.get("uhrnet_unet_forward_ratio"))
    ort = data.get("uhrnet_unet_onnxruntime_ratio")
    ov = data.get("uhrnet_unet_openvino_ratio")
    best = data.get("uhrnet_unet_best_deployable_ratio")
    rows.append(f"| {name} | | | **UHRNet / U-Net** | | | | **{_f(ratio, '{:.2f}')}** | | "
                f"{_f(ort, '{:.2f}')} | {_f(ov, '{:.2f}')} | **{_f(best, '{:.2f}')}** | |")
    return rows


def render(folder: Path, note: str | None = None) -> str:
    files = sorted(folder.glob("*.json"))
    m = machine()
    lines = [
        "# Benchmarks",
        "",
        f"Collected by `python pipelines/bench_report.py {folder}` on {dt.date.today().isoformat()}.",
        "",
        f"Machine: {m['cpu']}, {m['cores']} logical cores; Python {m['python']}, torch {m['torch']}.",
        "",
    ]
    if note:
        lines += [note, ""]
    groups: dict[str, list[tuple[str, dict]]] = {}
    for f in files:
        try:
            data = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            print(f"bench_report: skipping {f}: {exc}", file=sys.stderr)
            continue
        if isinstance(data, dict):
            groups.setdefault(kind(data), []).append((f.stem, data))
    if "uhrnet_bench" in groups:
        lines += [
            "## uhrnet bench (forward time per image, median)",
            "",
            "`best ms` is the fastest deployable torch form (`--optimize`: batch norms folded; + channels_last; "
            "+ torch.compile), each checked to match the eager model within 1e-4 of the "
            "output range; `onnxruntime ms` / `openvino ms` run the folded ONNX export (OpenVINO in float32); "
            "`fastest ms` is the fastest of all forms.",
            "",
            "| file | device | input | model | base | parameters | eager ms | best ms | best form | onnxruntime ms "
            "| openvino ms | fastest ms (form) | train step ms |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, data in groups["uhrnet_bench"]:
            lines += uhrnet_rows(name, data)
        lines.append("")
    if "generate" in groups:
        lines += ["## fppsim generator", "", "| file | mesh | psp | write | ms/sample | samples/s | x floor |",
                  "|---|---|---|---|---|---|---|"]
        for name, d in groups["generate"]:
            lines.append(f"| {name} | {Path(str(d.get('mesh', '?'))).name} | {d.get('psp')} | {d.get('write')} | "
                         f"{_f(1000 * d['sample_s_median'])} | {_f(d.get('samples_per_s'), '{:.2f}')} | "
                         f"{_f(d['cost_over_floor'], '{:.2f}')} |")
        lines.append("")
    if "gpu" in groups:
        lines += ["## GPU (pipelines/gpu_bench.sh)", "", "| file | step | result |", "|---|---|---|"]
        for name, d in groups["gpu"]:
            lines.append(f"| {name} | device | {d.get('device', '?')} |")
            for step, value in d.get("steps", {}).items():
                lines.append(f"| {name} | {step} | {json.dumps(value, sort_keys=True)[:300]} |")
        lines.append("")
    else:
        lines += ["## GPU", "", "Not run: no GPU was available where these numbers were taken "
                  "(`bash pipelines/gpu_bench.sh OUTDIR` measures one).", ""]
    if "other" in groups:
        lines += ["## Other JSON files", ""] + [f"- `{n}`" for n, _ in groups["other"]] + [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", type=Path, help="folder of benchmark JSON files")
    p.add_argument("--out", type=Path, default=None, help="Markdown file to write (default: print)")
    p.add_argument("--note", default=None, help="a paragraph to put under the machine line")
    args = p.parse_args(argv)
    if not args.folder.is_dir():
        print(f"bench_report: not a folder: {args.folder}", file=sys.stderr)
        return 2
    page = render(args.folder, args.note)
    if args.out is None:
        print(page)
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(f".{args.out.name}.tmp")
        tmp.write_text(page + "\n")
        tmp.replace(args.out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
