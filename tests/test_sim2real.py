"""uhrnet.workflows.sim2real: object mask, metrics on real data, variants/ablation parsing (``uhrnet sim2real``),
stage configs, report, evaluation, and a whole tiny experiment run twice (resumed)."""

from pathlib import Path

import numpy as np
import pytest

from uhrnet.cli import variant_commands
from uhrnet.errors import UsageError
from uhrnet.workflows.sim2real.variants import (
    VariantFlags, load_variants, parse_variant, recipe_commands, variant_from_flags,
)
from uhrnet.workflows.sim2real import (
    SCALES, Sim2RealConfig, Sim2RealError, Variant, data_key, evaluate_level, evaluate_real, generate_config,
    level_response, markdown_report, object_mask, plane_level, real_metrics, train_config,
)

from _helpers import REAL_SAMPLE, load_pipeline, train_tiny, write_figshare


def _scene(h=60, w=80, plane=-97.0, bump_mm=30.0):
    """A plane label with noise +-0.5 units, a disc 'object' of bump_mm and a shadow of -105."""
    rng = np.random.default_rng(0)
    label = plane + rng.uniform(-0.5, 0.5, (h, w))
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (yy - 30) ** 2 + (xx - 40) ** 2 < 15 ** 2
    label[disc] = plane + 6.0 * bump_mm
    shadow = (yy - 30) ** 2 + (xx - 20) ** 2 < 5 ** 2
    label[shadow & ~disc] = -105.0
    return label, label > -100, disc, shadow & ~disc


def test_plane_level_and_object_mask_against_construction():
    label, valid, disc, _ = _scene()
    assert plane_level(label, valid) == pytest.approx(-97.0, abs=0.2)
    obj, plane = object_mask(label, valid, 6.0, 1.0)
    np.testing.assert_array_equal(obj, disc)
    # a bump lower than object_mm is not an object
    low, v, _, _ = _scene(bump_mm=0.5)
    assert not object_mask(low, v, 6.0, 1.0)[0].any()


def test_real_metrics_perfect_flat_and_offset_predictions():
    label, valid, disc, _ = _scene(bump_mm=30.0)
    m = real_metrics(label, label, valid)
    assert m["object_rmse_mm"] == 0 and m["valid_rmse_mm"] == 0
    assert m["true_object_mean_mm"] == pytest.approx(30.0, abs=0.1)
    assert m["object_fraction"] == pytest.approx(disc.mean())
    flat = np.full_like(label, -97.0)
    m = real_metrics(flat, label, valid)
    assert m["object_rmse_mm"] == pytest.approx(30.0, abs=0.1) == m["flat_object_rmse_mm"]
    assert m["pred_object_mean_mm"] == pytest.approx(0.0, abs=0.1)
    expected_valid = np.sqrt(np.mean(((flat - label)[valid] / 6.0) ** 2))
    assert m["valid_rmse_mm"] == pytest.approx(expected_valid)
    half = label + np.where(disc, -6.0 * 15.0, 0.0)  # objects predicted 15 mm too low
    m = real_metrics(half, label, valid)
    assert m["object_rmse_mm"] == pytest.approx(15.0) and m["object_bias_mm"] == pytest.approx(-15.0)
    assert m["background_rmse_mm"] == 0


def test_parse_variant_forms():
    assert parse_variant("base") == VariantFlags("base", [], [])
    v = parse_variant("aug-off: | --no-augment")
    assert v.generate == [] and v.train == ["--no-augment"]
    v = parse_variant("rig: --rig-jitter 0 --optics 'gain=200,210'")
    assert v.generate == ["--rig-jitter", "0", "--optics", "gain=200,210"] and v.train == []
    v = parse_variant("both: --procedural-share 0 | --no-augment --lr 1e-3")
    assert v.generate == ["--procedural-share", "0"] and v.train == ["--no-augment", "--lr", "1e-3"]
    with pytest.raises(Sim2RealError, match="variant name"):
        parse_variant("a/b")
    with pytest.raises(Sim2RealError, match="quotation"):
        parse_variant("x: --optics 'gain=1")


