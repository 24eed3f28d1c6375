"""The orders scripts (pipelines/orders_study.py, pipelines/orders_rendered.py) keep what they did not write:
their --out folders carry an ownership record, a foreign file there is refused in one line (exit 2) before any
work, and so is a bad checkpoint."""

from __future__ import annotations

import numpy as np
import pytest

from _helpers import load_pipeline, train_tiny, write_figshare


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("orders_scripts")
    write_figshare(root / "data", n=8, h=32, w=64, seed=3)
    return train_tiny(root / "run", "--real", root / "data")


def _one_line(capsys, *parts):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for p in parts:
        assert p in err, err
    return err


def _pair(folder):
    folder.mkdir()
    np.save(folder / "fringe_pattern.npy", np.zeros((32, 64), np.float32))
    np.save(folder / "height_map.npy", np.zeros((32, 64), np.float32))
    return folder


@pytest.mark.parametrize("name", ["orders.json", "orders.md"])
def test_orders_study_refuses_a_file_it_did_not_write(run_dir, tmp_path, capsys, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text("someone's notes\n")
    study = load_pipeline("orders_study")
    rc = study.main(["--runs", str(run_dir), "--out", str(out), "--pair", str(_pair(tmp_path / "pair")), "--phase"])
    assert rc == 2
    _one_line(capsys, name, "not written by orders_study")
    assert (out / name).read_text() == "someone's notes\n"
    assert not (out / "figures").exists()


def test_orders_study_names_a_bad_checkpoint_and_a_missing_pair_file(run_dir, tmp_path, capsys):
    study = load_pipeline("orders_study")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"")
    assert study.main(["--runs", str(bad), "--out", str(tmp_path / "o1"), "--phase"]) == 2
    _one_line(capsys, "bad.pt")
    assert not (tmp_path / "o1").exists()
    pair = _pair(tmp_path / "pair")
    (pair / "height_map.npy").unlink()
    assert study.main(["--runs", str(run_dir), "--out", str(tmp_path / "o2"), "--pair", str(pair), "--phase"]) == 2
    _one_line(capsys, "height_map.npy")
    assert not (tmp_path / "o2").exists()


def test_orders_study_refuses_a_rig_file_it_did_not_write(tmp_path):
    study = load_pipeline("orders_study")
    out = tmp_path / "out"
    (out / "rigs").mkdir(parents=True)
    (out / "rigs" / "FP1.json").write_text("{}")
    from fppsim.errors import ForeignFiles
    with pytest.raises(ForeignFiles, match="FP1.json"):
        study.fitted_rig(tmp_path / "FP1", out / "rigs" / "FP1.json", out)
    assert (out / "rigs" / "FP1.json").read_text() == "{}"


def test_orders_rendered_refuses_a_file_it_did_not_write(run_dir, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "rendered.json").write_text("[]")
    rendered = load_pipeline("orders_rendered")
    assert rendered.main(["--runs", str(run_dir), "--out", str(out), "--scenes", str(tmp_path)]) == 2
    _one_line(capsys, "rendered.json")
    assert (out / "rendered.json").read_text() == "[]"
