#!/usr/bin/env python
"""Scaling study of the sim-to-real recipe: arms x training seeds, resumable, one command (issue 32).

Each ARM is a set of ``uhrnet sim2real`` options (sample count, epochs, extra ``fppsim generate`` /
``uhrnet train`` flags) read from an arms file (default ``pipelines/scaling_arms.yaml``); each arm runs once
per training SEED (``uhrnet train --seed``; the synthetic data, generator seed 100, is the same for every
seed of an arm, so the spread is the training seed's). Every (arm, seed) is a sim-to-real experiment run in
this process through the workflow layer (``uhrnet.workflows.sim2real.run_sim2real(Sim2RealConfig)``):

    OUT/<arm>/                 the arm's sim2real folder: data/<key> (its synthetic set, shared by its seeds),
                               report.md / report.json (every finished seed of the arm)
    OUT/<arm>/s<seed>/         one (arm, seed): run/ (training), eval/ (real metrics, phase residuals), logs
    OUT/scaling.json           every arm: the exact equivalent command lines, per-seed results, mean +- std
    OUT/scaling_table.md       the same as a table (OUT: or beside --ledger FILE)
    OUT/scaling_samples.png    pair object RMSE (with its level / relief parts) and held-out phase residual
    OUT/scaling_steps.png      against synthetic samples (arms of series "samples") and training steps ("steps")

A killed study resumes with the same command: sim2real re-uses finished datasets, runs and evaluations and
continues an interrupted training run; a finished (arm, seed) is not touched. ``--report-only`` rebuilds
the JSON, table and figures from the finished folders without running anything.

    python pipelines/scaling.py --arms n100 n400 n1600 n6400 --seeds 0 1 2 \\
        --real ../shared/real-sample --real-phase ../shared/real-phase --out runs/scaling
    python pipelines/scaling.py --list                          # the arms and their commands; runs nothing
    python pipelines/scaling.py --out runs/scaling --report-only
    python pipelines/scaling.py --arms n100 n400 --device cuda --jobs 2 --deadline 500 --out runs/s  # on a GPU
    python pipelines/scaling.py --ledger docs/experiments/scaling.json --merge study.json  # a record from elsewhere

Results per seed (``scaling.json``): ``pair_object_rmse_mm`` (object RMSE on the labelled real pair(s), mean
over images), its split into ``pair_level_rmse_mm`` (each connected object region's median error) and
``pair_relief_rmse_mm`` (the rest), the exact mean split (``pair_level_rmse_mean_mm`` /
``pair_relief_rmse_mean_mm``: level^2 + relief^2 = RMSE^2; :func:`uhrnet.workflows.sim2real.real_metrics.error_split`) and
``phase_residual_rad`` (``uhrnet evaluate-phase``'s calibration-free residual on each held-out real
phase-shifting frame). Per arm: mean and sample standard deviation (ddof 1) over the finished seeds.

Arms file (YAML/JSON): ``{defaults: {...}, arms: [{name, description, series, count, epochs, batch_size, lr,
base_channels, model, loss, workers, scale, generate, train}, ...]}``; ``defaults`` apply to every arm,
``generate`` / ``train`` are flag strings (or lists) of ``fppsim generate`` / ``uhrnet train``, relative
paths in them are taken from the current folder, else from the repository root. ``series``: the figures the
arm is a point of (``samples``: x = its sample count; ``steps``: x = its optimizer steps).

Exit status: 0 done; 1 an (arm, seed) failed (the others still ran; its log is named); 2 bad usage (arms
file, arm names, seeds, real folders, flags), refused before anything runs.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# the study's library is uhrnet.workflows.scaling (arms file, seed results, record, statistics, table, figures);
# it is imported inside the functions: an arm's process (run_jobs) sets its parent-death signal and its SIGINT
# handler (main) before the seconds that importing torch takes

SHARED = ROOT.parent / "shared"
DEFAULT_ARMS = ROOT / "pipelines" / "scaling_arms.yaml"
COMMIT_RE = r"[0-9a-f]{40}"  # what $STUDY_COMMIT must be: a full commit


# ============================================================================================ one (arm, seed)
def phase_folders(dirs: list[str]) -> list[str]:
    """Real phase-shifting folders: each given folder, or the scan folders inside it (e.g. ../shared/real-phase
    -> ../shared/real-phase/FP1523)."""
    from fppsim.dataio.readers import is_psp_folder

    out = []
    for d in dirs:
        p = Path(d)
        inner = sorted(str(s) for s in p.iterdir() if s.is_dir() and is_psp_folder(s)) if p.is_dir() else []
        out += [str(d)] if is_psp_folder(p) or not inner else inner
    return out


def arm_config(arm: dict, seed: int, args) -> tuple[object, list[str]]:
    """``(Sim2RealConfig, argv)`` of ``arm`` at training ``seed`` with this command line's options
    (:func:`uhrnet.workflows.scaling.arms.arm_config`, ``--variant`` flags read by ``uhrnet``'s own parsers)."""
    from uhrnet.cli import variant_commands
    from uhrnet.workflows.scaling.arms import arm_config as study_arm_config

    return study_arm_config(arm, seed, args, variant_commands())


def code_version() -> dict:
    """``{"commit": HEAD of this checkout or None, "dirty": uncommitted changes to tracked files}``.

    ``$STUDY_COMMIT`` (40 hex digits), when set, is the commit whose tree this is, given by whoever copied the
    checkout elsewhere (a lent GPU machine gets the working tree, on top of the git folder of an older commit:
    its HEAD would be wrong). It is recorded as the commit (``"commit_from": "STUDY_COMMIT"``), beside what the
    copy's git says (``checkout_head``, ``checkout_dirty``)."""
    import os
    import re
    import subprocess

    def git(*a):
        return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True, timeout=30)
    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
        seen = {"commit": head.stdout.strip(), "dirty": bool(dirty.stdout.strip())} if not head.returncode else None
    except (OSError, subprocess.SubprocessError):
        seen = None
    given = os.environ.get("STUDY_COMMIT", "")
    if re.fullmatch(COMMIT_RE, given):
        return {"commit": given, "dirty": None, "commit_from": "STUDY_COMMIT",
                "checkout_head": seen and seen["commit"], "checkout_dirty": seen and seen["dirty"]}
    return seen or {"commit": None, "dirty": None}


