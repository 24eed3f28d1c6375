"""pipelines/scaling.py (issue 32): the arms file, the exact equivalent `uhrnet sim2real` commands, bad input
refused before anything runs, and a tiny study end to end (2 arms x 2 seeds) that resumes without training."""

import json
import shlex
from pathlib import Path

import numpy as np
import pytest

from fppsim.fitting.height_sensitivity import surface_phase
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

from uhrnet.workflows.scaling.arms import UsageProblem, arm_label, load_arms, steps_of

from _helpers import load_pipeline, rig_fringe, tiny_rig, write_figshare

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


def _load():
    return load_pipeline("scaling")


scaling = _load()

TINY = """
defaults: {base_channels: 4, epochs: 1, batch_size: 2, workers: 1, loss: l2}
arms:
  - name: a6
    series: [samples, steps]
    count: 6
    train: --resize 32x64 --no-augment
  - name: a8
    series: [samples]
    count: 8
    train: [--resize, 32x64, --no-augment, --samples-per-epoch, "4"]
"""


@pytest.fixture
def world(tmp_path):
    """A tiny arms file, 2 labelled real pairs (32 x 64) and one real phase-shifting frame (folder of folders)."""
    (tmp_path / "arms.yaml").write_text(TINY)
    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    rig = tiny_rig()
    yy, xx = np.mgrid[0:32, 0:64].astype(float)
    h = 6.0 * np.exp(-((xx - 25.0) ** 2 + (yy - 15.0) ** 2) / 98.0)
    save_psp_folder_sample(tmp_path / "phase" / "F1", "1201", *sums_from_phase(surface_phase(rig, h) + 72.0),
                           rig_fringe(rig, h))
    return tmp_path


def _argv(w, *extra):
    return ["--arms-file", str(w / "arms.yaml"), "--seeds", "0", "1", "--real", str(w / "real"),
            "--real-phase", str(w / "phase"), "--out", str(w / "study"), "--meshes", str(ROOT / "assets" / "meshes"),
            "--no-figures", *extra]


def test_shipped_arms_file_fixed_step_budget_and_commands(tmp_path):
    arms = {a["name"]: a for a in load_arms(scaling.DEFAULT_ARMS, ROOT)}
    assert {"n100", "n400", "n1600", "n6400", "n400-e20", "n400-e40", "depth-rig"} <= set(arms)
    args = scaling.parse_args(["--out", str(tmp_path / "o"), "--real", "R", "--real-phase", "none", "--meshes", "M"])
    args.real_phase, args.meshes = [], ["M"]
    steps = {}
    for name in ("n100", "n400", "n1600", "n6400", "n400-e40"):
        cfg, argv = scaling.arm_config(arms[name], 1, args)
        steps[name] = steps_of(cfg, cfg.variants[0])
        assert cfg.variants[0].train["seed"] == 1 and argv[-1].endswith("--seed 1")
        assert cfg.out == str(tmp_path / "o" / name)
    # the recipe: 80 % of 400 samples, 10 epochs, batch 2 = 1,600 steps; every count arm the same budget
    assert steps == {"n100": 1600, "n400": 1600, "n1600": 1600, "n6400": 1600, "n400-e40": 6400}
    cfg, _ = scaling.arm_config(arms["depth-rig"], 0, args)
    assert cfg.variants[0].generate["rig"].endswith("figshare_depth_rig.json")


def test_commands_are_exactly_what_the_driver_runs(world, monkeypatch):
    """Each recorded command, run through `uhrnet sim2real`'s own parser, gives the very config the driver runs."""
    import uhrnet.workflows.sim2real
    from uhrnet.cli import main

    args = scaling.parse_args(_argv(world))
    arms, configs = scaling.check(args)
    seen = []
    monkeypatch.setattr(uhrnet.workflows.sim2real, "run_sim2real",
                        lambda cfg, **kw: seen.append(cfg) or {"variants": []})
    monkeypatch.setattr(uhrnet.workflows.sim2real, "markdown_report", lambda report: "")
    for (name, seed), (cfg, argv) in configs.items():
        assert argv[:2] == ["uhrnet", "sim2real"] and shlex.split(shlex.join(argv)) == argv
        assert main(argv[1:]) == 0
        assert seen[-1] == cfg, (name, seed)
    assert configs["a6", 1][0].real_phase == [str(world / "phase" / "F1")]  # the folder of scan folders, expanded
    assert not (world / "study").exists()


