"""uhrnet.workflows.scaling, the scaling study's library (``pipelines/scaling.py`` only parses its command line
and launches the arms): the arms file, a seed's folder and record, the statistics and the table, and the study
record (``scaling.json``): read strictly, added to without dropping a result, merged, written."""

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from uhrnet.workflows.scaling.arms import UsageProblem, arm_key, arm_label, load_arms, select_arms
from uhrnet.workflows.scaling.ledger import (
    add_seed, check_finite, definition_conflict, load_ledger, merge_records, write_ledger,
)
from fppsim.files import finite_or_null
from uhrnet.workflows.scaling.report import TABLE_MARK, markdown
from uhrnet.workflows.scaling.results import result_line, seed_result, write_seed_record
from uhrnet.workflows.scaling.stats import compare, mean_std, series_slope, summarise

ROOT = Path(__file__).resolve().parents[1]


def test_bad_arms_files_are_refused(tmp_path):
    for text, message in (("- name: x", "a mapping with a non-empty list"),
                          ("arms: [{name: x, cuont: 4}]", "unknown keys ['cuont']"),
                          ("arms: [{name: x}, {name: x}]", "unique word"),
                          ("arms: [{name: x, series: [time]}]", "series must be"),
                          ("arms: [{name: x, train: '--a \"b'}]", "train"),
                          ("arms: [{name: x, count: 1.5}]", "count must be an integer"),
                          ("arms: [{name: x, lr: fast}]", "lr must be a number")):
        (tmp_path / "a.yaml").write_text(text)
        with pytest.raises(UsageProblem, match=message.replace("[", r"\[").replace("]", r"\]")):
            load_arms(tmp_path / "a.yaml")
    (tmp_path / "a.yaml").write_text("arms: [{name: x, lr: 5e-4, count: '400'}]")  # YAML reads 5e-4 as text
    assert {k: load_arms(tmp_path / "a.yaml")[0][k] for k in ("lr", "count")} == {"lr": 5e-4, "count": 400}


def test_what_moves_compares_with_n400_and_fits_the_samples_slope():
    """The table's comparison with n400 (difference, larger seed std, Welch t by hand) and the slope per doubling
    of samples (exact on results that lie on a line in log2(samples))."""
    def arm(name, count, pair, phase=None):
        seeds = [{"seed": i, "pair_object_rmse_mm": v,
                  "phase_residual_rad": {"F/1": phase[i]} if phase else {}} for i, v in enumerate(pair)]
        return {"name": name, "device": "cuda", "resize": None, "count": count, "series": ["samples"],
                "seeds": seeds, "summary": summarise(seeds)}
    ref = arm("n400", 400, [5.0, 6.0, 7.0], [1.0, 1.2, 1.4])
    other = arm("n1600", 1600, [3.0, 3.5, 4.0], [1.1, 1.3, 1.5])
    c = compare(other, ref, "pair_object_rmse_mm")
    assert c["diff"] == pytest.approx(-2.5) and c["spread"] == pytest.approx(1.0) and c["beyond"]
    assert c["t"] == pytest.approx(-2.5 / np.sqrt(1.0 / 3 + 0.25 / 3))
    p = compare(other, ref, "", "F/1")
    assert p["diff"] == pytest.approx(0.1) and not p["beyond"]
    assert compare(arm("x", 1, [5.0]), ref, "pair_object_rmse_mm") is None  # one seed: no spread
    line = [arm(f"n{c}", c, [8.0 - 0.5 * np.log2(c / 100)] * 2) for c in (100, 400, 1600)]
    fit = series_slope(line, "pair_object_rmse_mm")
    assert fit["slope"] == pytest.approx(-0.5) and fit["stderr"] == pytest.approx(0, abs=1e-6) and fit["n"] == 6
    md = markdown({"arms": [ref, other]})
    assert "## Against n400 (cuda)" in md and "| n1600 [cuda] | -2.50 (beyond ±1.00; t -3.9) | +0.10 (within ±0.20" in md