def test_load_variants_yaml(tmp_path):
    p = tmp_path / "abl.yaml"
    p.write_text("- name: base\n- name: no-aug\n  train: --no-augment\n"
                 "- name: parallel\n  generate: [--rig, assets/parallel.json]\n- 'x: --count 3 | --lr 1'\n")
    vs = load_variants(p)
    assert [v.name for v in vs] == ["base", "no-aug", "parallel", "x"]
    assert vs[1].train == ["--no-augment"] and vs[2].generate == ["--rig", "assets/parallel.json"]
    p.write_text("- name: a\n  bogus: 1\n")
    with pytest.raises(Sim2RealError, match="unknown keys"):
        load_variants(p)
    p.write_text("{}")
    with pytest.raises(Sim2RealError, match="non-empty list"):
        load_variants(p)
    with pytest.raises(Sim2RealError, match="not found"):
        load_variants(tmp_path / "nope.yaml")



@pytest.mark.parametrize("entry, key", [("{name: a, generate: 5}", "generate"), ("{name: a, train: {lr: 1}}", "train"),
                                        ("{name: a, adapt: 0}", "adapt"), ("{name: a, refine: 3}", "refine"),
                                        ("{name: a, train: [[--lr, 1]]}", "train")])
def test_an_ablation_value_of_the_wrong_type_is_refused_not_ignored(tmp_path, entry, key):
    """``generate: 5`` ran the default generate flags: a value that is not flags was read as none."""
    p = tmp_path / "abl.yaml"
    p.write_text(f"- {entry}\n")
    with pytest.raises(Sim2RealError, match=f"item 0 \\(a\\): {key} must be a string of"):
        load_variants(p)
    p.write_text("- {name: a, generate: [--seed, 3], adapt: true, refine: true}\n- {name: b, adapt: false, refine: null}\n")
    a, b = load_variants(p)
    assert a == VariantFlags("a", ["--seed", "3"], [], [], ("relief",)) and b == VariantFlags("b", [], [], None, ())


@pytest.mark.parametrize("spec, code, says", [
    ("a: --bogus 3", 2, "variant 'a': generate: unrecognized arguments: --bogus 3"),
    ("a: --count -3", 2, "variant 'a': generate: argument --count"),
    ("a: | --epochs -3", 2, "variant 'a': train: --epochs must be >= 1"),
    ("a: | | adapt --bogus", 2, "variant 'a': adapt: unrecognized arguments: --bogus"),
    ("a: --optics-file /nonexistent/o.yaml", 1, "variant 'a': generate: "),
    ("a: | --init-from /nonexistent/run", 1, "variant 'a': train: "),
])
def test_variant_flag_errors_exit_as_their_commands_would(tmp_path, capsys, spec, code, says):
    """A flag a variant's command does not take, or a value its parser or config refuses on its own, exits 2 as on
    that command's own line (they exited 1); a missing file stays exit 1. One line, nothing written."""
    from uhrnet.cli import main

    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    out = tmp_path / "o"
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--variant", spec]) == code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert not out.exists()


def test_an_ablation_files_flag_error_names_the_file(tmp_path, capsys):
    """A flag an --ablation entry's command does not take is the file's error (exit 1, the file named), as its
    other errors; the same flag on the command line is a usage error (exit 2)."""
    from uhrnet.cli import main

    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    (tmp_path / "abl.yaml").write_text("- {name: a, train: --bogus}\n")
    out = tmp_path / "o"
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--ablation",
                 str(tmp_path / "abl.yaml")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{tmp_path / 'abl.yaml'}: variant 'a': train: unrecognized" in err, err
    assert not out.exists()


@pytest.mark.parametrize("flags", [["--lr", "-1"], ["--lr", "nan"], ["--batch-size", "0"], ["--base-channels", "-3"],
                                   ["--seed", "-1"]])
def test_recipe_training_numbers_are_usage_errors_before_anything_runs(tmp_path, capsys, flags):
    """They were checked when the training config was built (Sim2RealError, exit 1), or, for --base-channels,
    only when the model was built, after the dataset had been generated."""
    from uhrnet.cli import main

    out = tmp_path / "o"
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--count", "6", *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and flags[0] in err and "variant" not in err, err
    assert not out.exists()


