"""uhrnet sim2real's physics rows (issue 25): variant steps (adapt, refine), the physics head as a train
override, evaluation on real phase-shifting frames, the new real-pair metrics, and re-using finished runs
(--reuse-run, or a run folder copied into the experiment) without training again."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fppsim.fitting.height_sensitivity import surface_phase
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.cli import main, variant_commands
from uhrnet.errors import UsageError
from uhrnet.workflows.sim2real.variants import (
    VariantFlags, load_variants, parse_variant, recipe_commands, variant_from_flags,
)
from uhrnet.workflows.sim2real import (
    Sim2RealConfig, Sim2RealError, Variant, markdown_report, real_metrics, run_sim2real,
)

from _helpers import rig_fringe, tiny_rig, train_tiny, write_figshare, write_native_rig

pytestmark = pytest.mark.usefixtures("one_thread")


def test_variant_steps_parse_into_adapt_and_refine(tmp_path):
    assert parse_variant("adapt: | | adapt") == VariantFlags("adapt", [], [], [], ())
    v = parse_variant("ph: --pedestal 0 | --head phase | adapt --epochs 20 --lr 1e-3 | refine relief,orders")
    assert v == VariantFlags("ph", ["--pedestal", "0"], ["--head", "phase"], ["--epochs", "20", "--lr", "1e-3"],
                             ("relief", "orders"))
    assert parse_variant("r: | | refine").refine == ("relief",) and parse_variant("r: | | refine").adapt is None
    assert parse_variant("r: | | refine orders | adapt").adapt == []
    for bad, match in (("x: | | bogus", "a step after the train flags"), ("x: | | adapt | adapt", "once each")):
        with pytest.raises(Sim2RealError, match=match):
            parse_variant(bad)
    cfg = Sim2RealConfig(out=str(tmp_path), real=["r"], meshes=["m"])
    var = variant_from_flags(cfg, v, variant_commands())
    assert var.train == {"head": "phase"} and var.adapt == {"epochs": 20, "lr": 1e-3}
    assert var.refine == ["relief", "orders"] and var.described("adapt") == ["--epochs", "20", "--lr", "1e-3"]
    from uhrnet.training.adapt import AdaptConfig

    default = AdaptConfig.__dataclass_fields__["epochs"].default
    assert variant_from_flags(cfg, parse_variant(f"a: | | adapt --epochs {default}"), variant_commands()).adapt == {}  # the default
    assert variant_from_flags(cfg, parse_variant("n: | --no-augment"), variant_commands()).adapt is None
    with pytest.raises(Sim2RealError, match="set by the experiment"):
        variant_from_flags(cfg, parse_variant("a: | | adapt --overwrite"), variant_commands())
    with pytest.raises(UsageError, match="variant 'a': adapt: argument --lr"):
        variant_from_flags(cfg, parse_variant("a: | | adapt --lr x"), variant_commands())
    with pytest.raises(Sim2RealError, match="refine methods"):
        variant_from_flags(cfg, parse_variant("a: | | refine sharpen"), variant_commands())
    with pytest.raises(Sim2RealError, match="AdaptConfig has no field"):
        Variant("a", adapt={"epoch": 3})
    r = recipe_commands(Sim2RealConfig(out=str(tmp_path / "o"), real=["R"], real_phase=["P"], meshes=["m"]), var,
                        "D", tmp_path / "run")
    a = r["adapt"].split()
    assert a[:2] == ["adapt", str(tmp_path / "run" / "last.pt")] and a[a.index("--images") + 1:][:2] == ["R", "P"]
    assert a[a.index("--out") + 1] == str(tmp_path / "o" / "ph" / "adapt") and a[-4:] == ["--epochs", "20", "--lr", "1e-3"]
    assert "adapt" not in recipe_commands(cfg, variant_from_flags(cfg, parse_variant("n"), variant_commands()), "D", "R")
    p = tmp_path / "abl.yaml"
    p.write_text("- name: a\n  adapt: true\n  refine: relief, orders\n- name: b\n  train: --head phase\n"
                 "  adapt: --epochs 5\n  refine: true\n- name: c\n")
    a, b, c = load_variants(p)
    assert (a.adapt, a.refine) == ([], ("relief", "orders")) and (b.adapt, b.refine) == (["--epochs", "5"], ("relief",))
    assert (c.adapt, c.refine) == (None, ())


def test_real_metrics_median_within_and_coverage_against_construction():
    rng = np.random.default_rng(0)
    label = -97.0 + rng.uniform(-0.3, 0.3, (40, 60))
    obj = np.zeros(label.shape, bool)
    obj[10:30, 20:40] = True  # 400 object pixels, 20 mm up
    label[obj] = -97.0 + 120.0
    err_mm = np.zeros(label.shape)
    err_mm[obj] = np.tile(np.r_[np.full(10, 0.5), np.full(5, 2.0), np.full(5, -3.0)], 20)  # 50% / 25% / 25%
    pred = label + 6.0 * err_mm
    pred[10:12, 20:40] = -105.0  # 40 object pixels predicted invalid (labels -105: errors of their own)
    m = real_metrics(pred, label, label > -100, invalid_threshold=-100.0)
    e = np.abs((pred - label)[obj]) / 6.0
    assert m["object_median_abs_mm"] == pytest.approx(np.median(e))
    assert m["object_within_1mm"] == pytest.approx(np.mean(e <= 1.0))
    assert m["object_coverage"] == pytest.approx(1 - 40 / 400)
    assert real_metrics(pred, label, label > -100)["object_coverage"] == 1.0  # no threshold: every finite pixel
    perfect = real_metrics(label, label, label > -100, invalid_threshold=-100.0)
    assert (perfect["object_median_abs_mm"], perfect["object_within_1mm"], perfect["object_coverage"]) == (0, 1, 1)


def _bump(rig, peak, cx, cy=15.0, sigma=7.0):
    yy, xx = np.mgrid[0:rig.camera.height, 0:rig.camera.width].astype(float)
    return peak * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A tiny rig (file), real data of it (2 labelled pairs, 1 phase-shifting frame), and two finished runs
    trained outside any experiment: a height head on figshare data and a phase head on native data."""
    import torch

    tmp = tmp_path_factory.mktemp("s2r_rows")
    torch.set_num_threads(1)
    rig = tiny_rig()
    rig.save(tmp / "rig.json")
    heights = [_bump(rig, 8.0, 30.0), _bump(rig, 5.0, 40.0, sigma=6.0)]
    real = tmp / "real"
    real.mkdir()
    np.save(real / "f1_80.npy", np.stack([rig_fringe(rig, h).astype(np.float32) / 127.5 - 1 for h in heights])[..., None])
    np.save(real / "Z.npy", np.stack([(6.0 * h - 97.0).astype(np.float32) for h in heights])[..., None])
    h = _bump(rig, 6.0, 25.0)
    save_psp_folder_sample(tmp / "phase", "1201", *sums_from_phase(surface_phase(rig, h) + 72.0), rig_fringe(rig, h))
    write_figshare(tmp / "syn", n=6, h=32, w=64, seed=1)
    base = train_tiny(tmp / "base", "--synthetic", tmp / "syn")
    write_native_rig(tmp / "nat", rig, n=6, seed=2)
    phase = train_tiny(tmp / "phase_run", "--synthetic", tmp / "nat", extra=["--head", "phase"])
    return tmp, base, phase


