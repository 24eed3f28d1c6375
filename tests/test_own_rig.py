"""Bring your own rig, end to end (docs/own_rig.md), on a rig that is not the default.

The user's rig here is a small one (camera 128 x 64 px at f = 246 px, 500 mm above the plane;
projector 228 x 285 px, 250 mm to the side, yawed 2.9 deg, 16 fringe periods: about 12 camera px
per period and 0.13 rad of phase per mm, one period per 49 mm of height; the default rig has 7.2 mm),
delivered as an OpenCV stereo calibration (cv2.FileStorage YAML with M1 D1 M2 D2 R T, the plane
distance, the sizes and the periods), read by every command through ``--rig``.

The user's "real" scans are fppsim renders of that rig with phase-shifting images, made different
from the synthetic pretraining data on purpose, in ways a network can learn from labelled scans:
other objects (procedural sculptures, not assets/meshes), other seeds and other optics (projector
gamma 2.2, which also distorts the four-step PSP labels as a real projector would; camera blur 1 px;
dark plaster, object albedo 0.3-0.4 instead of 0.8-1). The test walks the guide's commands through
the CLIs' ``main``:

1. ``fppsim generate --rig stereo.yml --format figshare --no-psp``: pretraining data;
2. ``fppsim generate --rig stereo.yml --psp-freqs 1,4,16 --optics ...``: the "scans";
3. ``fppsim label-real --rig stereo.yml``: labels from the decoded PSP images (checked against the
   exact rendered heights, which only this test reads), split into 5 training and 6 held-out scans;
4. ``uhrnet train``: a tiny U-Net (base 8) on the synthetic data; then ``--init-from`` it, fine-tuned
   on the 5 labelled scans mixed 50/50 with synthetic batches (144 steps at lr 3e-4: the guide's 1e-4
   is for the recipe's bigger network and longer runs), and as a control the same steps from the same
   start on synthetic data alone (the pretraining has not converged, so more synthetic steps help too);
5. ``uhrnet evaluate --real HELDOUT --split all``: the fine-tuned model must beat the synthetic-only
   model (< 0.85 x its RMSE) and the control (< 0.9 x). Measured on four seed sets (1/7, the test's,
   2/9, 3/11, 4/13): fine-tuned / synthetic-only 0.74, 0.68, 0.59, 0.77; fine-tuned / control 0.82,
   0.73, 0.68, 0.76 (held-out RMSE 10.3-11.4 mm against 14.7-18.0 mm; a plane predictor 15-19 mm).

Everything is seeded; torch runs on one thread. About 40-60 s on 2 shared cores (marked slow).
A fast test checks the guide's way to hand one's own decoded scans to label-real (fppsim's writer of
the public PSin/PCos/Fringe/iPattern layout) at phases exactly on a wrap.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _helpers import REPO

SCANS_TRAIN = [f"{i:06d}" for i in range(5)]
SCANS_HELDOUT = [f"{i:06d}" for i in range(5, 11)]
SCAN_OPTICS = ["projector_gamma=2.2", "camera_blur=1.0", "albedo_object=0.3,0.4"]
MODEL = ["--model", "unet", "--base-channels", "8", "--loss", "l2", "--batch-size", "2", "--device", "cpu",
         "--no-progress"]


def small_rig():
    """The user's rig (see the module docstring) as an fppsim :class:`Rig`."""
    from fppsim.geometry.rig import Device, Rig, projector_for

    cam = Device.looking_down([0.0, 0.0, 500.0], 246.0, 246.0, 63.5, 31.5, 128, 64)
    proj = projector_for(cam, yaw=0.05, focal=1208.8 / 4, baseline=250.0, width=228, rows=285)
    return Rig(cam, proj, periods=16.0, name="own small rig")


