#!/usr/bin/env python
"""Helpers of pipelines/gpu_check.sh (standard library, pip's tag parser, the project's ownership record;
``report`` reads the sample count with numpy and the run's history through :mod:`uhrnet.run_folder`, no torch).

    python pipelines/gpu_check.py begin OUT                     OUT made ready for a run (below), or one line, exit 2
    python pipelines/gpu_check.py settle OUT                    record what this run wrote under OUT/work
    python pipelines/gpu_check.py guard OUT LIMIT CMD...        CMD in its own process group, stopped after LIMIT s,
                                                                on SIGINT/SIGTERM, or when the script dies (kill -9)
    python pipelines/gpu_check.py wheels DIR                    the carried wheels this Python can install
    python pipelines/gpu_check.py env OUT BUDGET TINY PLATFORM  OUT/step_env.json: machine, versions, sizes
    python pipelines/gpu_check.py step OUT NAME RC START LIMIT  OUT/step_NAME.json: exit code, seconds
    python pipelines/gpu_check.py report OUT                    OUT/gpu_check.json + OUT/gpu_check.md

What is the script's own in OUT: the ownership record ``OUT/.fppsim-owned.json`` (:mod:`fppsim.owned`),
beside the ``OUT/.gpu_check`` marker. ``begin`` claims the fixed names the run writes (:data:`FILES`) and the
folders its steps fill (:data:`TREES`, recorded as being written: everything in them was made by the run,
since each is refused when it exists and is not the script's) before anything is written; ``settle`` (at the
end of the run, and when it is stopped) replaces each such folder's claim by the list of what is in it. A
re-run removes exactly the recorded paths (and what a killed run left in the folders it was writing), and
leaves everything else in OUT alone, at any depth; a path it has to write that exists and is not its own is
refused in one line naming it, before anything is removed or written.

A run stopped uncleanly (the script killed with -9: no ``settle``) leaves folders recorded as being written.
The steps die with the script (``guard``: the parent-death signal, forwarded to the step's process group), and
the marker says when the run claimed them (its JSON ``claimed``) and when it was last alive (its mtime, touched
by ``guard`` every second and when the step has stopped). A re-run takes as the stopped run's only the paths in
those folders whose inode changed (ctime) between the two; anything newer, or any file at all where the times
are unknown (a marker of an earlier version), is refused in one line naming it: never deleted.
"""

from __future__ import annotations

import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # fppsim from the checkout (run as a script)

from fppsim.files import json_text  # noqa: E402

PAPER_MS = {"uhrnet": 22.4, "unet": 8.1, "hnet": None}  # Table 3 of the paper, an RTX 2080 Ti


TOOL = "pipelines/gpu_check.sh"
WRITING = TOOL + " (folder being written)"  # a TREES entry of a run that has not settled: all of it is the run's
MARKER = ".gpu_check"
STEPS = ("speed", "study", "forward_fp32", "forward_fp16", "generate", "train", "ddp", "sim2real")
STUDY_FILES = ("study.json", "study_table.md", "study_samples.png", "study_steps.png")  # scaling.py --ledger's
FILES = (MARKER, "setup.log", "step_env.json", *(f"{s}.log" for s in STEPS), *(f"step_{s}.json" for s in STEPS),
         "forward_fp32.json", "forward_fp16.json", "speed.json", "gpu_check.json", "gpu_check.md", *STUDY_FILES)  # fixed names
TREES = ("work/site", "work/x11", "work/speed", "work/study", "work/syn", "work/run", "work/ddp", "work/s2r")  # steps fill these
HEARTBEAT_S = 1.0  # how often guard marks the run alive (the marker's mtime)
GRACE_S = 10.0     # a stopped step's time to exit after SIGINT/SIGTERM before SIGKILL
SLACK_S = 1.0      # coarse file-system clocks: a path's ctime may read this much before the claim


class Refused(Exception):
    """OUT cannot be used as it is (one line naming the path)."""


def _exists(p: Path) -> bool:
    return p.exists() or p.is_symlink()


def _walk(top: Path) -> list[str]:
    """Every path under ``top`` (files, folders, links; links never followed), relative to ``top``, parents first."""
    found = []
    for d, dirs, files in os.walk(top):
        rel = Path(d).relative_to(top)
        found += [str(rel / n) for n in sorted(dirs) + sorted(files)]
        dirs[:] = [n for n in dirs if not os.path.islink(os.path.join(d, n))]
    return found