def test_arm_paths_resolve_from_the_root_and_an_arm_is_keyed_by_resize_and_device(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "arms.yaml").write_text("arms: [{name: r, generate: --rig assets/figshare_depth_rig.json}]")
    assert load_arms(tmp_path / "arms.yaml")[0]["generate"] == ["--rig", "assets/figshare_depth_rig.json"]
    rig = str(ROOT / "assets" / "figshare_depth_rig.json")
    assert load_arms(tmp_path / "arms.yaml", ROOT)[0]["generate"] == ["--rig", rig]
    assert arm_label({"name": "n400", "resize": "32x64", "device": "cuda"}) == "n400 @32x64 [cuda]"
    assert arm_label({"name": "n400"}) == "n400" and arm_key({"name": "n400"}) == ("n400", None, "cpu")


def test_arms_are_chosen_by_name_in_the_order_given():
    arms = [{"name": "a"}, {"name": "b"}, {"name": "c"}]
    assert select_arms(arms, None, "f.yaml") == arms
    assert [a["name"] for a in select_arms(arms, ["c", "a"], "f.yaml")] == ["c", "a"]
    for names, message in ((["a", "x"], "unknown or repeated arm.s. x .arms of f.yaml: a, b, c."),
                           (["a", "a"], "repeated")):
        with pytest.raises(UsageProblem, match=message):
            select_arms(arms, names, "f.yaml")


def test_a_seed_result_in_one_line():
    res = {"pair_object_rmse_mm": 4.25, "pair_level_rmse_mm": None, "pair_relief_rmse_mm": 2.0,
           "phase_residual_rad": {"F/1": 1.23456}}
    assert result_line(res) == "pair object RMSE 4.25 mm, relief 2.00 mm; F/1 1.235 rad"
    assert result_line({}) == ""


def test_mean_std_skips_missing_and_non_finite_values():
    assert mean_std([1.0, None, float("nan"), 3.0]) == {"mean": 2.0, "std": pytest.approx(math.sqrt(2)), "n": 2}
    assert mean_std([4.0]) == {"mean": 4.0, "std": None, "n": 1}
    assert mean_std([]) == {"mean": None, "std": None, "n": 0}


def test_a_seed_folder_is_read_only_when_finished_and_its_record_keeps_the_first_start(tmp_path):
    assert seed_result(tmp_path / "s0", SimpleNamespace(epochs=1), SimpleNamespace(train={})) is None
    rec = {"arm": "a", "seed": 0, "commit": "c1", "dirty": False, "torch_threads": 2, "started": "t1"}
    write_seed_record(tmp_path / "s0", rec)
    write_seed_record(tmp_path / "s0", {**rec, "commit": "c2", "started": "t2"})
    got = json.loads((tmp_path / "s0" / "study.json").read_text())
    assert got["commit"] == "c1" and got["resumes"] == [{"commit": "c2", "dirty": False, "torch_threads": 2,
                                                         "started": "t2"}]


def _meta(**kw):
    return {"name": "a", "resize": None, "device": "cpu", "count": 6, "epochs": 1, **kw}


def test_add_seed_keeps_every_result_and_refuses_another_definition():
    entries = {}
    assert add_seed(entries, _meta(), {"seed": 1, "pair_object_rmse_mm": 1.0}) == "added"
    assert add_seed(entries, _meta(), {"seed": 0, "pair_object_rmse_mm": 2.0, "commit": "x"}) == "added"
    assert add_seed(entries, _meta(), {"seed": 0, "pair_object_rmse_mm": 2.0, "commit": "x"}) == "same"
    assert add_seed(entries, _meta(), {"seed": 0, "pair_object_rmse_mm": 3.0, "commit": "y"}) == "rerun"
    seeds = entries["a", None, "cpu"]["seeds"]
    assert [s["seed"] for s in seeds] == [0, 1]
    assert seeds[0]["pair_object_rmse_mm"] == 3.0 and [r["pair_object_rmse_mm"] for r in seeds[0]["reruns"]] == [2.0]
    with pytest.raises(UsageProblem, match="here: arm a is not the recorded a .count 8 vs 6."):
        add_seed(entries, _meta(count=8), {"seed": 2}, "here")
    # another machine's checkout: absolute paths compare by their name
    assert definition_conflict({"generate": ["--rig", "/a/x.json"]}, {"generate": ["--rig", "/b/x.json"]}) is None
    assert finite_or_null({"a": [1.0, float("nan")], "b": float("inf"), "c": "t"}) == {"a": [1.0, None], "b": None, "c": "t"}
    with pytest.raises(UsageProblem, match="where: holds a non-finite number"):
        check_finite({"x": [1.0, float("nan")]}, "where")