def test_devices_and_training_inputs_are_checked_before_generating(tmp_path, monkeypatch):
    """No CUDA for --device cuda / --scale gpu, a variant's missing --init-from checkpoint, --val-phase folder or
    --rig file: refused before the first stage (they failed in the train stage, after generating the data)."""
    import torch

    from uhrnet.workflows.sim2real import run_sim2real

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    out = tmp_path / "o"

    def cfg(**kw):
        return Sim2RealConfig(out=str(out), real=[str(tmp_path / "real")], count=6, epochs=1, base_channels=4, **kw)

    for kw, match in (({"device": "cuda"}, "--device cuda: no CUDA device"),
                      ({"scale": "gpu"}, "--scale gpu recipe's device"),
                      ({"variants": [Variant("x", train={"device": "cuda"})]}, "variant 'x': train: --device cuda"),
                      ({"variants": [Variant("x", train={"init_from": str(tmp_path / "none")})]},
                       "variant 'x': train: .*none: checkpoint not found"),
                      ({"variants": [Variant("x", train={"val_phase": [str(tmp_path / "none")]})]},
                       "variant 'x': train: --val-phase: .*none"),
                      ({"variants": [Variant("x", train={"head": "phase", "rig": str(tmp_path / "none.json")})]},
                       "variant 'x': train: .*none.json")):
        with pytest.raises(Sim2RealError, match=match):
            run_sim2real(cfg(**kw), log=None)
        assert not out.exists()


def test_config_scales_and_stage_configs(tmp_path):
    cfg = Sim2RealConfig(out=str(tmp_path), real=["r"], meshes=["../shared/meshes", "assets/meshes"])
    assert (cfg.count, cfg.seed, cfg.epochs, cfg.model, cfg.base_channels) == (400, 100, 10, "unet", 16)
    g = generate_config(cfg, Variant("v", {"rig_jitter": (0.02, 0.03)}), tmp_path / "syn")
    assert g.meshes == ["../shared/meshes", "assets/meshes"] and g.out == str(tmp_path / "syn")
    assert (g.count, g.seed, g.workers, g.format, g.psp_freqs, g.rig_jitter) == (400, 100, 2, "figshare", (), (0.02, 0.03))
    assert g.label.name == "figshare" and g.preview and not g.progress
    t = train_config(cfg, Variant("v", train={"augment": "off"}), tmp_path / "syn", tmp_path / "run")
    assert (t.model, t.base_channels, t.loss, t.epochs, t.batch_size, t.lr, t.device) == \
        ("unet", 16, "compound", 10, 2, 5e-4, "cpu")
    assert t.synthetic == [str(tmp_path / "syn")] and t.augment == "off" and t.resume is None and not t.amp
    assert train_config(cfg, Variant("v"), "d", "r", resume=True).resume == "auto"
    gpu = Sim2RealConfig(out=str(tmp_path), real=["r"], scale="gpu")
    tg = train_config(gpu, Variant("v"), tmp_path, tmp_path)
    assert gpu.model == "uhrnet" and gpu.count >= 2000 and tg.base_channels is None and tg.amp is True
    with pytest.raises(Sim2RealError, match="unknown scale"):
        Sim2RealConfig(out="o", real=["r"], scale="tpu")
    with pytest.raises(Sim2RealError, match="unique"):
        Sim2RealConfig(out="o", real=["r"], variants=[Variant("a"), Variant("a")])
    with pytest.raises(Sim2RealError, match="no real data"):
        Sim2RealConfig(out="o", real=[])
    with pytest.raises(Sim2RealError, match="has no field"):
        Variant("v", generate={"pedestals": 0})
    with pytest.raises(Sim2RealError, match="set by the experiment"):
        Variant("v", train={"out": "x"})
    assert set(SCALES) == {"cpu", "gpu"}
    assert data_key({}) == "defaults" and data_key({"pedestal": 0.0}) == data_key({"pedestal": 0.0}) != \
        data_key({"pedestal": 0.5})