@pytest.mark.parametrize("change, message", [
    (["--arms", "a6", "nope"], "unknown or repeated arm(s) nope"),
    (["--seeds", "0", "0"], "--seeds: distinct"),
    (["--real", "/no/such/real"], "no labelled real samples"),
    (["--resize", "banana"], "resize"),
    (["--report-only"], "does not exist"),
])
def test_bad_input_is_one_line_and_exit_2_before_anything_runs(world, capsys, change, message):
    assert scaling.main(_argv(world) + change) == 2  # a flag given again overrides the first
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scaling.py: error:") and message in err[0]
    assert not (world / "study").exists()


def test_an_arm_whose_flags_its_command_refuses_is_refused_by_check(tmp_path):
    args = scaling.parse_args(["--arms-file", str(tmp_path / "b.yaml"), "--out", str(tmp_path), "--real", "r",
                               "--real-phase", "none", "--list"])
    (tmp_path / "b.yaml").write_text("arms: [{name: x, count: 6, train: --no-such-flag}]")
    with pytest.raises(UsageProblem, match="variant 's0': train"):
        scaling.check(args)


@pytest.mark.slow
def test_a_tiny_study_runs_resumes_and_reports(world, capsys):
    """2 arms x 2 seeds of tiny sim2real runs (about 30 s on 2 cores): scaling.json's schema, figures; the same
    command again trains nothing (files untouched); --report-only rebuilds the report alone."""
    out = world / "study"
    assert scaling.main(_argv(world)) == 0
    text = capsys.readouterr().out
    assert "[1/4 a6 seed 0] start" in text and "[4/4 a8 seed 1] done in" in text and "pair object RMSE" in text
    doc = json.loads((out / "scaling.json").read_text())
    assert [a["name"] for a in doc["arms"]] == ["a6", "a8"]
    a6, a8 = doc["arms"]
    assert (a6["count"], a6["steps"], a8["steps"]) == (6, 2, 2)  # 4 training samples / batch 2; 4 draws / 2
    s1 = a6["seeds"][1]
    assert s1["sim2real_command"].startswith("uhrnet sim2real ") and s1["device"] == "cpu"
    assert "--variant 's1:  | --resize 32x64 --no-augment --threads 2 --seed 1'" in s1["sim2real_command"]
    assert s1["command"].startswith("python pipelines/scaling.py ") and "--arms a6 --seeds 1" in s1["command"]
    assert s1["commit"] and len(s1["commit"]) == 40
    for arm in doc["arms"]:
        assert [s["seed"] for s in arm["seeds"]] == [0, 1]
        for s in arm["seeds"]:
            for key in ("pair_object_rmse_mm", "pair_level_rmse_mm", "pair_relief_rmse_mm",
                        "pair_level_rmse_mean_mm", "pair_relief_rmse_mean_mm"):
                assert np.isfinite(s[key]), key
            assert s["pair_images"] == 2 and len(s["pair_regions_per_image"]) == 2
            for r in json.loads((Path(s["folder"]) / "eval" / "real_metrics.json").read_text())["per_image"]:
                assert r["object_level_rmse_mean_mm"] ** 2 + r["object_relief_rmse_mean_mm"] ** 2 == pytest.approx(
                    r["object_rmse_mm"] ** 2)
            assert set(s["phase_residual_rad"]) == {"F1/1201"} and np.isfinite(s["phase_residual_rad"]["F1/1201"])
            assert Path(s["folder"]) == out / arm["name"] / f"s{s['seed']}"
        summ = arm["summary"]
        vals = [s["pair_object_rmse_mm"] for s in arm["seeds"]]
        assert summ["pair_object_rmse_mm"] == {"mean": pytest.approx(np.mean(vals)),
                                               "std": pytest.approx(np.std(vals, ddof=1)), "n": 2}
        assert summ["phase_residual_rad"]["F1/1201"]["n"] == 2
    assert (out / "scaling_samples.png").stat().st_size > 0 and (out / "scaling_steps.png").is_file()
    md = (out / "scaling_table.md").read_text()
    assert "| a6 | 6 | 2 | 2 |" in md
    arm_md = (out / "a6" / "report.md").read_text()  # the arm's own sim2real report lists both seeds
    assert "| s0 |" in arm_md and "| s1 |" in arm_md and "level and relief" in arm_md

    runs = sorted(p for p in out.rglob("*") if p.is_file() and "scaling" not in p.name and p.name != "study.json")
    before = {p: p.stat().st_mtime_ns for p in runs}
    assert scaling.main(_argv(world)) == 0
    text = capsys.readouterr().out
    assert text.count("finished before: re-used") == 4 and "start" not in text
    assert {p: p.stat().st_mtime_ns for p in runs} == before
    assert json.loads((out / "scaling.json").read_text())["arms"] == doc["arms"]

    (out / "scaling.json").unlink()
    assert scaling.main(_argv(world, "--report-only", "--seeds", "0", "1", "2")) == 0
    assert "pending: a6 s2, a8 s2" in capsys.readouterr().out
    again = json.loads((out / "scaling.json").read_text())
    assert again["arms"][0]["seeds"] == a6["seeds"]
    assert {p: p.stat().st_mtime_ns for p in runs} == before

    # the report never loses a result: other default paths (here the real folders named through another
    # path, and a ledger elsewhere holding an earlier arm) find the same seeds and keep what was recorded
    ledger = world / "docs" / "scaling.json"
    ledger.parent.mkdir()
    old = {"arms": [{"name": "a6", "seeds": [{"seed": 0, "pair_object_rmse_mm": 9.0}],
                     "commands": ["uhrnet sim2real --variant 's0:  | --resize 16x32 --seed 0'"]}]}
    ledger.write_text(json.dumps(old))
    other = [a.replace(str(world / "real"), str(world / "phase" / ".." / "real")) for a in _argv(world)]
    assert scaling.main(other + ["--report-only", "--ledger", str(ledger)]) == 0
    merged = json.loads(ledger.read_text())
    labels = [arm_label(a) for a in merged["arms"]]
    assert labels == ["a6", "a6 @16x32", "a8"], labels
    assert merged["arms"][1]["seeds"] == [{"seed": 0, "pair_object_rmse_mm": 9.0, "device": "cpu",
                                            "sim2real_command": old["arms"][0]["commands"][0]}]
    assert [s["seed"] for s in merged["arms"][0]["seeds"]] == [0, 1]
    assert (ledger.parent / "scaling_table.md").read_text().count("| a6 @16x32 |") == 1
    # a re-run of a seed that gives another result keeps the earlier one
    merged["arms"][0]["seeds"][0]["pair_object_rmse_mm"] = 1.0
    ledger.write_text(json.dumps(merged))
    assert scaling.main(other + ["--report-only", "--ledger", str(ledger)]) == 0
    s0 = json.loads(ledger.read_text())["arms"][0]["seeds"][0]
    assert s0["reruns"][0]["pair_object_rmse_mm"] == 1.0 and s0["pair_object_rmse_mm"] == a6["seeds"][0]["pair_object_rmse_mm"]
    # a ledger that is not a study record is never replaced
    notes = world / "notes.json"
    notes.write_text('{"mine": 1}')
    assert scaling.main(other + ["--report-only", "--ledger", str(notes)]) == 2
    assert notes.read_text() == '{"mine": 1}'
    # nor a table of that name that the study did not write (docs/experiments/scaling.md is a hand-written page)
    (ledger.parent / "scaling_table.md").write_text("# my page\n")
    assert scaling.main(other + ["--report-only", "--ledger", str(ledger)]) == 2
    assert (ledger.parent / "scaling_table.md").read_text() == "# my page\n"