def _rel(path: str) -> str:
    """A path as the recorded commands give it: relative to the repository root (they run from there)."""
    import os

    p = Path(path)
    return os.path.relpath(p.resolve(), ROOT) if p.exists() or p.is_absolute() else str(path)


def study_command(args, arm: dict, seed: int | list[int]) -> list[str]:
    """The ``python pipelines/scaling.py`` command, run from the repository root, that runs exactly this
    (arm, seed) (or these seeds): every input the study reads named explicitly (no default taken from the
    folder layout)."""
    seeds = [seed] if isinstance(seed, int) else list(seed)
    argv = ["python", "pipelines/scaling.py", "--arms-file", _rel(args.arms_file), "--arms", arm["name"],
            "--seeds", *map(str, seeds), "--out", _rel(args.out), "--real", *map(_rel, args.real),
            "--real-phase", *(map(_rel, args.real_phase) if args.real_phase else ["none"]),
            "--meshes", *map(_rel, args.meshes)]
    for flag, value in (("--resize", args.resize), ("--threads", args.threads), ("--device", args.device),
                        ("--workers", args.workers)):
        if value is not None:
            argv += [flag, str(value)]
    return argv + (["--no-figures"] if args.no_figures else [])


def seed_commands(args, arm: dict, seed: int, argv: list[str]) -> dict:
    """The (arm, seed)'s command lines as its record holds them: this study's and ``uhrnet sim2real``'s."""
    return {"command": shlex.join(study_command(args, arm, seed)), "sim2real_command": shlex.join(argv)}


def arm_order(args) -> list[str]:
    """The arms file's arm names, in its order (the record's and the table's order)."""
    from uhrnet.workflows.scaling.arms import load_arms

    return [a["name"] for a in load_arms(args.arms_file, ROOT)]


