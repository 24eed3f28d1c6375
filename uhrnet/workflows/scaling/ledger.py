"""The scaling study's record (``scaling.json``, or any ``--ledger FILE``): every arm (keyed by name, resize and
device) with its definition and its seeds' results, read strictly, added to without ever dropping a result (a
seed's differing result keeps the earlier one under ``reruns``), merged from other records, and written with
its table and figures beside it (claimed in the folder's ownership record)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Callable

from fppsim.errors import ForeignFiles
from fppsim.files import atomic_write_text, finite_or_null
from fppsim.owned import claim
from uhrnet.workflows.scaling.arms import SERIES, UsageProblem, arm_key, arm_label, seed_folder, variant_of
from uhrnet.workflows.scaling.report import TABLE_MARK, markdown, plot_series
from uhrnet.workflows.scaling.results import arm_meta, seed_result
from uhrnet.workflows.scaling.stats import summarise

__all__ = ["STUDY", "STUDY_TOOL", "DEFINITION", "load_ledger", "definition_conflict", "check_finite",
           "add_seed", "add_finished", "merge_records", "claim_beside", "write_ledger"]

STUDY = "sim-to-real scaling (pipelines/scaling.py)"  # the record's "study"
STUDY_TOOL = "pipelines/scaling.py"  # who writes the table and figures (the folder's ownership record)


def strict_json(text: str):
    """``json.loads`` that refuses NaN and Infinity (not JSON; a record holding them is not strict JSON)."""
    def bad(name):
        raise ValueError(f"non-finite number {name}")
    return json.loads(text, parse_constant=bad)


def load_ledger(path: Path, role: str = "--ledger") -> dict:
    """The results recorded so far in ``path`` (a ``scaling.json``; ``{"arms": []}`` when there is none).
    Files of the first version (arm-level ``commands``, no resize or device) are read too: the resize comes
    from their commands, the device is the CPU. Anything else is refused (:class:`UsageProblem`, naming
    ``role``: ``--ledger`` for the record written, ``--merge`` for one read into it): the report replaces only
    a study record, and a record holds strict JSON (no NaN), each arm (name, resize, device) once."""
    hint = "name another --ledger" if role == "--ledger" else "nothing merged"
    if not path.exists():
        return {"arms": []}
    try:
        doc = strict_json(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        why = str(exc) if str(exc).startswith("non-finite") else type(exc).__name__
        raise UsageProblem(f"{role} {path}: not a readable scaling.json ({why}); {hint}") from None
    if not (isinstance(doc, dict) and isinstance(doc.get("arms"), list)
            and all(isinstance(a, dict) and isinstance(a.get("name"), str) and isinstance(a.get("seeds"), list)
                    for a in doc["arms"])):
        raise UsageProblem(f"{role} {path}: not a scaling study record (no list of arms with seeds); {hint}")
    bad = next((a["name"] for a in doc["arms"] for s_ in a["seeds"]
                if not (isinstance(s_, dict) and isinstance(s_.get("seed"), int) and not isinstance(s_["seed"], bool))),
               None)
    if bad is not None:
        raise UsageProblem(f"{role} {path}: arm {bad!r} holds a seed entry without an integer 'seed'; "
                           f"not a study record; {hint}")
    for arm in doc["arms"]:
        commands = arm.pop("commands", None) or []
        if "resize" not in arm:
            sizes = {m for c in commands for m in re.findall(r"--resize[ =]([0-9]+x[0-9]+)", c)}
            arm["resize"] = sizes.pop() if len(sizes) == 1 else None
        arm.setdefault("device", "cpu")
        arm.pop("missing_seeds", None)
        for seed in arm["seeds"]:
            seed.setdefault("device", arm["device"])
            if "command" not in seed and "sim2real_command" not in seed:
                match = [c for c in commands if f"--seed {seed['seed']}'" in c]
                if match:
                    seed["sim2real_command"] = match[0]
    keys = [arm_key(a) for a in doc["arms"]]
    twice = next((k for k in keys if keys.count(k) > 1), None)
    if twice is not None:
        raise UsageProblem(f"{role} {path}: holds arm {arm_label(dict(zip(('name', 'resize', 'device'), twice)))} "
                           f"twice; not a study record; {hint}")
    for arm in doc["arms"]:
        seeds = [s_["seed"] for s_ in arm["seeds"]]
        if len(set(seeds)) != len(seeds):
            raise UsageProblem(f"{role} {path}: arm {arm_label(arm)} holds a seed twice; not a study record; {hint}")
    return doc


def same_result(a: dict, b: dict) -> bool:
    keys = ("pair_object_rmse_mm", "phase_residual_rad", "commit", "synthetic_val_rmse_mm")
    return all(a.get(k) == b.get(k) for k in keys)


# what defines an arm beside its key (name, resize, device): seeds of two definitions are never pooled
DEFINITION = ("count", "epochs", "steps", "batch_size", "lr", "base_channels", "model", "loss", "scale",
              "generate", "train")


def flag_key(value):
    """An arm's flag list as compared between records: absolute paths by their name (another machine's
    checkout has another root)."""
    if isinstance(value, list):
        return [Path(v).name if isinstance(v, str) and v.startswith("/") else v for v in value]
    return value


def definition_conflict(have: dict, new: dict) -> str | None:
    """How ``new``'s arm definition differs from ``have``'s (``"count 50 vs 400, epochs 2 vs 10"``), over the
    :data:`DEFINITION` keys both give; None when they agree (a key only one gives is no conflict: records of
    the first version carry fewer)."""
    diffs = [f"{k} {new[k]} vs {have[k]}" for k in DEFINITION
             if have.get(k) is not None and new.get(k) is not None and flag_key(have[k]) != flag_key(new[k])]
    return ", ".join(diffs) or None


def check_finite(value, where: str) -> None:
    """Refuse a non-finite number anywhere in ``value`` (:class:`UsageProblem` naming ``where``)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise UsageProblem(f"{where}: holds a non-finite number ({value}); a study record holds finite numbers")
    if isinstance(value, dict):
        for v in value.values():
            check_finite(v, where)
    elif isinstance(value, list):
        for v in value:
            check_finite(v, where)


