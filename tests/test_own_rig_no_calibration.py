"""No calibration file, end to end (docs/own_rig.md, "No calibration"): images -> rig -> data -> network -> score.

The user's rig here is not the default and has no calibration: a 144 x 108 px camera (sides that are not
multiples of 16) 420 mm above the plane with a 34 deg field of view, the projector 260 mm BELOW it
(horizontal fringes), turned by a few degrees about each axis. Its "real" scans are fppsim renders of
that rig with phase-shifting images (other objects and optics than the pretraining data), written in
the public PSin / PCos / Fringe / iPattern layout as the guide shows. The test walks the guide's
commands through the CLIs' ``main``:

1. ``fppsim fit-rig SCANS --out rig.json`` (no ``--base``): the rig from the scans alone; its plane
   phase must match the truth's (it can: the plane's phase pins the projector's pose and periods) and
   the projector must be below the camera; the depth scale is assumed (the default rig's field of
   view; distance and triangulation angle the default rig's) and the report says so; the rig file's scenes
   follow the scans' objects;
2. ``fppsim fit-optics SCANS --rig rig.json --out optics.yaml --compare 0``: how the scans look;
3. ``fppsim generate --rig rig.json --format figshare --no-psp --optics-file optics.yaml``: pretraining
   data of that rig;
4. ``uhrnet train``: a tiny U-Net on 144 x 108 images (padded inside the model);
5. ``uhrnet evaluate-phase --phase-root SCANS --ids`` on scans fit-rig did not read: the calibration-free
   phase residual must be well below the flat-plane predictor's (measured: 0.48 of it);
6. ``uhrnet predict --rig``, ``--refine phase``, ``uhrnet adapt --rig`` and ``fppsim label-real --rig``
   run on the same rig.

Everything is seeded; torch runs on one thread. About 2-3 minutes on 2 shared cores (marked slow).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from _helpers import REPO

MODEL = ["--model", "unet", "--base-channels", "8", "--loss", "l2", "--batch-size", "2", "--device", "cpu",
         "--no-progress"]
FIT_IDS = ["000000", "000001", "000002", "000003"]
HELDOUT = ["000004", "000005", "000006", "000007"]


def truth_rig():
    """The user's rig (module docstring)."""
    from fppsim.fitting.fit_periods import adjust_rig
    from fppsim.fitting.rig_start import start_rig

    start = start_rig(144, 108, (0.0, 2 * math.pi / 11.0), 1, distance=420.0, baseline=260.0, fov=34.0)
    rig = adjust_rig(start, yaw=0.04, pitch=-0.05, roll=0.03, periods=round(start.periods))
    rig.name = "no-calibration test rig: 144 x 108, projector 260 mm below, horizontal fringes"
    return rig


def _fppsim(*args) -> None:
    from fppsim.cli import main

    assert main([str(a) for a in args]) == 0, args


def _uhrnet(*args) -> None:
    from uhrnet.cli import main

    assert main([str(a) for a in args]) == 0, args