def _argv(tmp, out, *extra):
    return ["sim2real", "--real", str(tmp / "real"), "--out", str(out), "--count", "6", "--epochs", "1",
            "--model", "unet", "--base-channels", "4", "--loss", "l2", "--lr", "1e-3", "--batch-size", "1",
            "--no-figures", *map(str, extra)]


def _listing(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_mtime_ns) for p in Path(folder).rglob("*"))


def test_reused_runs_give_every_row_with_phase_residuals_and_resume(world, tmp_path, capsys):
    """Both runs re-used (nothing generated or trained), the height run adapted and refined: rows base,
    base +refine relief, base +adapt, base +adapt +refine relief, ph, ph +refine orders; then re-run: all re-used."""
    tmp, base, phase = world
    before = _listing(base), _listing(phase)
    out = tmp_path / "o"
    argv = _argv(tmp, out, "--real-phase", tmp / "phase", "--rig", tmp / "rig.json",
                 "--variant", "base: | | adapt --epochs 1 | refine relief", "--variant", "ph: | --head phase | refine orders",
                 "--reuse-run", f"base={base}", "--reuse-run", f"ph={phase}")
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "generate ->" not in text and "train ->" not in text and "[base] adapt on 2 unlabelled" in text
    assert (_listing(base), _listing(phase)) == before  # re-used runs are read, never written
    assert not (out / "data").exists() and not (out / "base" / "run").exists()
    report = json.loads((out / "report.json").read_text())
    b, ph = report["variants"]
    assert [r["row"] for r in b["rows"]] == ["base", "base +refine relief", "base +adapt", "base +adapt +refine relief"]
    assert [r["row"] for r in ph["rows"]] == ["ph", "ph +refine orders"]
    assert b["reused"] and b["run"] == str(base) and b["data"] == str(tmp / "syn") and ph["data"] == str(tmp / "nat")
    assert b["real"] == b["rows"][0]["real"] and b["images"] == 2 and "relief_effect_mm" in b["real"]
    assert b["adapt"]["images"] == [str(tmp / "real"), str(tmp / "phase")] and b["adapt"]["labels_read"] is False
    assert (out / "base" / "adapt" / "last.pt").is_file() and b["adapt"]["epochs"] == 1
    for r in b["rows"] + ph["rows"]:
        assert {"object_rmse_mm", "object_median_abs_mm", "object_within_1mm", "object_coverage"} <= set(r["real"])
        assert 0 <= r["real"]["object_coverage"] <= 1 and 0 <= r["real"]["object_within_1mm"] <= 1
        [frame] = r["real_phase"]
        assert frame["id"] == "1201" and np.isfinite(frame["rmse_rad"]) and frame["flat_rmse_rad"] > 0
        assert Path(r["eval"], "real_metrics.json").is_file() and Path(r["eval"], "real_phase.json").is_file()
    assert b["rows"][2]["checkpoint"] == str(out / "base" / "adapt" / "last.pt")
    refined = json.loads((out / "base" / "eval-refine-relief" / "real_metrics.json").read_text())
    assert refined["refine"] == "relief" and "refine_moved_fraction" in refined["mean"]
    assert "relief_effect_mm" not in refined["mean"]  # the fringe twins measure the network alone
    assert refined["mean"]["refine_moved_fraction"] > 0
    net, ref = (np.load(out / "base" / e / "predictions.npz") for e in ("eval", "eval-refine-relief"))
    assert any((net[k] != ref[k]).any() for k in net.files)  # the refined row measures the refined heights
    md = (out / "report.md").read_text()
    assert "| base +adapt +refine relief |" in md and "phase/1201 residual (rad)" in md
    assert f"adapted on: {tmp / 'real'}, {tmp / 'phase'} (no labels" in md and "| flat plane (h = 0) |" in md
    assert f"reused the finished run {phase}" in md
    assert report["recipe"]["base"]["adapt"].startswith("adapt ")
    # the same command again: every stage re-used
    assert main(argv) == 0
    again = capsys.readouterr().out
    assert "evaluate on" not in again and "adapt on" not in again and "phase residual on" not in again
    assert json.loads((out / "report.json").read_text())["variants"][0]["rows"] == b["rows"]
    # the report of an older experiment (no rows) still renders
    old = {**report, "variants": [{k: v for k, v in b.items() if k not in ("rows", "adapt", "reused")}]}
    assert "Every row" not in markdown_report(old)


