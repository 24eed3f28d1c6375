"""fppsim.fitting.label_real / `fppsim label-real`: phase-shifting scans -> figshare arrays (f1_80.npy + Z.npy).

Ground truth: fppsim's own renders of the parallel rig (exact heights in arrays.npz, read only here),
labelled from their PSP images, and the same renders written in the public PSin/PCos/Fringe/iPattern
layout by fppsim's own writer with a known phase offset. The shared real frame (../shared/real-phase)
checks the reference plane at 0 mm through the default rig.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _helpers import REPO, SHARED
from fppsim.cli import main
from fppsim.errors import ConfigError, DatasetError, PSPMatError, UsageError
from fppsim.dataio.formats import PRESETS, manifest_ids
from fppsim.dataio.readers import load_native_sample
from fppsim.fitting.label_real import (LabelRealConfig, fit_phase_offset, label_real, plane_flatness,
                               reference_plane_phase)
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from fppsim.geometry.rig import Rig, load_rig

PARALLEL = REPO / "assets" / "parallel_rig.json"
REAL_PHASE = SHARED / "real-phase" / "FP1523"
FIG = PRESETS["figshare"]
OFFSET = 37.25  # rad: the public copy's phase is the rig's minus this


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    """Two samples of the parallel rig with PSP images, rendered by `fppsim generate`'s library call."""
    import fppsim

    out = tmp_path_factory.mktemp("lr") / "native"
    fppsim.generate(fppsim.GenerateConfig(meshes=[REPO / "assets" / "meshes"], out=out, count=2, seed=3,
                                          rig=load_rig(PARALLEL), progress=False))
    return out


@pytest.fixture(scope="module")
def public(rendered, tmp_path_factory) -> Path:
    """The renders in the public layout (benchmark convention) with the phase shifted by -OFFSET."""
    root = tmp_path_factory.mktemp("lr") / "public"
    for sid in manifest_ids(rendered):
        s = load_native_sample(rendered / sid, keys=("phase_true", "mask"), meta=False)
        phase = s["phase_true"].astype(np.float64) - OFFSET
        save_psp_folder_sample(root, sid, *sums_from_phase(phase, s["mask"] > 0, 100.0), s["fringe"])
    return root


def _rmse_vs_exact(out: Path, native: Path) -> float:
    z = np.load(out / "Z.npy")
    err = []
    for i, sid in enumerate(manifest_ids(native)):
        s = load_native_sample(native / sid, keys=("height", "mask"), meta=False)
        ok = (z[i, ..., 0] != FIG.invalid_value) & (s["mask"] > 0)
        assert ok.mean() > 0.8
        err.append(FIG.height_mm(z[i, ..., 0][ok].astype(np.float64)) - s["height"][ok])
    e = np.concatenate(err)
    return float(np.sqrt(np.mean(e ** 2)))


def test_native_psp_labels_match_the_exact_height(rendered, tmp_path):
    rep = label_real(LabelRealConfig(root=rendered, out=tmp_path / "o", rig=PARALLEL, previews=False))
    fr, z = np.load(tmp_path / "o" / "f1_80.npy"), np.load(tmp_path / "o" / "Z.npy")
    assert fr.shape == z.shape == (2, 352, 640, 1) and fr.dtype == z.dtype == np.float32
    assert _rmse_vs_exact(tmp_path / "o", rendered) < 0.25  # the acceptance bound
    assert rep.layout == "native" and rep.policy == "none"
    for r in rep.scans:  # absolute in rig terms: the fit agrees with "none", the plane lies at 0
        assert abs(r["phase_offset_fit_rad"]) < 0.01 and r["phase_offset_rad"] == 0
        assert abs(r["plane"]["level_mm"]) < 0.05 and r["plane"]["rms_mm"] < 0.5 and r["fits"]
    assert not rep.warnings
    # the fringe: 8-bit / 127.5 - 1, -1 exactly where the label is the invalid marker
    s = load_native_sample(rendered / "000000", keys=(), meta=False)
    bad = z[0, ..., 0] == FIG.invalid_value
    assert np.all(fr[0, ..., 0][bad] == -1)
    np.testing.assert_allclose(fr[0, ..., 0][~bad], s["fringe"][~bad] / 127.5 - 1, atol=1e-6)
    doc = json.loads((tmp_path / "o" / "label_real.json").read_text())
    assert doc["status"] == "done" and doc["ids"] == ["000000", "000001"] and doc["tool"] == "fppsim label-real"