def write_report(args, arms: list[dict], configs: dict) -> dict:
    """Add the finished (arm, seed) folders under ``args.out`` to the study record ``args.ledger`` (default
    ``OUT/scaling.json``) and rewrite it, its table (``scaling_table.md``) and figures beside it.

    Nothing recorded is lost: a seed is keyed by (arm, resize, device, seed); results already in the record
    stay whether or not their folders are still here, and a folder whose result differs from the recorded one
    (another commit, or a re-run) keeps the earlier result in the seed's ``reruns``."""
    from uhrnet.workflows.scaling.arms import arm_key
    from uhrnet.workflows.scaling.ledger import add_finished, load_ledger, write_ledger

    ledger = Path(args.ledger)
    entries = {arm_key(a): a for a in load_ledger(ledger)["arms"]}
    found, pending = add_finished(entries, Path(args.out), arms, args.seeds, configs, args.resize,
                                  lambda arm, seed: seed_commands(args, arm, seed, configs[arm["name"], seed][1]),
                                  f"of {args.arms_file} against --ledger {ledger}")
    return write_ledger(ledger, entries, found, pending, arm_order(args), _rel(args.arms_file))


# ============================================================================================ main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="scaling.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="study folder (created; re-running the same command resumes it)")
    p.add_argument("--arms-file", default=str(DEFAULT_ARMS), help="YAML/JSON arms file [%(default)s]")
    p.add_argument("--arms", nargs="+", metavar="NAME", help="arms to run, in this order [every arm of the file]")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], metavar="N",
                   help="training seeds (uhrnet train --seed) of every arm [0 1 2]")
    real = SHARED / "real-sample"
    p.add_argument("--real", nargs="+", metavar="DIR", default=[str(real)] if real.is_dir() else None,
                   help="labelled real figshare-format folder(s), evaluation only [../shared/real-sample when present]")
    phase = SHARED / "real-phase"
    p.add_argument("--real-phase", nargs="+", metavar="DIR", default=[str(phase)] if phase.is_dir() else [],
                   help="held-out real phase-shifting folder(s), or a folder of them ('none': no phase residual) "
                        "[../shared/real-phase when present]")
    p.add_argument("--meshes", nargs="+", metavar="PATH", default=None,
                   help="meshes of the synthetic scenes [../shared/meshes (when present) and assets/meshes]")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="training device [the arm's scale: cpu]")
    p.add_argument("--workers", type=int, metavar="N", help="generator processes, 0: all cores [the scale's: 2]")
    p.add_argument("--resize", metavar="HxW", help="uhrnet train --resize HxW for every arm (e.g. quick looks)")
    p.add_argument("--threads", type=int, default=2, metavar="N",
                   help="uhrnet train --threads N for every arm: a seeded run repeats bit for bit only at the same "
                        "CPU thread count (0: torch's default, the cores) [2, the recipe's machine]")
    p.add_argument("--no-figures", action="store_true", help="no per-image figure of the real pairs (sim2real's)")
    p.add_argument("--ledger", metavar="FILE",
                   help="the study record the finished seeds are added to (never dropping one already recorded); "
                        "its table and figures are written beside it [OUT/scaling.json]")
    p.add_argument("--report-only", action="store_true",
                   help="add the finished folders to the record, rewrite its table and figures; run nothing")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="arms run at once, each in its own process (its seeds one after another: they share the "
                        "arm's folder), e.g. several arms on one GPU; output lines start with the arm [1]")
    p.add_argument("--deadline", type=float, metavar="SECONDS",
                   help="stop after this many seconds: the running seeds are interrupted (the same command "
                        "resumes them), no new one starts, and the finished ones are recorded [no limit]")
    p.add_argument("--merge", nargs="+", metavar="FILE",
                   help="add the seeds of these study records (e.g. a scaling.json brought back from a GPU "
                        "machine) to --ledger and rewrite its table and figures; runs nothing, needs no --out")
    p.add_argument("--no-report", action="store_true",
                   help="run only, write no record (what --jobs gives each arm's process; the parent reports)")
    p.add_argument("--list", action="store_true", help="print the arms and their commands; run nothing")
    return p.parse_args(argv)


def check_merge(args) -> None:
    """``--merge``'s own checks (:class:`UsageProblem`): a --ledger to merge into, nothing to run."""
    from uhrnet.workflows.scaling.arms import UsageProblem

    if not args.ledger:
        raise UsageProblem("--merge: give the study record to merge into as --ledger FILE")
    if Path(args.ledger).is_dir():
        raise UsageProblem(f"--ledger {args.ledger}: is a folder (give the scaling.json file)")
    if args.out or args.report_only or args.list or args.arms:
        raise UsageProblem("--merge runs nothing: give it no --out, --arms, --report-only or --list")
    arm_order(args)  # the arms' order in the table