def _cfg(tmp, out, **kw):
    base = dict(out=str(out), real=[str(tmp / "real")], count=6, epochs=1, model="unet", base_channels=4, loss="l2",
                lr=1e-3, batch_size=1, figures=False)
    return Sim2RealConfig(**{**base, **kw})


def test_a_copied_run_is_taken_and_runs_of_other_options_are_refused(world, tmp_path):
    tmp, base, _ = world
    out = tmp_path / "o"
    shutil.copytree(base, out / "v" / "run")
    lines = []
    report = run_sim2real(_cfg(tmp, out, variants=[Variant("v")]), log=lines.append)
    assert not any("train ->" in line or "generate ->" in line for line in lines)
    v = report["variants"][0]
    assert v["run"] == str(out / "v" / "run") and v["data"] == str(tmp / "syn") and not v["reused"]
    assert v["rows"][0]["real_phase"] is None and "phase/" not in markdown_report(report)
    # other training options: refused before anything runs, naming what differs
    with pytest.raises(Sim2RealError, match=r"other training options.*lr 0\.001 \(wanted 0\.002\).*move it away"):
        run_sim2real(_cfg(tmp, tmp_path / "o", lr=2e-3, variants=[Variant("v")]), log=None)
    with pytest.raises(Sim2RealError, match=r"reuse-run v=.*head 'height' \(wanted 'phase'\)"):
        run_sim2real(_cfg(tmp, tmp_path / "p", variants=[Variant("v", train={"head": "phase"})], reuse={"v": str(base)}),
                     log=None)
    with pytest.raises(Sim2RealError, match="6 synthetic samples \\(wanted 7\\)"):
        run_sim2real(_cfg(tmp, tmp_path / "p", count=7, reuse={"default": str(base)}), log=None)
    with pytest.raises(Sim2RealError, match="not a finished run \\(epoch 1 of 2"):
        run_sim2real(_cfg(tmp, tmp_path / "p", epochs=2, reuse={"default": str(base)}), log=None)
    with pytest.raises(Sim2RealError, match="reuse: no variant named w"):
        _cfg(tmp, tmp_path / "p", reuse={"w": str(base)})
    assert not (tmp_path / "p").exists()
    assert main(["sim2real", "--real", "r", "--out", "o", "--reuse-run", "nameonly"]) == 2


@pytest.mark.slow
def test_a_phase_head_variant_generates_and_trains_in_the_experiment(tmp_path, capsys):
    """`--variant "ph: | --head phase"` end to end (about 10 s on 2 cores): the generated figshare set's native/
    folder gives the phase head its exact phase and rig; the checkpoint is evaluated like any other."""
    write_figshare(tmp_path / "real", n=1, h=352, w=640, seed=2)
    out = tmp_path / "o"
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--count", "6", "--epochs", "1",
                 "--base-channels", "4", "--batch-size", "2", "--workers", "1", "--no-figures",
                 "--variant", "ph: | --head phase --no-augment"]) == 0
    v = json.loads((out / "report.json").read_text())["variants"][0]
    assert v["train"] == ["--head", "phase", "--no-augment"] and v["images"] == 1
    config = json.loads((out / "ph" / "run" / "config.json").read_text())
    assert config["head"] == "phase" and config["synthetic"] == [v["data"]]
    assert np.isfinite(v["real"]["object_rmse_mm"]) and "| ph |" in capsys.readouterr().out
