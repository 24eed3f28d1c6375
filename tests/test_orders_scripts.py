"""The orders scripts (pipelines/orders_study.py, pipelines/orders_rendered.py) keep what they did not write:
their --out folders carry an ownership record, a foreign file there is refused in one line (exit 2) before any
work, and so is a bad checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import load_pipeline, one_line, train_tiny, write_figshare


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("orders_scripts")
    write_figshare(root / "data", n=8, h=32, w=64, seed=3)
    return train_tiny(root / "run", "--real", root / "data")


def _pair(folder, real: bool = False):
    """A pair folder of the depth rig's size: zeros, or (``real``) a 20 mm box on the plane seen through the rig
    (the dataset's encoding: label = 6 x mm, the plane near -98)."""
    folder.mkdir()
    h = np.zeros((352, 640))
    if real:
        from fppsim.geometry.rig import load_rig
        from _helpers import rig_fringe

        h[120:230, 250:400] = 20.0
        fringe = rig_fringe(load_rig(Path(__file__).resolve().parents[1] / "assets" / "figshare_depth_rig.json"), h)
        np.save(folder / "fringe_pattern.npy", (fringe.astype(np.float32) / 127.5 - 1.0))
    else:
        np.save(folder / "fringe_pattern.npy", np.zeros((352, 640), np.float32))
    np.save(folder / "height_map.npy", (6.0 * h - 98.0).astype(np.float32))
    return folder


def _phase_folder(folder):
    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

    phase = np.tile(np.linspace(0, 40, 64), (32, 1))
    psin, pcos, order = sums_from_phase(phase)
    save_psp_folder_sample(folder, "1", psin, pcos, order, np.full((32, 64), 100, np.uint8))
    return folder


@pytest.mark.parametrize("name", ["orders.json", "orders.md"])
def test_orders_study_refuses_a_file_it_did_not_write(run_dir, tmp_path, capsys, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text("someone's notes\n")
    study = load_pipeline("orders_study")
    rc = study.main(["--runs", str(run_dir), "--out", str(out), "--pair", str(_pair(tmp_path / "pair")), "--phase"])
    assert rc == 2
    one_line(capsys, name, "not written by orders_study")
    assert (out / name).read_text() == "someone's notes\n"
    assert not (out / "figures").exists()


def test_orders_study_names_a_bad_checkpoint_and_a_missing_pair_file(run_dir, tmp_path, capsys):
    study = load_pipeline("orders_study")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"")
    assert study.main(["--runs", str(bad), "--out", str(tmp_path / "o1"), "--phase"]) == 2
    one_line(capsys, "bad.pt")
    assert not (tmp_path / "o1").exists()
    pair = _pair(tmp_path / "pair")
    (pair / "height_map.npy").unlink()
    assert study.main(["--runs", str(run_dir), "--out", str(tmp_path / "o2"), "--pair", str(pair), "--phase"]) == 2
    one_line(capsys, "height_map.npy")
    assert not (tmp_path / "o2").exists()


def test_orders_study_refuses_a_rig_or_figure_it_did_not_write_before_any_work(run_dir, tmp_path, capsys):
    study = load_pipeline("orders_study")
    phase = _phase_folder(tmp_path / "FPX")
    pair = _pair(tmp_path / "pair")
    for name in ("rigs/FPX.json", "figures/FPX_1_seed0.png", "figures/pair_seed0.png"):
        out = tmp_path / name.replace("/", "_")
        (out / name).parent.mkdir(parents=True)
        (out / name).write_text("mine")
        rc = study.main(["--runs", str(run_dir), "--out", str(out), "--pair", str(pair), "--phase", str(phase)])
        assert rc == 2
        one_line(capsys, name, "not written by orders_study")
        assert (out / name).read_text() == "mine"
        assert sorted(p.name for p in out.iterdir()) == [name.split("/")[0]]  # nothing fitted or drawn


def test_orders_study_refuses_inputs_as_output_and_two_phase_folders_of_one_name(run_dir, tmp_path, capsys):
    study = load_pipeline("orders_study")
    pair = _pair(tmp_path / "pair")
    a, b = _phase_folder(tmp_path / "a" / "FPX"), _phase_folder(tmp_path / "b" / "FPX")
    assert study.main(["--runs", str(run_dir), "--out", str(pair), "--pair", str(pair), "--phase"]) == 2
    one_line(capsys, "--out", "--pair")
    assert sorted(p.name for p in pair.iterdir()) == ["fringe_pattern.npy", "height_map.npy"]
    assert study.main(["--runs", str(run_dir / "best.pt"), "--out", str(run_dir), "--pair", str(pair), "--phase"]) == 2
    one_line(capsys, "--out", "--runs")
    assert not (run_dir / "orders.json").exists()
    assert study.main(["--runs", str(run_dir), "--out", str(tmp_path / "o"), "--pair", str(pair),
                       "--phase", str(a), str(b)]) == 2
    one_line(capsys, "share the name")
    (pair / "height_map.npy").write_bytes(b"not numpy")
    assert study.main(["--runs", str(run_dir), "--out", str(tmp_path / "o"), "--pair", str(pair), "--phase"]) == 2
    one_line(capsys, "height_map.npy", "not a numpy array")
    assert not (tmp_path / "o").exists()


def test_orders_study_reruns_into_its_own_folder_but_refuses_a_file_edited_since(run_dir, tmp_path, capsys):
    study = load_pipeline("orders_study")
    pair, out = _pair(tmp_path / "pair", real=True), tmp_path / "out"
    args = ["--runs", str(run_dir), "--out", str(out), "--pair", str(pair), "--phase"]
    assert study.main(args) == 0
    assert (out / "orders.json").exists() and (out / "figures" / "pair_seed0.png").exists()
    assert study.main(args) == 0  # its own files: replaced
    capsys.readouterr()
    (out / "orders.md").write_text("my notes\n")
    assert study.main(args) == 2
    one_line(capsys, "orders.md", "changed since")
    assert (out / "orders.md").read_text() == "my notes\n"
    # edited while a run is under way that is then interrupted: the edit is not taken for the study's
    (out / "orders.md").unlink()
    assert study.main(args) == 0
    real = study._study

    def interrupted(*a, **k):
        (out / "orders.md").write_text("edited meanwhile\n")
        raise KeyboardInterrupt

    study._study = interrupted
    assert study.main(args) == 130
    study._study = real
    capsys.readouterr()
    assert study.main(args) == 2
    one_line(capsys, "orders.md", "changed since")
    assert (out / "orders.md").read_text() == "edited meanwhile\n"


def test_orders_rendered_refuses_a_file_it_did_not_write(run_dir, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "rendered.json").write_text("[]")
    rendered = load_pipeline("orders_rendered")
    assert rendered.main(["--runs", str(run_dir), "--out", str(out), "--scenes", str(tmp_path)]) == 2
    one_line(capsys, "rendered.json")
    assert (out / "rendered.json").read_text() == "[]"


def test_orders_study_takes_the_files_of_a_folder_it_wrote_before_keeping_a_record(tmp_path):
    import json

    study = load_pipeline("orders_study")
    rows = [{"run": "r", "seed": 3, "estimate": "mirror mean", "pair": {}, "frames": {"FP1523/1201": {}, "FP672/541": {}}}]
    (tmp_path / "orders.json").write_text(json.dumps(rows))
    assert study._legacy_files(tmp_path) == {"orders.json", "orders.md", "figures/pair_seed3.png",
                                             "figures/FP1523_1201_seed3.png", "figures/FP672_541_seed3.png",
                                             "rigs/FP672.json"}
    (tmp_path / "orders.md").write_text("my notes\n")  # not the study's table: not taken
    assert "orders.md" not in study._legacy_files(tmp_path)
    (tmp_path / "orders.json").write_text('{"someone": "else"}')
    assert study._legacy_files(tmp_path) == set()