def write_opencv_stereo(rig, path: Path) -> Path:
    """``rig`` as an OpenCV stereo calibration written with cv2.FileStorage, as docs/own_rig.md shows:
    camera = device 1, projector = device 2, ``X_proj = R X_cam + T`` (cv2.stereoCalibrate), the
    reference plane as the distance along the camera axis, the sizes and the fringe periods."""
    import cv2

    cam, proj = rig.camera, rig.projector
    R = proj.R @ cam.R.T
    T = proj.t - R @ cam.t
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", cam.K)
    fs.write("D1", np.zeros((1, 5)))
    fs.write("M2", proj.K)
    fs.write("D2", np.zeros((1, 5)))
    fs.write("R", R)
    fs.write("T", T.reshape(3, 1))
    fs.write("plane_distance", float(cam.t[2]))
    for key, value in (("camera_width", cam.width), ("camera_height", cam.height),
                       ("projector_width", proj.width), ("projector_height", proj.height)):
        fs.write(key, int(value))
    fs.write("periods", float(rig.periods))
    fs.release()
    return path


def _fppsim(*args) -> None:
    from fppsim.cli import main

    assert main([str(a) for a in args]) == 0, args


def _uhrnet(*args) -> None:
    from uhrnet.cli import main

    assert main([str(a) for a in args]) == 0, args


def _label_rmse_vs_exact(labelled: Path, scans: Path, ids: list[str]) -> float:
    """RMSE (mm) of label-real's heights against the exact rendered heights on pixels valid in both."""
    from fppsim.dataio.formats import PRESETS
    from fppsim.dataio.readers import load_native_sample

    fig = PRESETS["figshare"]
    z = np.load(labelled / "Z.npy")[..., 0].astype(np.float64)
    err = []
    for k, sid in enumerate(ids):
        s = load_native_sample(scans / sid, keys=("height", "mask"), meta=False)
        ok = (z[k] > fig.invalid_threshold) & (s["mask"] > 0)
        assert ok.mean() > 0.7, sid
        err.append(fig.height_mm(z[k][ok]) - s["height"][ok])
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


@pytest.mark.parametrize("convention", ["benchmark", "fppsim"])
def test_own_decoded_phase_round_trips_through_the_public_layout(tmp_path, convention):
    """The guide's way to hand one's own scans to label-real: decode, then write PSin/PCos/Fringe/iPattern
    with fppsim's writer. Phases decoded from 8-bit images often sit exactly on a wrap (k pi), where
    sin(phi) is a rounding residue of either sign: the fringe order written must match the wrapped phase
    the reader computes, or those pixels come back one period (2 pi) off."""
    from fppsim.dataio.readers import load_psp_folder_sample
    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

    k = np.arange(-3, 161)
    phase = np.concatenate([k * np.pi, k * np.pi + 1e-12, k * np.pi - 1e-12, np.linspace(-7, 500, 508)])
    phase = phase.reshape(25, 40)
    valid = np.ones(phase.shape, bool)
    valid[0, :3] = False
    save_psp_folder_sample(tmp_path, "scan", *sums_from_phase(phase, valid, 37.0, convention=convention),
                           np.full(phase.shape, 120, np.uint8))
    back = load_psp_folder_sample(tmp_path, "scan", convention=convention)
    np.testing.assert_array_equal(back.valid, valid)
    np.testing.assert_allclose(back.phase[valid], phase[valid], atol=1e-9)