def _run_times(out: Path) -> tuple[float, float] | None:
    """(claimed, last alive) of the run that wrote the marker, or None where unknown (an earlier version's)."""
    try:
        claimed = float(json.loads((out / MARKER).read_text())["claimed"])
        return claimed, (out / MARKER).stat().st_mtime
    except (OSError, ValueError, TypeError, KeyError):
        return None


def heartbeat(out: Path) -> None:
    """The run is alive now (the marker's mtime: what a re-run after an unclean stop takes as its end)."""
    try:
        os.utime(out / MARKER)
    except OSError:
        pass


def _own(out: Path, record: dict[str, str]) -> set[str]:
    """The paths in ``out`` that are the script's: recorded ones, and in each folder a stopped run was writing
    what changed while it ran (module docstring); :class:`Refused` for a file there it cannot vouch for."""
    own = {n for n, t in record.items() if t in (TOOL, WRITING)}
    writing = [n for n, t in record.items() if t == WRITING]
    times = _run_times(out) if writing else None
    for tree in writing:
        top = out / tree
        if not top.is_dir() or top.is_symlink():
            continue
        for rel in _walk(top):
            p = top / rel
            if p.is_dir() and not p.is_symlink():
                own.add(f"{tree}/{rel}")  # a folder goes only when nothing else is left in it
                continue
            if times is None:
                raise Refused(f"{top}: a stopped run was writing it and when it stopped is not known ({rel} may be "
                              "someone's): move it away or give another OUTDIR")
            ctime = p.lstat().st_ctime
            if not times[0] - SLACK_S <= ctime <= times[1]:
                raise Refused(f"{p} changed after the stopped run that was writing {top} ended: move it away or "
                              "give another OUTDIR")
            own.add(f"{tree}/{rel}")
    return own


def _remove(out: Path, names: set[str]) -> None:
    """Delete the paths ``names`` (relative to ``out``) that exist: files and links, then the folders they
    leave empty (deepest first; a folder holding anything else stays)."""
    folders = []
    for n in names:
        p = out / n
        if p.is_symlink() or p.is_file():
            p.unlink()
        elif p.is_dir():
            folders.append(p)
    for p in sorted(folders, key=lambda f: -len(f.parts)):
        try:
            p.rmdir()
        except OSError:
            pass


def begin(out: Path) -> None:
    """Make ``out`` ready for a run: refuse (:class:`Refused`) before touching anything when it is not a folder,
    holds files but no marker (someone else's folder), or holds a path the run writes that is not the
    script's; else remove the earlier run's own files, claim this run's (module docstring), write the marker."""
    from fppsim.files import atomic_write_text, clean_stale_tmp
    from fppsim.owned import RECORD, ForeignFiles, owners

    if _exists(out) and not out.is_dir():
        raise Refused(f"{out} exists and is not a folder: give a new or empty OUTDIR")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise Refused(f"{out} holds files this script did not write: give a new or empty OUTDIR")
    try:
        record = owners(out) if out.is_dir() else {}
    except ForeignFiles as exc:
        raise Refused(str(exc).replace("choose another --out", "give another OUTDIR")) from None
    if record is None:  # a marker from before the record: the fixed names are the ones that run wrote
        record = {n: TOOL for n in FILES if (out / n).is_file() and not (out / n).is_symlink()}
    own = _own(out, record)
    if out.is_dir() and not os.access(out, os.W_OK | os.X_OK):
        raise Refused(f"{out}: cannot write there (Permission denied)")
    for name in FILES + ("work",) + TREES:
        p = out / name
        if not _exists(p) or name in own:
            if name in TREES and p.is_dir() and not p.is_symlink():
                for rel in _walk(p):
                    if f"{name}/{rel}" not in own:
                        raise Refused(f"{p / rel} exists and was not written by {TOOL}: move it away or give "
                                      "another OUTDIR")
            continue
        if name == "work" and p.is_dir() and not p.is_symlink():
            continue  # OUT/work may hold other files (they stay); the script writes only in its TREES there
        raise Refused(f"{p} exists and was not written by {TOOL}: move it away or give another OUTDIR")
    existed = out.is_dir()
    try:
        _remove(out, own - {"work"})
    except OSError as exc:
        raise Refused(f"{exc.filename or out}: cannot write there ({exc.strerror})") from None
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise Refused(f"{out}: cannot create the folder ({exc.strerror})") from None
    try:
        made_work = not (out / "work").is_dir()
        (out / "work").mkdir(exist_ok=True)
    except OSError as exc:
        raise Refused(f"{out if existed else out / 'work'}: cannot write there ({exc.strerror})") from None
    clean_stale_tmp(out)  # temp files of a killed step's writers (.fppsim-tmp-<dead pid>-<name>)
    kept = {n: t for n, t in record.items() if t not in (TOOL, WRITING) or n == "work" and _exists(out / n)}
    if made_work:
        kept["work"] = TOOL
    claimed = time.time()  # before the folders are claimed: every path a step writes there changes later
    try:
        atomic_write_text(out / RECORD, json_text({"files": dict(sorted({**kept, **{n: TOOL for n in FILES},
                                                                          **{t: WRITING for t in TREES}}.items()))},
                                                   indent=1))
        (out / MARKER).write_text(json_text({"claimed": claimed}) + "\n")
    except OSError as exc:
        raise Refused(f"{out}: cannot write there ({exc.strerror})") from None