def add_seed(entries: dict, meta: dict, new: dict, source: str = "the arms file") -> str:
    """Put one seed's result ``new`` into the arm entry of ``meta`` (its name, resize, device, definition and
    description) in ``entries`` (keyed by :func:`~uhrnet.workflows.scaling.arms.arm_key`): a seed recorded
    before with another result keeps that under ``reruns``. An arm recorded with another definition
    (:data:`DEFINITION`) is refused (:class:`UsageProblem` naming ``source``): its seeds are not the recorded
    arm's. Returns ``"added"``, ``"rerun"`` (another result for a recorded seed) or ``"same"`` (already
    recorded: nothing changed)."""
    entry = entries.get(arm_key(meta))
    if entry is not None:
        conflict = definition_conflict(entry, meta)
        if conflict:
            raise UsageProblem(f"{source}: arm {arm_label(meta)} is not the recorded {arm_label(entry)} ({conflict}): "
                               "its seeds would be pooled with another recipe's; rename the arm or use another "
                               "--ledger (nothing written)")
    entry = entries.setdefault(arm_key(meta), {"name": meta["name"], "resize": meta.get("resize"),
                                            "device": meta.get("device", "cpu"), "seeds": []})
    entry.update({k: v for k, v in meta.items() if k not in ("name", "resize", "device", "seeds", "summary")})
    old = next((s for s in entry["seeds"] if s["seed"] == new["seed"]), None)
    status = "added"
    if old is not None:
        if old == new:
            return "same"
        entry["seeds"].remove(old)
        earlier = old.pop("reruns", [])
        mine = [r for r in new.pop("reruns", []) if r not in earlier]
        status = "same" if same_result(old, new) and not mine else "rerun"
        if not same_result(old, new):
            earlier = [*earlier, old]
        if earlier or mine:
            new["reruns"] = [*earlier, *mine]
    entry["seeds"] = sorted([*entry["seeds"], new], key=lambda s: s["seed"])
    return status


def add_finished(entries: dict, out: Path, arms: list[dict], seeds: list[int], configs: dict, resize: str | None,
                 commands: Callable[[dict, int], dict], where: str) -> tuple[int, list[str]]:
    """Add every finished (arm, seed) folder under ``out`` (:func:`~uhrnet.workflows.scaling.results.seed_result`
    of ``configs[name, seed][0]``, the seed's ``Sim2RealConfig``) to ``entries`` (:func:`add_seed`; a refusal
    names the arm and ``where``: ``"of ARMS_FILE against --ledger FILE"``), its command lines the ones its
    ``study.json`` recorded, else ``commands(arm, seed)`` (``{"command", "sim2real_command"}``). Returns
    ``(found, pending)``: how many are finished and the others' ``"<arm> s<seed>"``."""
    found, pending = 0, []
    for arm in arms:
        for seed in seeds:
            cfg = configs[arm["name"], seed][0]
            var = variant_of(cfg, seed)
            res = seed_result(seed_folder(out, arm, seed), cfg, var)
            if res is None:
                pending.append(f"{arm['name']} s{seed}")
                continue
            found += 1
            for key, value in commands(arm, seed).items():
                res.setdefault(key, value)
            add_seed(entries, arm_meta(arm, cfg, var, resize, res["device"]), finite_or_null({"seed": seed, **res}),
                     f"arm {arm['name']!r} {where}")
    return found, pending