def test_variant_flags_become_config_overrides_and_the_recipe_command_lines(tmp_path):
    cfg = Sim2RealConfig(out=str(tmp_path), real=["r"], meshes=["../shared/meshes", "assets/meshes"])
    v = variant_from_flags(cfg, parse_variant("both: --pedestal 0 --rig-jitter 0.02,0.03 --seed 100 | "
                                              "--no-augment --lr 1e-3 --epochs 10"), variant_commands())
    # flags that repeat the recipe (--seed 100, --epochs 10) change nothing
    assert v.generate == {"pedestal": 0.0, "rig_jitter": (0.02, 0.03)}
    assert v.train == {"augment": "off", "lr": 1e-3}
    assert v.described("generate") == ["--pedestal", "0", "--rig-jitter", "0.02,0.03", "--seed", "100"]
    assert Variant("x", {"pedestal": 0.0}).described("generate") == ["pedestal=0.0"]
    assert variant_from_flags(cfg, parse_variant("rig: --rig assets/parallel_rig.json"), variant_commands()).generate == \
        {"rig": "assets/parallel_rig.json"}
    assert variant_from_flags(cfg, parse_variant("p: --no-psp --format figshare"), variant_commands()).generate == {}
    with pytest.raises(UsageError, match="variant 'bad': generate: unrecognized arguments: --bogus"):
        variant_from_flags(cfg, parse_variant("bad: --bogus"), variant_commands())
    with pytest.raises(UsageError, match="variant 'bad': train: argument --lr"):
        variant_from_flags(cfg, parse_variant("bad: | --lr x"), variant_commands())
    r = recipe_commands(cfg, v, tmp_path / "syn", tmp_path / "run")
    g, t = r["generate"].split(), r["train"].split()
    assert g[:3] == ["generate", "--meshes", "../shared/meshes"] and "--no-psp" in g
    assert g[-6:] == ["--pedestal", "0", "--rig-jitter", "0.02,0.03", "--seed", "100"]
    for a, b in (("--count", "400"), ("--seed", "100"), ("--workers", "2"), ("--format", "figshare")):
        assert g[g.index(a) + 1] == b
    for a, b in (("--model", "unet"), ("--base-channels", "16"), ("--loss", "compound"), ("--epochs", "10"),
                 ("--batch-size", "2"), ("--lr", "0.0005"), ("--device", "cpu")):
        assert t[t.index(a) + 1] == b
    assert t[-5:] == ["--no-augment", "--lr", "1e-3", "--epochs", "10"]
    gpu = Sim2RealConfig(out=str(tmp_path), real=["r"], scale="gpu")
    t = recipe_commands(gpu, Variant("v"), tmp_path, tmp_path)["train"].split()
    assert "--base-channels" not in t and t[-1] == "--amp"


def test_markdown_report_rows():
    real = {"object_rmse_mm": 12.3456, "valid_rmse_mm": 5.0, "flat_object_rmse_mm": 39.9,
            "true_object_mean_mm": 39.7, "pred_object_mean_mm": 25.7}
    report = {"config": {"scale": "cpu", "count": 400, "seed": 100, "model": "unet", "base_channels": 16,
                         "epochs": 10, "batch_size": 2, "lr": 5e-4, "loss": "compound", "object_mm": 1.0},
              "variants": [{"name": "base", "generate": [], "train": ["--no-augment"], "real": real,
                            "synthetic_val_rmse_mm": 3.9, "timing": {"train_s": 600.0}}]}
    md = markdown_report(report)
    row = [line for line in md.splitlines() if line.startswith("| base")][0]
    assert "12.35" in row and "39.7 / 25.7" in row and "--no-augment" in row and "(defaults)" in row
    assert "| 10.0 |" in row
    report["variants"][0]["synthetic_level"] = {"slope": -0.98, "intercept_mm": 30.4, "prior_level_mm": 31.02}
    row = [line for line in markdown_report(report).splitlines() if line.startswith("| base")][0]
    assert "| -0.98 / 31.0 |" in row
    # read back from real_metrics.json / synthetic_level.json, a metric that was not measured is null (None): a
    # blank cell, as NaN was (it was a TypeError on the resumed run's report)
    report["variants"][0]["real"] = {**real, "object_rmse_mm": None, "true_object_mean_mm": None,
                                     "pred_object_mean_mm": None, "relief_effect_mm": None}
    report["variants"][0]["synthetic_level"] = {"slope": None, "prior_level_mm": None}
    row = [line for line in markdown_report(report).splitlines() if line.startswith("| base")][0]
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[3] == "" and cells[4] == "5.00" and cells[6] == "/" and cells[7] == "" and cells[9] == ""