@pytest.mark.slow
def test_no_calibration_images_to_rig_to_network(tmp_path, one_thread, capsys):
    from fppsim.dataio.writers import export_psp_folders
    from fppsim.fitting.plane_phase import plane_phase_residual
    from fppsim.geometry.rig import Rig

    truth = truth_rig()
    truth.check_usable()
    truth_file = tmp_path / "truth.json"  # only the scans' renderer and the checks read it
    truth.save(truth_file)
    periods = int(truth.periods)

    # the user's scans: phase-shifting renders of the rig, in the public layout
    native, scans = tmp_path / "native", tmp_path / "scans"
    _fppsim("generate", "--meshes", "procedural", "--rig", truth_file, "--out", native, "--count", 8, "--seed", 7,
            "--psp-freqs", f"1,4,{periods}", "--optics", "camera_blur=1.0", "--optics", "albedo_object=0.4,0.6",
            "--no-preview", "-q")
    export_psp_folders(native, scans)
    fit_folder = tmp_path / "fit_scans"  # the frames fit-rig reads; the others are held out
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        (fit_folder / sub).mkdir(parents=True)
        for sid in FIT_IDS:
            (fit_folder / sub / f"{sid}.mat").symlink_to(scans / sub / f"{sid}.mat")
    capsys.readouterr()

    # 1. the rig from the scans alone
    rig_file, report = tmp_path / "rig.json", tmp_path / "fit.json"
    _fppsim("fit-rig", fit_folder, "--out", rig_file, "--json", report)
    text = capsys.readouterr().out
    assert "horizontal" in text and "below the camera" in text and "NOT identifiable" in text
    rig = Rig.load(rig_file)
    assert (rig.camera.width, rig.camera.height) == (144, 108)
    assert rig.projector.center[1] < rig.camera.center[1] and np.sign(rig.sensitivity()) == np.sign(truth.sensitivity())
    d = rig.phase_at_height(0.0) - truth.phase_at_height(0.0)
    assert np.nanmax(np.abs(d - np.nanmedian(d))) < 0.05  # the plane's phase, a constant apart
    # checked as the issue checks a rig: against a held-out frame's absolute phase, on its plane
    from fppsim.dataio.readers import load_native_sample, load_psp_folder_sample

    s = load_psp_folder_sample(scans, HELDOUT[0])
    exact = load_native_sample(native / HELDOUT[0], keys=("height", "mask"), meta=False)
    plane = s.valid & (exact["mask"] > 0) & (np.abs(exact["height"]) < 0.01)
    r, _ = plane_phase_residual(rig, s.phase, s.valid, plane)
    assert np.median(np.abs(r[plane])) < 0.1
    assert json.loads(report.read_text())["start"]["fringes"] == "horizontal"

    # 2. how the scans look, measured through the fitted rig
    optics = tmp_path / "optics.yaml"
    _fppsim("fit-optics", fit_folder, "--rig", rig_file, "--out", optics, "--compare", 0)
    assert "albedo_object" in optics.read_text()

    # 3-4. synthetic data through the fitted rig, looking like the scans; a network trained on it
    syn, run = tmp_path / "syn", tmp_path / "run"
    _fppsim("generate", "--meshes", REPO / "assets" / "meshes", "--rig", rig_file, "--out", syn, "--count", 64,
            "--seed", 1, "--format", "figshare", "--no-psp", "--no-preview", "-q", "--optics-file", optics)
    assert np.load(syn / "f1_80.npy", mmap_mode="r").shape == (64, 108, 144, 1)
    # the scenes follow the scans' objects: the rig file's scenes are what the data were drawn from
    drawn = json.loads((syn / "native" / "dataset.json").read_text())["config"]["scene_ranges"]
    assert drawn["footprint"] == json.loads(rig_file.read_text())["scenes"]["footprint"]
    _uhrnet("train", "--synthetic", syn, "--epochs", 12, "--lr", "1e-3", "--seed", 3, "--resize", "auto",
            "--val-phase", fit_folder, "--out", run, *MODEL)
    assert json.loads((run / "config.json").read_text())["resize"] is None  # 108 px: the network sees it whole

    # 5. the score without labels on the held-out scans
    ev = tmp_path / "ev"
    _uhrnet("evaluate-phase", run, "--phase-root", scans, "--ids", *HELDOUT, "--out", ev, "--device", "cpu",
            "--refine", "phase", "--rig", rig_file)
    model, path = json.loads((ev / "phase_results.json").read_text())["models"]
    ratio = model["rmse_rad"] / model["flat_rmse_rad"]
    assert ratio < 0.65, model  # measured 0.56 on 2026-11-28 (0.48 when fit-optics joined the path, 0.53 before)
    # the heights predict --rig returns, on the same pixels: measured 0.72 here, WORSE than the network: half of
    # this 144 x 108 rig's pixels have unreliable phase and the regions grow through them (real frames: 18-27 %)
    assert path["name"].endswith("+orders") and path["pixel_fraction"] == model["pixel_fraction"]
    assert path["rmse_rad"] / path["flat_rmse_rad"] < 0.9, path

    # 6. the rest of the path takes the same rig
    _uhrnet("predict", run / "best.pt", scans, "--out", tmp_path / "pred", "--rig", rig_file, "--refine", "phase")
    _uhrnet("adapt", run / "best.pt", "--images", scans, "--out", tmp_path / "adapt", "--rig", rig_file,
            "--epochs", 1, "--device", "cpu")
    _fppsim("label-real", scans, "--out", tmp_path / "labelled", "--rig", rig_file, "-q", "--no-preview")
    lab = json.loads((tmp_path / "labelled" / "label_real.json").read_text())
    assert lab["status"] == "done" and len(lab["ids"]) == 8, lab["status"]