def settle(out: Path) -> dict[str, str]:
    """Replace the claim of each folder the run was writing by its contents (the paths in it now), and drop
    claims of names the run never wrote; returns the record."""
    from fppsim.files import atomic_write_text
    from fppsim.owned import RECORD, owners

    record = owners(out) or {}
    new = {}
    for name, tool in record.items():
        if tool == WRITING:
            if (out / name).is_dir() and not (out / name).is_symlink():
                new[name] = TOOL
                new.update({f"{name}/{rel}": TOOL for rel in _walk(out / name)})
        elif tool != TOOL or _exists(out / name):
            new[name] = tool
    atomic_write_text(out / RECORD, json_text({"files": dict(sorted(new.items()))}, indent=1))
    return new


def _pdeathsig(sig: int) -> None:
    """Linux: this process gets ``sig`` when its parent dies (kept across exec)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(sig), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # elsewhere: guard still notices an orphaning within HEARTBEAT_S (its parent pid changes)


def _killpg(proc: subprocess.Popen, sig: int) -> None:
    for kill in (lambda: os.killpg(proc.pid, sig), lambda: proc.send_signal(sig)):
        try:
            kill()
            return
        except (ProcessLookupError, PermissionError):
            pass


def guard(out: Path, limit: float, cmd: list[str]) -> int:
    """Run ``cmd`` as a step of the script (its parent) and return its exit status: in a process group of its
    own, stopped (SIGTERM, SIGKILL ``GRACE_S`` later) after ``limit`` seconds (124, like ``timeout``), or with
    the signal this process gets (SIGINT/SIGTERM/SIGHUP: 128 + it), and when the script dies, even by
    SIGKILL (the parent-death signal). Meanwhile the run is marked alive (:func:`heartbeat`); a step stopped
    because the script died is settled here (the script's own settle never runs)."""
    parent = os.getppid()
    _pdeathsig(signal.SIGTERM)
    got: list[int] = []
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, lambda signum, _frame: got.append(signum))
    if os.getppid() != parent:  # the script died before the parent-death signal was set
        return 143

    def child() -> None:
        os.setpgid(0, 0)  # the script's signals reach the step only through this guard, once
        _pdeathsig(signal.SIGTERM)  # this guard killed with the script's process group: the step still stops
        for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(s, signal.SIG_DFL)

    try:
        proc = subprocess.Popen(cmd, preexec_fn=child)
    except OSError as exc:
        print(f"gpu_check: {cmd[0]}: {exc.strerror}", file=sys.stderr)
        return 127
    deadline = time.monotonic() + limit
    stop = None  # the signal the step was stopped with
    timed_out = killed = False
    kill_at = beat = 0.0
    while True:
        try:
            rc = proc.wait(timeout=0.2)
            break
        except subprocess.TimeoutExpired:
            pass
        now = time.monotonic()
        orphaned = os.getppid() != parent
        if stop is None and (got or orphaned or now >= deadline):
            stop = got[0] if got else signal.SIGTERM
            timed_out = not got and not orphaned
            _killpg(proc, stop)
            kill_at = now + GRACE_S
        elif stop is not None and not killed and now >= kill_at:
            _killpg(proc, signal.SIGKILL)
            killed = True
        if now - beat >= HEARTBEAT_S:
            heartbeat(out)
            beat = now
    if stop is not None:
        _killpg(proc, signal.SIGKILL)  # what the step started and left behind in its group
    heartbeat(out)  # the step has stopped: the run's last moment, if the script is gone
    if os.getppid() != parent:
        try:
            settle(out)
        except Exception:  # noqa: BLE001 -- a re-run still goes by the marker's times
            pass
    if timed_out:
        return 137 if killed else 124
    if stop is not None:
        return 128 + stop
    return rc if rc >= 0 else 128 - rc