def test_load_ledger_reads_the_first_version_and_refuses_what_is_not_a_record(tmp_path):
    p = tmp_path / "scaling.json"
    assert load_ledger(p) == {"arms": []}
    cmd = "uhrnet sim2real --variant 's0: | --resize 32x64 --seed 0'"
    p.write_text(json.dumps({"arms": [{"name": "n400", "commands": [cmd], "seeds": [{"seed": 0}]}]}))
    assert load_ledger(p)["arms"] == [{"name": "n400", "resize": "32x64", "device": "cpu",
                                       "seeds": [{"seed": 0, "device": "cpu", "sim2real_command": cmd}]}]
    for doc, message in (('{"arms": [{"name": "a", "seeds": [{"seed": NaN}]}]}', "non-finite number NaN"),
                         ('{"x": 1}', "not a scaling study record"),
                         ('{"arms": [{"name": "a", "seeds": [{"s": 0}]}]}', "without an integer 'seed'"),
                         ('{"arms": [{"name": "a", "seeds": []}, {"name": "a", "seeds": []}]}', "holds arm a twice"),
                         ('{"arms": [{"name": "a", "seeds": [{"seed": 0}, {"seed": 0}]}]}', "holds a seed twice")):
        p.write_text(doc)
        with pytest.raises(UsageProblem, match=f"--merge {p}: .*{message}.*nothing merged"):
            load_ledger(p, "--merge")


def test_write_ledger_writes_record_table_and_figures_and_merge_adds_records(tmp_path):
    entries, logged = {}, []
    add_seed(entries, _meta(name="n400", series=["samples"]), {"seed": 0, "pair_object_rmse_mm": 5.0})
    add_seed(entries, _meta(name="n100", series=["samples"]), {"seed": 0, "pair_object_rmse_mm": 6.0})
    ledger = tmp_path / "s.json"
    doc = write_ledger(ledger, entries, 2, ["n100 s1"], ["n100", "n400"], "arms.yaml", logged.append)
    assert [a["name"] for a in doc["arms"]] == ["n100", "n400"] and (doc["found"], doc["pending"]) == (2, ["n100 s1"])
    on_disk = json.loads(ledger.read_text())
    assert on_disk["arms_file"] == "arms.yaml" and on_disk["arms"][0]["summary"]["n_seeds"] == 1
    assert (tmp_path / "s_table.md").read_text().startswith(TABLE_MARK)
    assert (tmp_path / "s_samples.png").is_file() and len(logged) == 2  # each figure, or why not
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"arms": [{"name": "n400", "resize": None, "device": "cuda",
                                           "seeds": [{"seed": 0, "pair_object_rmse_mm": 4.0}]}]}))
    merged = merge_records(ledger, [other], ["n100", "n400"], "arms.yaml", logged.append)
    assert merged["merge_counts"] == {"added": 1, "rerun": 0, "same": 0} and merged["found"] == 1
    assert [arm_label(a) for a in json.loads(ledger.read_text())["arms"]] == ["n100", "n400", "n400 [cuda]"]
    with pytest.raises(UsageProblem, match="is the --ledger itself"):
        merge_records(ledger, [ledger], [], "arms.yaml")
    (tmp_path / "t_table.md").write_text("mine")
    with pytest.raises(UsageProblem, match="exists and was not written by scaling.py"):
        write_ledger(tmp_path / "t.json", entries, 0, [], [], "arms.yaml")
    assert not (tmp_path / "t.json").exists()