@pytest.mark.slow
def test_own_rig_scans_fine_tune_beats_synthetic_only(tmp_path, one_thread):
    from fppsim.geometry.rig import load_rig

    rig = small_rig()
    stereo = write_opencv_stereo(rig, tmp_path / "stereo.yml")
    back = load_rig(stereo)  # the import reproduces the rig, periods included
    assert back.periods == 16.0 and (back.camera.width, back.camera.height) == (128, 64)
    np.testing.assert_allclose(back.projector.center, rig.projector.center, atol=1e-9)
    np.testing.assert_allclose(back.projector.R, rig.projector.R, atol=1e-12)

    # 1-2. pretraining data and the user's scans, both through the user's calibration
    syn, scans = tmp_path / "syn", tmp_path / "scans"
    _fppsim("generate", "--meshes", REPO / "assets" / "meshes", "--rig", stereo, "--out", syn, "--count", 48,
            "--seed", 1, "--format", "figshare", "--no-psp", "--no-preview", "-q")
    optics = [a for o in SCAN_OPTICS for a in ("--optics", o)]
    _fppsim("generate", "--meshes", "procedural", "--rig", stereo, "--out", scans, "--count", 11, "--seed", 7,
            "--psp-freqs", "1,4,16", *optics, "--no-preview", "-q")

    # 3. label them through the calibration; the reference plane comes out flat at 0 mm
    labelled, heldout = tmp_path / "labelled", tmp_path / "heldout"
    for out, ids in ((labelled, SCANS_TRAIN), (heldout, SCANS_HELDOUT)):
        _fppsim("label-real", scans, "--out", out, "--rig", stereo, "--ids", *ids, "--no-preview", "-q")
        doc = json.loads((out / "label_real.json").read_text())
        assert doc["status"] == "done" and doc["ids"] == ids and not doc["warnings"]
        assert np.load(out / "Z.npy").shape == (len(ids), 64, 128, 1)
        for scan in doc["scans"]:
            assert scan["fits"] and abs(scan["plane"]["level_mm"]) < 0.1 and scan["plane"]["rms_mm"] < 1.0
            assert abs(scan["phase_offset_fit_rad"]) < 0.05  # fppsim scans are absolute in rig terms
        # PSP labels under gamma 2.2 are not exact (harmonics), but close to the rendered truth
        assert _label_rmse_vs_exact(out, scans, ids) < 1.5

    # 4. pretrain on synthetic data; fine-tune on the labelled scans + synthetic; control: synthetic only
    pre, ft, ctl = tmp_path / "pre", tmp_path / "ft", tmp_path / "ctl"
    _uhrnet("train", "--synthetic", syn, *MODEL, "--epochs", 15, "--lr", 1e-3, "--out", pre)
    steps = ["--epochs", 12, "--samples-per-epoch", 24, "--lr", 3e-4]
    _uhrnet("train", "--init-from", pre, "--real", labelled, "--real-split", "train", "--synthetic", syn,
            "--synthetic-ratio", 0.5, *MODEL, *steps, "--out", ft)
    _uhrnet("train", "--init-from", pre, "--synthetic", syn, *MODEL, *steps, "--out", ctl)
    config = json.loads((ft / "config.json").read_text())
    assert config["init_from"] == str((pre / "best.pt").resolve())
    assert [d["n_train"] for d in config["data"]["real"]] == [len(SCANS_TRAIN)]

    # 5. held-out scans of the rig, mm RMSE over their valid pixels
    _uhrnet("evaluate", pre, ft / "last.pt", ctl / "last.pt", "--names", "synthetic-only", "fine-tuned", "control",
            "--real", heldout, "--synthetic", "--split", "all", "--out", tmp_path / "eval", "--figures", 0,
            "--timing-repeats", 0, "--no-progress")
    models = {m["name"]: m for m in json.loads((tmp_path / "eval" / "results.json").read_text())["models"]}
    rmse = {name: m["rmse_mm"] for name, m in models.items()}
    assert all(m["images"] == len(SCANS_HELDOUT) for m in models.values())
    z = np.load(heldout / "Z.npy")[..., 0]
    flat = float(np.mean([np.sqrt(np.mean(((zi[zi > -100] + 97) / 6) ** 2)) for zi in z]))  # predicts the plane
    assert rmse["synthetic-only"] < flat, (rmse, flat)
    assert rmse["fine-tuned"] < 0.85 * rmse["synthetic-only"], rmse
    assert rmse["fine-tuned"] < 0.9 * rmse["control"], rmse