def wheels(folder: Path) -> list[str]:
    """The newest wheel per project in ``folder`` whose tags this interpreter supports (pip refuses a whole
    install over one foreign wheel, and .whl/ holds wheels for two Pythons)."""
    from pip._vendor.packaging.tags import sys_tags
    from pip._vendor.packaging.utils import parse_wheel_filename

    supported = list(sys_tags())
    rank = {t: i for i, t in enumerate(supported)}
    best: dict[str, tuple[int, Path]] = {}
    for f in sorted(folder.glob("*.whl")):
        name, _, _, tags = parse_wheel_filename(f.name)
        r = min((rank[t] for t in tags if t in rank), default=None)
        if r is not None and (name not in best or r < best[name][0]):
            best[name] = (r, f)
    return [str(p) for _, p in sorted(best.values(), key=lambda rp: str(rp[1]))]


def _json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def env(out: Path, budget: str, tiny: str, gl: str) -> dict:
    import torch

    cuda = torch.cuda.is_available()
    info = {"device": torch.cuda.get_device_name(0) if cuda else "cpu (no CUDA device)", "torch": torch.__version__,
            "cuda": torch.version.cuda, "python": platform.python_version(), "cpu_cores": os.cpu_count(),
            "gl_platform": gl, "budget_s": int(budget), "tiny_dry_run": tiny not in ("", "0"),
            "started_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    (out / "step_env.json").write_text(json_text(info, indent=1) + "\n")
    return info


def step(out: Path, name: str, rc: str, start: str, limit: str) -> dict:
    res = {"exit_code": int(rc), "seconds": round(time.time() - float(start), 2), "limit_s": int(limit),
           "timed_out": int(rc) in (124, 137)}
    log = out / f"{name}.log"
    if log.is_file():
        res["log_tail"] = log.read_text(errors="replace").splitlines()[-4:]
    (out / f"step_{name}.json").write_text(json_text(res, indent=1) + "\n")
    return res


def _forward(out: Path, tag: str) -> dict | None:
    data = _json(out / f"forward_{tag}.json")
    if not data:
        return None
    return {r["model"]: {"forward_ms": r["forward_ms"], "parameters": r.get("parameters")} for r in data["results"]}


def _count(syn: Path) -> int | None:
    """Samples in a figshare-layout folder (f1_80.npy memory-mapped: only its header is read)."""
    try:
        import numpy as np

        return int(np.load(syn / "f1_80.npy", mmap_mode="r").shape[0])
    except (OSError, ValueError, ImportError):
        return None


def report(out: Path) -> dict:
    from uhrnet.run_folder import CONFIG_JSON, LAST_PT, read_history  # the project's run folder (numpy, no torch)

    steps = {p.stem[5:]: _json(p) for p in sorted(out.glob("step_*.json"))}
    env_info = steps.pop("env", None) or {}
    work = out / "work"
    res: dict = {"kind": "gpu_check", **env_info, "steps": steps}
    res["forward_ms"] = {tag: f for tag in ("fp32", "fp16") if (f := _forward(out, tag))}
    gen = steps.get("generate") or {}
    n = _count(work / "syn")
    if gen.get("exit_code") == 0 and n:
        res["generate"] = {"samples": n, "seconds": gen["seconds"], "samples_per_s": n / gen["seconds"],
                           "note": "whole command (process start, mesh loading, all workers), figshare layout, --no-psp"}
    hist = read_history(work / "run")
    if hist:
        secs = [float(r["seconds"]) for r in hist if r.get("seconds") is not None]
        cfg = _json(work / "run" / CONFIG_JSON) or {}
        train = {"model": cfg.get("model", "uhrnet"), "amp": cfg.get("amp"), "epochs": len(hist), "epoch_seconds": secs,
                 "val_rmse_mm": [float(r["val_rmse_mm"]) for r in hist if r.get("val_rmse_mm") is not None]}
        if n and secs:
            # the reference split trains on 80 % of the samples; later epochs exclude cuDNN's autotuning.
            # history.csv's epoch seconds hold the epoch's validation (and checkpoint) too: the rate says so
            n_train = round(0.8 * n)
            steady = secs[1:] or secs
            train.update(train_samples=n_train, samples_per_s=n_train / (sum(steady) / len(steady)),
                         samples_per_s_note="training samples per second of whole epochs (validation and checkpoint "
                                            "included)" + (", first epoch left out" if len(secs) > 1 else ""))
        res["train"] = train
    ddp = steps.get("ddp") or {}
    if ddp:
        res["ddp"] = {"exit_code": ddp.get("exit_code"), "seconds": ddp.get("seconds"),
                      "backend": "gloo" if env_info.get("device", "cpu").startswith("cpu") else "nccl",
                      "world_size": 1, "checkpoint_written": (work / "ddp" / LAST_PT).is_file()}
    s2r = _json(work / "s2r" / "report.json")
    if s2r:
        v = s2r["variants"][0]
        row = (v.get("rows") or [{}])[0]
        res["sim2real"] = {"samples": s2r["config"]["count"], "epochs": s2r["config"]["epochs"],
                           "model": s2r["config"]["model"], "pair_object_rmse_mm": v["real"]["object_rmse_mm"],
                           "pair_object_median_abs_mm": (row.get("real") or {}).get("object_median_abs_mm"),
                           "phase_residual_rad": {f"{Path(f['folder']).name}/{f['id']}": f["rmse_rad"]
                                                  for f in row.get("real_phase") or []}}
    speed = _json(out / "speed.json")
    if speed:
        res["speed"] = speed
    study = _json(out / "study.json")
    if study:
        res["study"] = [{"arm": a["name"], "device": a.get("device"), "seeds": [x["seed"] for x in a["seeds"]],
                         "minutes": [x.get("minutes") for x in a["seeds"]],
                         "pair_object_rmse_mm": a["summary"].get("pair_object_rmse_mm"),
                         "phase_residual_rad": a["summary"].get("phase_residual_rad")} for a in study["arms"]]
    (out / "gpu_check.json").write_text(json_text(res, indent=1) + "\n")
    (out / "gpu_check.md").write_text(markdown(res))
    return res


PHASES = ("data", "forward", "backward", "optimizer")


def speed_table(speed: dict | None) -> list[str]:
    """The speed step's table (pipelines/gpu_speed.py): before / after the speed options, one row each."""
    if not speed:
        return []
    s = speed["sizes"]
    lines = ["", f"Training speed ({speed['device']}, commit {speed['commit'][:12]}; gpu_speed.py):", "",
             f"| setting | UHRNet samples/s ({s['h']}x{s['w']}, batch {s['uhrnet_batch']}{', AMP' if speed.get('amp') else ''}, validation incl.) | "
             f"U-Net recipe samples/s | s per study seed ({s['recipe_epochs']} x {s['recipe_draws']} draws) | "
             + " | ".join(f"{p} %" for p in PHASES) + " | step ms |",
             "|---|---|---|---|" + "---|" * len(PHASES) + "---|"]
    for name in ("before", "after"):
        r = speed[name]
        share = r["uhrnet_step"]["share"]
        lines.append(f"| {name} | {r['uhrnet_train_samples_per_s']:.1f} | {r['unet_recipe_samples_per_s']:.1f} | "
                     f"{r['unet_recipe_seed_train_s']:.1f} | " + " | ".join(f"{100 * share[p]:.0f}" for p in PHASES)
                     + f" | {r['uhrnet_step']['step_ms']:.1f} |")
    lines += ["", "before: " + ", ".join(f"{k} {v}" for k, v in speed["before"]["settings"].items()) + "; after: "
              + ", ".join(f"{k} {v}" for k, v in speed["after"]["settings"].items())
              + (" (TINY dry run: numbers not meaningful)" if speed.get("tiny_dry_run") else "") + "."]
    if "unet_recipe_amp_seed_train_s" in speed["after"]:
        lines.append(f"The recipe seed with --amp too ('after'): {speed['after']['unet_recipe_amp_seed_train_s']:.1f} s.")
    return lines


def markdown(res: dict) -> str:
    lines = [f"# GPU check: {res.get('device', '?')}", "",
             f"torch {res.get('torch')} (CUDA {res.get('cuda')}), Python {res.get('python')}, "
             f"{res.get('cpu_cores')} CPU cores, GL {res.get('gl_platform')}, budget {res.get('budget_s')} s"
             + (" (TINY dry run: sizes are not meaningful)" if res.get("tiny_dry_run") else ""), "",
             "| step | exit | seconds | limit (s) |", "|---|---|---|---|"]
    for name, s in res["steps"].items():
        if s:
            lines.append(f"| {name} | {s['exit_code']}{' (timed out)' if s['timed_out'] else ''} | "
                         f"{s['seconds']:.0f} | {s['limit_s']} |")
    lines += speed_table(res.get("speed"))
    if res.get("study"):  # scaling.py writes the study's own table beside its record
        lines += ["", f"Scaling study: {sum(len(a['seeds']) for a in res['study'])} (arm, seed) finished in "
                      f"{len(res['study'])} arm(s); record study.json, table (mean +- std) study_table.md."]
    if res["forward_ms"]:
        lines += ["", "Forward ms per image, batch 1 (median):", "",
                  "| model | " + " | ".join(res["forward_ms"]) + " | paper (RTX 2080 Ti) |",
                  "|---|" + "---|" * len(res["forward_ms"]) + "---|"]
        models = list(next(iter(res["forward_ms"].values())))
        for m in models:
            cells = [f"{res['forward_ms'][t][m]['forward_ms']:.2f}" if m in res["forward_ms"][t] else ""
                     for t in res["forward_ms"]]
            lines.append(f"| {m} | " + " | ".join(cells) + f" | {PAPER_MS.get(m) or ''} |")
    if "generate" in res:
        g = res["generate"]
        lines += ["", f"Generation: {g['samples']} samples in {g['seconds']:.1f} s = **{g['samples_per_s']:.1f} "
                      f"samples/s** ({g['note']})."]
    if "train" in res:
        t = res["train"]
        sps = (f" = **{t['samples_per_s']:.1f} training samples/s, validation included**"
               + (" (first epoch left out)" if len(t["epoch_seconds"]) > 1 else "") if "samples_per_s" in t else "")
        name = {"uhrnet": "UHRNet", "unet": "U-Net", "hnet": "hNet"}.get(t.get("model"), t.get("model"))
        lines += ["", f"Training ({name}{', AMP' if t.get('amp') else ''}): {t['epochs']} epochs, epoch seconds "
                      f"{', '.join(f'{s:.1f}' for s in t['epoch_seconds'])}{sps}; "
                      f"val RMSE {', '.join(f'{v:.2f}' for v in t['val_rmse_mm'])} mm."]
    if "ddp" in res:
        d = res["ddp"]
        lines += ["", f"DDP ({d['backend']}, world size 1): exit {d['exit_code']}, {d['seconds']:.0f} s, "
                      f"checkpoint written: {d['checkpoint_written']}."]
    if "sim2real" in res:
        s = res["sim2real"]
        def num(x, spec):  # None: not measured (null in the report.json read back)
            return "n/a" if x is None else format(x, spec)

        ph = ", ".join(f"{k} {num(v, '.3f')} rad" for k, v in s["phase_residual_rad"].items())
        lines += ["", f"Sim-to-real point: {s['model']}, {s['samples']} samples, {s['epochs']} epochs: real pair "
                      f"object RMSE **{num(s['pair_object_rmse_mm'], '.2f')} mm**" + (f"; phase residual {ph}" if ph else "")
                  + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    cmds = {"begin": 1, "settle": 1, "wheels": 1, "env": 4, "step": 5, "report": 1}
    if argv[:1] == ["guard"] and len(argv) >= 4:
        return guard(Path(argv[1]), float(argv[2]), argv[3:])
    if not argv or argv[0] not in cmds or len(argv) != cmds[argv[0]] + 1:
        print(__doc__, file=sys.stderr)
        return 2
    cmd, *args = argv
    if cmd == "begin":
        try:
            begin(Path(args[0]))
        except Refused as exc:
            print(f"gpu_check: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"gpu_check: {exc.filename or args[0]}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    elif cmd == "settle":
        settle(Path(args[0]))
    elif cmd == "wheels":
        print("\n".join(wheels(Path(args[0]))))
    elif cmd == "env":
        env(Path(args[0]), *args[1:])
    elif cmd == "step":
        step(Path(args[0]), *args[1:])
    else:
        print(markdown(report(Path(args[0]))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