def merge_records(ledger: Path, paths: list, order: list[str], arms_file: str,
                  log: Callable[[str], None] = print) -> dict:
    """``--merge FILE ...``: add every seed of the study records ``paths`` (e.g. brought back from a GPU machine)
    to ``ledger``, with the same rules as a finished folder (nothing recorded is dropped; a differing result
    keeps the earlier one under ``reruns``; an arm of another definition under the same name, or a non-finite
    number, refuses the whole merge before anything is written), and rewrite its table and figures
    (:func:`write_ledger`: ``order``, ``arms_file``, ``log``). The record returned counts ``found`` (seeds
    added or re-run) and ``merge_counts``."""
    ledger = Path(ledger)
    entries = {arm_key(a): a for a in load_ledger(ledger)["arms"]}
    counts = {"added": 0, "rerun": 0, "same": 0}
    for path in paths:
        if not Path(path).is_file():
            raise UsageProblem(f"--merge {path}: no such file")
        if Path(path).resolve() == ledger.resolve():
            raise UsageProblem(f"--merge {path}: is the --ledger itself")
        for arm in load_ledger(Path(path), "--merge")["arms"]:
            meta = {k: v for k, v in arm.items() if k not in ("seeds", "summary")}
            check_finite(meta, f"--merge {path}: arm {arm_label(arm)}")
            for seed in arm["seeds"]:
                check_finite(seed, f"--merge {path}: arm {arm_label(arm)} seed {seed['seed']}")
                counts[add_seed(entries, meta, dict(seed), f"--merge {path}")] += 1
    doc = write_ledger(ledger, entries, counts["added"] + counts["rerun"], [], order, arms_file, log)
    doc["merge_counts"] = counts
    return doc


def claim_beside(ledger: Path, files: list[Path]) -> None:
    """Claim the files written beside ``ledger`` (its table and figures) in the folder's ownership record
    (:mod:`fppsim.owned`) before anything is written: a file there that the study did not write (a user's
    ``study_samples.png``) is refused (:class:`UsageProblem`). A folder without a record adopts the table
    scaling.py wrote (its first line) and, with it, that ledger's figures."""
    folder = ledger.parent
    table = files[0]

    def legacy():
        try:
            ours = table.is_file() and table.read_text(errors="replace").startswith(TABLE_MARK)
        except OSError:
            ours = False
        return [f.name for f in files] if ours else []
    try:
        claim(folder, STUDY_TOOL, [f.name for f in files], legacy=legacy,
              hint="move it away or name another --ledger (nothing written)")
    except ForeignFiles as exc:
        raise UsageProblem(str(exc)) from None


def write_ledger(ledger: Path, entries: dict, found: int, pending: list[str], order: list[str], arms_file: str,
                 log: Callable[[str], None] = print) -> dict:
    """Write the study record ``ledger`` from ``entries`` (arms in the arms file's ``order`` of names, the others
    after them; ``arms_file`` as the record names it), its table and its figures (each figure written, or
    why not, said to ``log``); returns the record with ``found`` / ``pending`` added."""
    ledger = Path(ledger)
    order = {name: i for i, name in enumerate(order)}
    arm_list = sorted(entries.values(), key=lambda a: (order.get(a["name"], len(order)), a["name"],
                                                       a.get("resize") or "", a.get("device", "cpu")))
    for entry in arm_list:
        entry["summary"] = summarise(entry["seeds"])
    doc = {"study": STUDY, "arms_file": arms_file, "arms": arm_list}
    table = ledger.with_name(f"{ledger.stem}_table.md")
    if table.exists() and not (table.is_file() and table.read_text(errors="replace").startswith(TABLE_MARK)):
        raise UsageProblem(f"{table}: exists and was not written by scaling.py; move it away")
    try:
        text = json.dumps(doc, indent=2, allow_nan=False)
    except ValueError:
        raise UsageProblem(f"--ledger {ledger}: a result is not a finite number; nothing written") from None
    ledger.parent.mkdir(parents=True, exist_ok=True)
    figures = {series: ledger.with_name(f"{ledger.stem}_{series}.png") for series in SERIES}
    claim_beside(ledger, [table, *figures.values()])
    atomic_write_text(ledger, text)
    atomic_write_text(table, TABLE_MARK + "\n" + markdown(doc))
    for series, path in figures.items():
        fig = plot_series(doc, series, path)
        log(f"figure: {fig}" if fig else f"figure {path.name}: no finished full-size arm of series {series!r}")
    doc["found"], doc["pending"] = found, pending
    return doc