def test_uhrnet_reads_the_output_back_to_the_same_millimetres(rendered, tmp_path):
    from uhrnet.data.datasets import FigshareArrays, load_sources

    label_real(LabelRealConfig(root=rendered, out=tmp_path / "o", rig=PARALLEL, previews=False))
    z = np.load(tmp_path / "o" / "Z.npy")[..., 0].astype(np.float64)
    ds = FigshareArrays(tmp_path / "o")  # what `uhrnet train --real DIR` opens
    assert len(ds) == 2
    for i in range(2):
        item = ds[i]
        m = item["mask"][0].numpy() > 0
        mm = ds.transform.height_mm(item["height"][0].numpy().astype(np.float64))
        np.testing.assert_allclose(mm[m], FIG.height_mm(z[i])[m], atol=1e-4)
        assert item["mm_per_unit"] == pytest.approx(1 / 6)
    src = load_sources(real=[str(tmp_path / "o")], real_split="train")
    assert len(src.train) == 2


def test_public_layout_recovers_a_known_phase_offset(public, rendered, tmp_path):
    rep = label_real(LabelRealConfig(root=public, out=tmp_path / "o", rig=PARALLEL))
    assert rep.layout == "public" and rep.policy == "auto"
    for r in rep.scans:
        assert r["phase_offset_rad"] == pytest.approx(OFFSET, abs=0.01)
        assert abs(r["plane"]["level_mm"]) < 0.05 and r["fits"]
        assert (tmp_path / "o" / r["preview"]).is_file()
    assert _rmse_vs_exact(tmp_path / "o", rendered) < 0.05  # exact phase in, only float32 rounding
    # a given offset gives the same labels; no offset leaves the plane far off and warns
    label_real(LabelRealConfig(root=public, out=tmp_path / "g", rig=PARALLEL, phase_offset=f"{OFFSET}",
                               previews=False))
    np.testing.assert_allclose(np.load(tmp_path / "g" / "Z.npy"), np.load(tmp_path / "o" / "Z.npy"), atol=0.05)
    # ... and is refused (one line naming the scan, nothing written) unless --keep-unfit keeps the labels
    with pytest.raises(DatasetError, match=r"does not fit \(plane at .* nothing written; try --phase-offset auto") as exc:
        label_real(LabelRealConfig(root=public, out=tmp_path / "n", rig=PARALLEL, phase_offset="none",
                                   previews=False))
    assert "\n" not in str(exc.value) and not (tmp_path / "n" / "Z.npy").exists()
    rep = label_real(LabelRealConfig(root=public, out=tmp_path / "n", rig=PARALLEL, phase_offset="none",
                                     previews=False, keep_unfit=True))
    assert all(not r["fits"] and abs(r["plane"]["level_mm"]) > 5 for r in rep.scans)
    assert len(rep.warnings) == 1 and "the rig does not fit these scans" in rep.warnings[0]
    assert "--phase-offset auto" in rep.warnings[0]
    # a rig fitted with no plane in view has no plane to fit the offset on: refused in one line, nothing written
    flagged = Rig.from_dict({**Rig.load(PARALLEL).to_dict(), "plane_in_view": False})
    with pytest.raises(ConfigError, match="no plane in view: give --phase-offset"):
        label_real(LabelRealConfig(root=public, out=tmp_path / "np", rig=flagged))
    assert not (tmp_path / "np").exists()