def check(args) -> tuple[list[dict], dict]:
    """Arms chosen and every (arm, seed)'s ``(Sim2RealConfig, argv)``; :class:`UsageProblem` before anything runs."""
    import os
    import re

    from uhrnet.errors import UhrnetError
    from uhrnet.run_folder import default_meshes
    from uhrnet.workflows.scaling.arms import UsageProblem, load_arms, select_arms, variant_of
    from uhrnet.workflows.scaling.ledger import load_ledger
    from uhrnet.workflows.sim2real import (
        Sim2RealError, find_phase_frames, find_real_pairs, generate_config, train_config,
    )

    arms = select_arms(load_arms(args.arms_file, ROOT), args.arms, args.arms_file)
    if any(s < 0 for s in args.seeds) or len(set(args.seeds)) != len(args.seeds):
        raise UsageProblem(f"--seeds: distinct non-negative integers, got {args.seeds}")
    if not args.out and not args.list:
        raise UsageProblem("--out DIR is required")
    given = os.environ.get("STUDY_COMMIT")
    if given is not None and not re.fullmatch(COMMIT_RE, given):
        raise UsageProblem(f"STUDY_COMMIT={given!r}: give the full commit (40 lowercase hex digits, "
                           "git rev-parse HEAD) or unset it")
    if not 1 <= args.jobs <= 64:
        raise UsageProblem(f"--jobs: 1 to 64 arms at once, got {args.jobs}")
    if args.deadline is not None and not (math.isfinite(args.deadline) and 0 < args.deadline <= 30 * 86400):
        raise UsageProblem(f"--deadline: seconds, more than 0 and at most 30 days, got {args.deadline}")
    if not args.real:
        raise UsageProblem("--real DIR: no labelled real folder given (../shared/real-sample is absent)")
    args.meshes = args.meshes or default_meshes(SHARED)
    args.real_phase = [] if args.real_phase in (["none"], None) else phase_folders(args.real_phase)
    args.out = args.out or "OUT"
    args.ledger = args.ledger or str(Path(args.out) / "scaling.json")
    if Path(args.ledger).is_dir():
        raise UsageProblem(f"--ledger {args.ledger}: is a folder (give the scaling.json file)")
    if args.report_only or not args.list:
        load_ledger(Path(args.ledger))  # an unreadable record is refused before anything runs
    if args.report_only and not Path(args.out).is_dir():
        raise UsageProblem(f"--report-only: {args.out} " + ("is a file, not a study folder" if Path(args.out).exists()
                                                           else "does not exist (nothing to report)"))
    configs = {}
    try:
        if not args.list:
            find_real_pairs(args.real)
            find_phase_frames(args.real_phase)
        for arm in arms:
            for seed in args.seeds:
                cfg, argv = configs[arm["name"], seed] = arm_config(arm, seed, args)
                var = variant_of(cfg, seed)  # the stage configs check themselves (e.g. a bad --resize)
                generate_config(cfg, var, "DATA")
                train_config(cfg, var, "DATA", "RUN")
    except (Sim2RealError, UhrnetError, ValueError) as exc:
        raise UsageProblem(str(exc).strip().splitlines()[0]) from None
    return arms, configs