@pytest.mark.slow
def test_jobs_run_arms_at_once_deadline_stops_and_merge_keeps_everything(world, capsys):
    """--jobs 2 runs both arms at once (each in its own process, lines tagged with the arm) and records the same
    seeds as one process would; --deadline stops the running arms, resumable; --merge adds a record brought
    back from elsewhere (a GPU machine) to a ledger without losing what it held."""
    out = world / "study"
    assert scaling.main(_argv(world, "--jobs", "2")) == 0
    text = capsys.readouterr().out
    assert "[a6] [1/2 a6 seed 0] start" in text and "[a8] [2/2 a8 seed 1] done in" in text
    doc = json.loads((out / "scaling.json").read_text())
    assert [(a["name"], [s["seed"] for s in a["seeds"]]) for a in doc["arms"]] == [("a6", [0, 1]), ("a8", [0, 1])]
    assert "--arms a8 --seeds 1 " in doc["arms"][1]["seeds"][1]["command"]
    assert (out / "a6" / "scaling.log").read_text().count("done in") == 2
    # the same command again: every seed re-used, nothing trained
    assert scaling.main(_argv(world, "--jobs", "2")) == 0
    assert capsys.readouterr().out.count("finished before: re-used") == 4
    assert json.loads((out / "scaling.json").read_text())["arms"] == doc["arms"]

    # a deadline reached at once: the arm's process is stopped, nothing recorded, exit 0, the seeds pending
    late = world / "late"
    assert scaling.main(_argv(world, "--out", str(late), "--deadline", "0.5", "--arms", "a6")) == 0
    text = capsys.readouterr().out
    assert "deadline (0 s) reached: stopping a6" in text or "deadline" in text
    assert "pending: a6 s0, a6 s1" in text
    assert json.loads((late / "scaling.json").read_text())["arms"] == []

    # merge: a record from elsewhere (another device) joins the ledger; a seed it holds with another result
    # keeps the ledger's under reruns; merging the same again changes nothing
    ledger = world / "docs" / "scaling.json"
    ledger.parent.mkdir()
    ledger.write_text(json.dumps({"arms": [{"name": "a6", "seeds": [{"seed": 0, "pair_object_rmse_mm": 9.0}]}]}))
    gpu = json.loads((out / "scaling.json").read_text())
    for arm in gpu["arms"]:
        arm["device"] = "cuda"
    gpu["arms"].append({"name": "a6", "device": "cpu", "resize": None, "seeds": [{"seed": 0, "pair_object_rmse_mm": 5.0}]})
    (world / "gpu.json").write_text(json.dumps(gpu))
    assert scaling.main(["--arms-file", str(world / "arms.yaml"), "--ledger", str(ledger),
                         "--merge", str(world / "gpu.json")]) == 0
    assert "5 seed result(s) merged" in capsys.readouterr().out
    merged = json.loads(ledger.read_text())
    assert [arm_label(a) for a in merged["arms"]] == ["a6", "a6 [cuda]", "a8 [cuda]"]
    cpu0 = merged["arms"][0]["seeds"][0]
    assert cpu0["pair_object_rmse_mm"] == 5.0 and cpu0["reruns"] == [{"seed": 0, "pair_object_rmse_mm": 9.0, "device": "cpu"}]
    assert merged["arms"][1]["seeds"] == doc["arms"][0]["seeds"]
    assert merged["arms"][1]["summary"] == doc["arms"][0]["summary"]
    assert scaling.main(["--arms-file", str(world / "arms.yaml"), "--ledger", str(ledger),
                         "--merge", str(world / "gpu.json")]) == 0
    assert json.loads(ledger.read_text()) == merged
    for bad, message in ((["--merge", str(world / "nope.json")], "no such file"),
                         (["--merge", str(ledger)], "is the --ledger itself"),
                         (["--merge", str(world / "gpu.json"), "--out", str(out)], "runs nothing")):
        assert scaling.main(["--arms-file", str(world / "arms.yaml"), "--ledger", str(ledger), *bad]) == 2
        assert message in capsys.readouterr().err
    assert json.loads(ledger.read_text()) == merged