def test_evaluate_real_writes_metrics_predictions_and_figure(tmp_path):
    write_figshare(tmp_path / "syn", n=8, h=32, w=64, seed=1)
    real = tmp_path / "real"
    fr, z = write_figshare(real, n=2, h=32, w=64, seed=2)
    run = train_tiny(tmp_path / "run", "--synthetic", tmp_path / "syn", "--synthetic-split", "train",
                     extra=["--no-augment"])
    doc = evaluate_real(run / "last.pt", [str(real)], tmp_path / "ev", figures=True)
    assert doc["images"] == 2 and len(doc["per_image"]) == 2
    preds = np.load(tmp_path / "ev" / "predictions.npz")
    assert sorted(preds.files) == ["0_000000", "0_000001"]
    # the stored metrics are those of the stored predictions
    for row in doc["per_image"]:
        label = z[row["index"], ..., 0]
        m = real_metrics(preds[row["key"]], label, label > -100)
        assert m["valid_rmse_mm"] == pytest.approx(row["valid_rmse_mm"])
    assert (tmp_path / "ev" / "real_0_000000.png").stat().st_size > 1000
    assert (tmp_path / "ev" / "real_metrics.json").is_file()
    with pytest.raises(Sim2RealError, match="no labelled real samples"):
        evaluate_real(run / "last.pt", [str(tmp_path)], tmp_path / "ev2")
    # a pair whose label is the plane alone has no object pixel: its object metrics are not numbers, and the
    # file holds null for them (strict JSON), the measured ones as numbers
    flat = tmp_path / "flat"
    flat.mkdir()
    np.save(flat / "f1_80.npy", fr[:1])
    np.save(flat / "Z.npy", np.full_like(z[:1], -97.0))
    assert not object_mask(np.full(z.shape[1:3], -97.0), np.ones(z.shape[1:3], bool), 6.0, 1.0)[0].any()
    with pytest.warns(RuntimeWarning):  # nanmean of no number
        doc = evaluate_real(run / "last.pt", [str(flat)], tmp_path / "evf", figures=False)
    import json

    text = (tmp_path / "evf" / "real_metrics.json").read_text()
    back = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    assert np.isnan(doc["mean"]["object_rmse_mm"]) and back["mean"]["object_rmse_mm"] is None
    assert back["per_image"][0]["object_coverage"] is None and back["per_image"][0]["object_fraction"] == 0.0
    assert back["mean"]["valid_rmse_mm"] == pytest.approx(doc["mean"]["valid_rmse_mm"]) and "NaN" not in text


@pytest.mark.skipif(not (REAL_SAMPLE / "height_map.npy").is_file(), reason="../shared/real-sample absent")
def test_real_sample_object_pixels_reproduce_the_issue_numbers():
    """Object pixels of the published pair: 14.8% of the image, true mean 39.7 mm above the plane."""
    z = np.load(REAL_SAMPLE / "height_map.npy")
    m = real_metrics(np.full_like(z, -97.0), z, z > -100)
    assert m["true_object_mean_mm"] == pytest.approx(39.7, abs=0.1)
    assert m["flat_object_rmse_mm"] == pytest.approx(39.9, abs=0.5)
    assert m["object_fraction"] == pytest.approx(0.148, abs=0.002)


def test_pipeline_script_parses_variants_and_reports_bad_real_folders(tmp_path, capsys):
    mod = load_pipeline("sim2real")
    rc = mod.main(["--real", str(tmp_path), "--out", str(tmp_path / "o"), "--variant", "a: | --no-augment"])
    assert rc == 1 and "no labelled real samples" in capsys.readouterr().err
    abl = load_variants(Path(__file__).resolve().parents[1] / "pipelines" / "sim2real_ablation.yaml")
    assert abl[0].name == "defaults" and abl[0].generate == abl[0].train == []
    assert {"no-pedestal", "parallel-rig", "no-augment", "old-defaults", "procedural"} <= {v.name for v in abl}
    assert all(v.generate or v.train for v in abl[1:])  # every other row changes an option
    # every generate/train option of the rows parses with the real command lines
    from fppsim.cli import build_parser as fppsim_parser
    from uhrnet.cli import build_parser as uhrnet_parser

    for v in abl[1:]:
        if v.generate:
            fppsim_parser().parse_args(["generate", "--meshes", "m", "--out", "o", "--count", "1", *v.generate])
        if v.train:
            uhrnet_parser("train").parse_args(["train", "--synthetic", "s", "--out", "o", *v.train])