def run(args, arms: list[dict], configs: dict) -> int:
    """Every (arm, seed) not finished yet, in order; 1 if one failed (the others still run)."""
    from uhrnet.workflows.sim2real.variants import recipe_commands
    from uhrnet.errors import UhrnetError
    from fppsim.errors import FppsimError
    from uhrnet.workflows.sim2real import run_sim2real
    from uhrnet.workflows.scaling.arms import seed_folder, variant_of
    from uhrnet.workflows.scaling.results import (
        result_line, seed_record, seed_result, with_finished_seeds, write_seed_record,
    )

    out, t_start, failed = Path(args.out), time.perf_counter(), []
    todo = [(arm, seed) for arm in arms for seed in args.seeds]
    for i, (arm, seed) in enumerate(todo, 1):
        cfg, argv = configs[arm["name"], seed]
        tag = f"[{i}/{len(todo)} {arm['name']} seed {seed}]"
        folder = seed_folder(out, arm, seed)
        if seed_result(folder, cfg, variant_of(cfg, seed)) is not None:
            print(f"{tag} finished before: re-used", flush=True)
            continue
        cfg = with_finished_seeds(out, arm, seed, args.seeds, configs)
        record = seed_record(arm, seed, args.resize, cfg.device, seed_commands(args, arm, seed, argv), code_version(),
                             args.threads)
        write_seed_record(folder, record)
        print(f"{tag} start ({(time.perf_counter() - t_start) / 60:.1f} min into the study): {shlex.join(argv)}",
              flush=True)
        t0 = time.perf_counter()

        def say(line, t0=t0, seed=seed):
            if line.startswith((f"[s{seed}]", f"[s{seed} ")):
                print(f"  {(time.perf_counter() - t0) / 60:5.1f} min  {line}", flush=True)

        try:
            run_sim2real(cfg, log=say, recipe=recipe_commands)
        except (UhrnetError, FppsimError, ValueError, OSError) as exc:
            failed.append(f"{arm['name']} seed {seed}")
            print(f"{tag} failed after {(time.perf_counter() - t0) / 60:.1f} min: {str(exc).strip().splitlines()[0]}",
                  file=sys.stderr, flush=True)
            continue
        res = seed_result(folder, cfg, variant_of(cfg, seed)) or {}
        print(f"{tag} done in {(time.perf_counter() - t0) / 60:.1f} min: {result_line(res)}", flush=True)
    if failed:
        print(f"scaling.py: error: failed: {', '.join(failed)} (re-run the same command to retry; logs in "
              f"{out}/<arm>/s<seed>/train.log and {out}/<arm>/data/*.log)", file=sys.stderr)
    return 1 if failed else 0


GRACE_S = 8.0  # a stopped arm's time to exit after SIGINT before SIGKILL (gpu_check's guard allows 10 s)
PARENT_ENV = "SCALING_PARENT_PID"  # set for the arms' processes: they die with the process that started them