def test_study_commit_names_the_tree_sent_to_another_machine(monkeypatch):
    """A copy sent to a GPU machine carries an older commit's git folder under the tree: STUDY_COMMIT, when
    given, is recorded as the commit, beside what the copy's git says; anything but 40 hex digits is ignored."""
    seen = scaling.code_version()
    monkeypatch.setenv("STUDY_COMMIT", "ab" * 20)
    given = scaling.code_version()
    assert given["commit"] == "ab" * 20 and given["commit_from"] == "STUDY_COMMIT" and given["dirty"] is None
    assert given["checkout_head"] == seen["commit"]
    monkeypatch.setenv("STUDY_COMMIT", "HEAD")
    assert scaling.code_version() == seen


def test_a_malformed_study_commit_is_refused_before_anything_runs(world, capsys, monkeypatch):
    monkeypatch.setenv("STUDY_COMMIT", "adc5f24")  # a short commit would record the copy's HEAD instead
    assert scaling.main(_argv(world)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "STUDY_COMMIT='adc5f24'" in err[0] and not (world / "study").exists()


def test_merge_keeps_both_histories_and_refuses_seed_entries_that_are_not_seeds(tmp_path, capsys):
    arms = tmp_path / "arms.yaml"
    arms.write_text(TINY)
    ledger, other = tmp_path / "scaling.json", tmp_path / "other.json"
    ledger.write_text(json.dumps({"arms": [{"name": "a6", "seeds": [
        {"seed": 0, "pair_object_rmse_mm": 2.0, "reruns": [{"seed": 0, "pair_object_rmse_mm": 1.0}]}]}]}))
    other.write_text(json.dumps({"arms": [{"name": "a6", "seeds": [
        {"seed": 0, "pair_object_rmse_mm": 3.0, "reruns": [{"seed": 0, "pair_object_rmse_mm": 0.5}]}]}]}))
    assert scaling.main(["--arms-file", str(arms), "--ledger", str(ledger), "--merge", str(other)]) == 0
    s0 = json.loads(ledger.read_text())["arms"][0]["seeds"][0]
    assert s0["pair_object_rmse_mm"] == 3.0
    assert [r["pair_object_rmse_mm"] for r in s0["reruns"]] == [1.0, 2.0, 0.5]
    before = ledger.read_text()
    other.write_text(json.dumps({"arms": [{"name": "a6", "seeds": [{"pair_object_rmse_mm": 3.0}]}]}))
    assert scaling.main(["--arms-file", str(arms), "--ledger", str(ledger), "--merge", str(other)]) == 2
    assert "without an integer 'seed'" in capsys.readouterr().err and ledger.read_text() == before