def test_fringe_twins_keep_the_envelope_and_drop_the_relief():
    from scipy import ndimage as ndi

    from uhrnet.workflows.sim2real import fringe_twins

    h, w = 96, 192
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    carrier = 2 * np.pi * xx / 11.7 + 0.3 * (xx / w) ** 2 + 0.1 * yy / h   # a slightly chirped carrier
    bump = np.exp(-((xx - 96) ** 2 + (yy - 48) ** 2) / (2 * 18.0 ** 2))
    obj = bump > 0.2
    relief = 5.0 * bump * obj                                              # up to 5 rad of relief phase
    shade = np.where(obj, 1.6, 1.0)                                        # a brighter object
    f = -0.5 + 0.1 * shade + 0.35 * shade * np.cos(carrier + relief)
    valid = np.ones((h, w), bool)
    valid[:, :6] = False
    f[~valid] = -1
    plane = valid & ~ndi.binary_dilation(obj, iterations=3)
    twins = fringe_twins(f, valid, plane)
    flat, env = twins["flat"], twins["envelope"]
    assert flat.dtype == np.float32 and np.all(flat[~valid] == -1) and np.all(env[~valid] == -1)
    inner = ndi.binary_erosion(obj, iterations=8)
    # under the object the flat twin follows the bare carrier, not the relief
    ac = flat - ndi.gaussian_filter(flat, 6)
    res = np.angle(ndi.gaussian_filter(ac * np.exp(-1j * carrier), 4))
    ref = np.angle(ndi.gaussian_filter((f - ndi.gaussian_filter(f, 6)) * np.exp(-1j * carrier), 4))
    assert np.abs(np.angle(np.exp(1j * (res - np.median(res[inner]))))[inner]).max() < 0.35
    assert np.ptp(np.unwrap(ref[48, 60:132])) > 3.0   # while the input's does carry it
    # the envelope (local background) keeps the object's brightness
    assert env[inner].mean() - env[plane & valid].mean() == pytest.approx(0.06, abs=0.02)


class _LevelModel:
    """Fake networks for level_response: ``truth`` returns the sample's own labels; ``prior`` the
    labels with every object pixel at one level (prior_mm above the plane) plus the true relief around
    the object's own mean (a network that reads relief but not level)."""

    def __init__(self, kind, labels, plane=-97.0, prior_mm=30.0):
        import torch

        self.kind, self.labels, self.plane, self.prior_mm = kind, labels, plane, prior_mm
        self.param = torch.nn.Parameter(torch.zeros(1))
        self.calls = 0

    def parameters(self):
        return iter([self.param])

    def eval(self):
        return self

    def __call__(self, x):
        import torch

        label = self.labels[self.calls]
        self.calls += 1
        out = label.copy()
        if self.kind == "prior":
            obj = label > self.plane + 5 * 6
            out[obj] = label[obj] - label[obj].mean() + self.plane + 6 * self.prior_mm
        return torch.from_numpy(out[None, None].astype(np.float32))


def _level_samples(levels_mm, h=48, w=64, plane=-97.0):
    import torch

    rng = np.random.default_rng(3)
    samples, labels = [], []
    yy, xx = np.mgrid[0:h, 0:w]
    for lv in levels_mm:
        label = plane + rng.uniform(-0.3, 0.3, (h, w))
        disc = (yy - 24) ** 2 + (xx - 32) ** 2 < 16 ** 2
        label[disc] = plane + 6 * (lv + 4 * np.cos(xx[disc] / 5.0))  # relief +-4 mm on a level lv
        labels.append(label)
        samples.append({"fringe": torch.zeros(1, h, w), "height": torch.from_numpy(label[None].astype(np.float32)),
                        "mask": torch.ones(1, h, w)})
    return samples, labels


def test_level_response_slope_zero_for_truth_and_minus_one_for_a_constant_level():
    levels = [15.0, 22.0, 31.0, 38.0, 45.0]
    samples, labels = _level_samples(levels)
    exact = level_response(_LevelModel("truth", labels), samples, min_pixels=100)
    assert exact["n_objects"] == 5 and exact["slope"] == pytest.approx(0.0, abs=1e-4)
    assert np.isnan(exact["prior_level_mm"]) and exact["shape_rmse_mm"] == pytest.approx(0.0, abs=1e-3)
    prior = level_response(_LevelModel("prior", labels, prior_mm=30.0), samples, min_pixels=100)
    # bias of each object = 30 - its true mean level: slope -1, prior 30 mm, no shape error
    truth_means = [h for h, _ in prior["objects"]]
    # (h is measured from the estimated plane, the fake network uses the exact one: a few 1e-3 mm apart)
    np.testing.assert_allclose([b for _, b in prior["objects"]], [30.0 - m for m in truth_means], atol=1e-2)
    assert prior["slope"] == pytest.approx(-1.0, abs=1e-4)
    assert prior["prior_level_mm"] == pytest.approx(30.0, abs=1e-2)
    assert prior["shape_rmse_mm"] == pytest.approx(0.0, abs=1e-3)
    few = level_response(_LevelModel("truth", labels), samples[:1], min_pixels=100)
    assert few["n_objects"] == 1 and np.isnan(few["slope"])