def run_jobs(args, arms: list[dict], started: float) -> int:
    """Run the arms in up to ``args.jobs`` processes at once (``scaling.py --arms ARM --no-report``: each arm's
    seeds one after another, since they share the arm's folder), their output echoed with the arm's name and
    kept in ``OUT/<arm>/scaling.log``. At ``args.deadline`` seconds after ``started`` (``time.monotonic()``; or on Ctrl-C /
    SIGTERM) the running ones are interrupted (SIGINT to each process group, SIGKILL :data:`GRACE_S` later): a
    seed cut off resumes with the same command. Returns 1 if an arm failed, 130 / 143 when interrupted
    (SIGINT / SIGTERM), else 0; arms left at the deadline are reported pending."""
    import os
    import signal
    import subprocess
    import threading

    out = Path(args.out)
    end = started + args.deadline if args.deadline else None
    queue, running, failed = list(arms), {}, []
    lock = threading.Lock()

    def echo(proc, name, log):
        # read to the end whatever happens, so that a child never blocks on a full pipe
        for line in proc.stdout:
            try:
                log.write(line)
                log.flush()
                with lock:
                    print(f"[{name}] {line}", end="", flush=True)
            except (OSError, ValueError):
                pass
        log.close()

    def start(arm):
        folder = out / arm["name"]
        folder.mkdir(parents=True, exist_ok=True)
        argv = [sys.executable, str(Path(__file__).resolve()), *study_command(args, arm, args.seeds)[2:],
                "--no-report"]
        log = open(folder / "scaling.log", "a", encoding="utf-8")
        log.write(f"# {shlex.join(argv)}\n")
        # its own process group (stopped as a whole); it dies with this process (PARENT_ENV, checked in main)
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                errors="replace", start_new_session=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())})
        thread = threading.Thread(target=echo, args=(proc, arm["name"], log), daemon=True)
        thread.start()
        running[proc] = (arm["name"], thread)

    def finished(proc, name, thread, stopped=False):
        thread.join(5)
        rc = proc.returncode
        if rc != 0 and not (stopped and rc in (130, -signal.SIGINT, -signal.SIGKILL)):
            failed.append(f"{name} (exit {rc}; {out / name / 'scaling.log'})")

    def stop_all():
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # stopping already: a second signal changes nothing
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        for proc in running:
            try:
                os.killpg(proc.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        limit = time.monotonic() + GRACE_S
        for proc, (name, thread) in running.items():
            try:
                proc.wait(max(0.1, limit - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait()
            finished(proc, name, thread, stopped=True)
        running.clear()

    caught = {}

    def on_term(signum, frame):
        caught["signal"] = signum
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, on_term), signal.getsignal(signal.SIGINT)
    rc = 0
    try:
        while queue or running:
            while queue and len(running) < args.jobs and (end is None or time.monotonic() < end):
                start(queue.pop(0))
            if end is not None and time.monotonic() >= end:
                print(f"scaling.py: deadline ({args.deadline:.0f} s) reached: stopping "
                      f"{', '.join(n for n, _ in running.values()) or 'nothing running'}"
                      + (f"; not started: {', '.join(a['name'] for a in queue)}" if queue else ""), flush=True)
                stop_all()
                break
            for proc in list(running):
                if proc.poll() is not None:
                    finished(proc, *running.pop(proc))
            time.sleep(0.5)
    except KeyboardInterrupt:
        stop_all()
        print("scaling.py: interrupted; the same command resumes (finished stages are re-used)", file=sys.stderr)
        rc = 143 if caught.get("signal") == signal.SIGTERM else 130
    finally:
        signal.signal(signal.SIGTERM, previous[0])
        signal.signal(signal.SIGINT, previous[1])
    if failed:
        print(f"scaling.py: error: failed: {', '.join(failed)}", file=sys.stderr)
    return rc or (1 if failed else 0)


def _die_with_starter() -> None:
    """An arm's process started by :func:`run_jobs` dies with it (kill -9 too): the parent-death signal,
    set here rather than between fork and exec (unsafe beside the parent's threads); exits at once when the
    parent is gone already."""
    import os
    import signal

    from fppsim.files import die_with_parent

    pid = os.environ.pop(PARENT_ENV, None)
    if pid:
        die_with_parent()
        if str(os.getppid()) != pid:
            sys.exit(130)
        # the parent stops an arm with SIGINT (--deadline, Ctrl-C): a study started from a non-interactive shell
        # with '&' hands its children SIGINT ignored, and the arm then ran on through the grace period and
        # recorded a seed after the deadline (seen in a whole-suite run started that way)
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv=None) -> int:
    started = time.monotonic()  # --deadline counts from here: the checks count too
    _die_with_starter()
    from uhrnet.workflows.scaling.arms import UsageProblem, arm_line, variant_of
    from uhrnet.workflows.scaling.ledger import merge_records

    args = parse_args(sys.argv[1:] if argv is None else list(argv))
    if args.merge:
        try:
            check_merge(args)
            doc = merge_records(Path(args.ledger), args.merge, arm_order(args), _rel(args.arms_file))
        except UsageProblem as exc:
            print(f"scaling.py: error: {exc}", file=sys.stderr)
            return 2
        c = doc["merge_counts"]
        print(f"study: {doc['found']} seed result(s) merged ({c['added']} new, {c['rerun']} replacing another result, "
              f"kept under its reruns; {c['same']} already recorded, unchanged); {args.ledger} records "
              f"{sum(len(a['seeds']) for a in doc['arms'])} (arm, seed) in {len(doc['arms'])} arm(s)", flush=True)
        return 0
    try:
        arms, configs = check(args)
    except UsageProblem as exc:
        print(f"scaling.py: error: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for arm in arms:
            cfg = configs[arm["name"], args.seeds[0]][0]
            print(arm_line(arm, cfg, variant_of(cfg, args.seeds[0])))
            for seed in args.seeds:
                print("    " + shlex.join(configs[arm["name"], seed][1]))
        return 0
    try:
        if args.report_only:
            rc = 0
        elif args.jobs > 1 or args.deadline:
            rc = run_jobs(args, arms, started)  # stops its arms on a signal: what finished is still recorded
        else:
            rc = run(args, arms, configs)
    except KeyboardInterrupt:
        print("scaling.py: interrupted; the same command resumes (finished stages are re-used)", file=sys.stderr)
        return 130
    if args.no_report:
        return rc
    try:
        doc = write_report(args, arms, configs)
    except UsageProblem as exc:
        print(f"scaling.py: error: {exc}", file=sys.stderr)
        return 2
    recorded = sum(len(a["seeds"]) for a in doc["arms"])
    print(f"study: {doc['found']} of {len(arms) * len(args.seeds)} (arm, seed) asked for are finished in {args.out}"
          + (f" (pending: {', '.join(doc['pending'])})" if doc["pending"] else "")
          + f"; {args.ledger} records {recorded} (arm, seed) in {len(doc['arms'])} arm(s), with {Path(args.ledger).stem}_table.md",
          flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