def test_public_layout_other_convention_and_sine_sign(rendered, tmp_path, capsys):
    sid = "000001"
    s = load_native_sample(rendered / sid, keys=("phase_true", "mask"), meta=False)
    psin, pcos, order = sums_from_phase(s["phase_true"].astype(np.float64) - OFFSET, s["mask"] > 0, 50.0,
                                        convention="fppsim")
    save_psp_folder_sample(tmp_path / "pub", sid, -psin, pcos, order, s["fringe"])
    assert main(["label-real", str(tmp_path / "pub"), "--out", str(tmp_path / "o"), "--rig", str(PARALLEL),
                 "--convention", "fppsim", "--negate-sin", "-q", "--no-preview"]) == 0
    doc = json.loads((tmp_path / "o" / "label_real.json").read_text())
    assert doc["scans"][0]["phase_offset_rad"] == pytest.approx(OFFSET, abs=0.01) and doc["scans"][0]["fits"]
    # read with the wrong sine sign, the phase is garbage and the plane shows it: refused, nothing written
    capsys.readouterr()
    assert main(["label-real", str(tmp_path / "pub"), "--out", str(tmp_path / "w"), "--rig", str(PARALLEL),
                 "--convention", "fppsim", "-q", "--no-preview"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "does not fit" in err and "--keep-unfit" in err
    assert not (tmp_path / "w" / "Z.npy").exists() and not (tmp_path / "w" / "f1_80.npy").exists()
    assert main(["label-real", str(tmp_path / "pub"), "--out", str(tmp_path / "w"), "--rig", str(PARALLEL),
                 "--convention", "fppsim", "-q", "--no-preview", "--keep-unfit"]) == 0
    assert "the rig does not fit these scans" in capsys.readouterr().err


def test_out_is_not_the_scans_own_folder(public, capsys):
    """Labels written beside PSin/ PCos/ ... would leave one folder of two layouts (each reader picking one):
    refused as a usage error, nothing written there."""
    before = sorted(p.name for p in public.iterdir())
    assert main(["label-real", str(public), "--out", str(public / "." ), "--rig", str(PARALLEL), "-q",
                 "--no-preview"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the scans' own folder" in err
    assert sorted(p.name for p in public.iterdir()) == before


def test_offset_fit_and_flatness_on_a_synthetic_plane():
    rig = load_rig(PARALLEL)
    plane = reference_plane_phase(rig)
    valid = np.ones(plane.shape, bool)
    phase = plane - 5.0
    phase[100:200, 200:300] -= 8.0  # an object (raised surfaces lower the phase on this rig)
    assert fit_phase_offset(phase, valid, rig) == pytest.approx(5.0, abs=1e-6)
    h = np.zeros(plane.shape)
    h[100:200, 200:300] = 20.0
    yy, xx = np.mgrid[0:plane.shape[0], 0:plane.shape[1]]
    p = plane_flatness(h + 2.0 * xx / (plane.shape[1] - 1), valid)  # a plane rising 2 mm left to right
    assert p.tilt_x_mm == pytest.approx(2.0, abs=1e-6) and p.rms_fit_mm < 1e-6
    assert p.level_mm == pytest.approx(1.0, abs=0.05) and not p.pixels[150, 250]


@pytest.mark.skipif(not (REAL_PHASE / "PSin").is_dir(), reason="../shared/real-phase absent")
def test_shared_real_frame_plane_at_zero_with_the_object_above(tmp_path, capsys):
    rc = main(["label-real", str(REAL_PHASE), "--out", str(tmp_path / "o"), "-q"])
    assert rc == 0
    doc = json.loads((tmp_path / "o" / "label_real.json").read_text())
    r = doc["scans"][0]
    assert r["id"] == "1201" and r["phase_offset_source"] == "auto"
    assert abs(r["plane"]["level_mm"]) < 1.5 and r["plane"]["rms_mm"] < 1.5 and r["fits"]
    assert 60 < r["phase_offset_rad"] < 80  # DESIGN.md section 9: about +72 rad through the default rig
    z = np.load(tmp_path / "o" / "Z.npy")[0, ..., 0]
    h = FIG.height_mm(z[z != FIG.invalid_value].astype(np.float64))
    assert np.mean(np.abs(h) < 3) > 0.6  # the plane
    assert np.percentile(h, 99) > 20 and r["object"]["share"] > 0.15  # the object stands above it
    assert r["below_plane_share"] < 0.01
    assert "1201" in capsys.readouterr().out


def test_cli_native_and_rig_that_does_not_fit(rendered, tmp_path, capsys):
    assert main(["label-real", str(rendered), "--out", str(tmp_path / "o"), "--rig", str(PARALLEL), "-q",
                 "--no-preview", "--ids", "000001"]) == 0
    assert np.load(tmp_path / "o" / "Z.npy").shape == (1, 352, 640, 1)
    capsys.readouterr()
    # the default rig is not the renders' rig: the plane tilts and the run says so on one stderr line
    assert main(["label-real", str(rendered), "--out", str(tmp_path / "d"), "--rig",
                 str(REPO / "assets" / "default_rig.json"), "-q", "--no-preview", "--phase-offset", "auto",
                 "--keep-unfit"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "the rig does not fit these scans" in err[0]
    # without --keep-unfit: exit 1, one line naming the scan and what is wrong; the earlier labels stay as they were
    before = (tmp_path / "d" / "Z.npy").read_bytes()
    assert main(["label-real", str(rendered), "--out", str(tmp_path / "d"), "--rig",
                 str(REPO / "assets" / "default_rig.json"), "-q", "--no-preview", "--phase-offset", "auto"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "does not fit (plane" in err[0] and "scan 0000" in err[0]
    assert (tmp_path / "d" / "Z.npy").read_bytes() == before
    # a bad threshold names its flag
    assert main(["label-real", str(rendered), "--out", str(tmp_path / "e"), "--plane-window", "0"]) == 2
    err = capsys.readouterr().err
    assert "--plane-window must be" in err and "plane_window_mm" not in err


# ------------------------------------------------------------------------------------------ bad inputs
def _small_public(root: Path, shape=(32, 64)) -> Path:
    phase = np.tile(np.linspace(3, 40, shape[1]), (shape[0], 1))
    save_psp_folder_sample(root, "7", *sums_from_phase(phase), np.full(shape, 90, np.uint8))
    return root


def _cli_error(args, capsys) -> tuple[int, str]:
    rc = main(["label-real", *map(str, args), "-q", "--no-preview"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    return rc, err[0]


def test_bad_inputs_give_one_line_errors(tmp_path, capsys):
    rc, err = _cli_error([tmp_path / "nowhere", "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "nowhere: no such folder" in err
    (tmp_path / "empty").mkdir()
    rc, err = _cli_error([tmp_path / "empty", "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "no scans found" in err and "plain image" not in err
    (tmp_path / "empty" / "frame.png").write_bytes(b"")  # plain images: told they carry no phase-shifting phase
    rc, err = _cli_error([tmp_path / "empty", "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "no scans found" in err and "it holds 1 plain image(s)" in err
    (tmp_path / "empty" / "frame.png").unlink()
    root = _small_public(tmp_path / "pub")
    rc, err = _cli_error([tmp_path, "--out", tmp_path / "o"], capsys)  # a folder of scan folders
    assert rc == 1 and "no scans found" in err and err.endswith(
        f"; it holds 1 scan folder(s) one level down (pub/): give one of them, e.g. {root}")
    # a rig whose camera is not the images' size
    rc, err = _cli_error([root, "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "rig camera is 640x352 but images are 64x32" in err
    # a missing sub-folder
    import shutil

    shutil.rmtree(root / "Fringe")
    rc, err = _cli_error([root, "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "missing folder(s) Fringe" in err
    # mismatched shapes between the quantities of one id
    root = _small_public(tmp_path / "pub2")
    import scipy.io

    scipy.io.savemat(root / "PCos" / "7.mat", {"PCos": np.ones((30, 64))})
    rc, err = _cli_error([root, "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "PCos/7.mat" in err and "differs" in err
    rc, err = _cli_error([root, "--out", tmp_path / "o", "--phase-offset", "lots"], capsys)
    assert rc == 2 and "--phase-offset" in err
    assert not (tmp_path / "o").exists()  # nothing created for inputs refused up front
    with pytest.raises(UsageError):
        LabelRealConfig(root=root, out=tmp_path / "o", plane_window_mm=0)
    with pytest.raises(PSPMatError):
        label_real(LabelRealConfig(root=root, out=tmp_path / "o"))
    with pytest.raises(ConfigError):
        label_real(LabelRealConfig(root=_small_public(tmp_path / "pub3"), out=tmp_path / "o"))


def test_native_without_psp_images_is_refused(tmp_path, capsys):
    from _helpers import write_native

    write_native(tmp_path / "nat", n=1)
    rc, err = _cli_error([tmp_path / "nat", "--out", tmp_path / "o"], capsys)
    assert rc == 1 and "no phase-shifting images" in err


def test_existing_outputs_are_not_clobbered(public, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "Z.npy").write_bytes(b"someone else's labels")
    rc, err = _cli_error([public, "--out", out, "--rig", PARALLEL], capsys)
    assert rc == 1 and "Z.npy exists and was not written by fppsim label-real" in err
    assert (out / "Z.npy").read_bytes() == b"someone else's labels"
    assert not (out / "f1_80.npy").exists() and not (out / "label_real.json").exists()
    (out / "Z.npy").unlink()
    (out / "label_real.json").write_text("{}")
    rc, err = _cli_error([public, "--out", out, "--rig", PARALLEL], capsys)
    assert rc == 1 and "label_real.json exists and was not written" in err
    # its own outputs are replaced by a re-run (and nothing else in the folder is touched)
    (out / "label_real.json").unlink()
    (out / "notes.txt").write_text("mine")
    cfg = dict(root=public, out=out, rig=PARALLEL)
    label_real(LabelRealConfig(**cfg, ids=["000001"]))
    assert np.load(out / "Z.npy").shape[0] == 1
    label_real(LabelRealConfig(**cfg, ids=["000000"]))  # previews/000001.png stays ours
    label_real(LabelRealConfig(**cfg))
    assert np.load(out / "Z.npy").shape[0] == 2 and (out / "notes.txt").read_text() == "mine"
    (tmp_path / "o2" / "previews").mkdir(parents=True)
    (tmp_path / "o2" / "previews" / "000001.png").write_bytes(b"a figure of mine")
    with pytest.raises(DatasetError, match="000001.png exists and was not written"):
        label_real(LabelRealConfig(**{**cfg, "out": tmp_path / "o2"}))
    assert (tmp_path / "o2" / "previews" / "000001.png").read_bytes() == b"a figure of mine"
    assert not [p for p in out.iterdir() if p.name.startswith(".fppsim-tmp-")]
    with pytest.raises(DatasetError, match="no scan with id 42"):
        label_real(LabelRealConfig(**cfg, ids=["42"]))


# ------------------------------------------------------------------------------------------ issue 30, case 11
@pytest.mark.parametrize("folder,var,offset", [("PSin", "PSin", "none"), ("Fringe", "Order", "auto"),
                                               ("Fringe", "Order", "1.5")])
def test_a_quantity_that_is_all_nan_is_named_and_nothing_is_written(tmp_path, capsys, folder, var, offset):
    import scipy.io

    from _helpers import tiny_rig

    tiny_rig().save(tmp_path / "rig.json")
    root = _small_public(tmp_path / "pub")
    scipy.io.savemat(root / folder / "7.mat", {var: np.full((32, 64), np.nan)})
    rc, err = _cli_error([root, "--out", tmp_path / "o", "--rig", tmp_path / "rig.json", "--phase-offset", offset],
                         capsys)
    assert rc == 1 and f"{folder}/7.mat" in err and "no finite value" in err and "rig" not in err.split(":")[-1]
    assert not (tmp_path / "o").exists()


def test_duplicate_ids_are_a_usage_error(public, tmp_path, capsys):
    rc, err = _cli_error([public, "--out", tmp_path / "o", "--rig", PARALLEL, "--ids", "000001", "000001"], capsys)
    assert rc == 2 and "--ids" in err and "000001" in err
    assert not (tmp_path / "o").exists()


def test_an_interrupted_rerun_leaves_the_earlier_result_whole(public, tmp_path, monkeypatch, capsys):
    import fppsim.fitting.label_real as lr

    out = tmp_path / "o"
    assert main(["label-real", str(public), "--out", str(out), "--rig", str(PARALLEL), "-q"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert f"rig {PARALLEL}," in line  # a user's rig file is named by its path, not its internal name
    before = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert {Path("previews/000000.png"), Path("previews/000001.png"), Path("label_real.json")} <= set(before)
    real = lr._label_scan
    calls = []

    def stop_on_the_second(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(lr, "_label_scan", stop_on_the_second)
    with pytest.raises(KeyboardInterrupt):  # a re-run with other options, stopped half-way
        label_real(LabelRealConfig(root=public, out=out, rig=REPO / "assets" / "default_rig.json",
                                   phase_offset="auto"))
    after = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert after == before  # arrays, previews and report: all still the earlier run's


def test_a_rig_that_cannot_measure_is_refused(tmp_path, capsys):
    """Issue 30 case 7: the one usability check (fppsim.geometry.rig.usable_rig) wherever a rig enters, here --rig."""
    from _helpers import tiny_rig

    d = tiny_rig().to_dict()
    d["projector"] = {**d["camera"], "width": 912, "height": 1140}  # the projector where the camera is
    (tmp_path / "zero.json").write_text(json.dumps(d))
    rc, err = _cli_error([_small_public(tmp_path / "pub"), "--out", tmp_path / "o", "--rig", tmp_path / "zero.json"],
                         capsys)
    assert rc == 1 and "zero.json" in err and "fringes do not move with height" in err
    assert not (tmp_path / "o").exists()


def test_a_full_disk_while_labelling_names_the_array_and_keeps_the_earlier_result(public, tmp_path, monkeypatch,
                                                                                   capsys):
    import errno
    import os

    import fppsim.dataio.writers as writers

    out = tmp_path / "o"
    assert main(["label-real", str(public), "--out", str(out), "--rig", str(PARALLEL), "-q", "--no-preview"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    capsys.readouterr()

    def full(fh, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(writers, "write_fully", full)
    rc, err = _cli_error([public, "--out", out, "--rig", PARALLEL], capsys)
    assert rc == 1 and str(out / "f1_80.npy") in err and "No space left on device" in err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_a_patch_whose_order_slipped_is_left_unlabelled_and_said(public, rendered, tmp_path):
    """A reference whose temporal orders are 3 periods off in a patch of the plane (its wrapped phase right, as
    real frames show beside shadows): those pixels get the invalid label and a warning, every other label is the
    clean scan's."""
    sid = manifest_ids(rendered)[0]
    s = load_native_sample(rendered / sid, keys=("phase_true", "mask", "height"), meta=False)
    phase = s["phase_true"].astype(np.float64) - OFFSET
    valid = s["mask"] > 0
    flat = valid & (np.abs(s["height"]) < 1e-6)
    yy, xx = np.mgrid[:flat.shape[0], :flat.shape[1]]
    cy, cx = next((y, x) for y in range(10, flat.shape[0] - 10, 4) for x in range(10, flat.shape[1] - 10, 4)
                  if flat[y - 6:y + 7, x - 6:x + 7].all())
    blob = (yy - cy) ** 2 + (xx - cx) ** 2 <= 25
    psin, pcos, order = sums_from_phase(phase, valid, 100.0)
    save_psp_folder_sample(tmp_path / "slipped", sid, psin, pcos, order + 3 * blob.astype(np.int32), s["fringe"])
    save_psp_folder_sample(tmp_path / "clean", sid, psin, pcos, order, s["fringe"])
    reps = {k: label_real(LabelRealConfig(root=tmp_path / k, out=tmp_path / f"o{k}", rig=PARALLEL, previews=False))
            for k in ("clean", "slipped")}
    assert reps["clean"].warnings == [] and reps["clean"].scans[0]["order_slips"]["pixels"] == 0
    rec = reps["slipped"].scans[0]
    assert rec["order_slips"]["pixels"] == int(blob.sum()) and rec["order_slips"]["patches"][0]["shift_periods"] == -3
    assert len(reps["slipped"].warnings) == 1 and "left unlabelled" in reps["slipped"].warnings[0]
    assert f"{int(blob.sum())} px" in reps["slipped"].warnings[0]
    z = {k: np.load(tmp_path / f"o{k}" / "Z.npy")[0, ..., 0] for k in reps}
    assert np.all(z["slipped"][blob] == FIG.invalid_value)
    np.testing.assert_array_equal(z["slipped"][~blob], z["clean"][~blob])