def test_evaluate_level_writes_the_report_file(tmp_path):
    write_figshare(tmp_path / "syn", n=8, h=32, w=64, seed=1)
    run = train_tiny(tmp_path / "run", "--synthetic", tmp_path / "syn", extra=["--no-augment"])
    doc = evaluate_level(run / "last.pt", [str(tmp_path / "syn")], tmp_path / "ev", object_mm=1.0)
    assert (tmp_path / "ev" / "synthetic_level.json").is_file()
    assert doc["epoch"] >= 1 and doc["n_objects"] == len(doc["objects"])


@pytest.mark.slow
def test_a_tiny_experiment_runs_its_stages_in_process_and_resumes(tmp_path, capsys):
    """`uhrnet sim2real` end to end (about 20 s on 2 cores): generate, train, evaluate, report; re-run: all re-used."""
    import json

    from uhrnet.cli import main

    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    out = tmp_path / "o"
    argv = ["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--count", "6", "--epochs", "1",
            "--base-channels", "4", "--batch-size", "2", "--workers", "1", "--no-figures",
            "--variant", "v: --pedestal 0 | --no-augment"]
    assert main(argv) == 0
    first = capsys.readouterr().out
    assert "[v] generate ->" in first and "[v] train ->" in first and "| v | --pedestal 0 | --no-augment |" in first
    report = json.loads((out / "report.json").read_text())
    v = report["variants"][0]
    assert v["generate"] == ["--pedestal", "0"] and v["train"] == ["--no-augment"] and v["images"] == 2
    assert report["config"]["count"] == 6 and "variants" not in report["config"]
    assert report["recipe"]["v"]["train"].endswith("--no-progress --threads 2 --no-augment")
    data = Path(v["data"])
    assert data.name == data_key({"pedestal": 0.0}) and (data / "Z.npy").is_file()
    assert (data.parent / f"{data.name}.log").read_text().startswith("$ generate --meshes")
    assert "epoch 1/1" in (out / "v" / "train.log").read_text()
    assert json.loads((out / "v" / "run" / "config.json").read_text())["augment"] == "off"
    assert {"generate_s", "train_s", "evaluate_s"} <= set(v["timing"])
    assert main(argv) == 0
    second = capsys.readouterr().out
    assert "generate ->" not in second and "train ->" not in second and "evaluate on" not in second
    assert json.loads((out / "report.json").read_text())["variants"][0]["real"] == v["real"]


def test_dataset_count_of_a_damaged_label_file_is_zero(tmp_path):
    """An .npz saved as Z.npy or an empty Z.npy was an AttributeError / EOFError traceback; now no dataset (0), so
    generate writes the folder afresh or says why it cannot."""
    from uhrnet.workflows.stages import dataset_count

    with open(tmp_path / "Z.npy", "wb") as fh:  # an archive under the label file's name
        np.savez(fh, a=np.zeros((2, 4, 4, 1), np.float32))
    assert dataset_count(tmp_path) == 0
    (tmp_path / "Z.npy").write_bytes(b"")
    assert dataset_count(tmp_path) == 0
    np.save(tmp_path / "Z.npy", np.zeros((3, 4, 4, 1), np.float32))
    assert dataset_count(tmp_path) == 3


