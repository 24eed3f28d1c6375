"""uhrnet.scoring.phase_residual on a folder (`uhrnet evaluate-phase`): checkpoints on a PSin/PCos/Fringe/iPattern
folder, no height labels."""

import json

import numpy as np
import pytest

from _helpers import scene, train_tiny, write_figshare
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.cli import main

pytestmark = pytest.mark.slow  # trains a tiny model (about 15 s on 2 cores)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ephase")
    write_figshare(tmp / "real", n=8, h=32, w=64, seed=1)
    run = train_tiny(tmp / "unet", "--real", tmp / "real")
    rng = np.random.default_rng(7)
    root = tmp / "phase"
    truth = {}
    for i in range(3):
        img, height, valid = scene(rng, 32, 64)
        xx = np.arange(64)[None, :] * np.ones((32, 1))
        phase = 1.0 + 2 * np.pi * xx / 11.6 - 0.45 * height  # the benchmark's carrier and sign
        save_psp_folder_sample(root, f"{i}", *sums_from_phase(phase, valid, 30.0), img)
        truth[f"{i}"] = (phase, height, valid)
    return tmp, run, root, truth


def test_report(setup, capsys):
    tmp, run, root, truth = setup
    out = tmp / "report"
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(out), "--figures", "2",
               "--names", "tiny", "--device", "cpu", "--degree", "2"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "Residual RMSE (rad)" in text and "| tiny |" in text
    doc = json.loads((out / "phase_results.json").read_text())
    assert [r["id"] for r in doc["per_image"]] == ["0", "1", "2"]
    assert doc["models"][0]["name"] == "tiny" and doc["degree"] == 2
    for rec in doc["per_image"]:
        m = rec["models"]["tiny"]
        assert m["flat"]["explained"] == pytest.approx(0.0, abs=1e-9)
        # the flat baseline's residual is the relief left by a degree-2 plane fit of the true phase
        phase, height, valid = truth[rec["id"]]
        assert m["flat"]["relief_rms_rad"] > 1.0
        assert m["prediction"]["rmse_rad"] <= m["flat"]["rmse_rad"] + 1e-9  # h terms can only lower SS
        assert rec["valid_phase_fraction"] == pytest.approx(valid.mean())
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["0.png", "1.png"]
    # the predicted-invalid mask option leaves out what the model calls shadow
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp / "r2"), "--figures", "0",
               "--device", "cpu", "--mask-predicted-invalid", "--ids", "1"])
    m = doc["per_image"][1]["models"]["tiny"]
    if rc == 0:
        doc2 = json.loads((tmp / "r2" / "phase_results.json").read_text())
        assert doc2["models"][0]["pixel_fraction"] <= m["pixel_fraction"]
    else:  # this model calls too much shadow to fit anything: a one-line error
        assert "valid pixels" in capsys.readouterr().err
    assert (out / "phase_results.md").read_text().startswith("# Calibration-free phase evaluation")


def test_errors_are_one_line(setup, capsys, tmp_path):
    tmp, run, root, truth = setup
    rc = main(["evaluate-phase", str(run), "--phase-root", str(tmp_path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1
    assert "missing folder(s) PSin, PCos, Fringe, iPattern" in err
    rc = main(["evaluate-phase", str(run), "--phase-root", str(root), "--out", str(tmp_path / "o"), "--ids", "9"])
    assert rc == 1 and "no such id(s): 9" in capsys.readouterr().err
