"""`fppsim validate-psp`: PSP ground truth vs exact height through the full renderer, sweeps, CLI errors.

Noise-free exactness settings (see test_noise_free_*): the renderer's noise is off and 8-bit
quantisation (projector pattern and camera) stays on. What remains is
* the camera's 8-bit quantisation: phase error ``sqrt(2/N) * 0.29 / B`` = ``0.204 / B`` rad for four
  steps, i.e. about ``0.42 / B`` mm with the default rig (0.48 rad of 80-period phase per mm of height).
  The darkest default draws (gain 150, plane albedo 0.30, projector blur 1.6 px) give B ~ 18 gray
  levels on the plane and ~0.023 mm, above 0.02 mm; so these tests fix a mid-range exposure
  (gain 200, plane albedo 0.40, projector blur 1.0 px: B ~ 32, expected ~0.013 mm).
* camera blur mixes the phases of object and background across occluding contours (order errors of
  several mm there) and, with the renderer's ``mode="nearest"`` border handling, shifts the phase of
  the outer image columns; so these tests set camera_blur = 0. The default-optics test keeps it.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fppsim.cli import main
from fppsim.validate import (DEFAULT_SWEEP, ValidateConfig, ValidateError, evaluate_sample, parse_sweep, resolve_dataset,
                             sweep_settings)

ROOT = Path(__file__).resolve().parents[2]
from _helpers import SHARED_MESHES, synthesize_stack

SPOT = SHARED_MESHES / "spot.obj"
NOISE_FREE = ["--noise-free", "--optics", "camera_blur=0", "--optics", "projector_blur=1.0",
              "--optics", "gain=200", "--optics", "albedo_plane=0.4"]
RMSE_BOUND_MM = 0.02


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    path = tmp_path_factory.mktemp("sphere") / "sphere.ply"
    trimesh.creation.icosphere(5, radius=40.0).export(path)
    return path


@pytest.fixture(scope="module")
def sculpture(tmp_path_factory):
    plys = sorted((ROOT / "fppsim" / "data" / "meshes").glob("*.ply"))
    if plys:
        return plys[0]
    # fallback: a bumpy, non-convex blob (sculpture-like relief) written to a temporary PLY
    m = trimesh.creation.icosphere(5, radius=35.0)
    v = m.vertices
    r = 1.0 + 0.15 * np.sin(3 * np.arctan2(v[:, 1], v[:, 0])) * np.cos(2 * np.arccos(v[:, 2] / 35.0))
    m.vertices = v * r[:, None] * [1.4, 1.0, 0.8]
    path = tmp_path_factory.mktemp("sculpture") / "blob.ply"
    m.export(path)
    return path


def _validate(args, capsys=None):
    rc = main(["validate-psp", "-q", *map(str, args)])
    out = capsys.readouterr() if capsys is not None else None
    return rc, out


def _report(out):
    return json.loads((Path(out) / "report.json").read_text())


# ---------------------------------------------------------------------------------------------- full renderer
def _check_noise_free(report):
    agg = report["aggregate"]
    for s in report["samples"]:
        assert s["noise_free"] is True and s["optics"]["camera_blur"] == 0
        assert s["n_valid"] > 100_000
        assert s["n_order_errors_accepted"] == 0, s["id"]
        assert s["rmse_mm_incl_order_errors"] < RMSE_BOUND_MM, (s["id"], s["rmse_mm_incl_order_errors"])
        assert s["rejected_fraction"] < 0.005
    assert agg["n_order_errors_accepted"] == 0
    assert agg["rmse_mm_incl_order_errors"] < RMSE_BOUND_MM
    assert agg["rmse_mm_incl_order_errors"] == agg["rmse_mm_excl_order_errors"]
    assert abs(agg["mean_mm_incl_order_errors"]) < 0.002  # no bias
    # wrong orders before rejection sit on unmodulated (grazing) pixels and are all rejected
    assert agg["order_errors_caught_fraction"] in (None, 1.0)
    return agg


def test_noise_free_sphere(tmp_path, sphere, capsys):
    out = tmp_path / "v"
    rc, io = _validate(["--meshes", sphere, "--count", 2, "--seed", 1, "--out", out, *NOISE_FREE], capsys)
    assert rc == 0, io.err
    rep = _report(out)
    agg = _check_noise_free(rep)
    assert "all (2, pooled)" in io.out and "RMSE mm" in io.out
    assert f"{agg['rmse_mm_incl_order_errors']:.4f}" in io.out
    for s in rep["samples"]:
        png = out / s["error_map"]
        assert png.is_file() and png.read_bytes()[:4] == b"\x89PNG"
    assert (out / "samples" / "manifest.jsonl").is_file()  # rendered set kept (resumable)
    assert rep["settings"]["config"]["optics_ranges"]["camera_blur"] == [0.0, 0.0]
    assert rep["analysis"]["edge_px"] == 3


@pytest.mark.parametrize("which", ["sculpture", "spot"])
def test_noise_free_sculpture(tmp_path, which, sculpture):
    mesh = sculpture if which == "sculpture" else SPOT
    if not Path(mesh).is_file():
        pytest.skip(f"{mesh} not present")
    out = tmp_path / "v"
    rc, _ = _validate(["--meshes", mesh, "--count", 2, "--seed", 2, "--objects", "1-2", "--out", out,
                       "--no-maps", *NOISE_FREE])
    assert rc == 0
    _check_noise_free(_report(out))


def test_default_optics_on_figshare_dataset(tmp_path, sculpture, capsys):
    """Default randomised optics (noise, gamma, blur): order errors stay below 0.1 % of valid pixels."""
    meshes = [sculpture] + ([SPOT] if SPOT.is_file() else [])
    ds = tmp_path / "ds"
    assert main(["generate", "-q", "--no-preview", "--meshes", *map(str, meshes), "--out", str(ds),
                 "--count", "3", "--seed", "5", "--format", "figshare"]) == 0
    capsys.readouterr()
    out = tmp_path / "v"
    rc, io = _validate([ds, "--out", out, "--no-maps"], capsys)  # figshare folder -> its native/ samples
    assert rc == 0, io.err
    rep = _report(out)
    agg = rep["aggregate"]
    assert rep["dataset"] == str((ds / "native").resolve())
    assert agg["n_samples"] == 3 and agg["n_valid"] > 300_000
    assert agg["order_error_fraction"] < 1e-3
    # the numbers are reported, not judged: every statistic is present and finite
    for key in ("rmse_mm_incl_order_errors", "rmse_mm_excl_order_errors", "p99_abs_mm_incl_order_errors",
                "p99_abs_mm_excl_order_errors", "max_abs_mm_incl_order_errors", "rejected_fraction",
                "order_error_fraction", "order_error_fraction_before_rejection", "flagged_unreliable_fraction",
                "low_modulation_fraction", "rmse_mm_interior_excl_order_errors"):
        assert np.isfinite(agg[key]), key
    assert agg["rmse_mm_excl_order_errors"] <= agg["rmse_mm_incl_order_errors"]
    assert agg["n_order_errors_accepted"] + agg["n_order_errors_rejected"] == agg["n_order_errors"]
    # the unwrapper flags conservatively: it rejects more than it gets wrong, and catches most errors
    assert agg["flagged_unreliable_fraction"] >= agg["flagged_unreliable_wrong_fraction"]
    for s in rep["samples"]:
        assert s["noise_free"] is False and s["optics"]["noise_sigma"] > 0
        assert 0.8 <= s["optics"]["projector_blur"] <= 1.6
    assert "noise_sigma" in json.dumps(rep["settings"]["config"]["optics_ranges"])
    assert "all (3, pooled)" in io.out and f"{100 * agg['order_error_fraction']:.3f}" in io.out


@pytest.mark.slow  # over 5 s on a shared 2-core machine
def test_sweep_grid_same_scenes_and_resume(tmp_path, sphere, capsys):
    out = tmp_path / "sw"
    args = ["--meshes", sphere, "--count", 1, "--seed", 3, "--out", out, "--no-maps",
            "--sweep", "noise=0,2", "gamma=1,2.2"]
    rc, io = _validate(args, capsys)
    assert rc == 0, io.err
    rep = _report(out)
    names = [r["name"] for r in rep["rows"]]
    assert names == ["noise_sigma=0__projector_gamma=1", "noise_sigma=0__projector_gamma=2.2",
                     "noise_sigma=2__projector_gamma=1", "noise_sigma=2__projector_gamma=2.2"]
    assert rep["combination"].startswith("full grid")
    for n in names:
        assert n in io.out
        assert (out / "sweep" / n / "report.json").is_file()
    # same scene and same other optics draws in every setting; swept values fixed, shot noise 0
    first = None
    for r in rep["rows"]:
        folder = out / "sweep" / r["name"] / "samples" / "000000"
        meta = json.loads((folder / "meta.json").read_text())
        with np.load(folder / "arrays.npz") as z:
            height = z["height"]
        o = meta["optics"]
        assert o["noise_sigma"] == r["setting"]["noise_sigma"] and o["shot_noise"] == 0.0
        assert o["projector_gamma"] == r["setting"]["projector_gamma"]
        if first is None:
            first = (height, o)
        else:
            assert np.array_equal(height, first[0])
            assert all(o[k] == first[1][k] for k in ("gain", "albedo_plane", "projector_blur", "camera_blur"))
    agg = {r["name"]: r["aggregate"] for r in rep["rows"]}
    for g in ("1", "2.2"):
        assert (agg[f"noise_sigma=2__projector_gamma={g}"]["rmse_mm_excl_order_errors"]
                > 2 * agg[f"noise_sigma=0__projector_gamma={g}"]["rmse_mm_excl_order_errors"])
    # resumable: a second run renders nothing new
    before = {p: p.stat().st_mtime_ns for p in out.glob("sweep/*/samples/*/arrays.npz")}
    rc, io = _validate(args, capsys)
    assert rc == 0
    assert io.out.count("0 written, 1 already there") == 4
    assert {p: p.stat().st_mtime_ns for p in out.glob("sweep/*/samples/*/arrays.npz")} == before


def test_sweep_from_dataset_rerenders_its_scenes(tmp_path, sphere, capsys):
    ds = tmp_path / "ds"
    assert main(["generate", "-q", "--no-preview", "--meshes", str(sphere), "--out", str(ds), "--count", "1",
                 "--seed", "4"]) == 0
    out = tmp_path / "v"
    rc, io = _validate([ds, "--out", out, "--no-maps", "--sweep", "blur=1.2"], capsys)
    assert rc == 0, io.err
    new = out / "sweep" / "projector_blur=1.2" / "samples" / "000000"
    with np.load(ds / "000000" / "arrays.npz") as a, np.load(new / "arrays.npz") as b:
        assert np.array_equal(a["height"], b["height"]) and np.array_equal(a["mask"], b["mask"])
    assert json.loads((new / "meta.json").read_text())["optics"]["projector_blur"] == 1.2


# ---------------------------------------------------------------------------------------------- CLI errors
def _error(args, capsys):
    rc = main(["validate-psp", "-q", *map(str, args)])
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1
    return err


def test_cli_errors(tmp_path, sphere, capsys):
    out = tmp_path / "out"
    assert "dataset folder not found" in _error([tmp_path / "nope", "--out", out], capsys)
    (tmp_path / "empty").mkdir()
    assert "empty folder" in _error([tmp_path / "empty", "--out", out], capsys)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.txt").write_text("x")
    assert "not an fppsim dataset" in _error([tmp_path / "junk", "--out", out], capsys)
    nopsp = tmp_path / "nopsp"
    assert main(["generate", "-q", "--no-preview", "--no-psp", "--meshes", str(sphere), "--out", str(nopsp),
                 "--count", "1"]) == 0
    capsys.readouterr()
    assert "no PSP data" in _error([nopsp, "--out", out], capsys)
    assert "no PSP data" in _error([nopsp, "--out", out, "--sweep"], capsys)
    assert not out.exists()


def test_cli_usage_errors_exit_2_before_writing(tmp_path, sphere, capsys):
    """Flags wrong on their own or together are usage errors: one line naming the flag, exit 2, nothing written
    (QA: they exited 1; --max-rows -1 printed 2 of 3 rows, --edge-px -3 turned the edge split off silently)."""
    out, ds = tmp_path / "out", tmp_path / "ds"
    ds.mkdir()
    for args, msg in (([], "nothing to validate"), (["--meshes", sphere], "--count"),
                      ([ds, "--meshes", sphere], "not both"), ([ds, "--optics", "gain=1"], "--optics"),
                      ([ds, "--count", 1], "--count"),
                      (["--meshes", sphere, "--count", 1, "--sweep", "colour=1,2"], "unknown optics parameter 'colour'"),
                      (["--meshes", sphere, "--count", 1, "--sweep", "noise=abc"], "--sweep noise: 'abc' is not a number"),
                      (["--meshes", sphere, "--count", 1, "--sweep", "noise=-1"], "--sweep noise: -1 is out of range"),
                      (["--meshes", sphere, "--count", 1, "--noise-free", "--sweep"], "noise-free"),
                      ([ds, "--edge-px", -3], "--edge-px"), ([ds, "--max-rows", -1], "--max-rows")):
        try:
            rc = main(["validate-psp", "-q", *map(str, args), "--out", str(out)])
        except SystemExit as exc:  # argparse's own refusals
            rc = exc.code
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and msg in err[-1], (args, err)
        assert not out.exists()
    with pytest.raises(ValidateError, match="--edge-px"):
        ValidateConfig(out=out, dataset=ds, edge_px=-1)
    with pytest.raises(SystemExit):
        main(["validate-psp", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "(default 3; 0: off)" in help_text and "(default 20;" in help_text


def test_never_replaces_a_users_report_or_map(tmp_path, sphere, capsys):
    """QA H2: validate-psp --out replaced the user's report.json and maps/<id>.png (exit 0) and kept no record."""
    ds = tmp_path / "ds"
    assert main(["generate", "-q", "--no-preview", "--meshes", str(sphere), "--out", str(ds), "--count", "1"]) == 0
    user = tmp_path / "user"
    (user / "maps").mkdir(parents=True)
    (user / "report.json").write_text("my notes")
    assert "report.json exists and was not written by fppsim validate-psp" in _error([ds, "--out", user], capsys)
    assert (user / "report.json").read_text() == "my notes" and not (user / ".fppsim-owned.json").exists()
    # review: a dataset.json that cannot be read back is the data's problem (exit 1, named), not a usage error
    settings = json.loads((ds / "dataset.json").read_text())
    settings.pop("seed")
    (ds / "dataset.json").write_text(json.dumps(settings))
    rc = main(["validate-psp", "-q", str(ds), "--out", str(tmp_path / "v"), "--sweep", "noise=0,1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and f"{ds / 'dataset.json'} cannot be turned back into generation settings" in err[-1], err
    assert sorted(p.name for p in user.rglob("*")) == ["maps", "report.json"]
    (user / "report.json").unlink()
    (user / "maps" / "000000.png").write_text("my image")
    assert "000000.png exists and was not written" in _error([ds, "--out", user], capsys)
    assert (user / "maps" / "000000.png").read_text() == "my image" and not (user / "report.json").exists()
    # its own folder: re-runs work, and the record names what it wrote
    out = tmp_path / "v"
    for _ in range(2):
        rc, io = _validate([ds, "--out", out], capsys)
        assert rc == 0, io.err
    assert set(json.loads((out / ".fppsim-owned.json").read_text())["files"]) == {"report.json", "maps/000000.png"}
    # a folder written before the record existed is adopted (its report lists its maps) ...
    (out / ".fppsim-owned.json").unlink()
    rc, io = _validate([ds, "--out", out], capsys)
    assert rc == 0, io.err
    # ... but not a user's PNG its old report does not prove its own
    (out / ".fppsim-owned.json").unlink()
    (out / "maps" / "000000.png").write_text("my image")
    assert "000000.png exists and was not written" in _error([ds, "--out", out], capsys)
    # --meshes: refused before anything is rendered into OUT/samples
    rc = main(["validate-psp", "-q", "--meshes", str(sphere), "--count", "1", "--out", str(user)])
    assert rc == 1 and not (user / "samples").exists()


# ---------------------------------------------------------------------------------------------- units
def test_evaluate_sample_counts_and_errors():
    H, W = 40, 60
    rng = np.random.default_rng(0)
    phase_true = np.tile(np.linspace(0, 100, W), (H, 1)).astype(np.float32)
    height = rng.uniform(0, 20, (H, W)).astype(np.float32)
    mask = np.ones((H, W), np.float32)
    mask[:, :5] = 0  # shadow
    err = rng.normal(0, 0.01, (H, W))
    phase_psp = phase_true + rng.normal(0, 0.01, (H, W)).astype(np.float32)
    mask_psp = mask.copy()
    phase_psp[10, 20] += 2 * np.pi  # accepted wrong order
    err[10, 20] = 5.0
    phase_psp[11, 21] -= 2 * np.pi  # wrong order, rejected
    mask_psp[11, 21] = 0
    mask_psp[12, 22] = 0  # rejected, correct order
    height_psp = np.where(mask_psp > 0, height + err, np.nan).astype(np.float32)
    arrays = {"height": height, "depth": 500 - height, "phase_true": phase_true, "mask": mask,
              "phase_psp": phase_psp, "height_psp": height_psp, "mask_psp": mask_psp}
    meta = {"psp": {"freqs": [1, 8, 80], "steps": 4}, "rig": {"periods": 80.0, "camera": {"K": np.eye(3) * 1000}}}
    s = evaluate_sample(arrays, meta, edge_px=2)
    nv = H * (W - 5)
    assert s["n_valid"] == nv and s["n_rejected"] == 2 and s["n_accepted"] == nv - 2
    assert s["n_order_errors"] == 2 and s["n_order_errors_accepted"] == 1 and s["n_order_errors_rejected"] == 1
    assert s["order_error_fraction"] == pytest.approx(1 / nv)
    assert s["rejected_fraction"] == pytest.approx(2 / nv)
    assert s["rejected_correct_order_fraction"] == pytest.approx(1 / nv)
    assert s["order_errors_caught_fraction"] == pytest.approx(0.5)
    acc = (mask > 0) & (mask_psp > 0)
    e = (height_psp.astype(np.float64) - height)[acc]
    assert s["rmse_mm_incl_order_errors"] == pytest.approx(np.sqrt(np.mean(e ** 2)), rel=1e-9)
    ok = acc.copy()
    ok[10, 20] = False
    e_ok = (height_psp.astype(np.float64) - height)[ok]
    assert s["rmse_mm_excl_order_errors"] == pytest.approx(np.sqrt(np.mean(e_ok ** 2)), rel=1e-9)
    assert s["max_abs_mm_incl_order_errors"] == pytest.approx(5.0, abs=1e-5)
    assert s["max_abs_mm_excl_order_errors"] < 0.1
    assert s["n_edge"] + s["n_interior"] == ok.sum() and s["n_edge"] > 0
    assert "flagged_unreliable_fraction" not in s  # no images given: no breakdown


def test_evaluate_sample_breakdown_from_images():
    """With the phase-shifted images, rejections split into low modulation vs unreliable order."""
    from fppsim.phase import psp

    H, W = 8, 912
    u = np.tile(np.arange(W, dtype=np.float64), (H, 1))
    B = np.full((H, W), 60.0)
    B[:, 400:410] = 1.0  # unmodulated stripe
    stacks = {f: np.clip(np.rint(synthesize_stack(2 * np.pi * f * u / W, 100.0, B)), 0, 255).astype(np.uint8)
              for f in (1, 8, 80)}
    phase_true = 2 * np.pi * 80 * u / W
    un = psp.unwrap_temporal([psp.wrapped_phase(stacks[f].astype(float)).phase for f in (1, 8, 80)], (1, 8, 80))
    ok = un.reliable & (B > 3)
    arrays = {"height": np.zeros((H, W)), "depth": np.full((H, W), 500.0), "phase_true": phase_true,
              "mask": np.ones((H, W)), "phase_psp": un.phase, "height_psp": np.where(ok, 0.0, np.nan),
              "mask_psp": ok.astype(float)}
    meta = {"psp": {"freqs": [1, 8, 80], "steps": 4}, "rig": {"periods": 80.0, "camera": {"K": np.eye(3) * 1000}}}
    s = evaluate_sample(arrays, meta, stacks)
    assert s["low_modulation_fraction"] == pytest.approx(10 / W)
    assert s["flagged_unreliable_fraction"] > 0  # the seam columns at the projector edges at least
    assert s["rejected_fraction"] == pytest.approx((~ok).mean())
    assert s["rejected_other_fraction"] == 0.0
    assert s["n_order_errors_accepted"] == 0


def test_parse_sweep_names_and_grid():
    assert parse_sweep([]) == parse_sweep(list(DEFAULT_SWEEP)) == [
        ("noise_sigma", [0.0, 0.5, 1.0, 2.0]), ("projector_gamma", [1.0, 2.2])]
    g = parse_sweep(["blur=0.5,1,2", "camera_blur=0,1", "pattern_bits=8,0"])
    assert g == [("projector_blur", [0.5, 1.0, 2.0]), ("camera_blur", [0.0, 1.0]), ("pattern_bits", [8, 0])]
    settings = sweep_settings(g)
    assert len(settings) == 12 and len({n for n, _ in settings}) == 12
    assert settings[0] == ("projector_blur=0.5__camera_blur=0__pattern_bits=8",
                           {"projector_blur": 0.5, "camera_blur": 0.0, "pattern_bits": 8})
    noise = sweep_settings(parse_sweep(["noise=1"]))
    assert noise == [("noise_sigma=1", {"noise_sigma": 1.0, "shot_noise": 0.0})]
    assert sweep_settings(parse_sweep(["noise=1"]), base={"shot_noise": 0.05})[0][1] == {"noise_sigma": 1.0}
    assert sweep_settings(parse_sweep(["noise=1", "shot_noise=0.1"]))[0][1] == {"noise_sigma": 1.0, "shot_noise": 0.1}
    for bad, msg in (["noise"], "NAME=V1"), (["gamma=0"], "out of range"), (["noise=a"], "not a number"), \
                    (["noise=1", "noise_sigma=2"], "twice"), (["foo=1"], "unknown"):
        with pytest.raises(ValidateError, match=msg):
            parse_sweep(bad)


def test_resolve_dataset(tmp_path):
    (tmp_path / "fig" / "native").mkdir(parents=True)
    (tmp_path / "fig" / "native" / "manifest.jsonl").write_text("")
    (tmp_path / "fig" / "Z.npy").write_text("")
    assert resolve_dataset(tmp_path / "fig") == tmp_path / "fig" / "native"
    with pytest.raises(ValidateError, match="not found"):
        resolve_dataset(tmp_path / "missing")