def test_a_complete_dataset_of_another_seed_is_refused_before_training(tmp_path, monkeypatch):
    """A run stopped while training (its dataset complete) and started again with another --seed re-used that
    dataset, trained on the old seed's samples and reported the new seed ("6 synthetic samples (seed 11)" over seed
    9's): now refused before the first stage, naming both seeds; the same seed is taken as before."""
    import json

    from uhrnet.workflows.sim2real import run_sim2real

    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    out = tmp_path / "o"
    data = out / "data" / data_key({})
    write_figshare(data, n=6, h=32, w=64)  # what the stopped run's generate stage left: figshare arrays + native/
    (data / "native").mkdir()
    (data / "native" / "dataset.json").write_text(json.dumps({"generator": "fppsim", "seed": 9, "count": 6}))

    def cfg(seed):
        return Sim2RealConfig(out=str(out), real=[str(tmp_path / "real")], count=6, seed=seed, epochs=1,
                              base_channels=4, figures=False)

    with pytest.raises(Sim2RealError, match=rf"^variant 'default': {data} holds 6 samples generated with seed 9, "
                                            rf"not 11: give --seed 9 to continue, or move {data} and .* away$"):
        run_sim2real(cfg(11), log=None)
    assert not (out / "default").exists() and not (out / "report.json").exists()
    import uhrnet.workflows.sim2real.run as stages  # the same seed goes on to train on it (stopped there)

    monkeypatch.setattr(stages, "train", lambda tr: (_ for _ in ()).throw(ValueError(f"trains on {tr.synthetic}")))
    with pytest.raises(Sim2RealError, match=r"^train failed: trains on \[.*defaults'\]"):
        run_sim2real(cfg(9), log=None)


def test_a_complete_dataset_of_other_meshes_is_refused_before_training(tmp_path, monkeypatch, capsys):
    """As a dataset of another seed: one made from other meshes (its dataset.json's ``meshes``, the files generate
    loaded) was re-used by a run started again with other --meshes, which trained on the old meshes' samples. Now
    refused in one line (exit 1) naming both sides; the same meshes resume, given through a link or beside a file
    generate skipped (it does not load, so it was never recorded)."""
    import json
    import shutil

    import uhrnet.workflows.sim2real.run as stages
    from uhrnet.cli import main
    from uhrnet.workflows.sim2real import run_sim2real

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name in ("vase_s0.ply", "mask_s0.ply"):
        shutil.copy(Path(__file__).resolve().parents[1] / "assets" / "meshes" / name, meshes / name)
    (tmp_path / "other").mkdir()
    shutil.copy(meshes / "vase_s0.ply", tmp_path / "other" / "c.ply")
    write_figshare(tmp_path / "real", n=2, h=32, w=64, seed=2)
    out = tmp_path / "o"
    data = out / "data" / data_key({})
    write_figshare(data, n=6, h=32, w=64)
    (data / "native").mkdir()
    recorded = sorted(str(p) for p in meshes.iterdir())
    (data / "native" / "dataset.json").write_text(json.dumps({"generator": "fppsim", "seed": 9, "meshes": recorded}))

    def cfg(*given):
        return Sim2RealConfig(out=str(out), real=[str(tmp_path / "real")], count=6, seed=9, epochs=1,
                              base_channels=4, figures=False, meshes=[str(g) for g in given])

    for given, says in (([meshes / "vase_s0.ply"], f"1 not among --meshes, e.g. {meshes / 'mask_s0.ply'}"),
                        ([meshes, tmp_path / "other"], f"not {tmp_path / 'other' / 'c.ply'}, which --meshes gives")):
        with pytest.raises(Sim2RealError, match=rf"^variant 'default': {data} holds 6 samples generated from 2 mesh "
                                                rf"file\(s\) \(listed in its dataset.json; .* away$") as exc:
            run_sim2real(cfg(*given), log=None)
        assert says in str(exc.value) and "give the --meshes it was made from to continue" in str(exc.value)
    assert not (out / "default").exists() and not (out / "report.json").exists()
    capsys.readouterr()
    assert main(["sim2real", "--real", str(tmp_path / "real"), "--out", str(out), "--count", "6", "--seed", "9",
                 "--meshes", str(tmp_path / "other"), "--epochs", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "generated from 2 mesh file(s)" in err and "--meshes " in err, err
    # the same meshes (through a link to their folder, beside a garbage file generate skipped) go on to train
    (meshes / "junk.stl").write_bytes(b"not a mesh at all")
    (tmp_path / "link").symlink_to(meshes)
    monkeypatch.setattr(stages, "train", lambda tr: (_ for _ in ()).throw(ValueError(f"trains on {tr.synthetic}")))
    for given in ([meshes], [tmp_path / "link"]):
        with pytest.raises(Sim2RealError, match=r"^train failed: trains on \[.*defaults'\]"):
            run_sim2real(cfg(*given), log=None)
