"""fppsim.fitting.fit_depth and the ``distance`` rig parameter: how the height sensitivity grows with height."""

import json

import numpy as np
import pytest

from fppsim.fitting import fit_depth as fd
from fppsim.fitting import fit_periods as fr
from fppsim.dataio import readers
from fppsim.fitting.height_sensitivity import centre_sensitivity
from fppsim.geometry.rig import Rig, RigError, make_default_rig

from _helpers import REAL_SAMPLE as REAL
from _helpers import SHARED


def _truth() -> Rig:
    """A rig at a known distance: the default moved to 300 mm, baseline 15 % short of the scaled one."""
    r = fr.adjust_rig(make_default_rig(), distance=300.0)
    return fr.adjust_rig(r, baseline=0.85 * fr.base_values(r)["baseline"])


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Three figshare-layout samples rendered by pyrender with the truth rig (independent of the
    re-projection fit_depth uses); seed 5 gives objects 20-50 mm high with projector shadows."""
    from fppsim.generation import generate_dataset
    from fppsim.rendering.optics import OpticsRanges
    from fppsim.geometry.rig import data_path
    from fppsim.rendering.synth import SynthConfig

    out = tmp_path_factory.mktemp("depth") / "syn"
    generate_dataset([str(data_path("meshes"))], out, 3, seed=5,
                     config=SynthConfig(rig=_truth(), optics=OpticsRanges(), psp_freqs=()), fmt="figshare",
                     progress=False)
    return out


def test_distance_keeps_the_plane_and_the_plane_sensitivity():
    base = make_default_rig()
    assert fr.base_values(base)["distance"] == pytest.approx(500.0)
    far = fr.adjust_rig(base, distance=1000.0)
    # the camera's view of the plane is unchanged (camera looking straight down, focal scaled with it)
    uv = base.camera.pixel_grid()[::40, ::40]
    X0 = base.camera.backproject(uv, base.camera.plane_depth(uv))
    X1 = far.camera.backproject(uv, far.camera.plane_depth(uv))
    np.testing.assert_allclose(X1, X0, atol=1e-9)
    assert far.camera.K[0, 0] == pytest.approx(2460.0) and far.camera.center[2] == pytest.approx(1000.0)
    assert far.projector.center[0] == pytest.approx(660.0)  # the baseline scales with it
    # same triangulation angle: the sensitivity at the plane stays, its growth with height shrinks
    assert centre_sensitivity(far) == pytest.approx(centre_sensitivity(base), rel=0.005)
    growth = lambda r: fd.sensitivity_at(r, 40.0) / fd.sensitivity_at(r, 0.0)  # noqa: E731
    assert growth(base) == pytest.approx((500 / 460) ** 2, rel=0.01)
    assert growth(far) == pytest.approx((1000 / 960) ** 2, rel=0.01)
    assert fr.plane_coverage(far) == 1.0 and far.periods == base.periods
    # given with it, the baseline is the value after scaling; nonsense is refused
    r = fr.adjust_rig(base, distance=250.0, baseline=100.0)
    assert r.projector.center[0] - r.camera.center[0] == pytest.approx(100.0)
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(RigError, match="distance"):
            fr.adjust_rig(base, distance=bad)
    # without distance the camera never moves (the old parameters behave as before)
    r = fr.adjust_rig(base, yaw=0.01, baseline=300.0)
    np.testing.assert_array_equal(r.camera.K, base.camera.K)
    np.testing.assert_array_equal(r.camera.t, base.camera.t)


def test_shadow_edges_both_sides():
    valid = np.ones((4, 60), bool)
    valid[:, 20:35] = False  # shadow
    plane = valid.copy()
    plane[:, 35:] = False
    obj = valid & ~plane
    e = fd.shadow_edges(valid, plane, obj)
    assert e.tolist() == [[r, 19, 35] for r in range(4)]
    # mirrored scene, projector on the other side
    m = fd.shadow_edges(valid[:, ::-1], plane[:, ::-1], obj[:, ::-1], shadow_left=False)
    assert m.tolist() == [[r, 40, 24] for r in range(4)]
    assert fd.shadow_edges(valid, obj, plane).shape == (0, 3)  # object before the shadow: not a crossing


def test_depth_check_on_rendered_images(rendered):
    """Through its own rig a rendered image has no residual; the default rig's is whole radians, and the
    shadows say which way."""
    images, _ = readers.load_fringe_images(rendered)
    truth, default = _truth(), make_default_rig()
    for im in images:
        c = fd.depth_check(truth, im)
        assert c is not None and c.n_edges >= 10
        assert c.fringes == 0 and abs(c.object_offset) < 0.05 and abs(c.slope) < 0.005
        assert c.object_residual < 0.05 and c.plane_residual < 0.02
    c = fd.depth_check(default, images[2])  # the default rig shifts the phase too much at 35 mm
    assert c.object_offset > 3.0 and c.fringes == 1
    plain = readers.FringeImage(images[0].gray, images[0].valid, "plain")
    assert fd.depth_check(truth, plain) is None


@pytest.mark.slow
def test_fit_rig_with_distance_recovers_the_rendering_rig(rendered, tmp_path, capsys):
    """fit-rig --params yaw,roll,focal,distance from the default rig finds the rendering rig's distance."""
    from fppsim.cli import main

    out, rep = tmp_path / "rig.json", tmp_path / "fit.json"
    assert main(["fit-rig", str(rendered), "--out", str(out), "--base", "default", "--params", "yaw,roll,focal,distance",
                 "--json", str(rep)]) == 0
    text = capsys.readouterr().out
    assert "phase-height relation" in text and "chosen: distance 500.0 ->" in text
    truth, rig = _truth(), Rig.load(out)
    depth = json.loads(rep.read_text())["depth"]
    assert depth["distance_mm"] == pytest.approx(300.0, abs=15.0)
    assert depth["baseline_mm"] == pytest.approx(fr.base_values(truth)["baseline"], rel=0.05)
    assert rig.camera.center[2] == pytest.approx(depth["distance_mm"])
    assert centre_sensitivity(rig) == pytest.approx(centre_sensitivity(truth), rel=0.02)
    assert fd.sensitivity_at(rig, 40.0) == pytest.approx(fd.sensitivity_at(truth, 40.0), rel=0.02)
    assert rig.periods == 80.0  # focal refitted, not the fringe count
    # the old behaviour without distance is untouched: no depth section
    assert main(["fit-rig", str(rendered), "--out", str(tmp_path / "r2.json"), "--base", "default", "--json",
                 str(tmp_path / "f2.json")]) == 0
    assert "depth" not in json.loads((tmp_path / "f2.json").read_text())


def test_distance_needs_labels(tmp_path):
    import cv2

    from fppsim.fitting.fit_rig import FitRigConfig, fit_rig_images

    rig = make_default_rig()
    cam = rig.camera
    uv = cam.pixel_grid()
    up = rig.projector.project(cam.backproject(uv, cam.plane_depth(uv)))[0][..., 0]
    img = np.clip(60 + 45 * np.cos(2 * np.pi * rig.periods * up / rig.projector.width), 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    with pytest.raises(RigError, match="height labels"):
        fit_rig_images(FitRigConfig(real=tmp_path, out=tmp_path / "r.json", params=("yaw", "distance")))
    with pytest.raises(RigError, match="height labels"):
        fit_rig_images(FitRigConfig(real=tmp_path, out=tmp_path / "r.json", params=("yaw", "distance"),
                                    sensitivity="off"))
    assert not (tmp_path / "r.json").exists()


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "fringe_pattern.npy").is_file(), reason="../shared/real-sample not present")
def test_real_pair_phase_height_relation():
    """The measured facts: through the default rig the real object (30-46 mm) sits 3.46 rad (one fringe
    minus 2.82 rad, the shadows fix the fringe) away from the labels; the fit zeroes it at about 235 mm
    with 0.71 rad/mm at the plane and the default rig's 1.02 rad/mm at 40 mm."""
    images, _ = readers.load_fringe_images(REAL)
    base = make_default_rig()
    c = fd.depth_check(base, images[0])
    assert c.fringes == 1 and c.object_offset == pytest.approx(3.46, abs=0.15) and c.vote_share > 0.9
    fit = fd.fit_depth(images, fr.measure_bands(images), base)
    assert 210.0 < fit.distance < 270.0
    assert abs(fit.sensitivity) == pytest.approx(0.714, abs=0.02)
    assert abs(fit.sensitivity_40) == pytest.approx(1.02, abs=0.03)
    (chk,) = fit.checks
    assert chk.object_residual < 0.15 and chk.plane_residual < 0.2 and chk.fringes == 0
    model = fr.band_model(fit.fit.rig)
    np.testing.assert_allclose(model["columns"], [12.06, 11.85, 11.61, 11.39], atol=0.02)
    assert float(model["tilt_deg"][0]) == pytest.approx(-1.34, abs=0.03)
    assert "distance" in fd.format_depth_fit(fit)


@pytest.fixture(scope="module")
def rendered_default(tmp_path_factory):
    """One figshare-layout sample rendered through the default rig itself: labels that can only confirm it."""
    from fppsim.generation import generate_dataset
    from fppsim.rendering.optics import OpticsRanges
    from fppsim.geometry.rig import data_path
    from fppsim.rendering.synth import SynthConfig

    out = tmp_path_factory.mktemp("depth_default") / "syn"
    generate_dataset([str(data_path("meshes"))], out, 1, seed=5,
                     config=SynthConfig(rig=make_default_rig(), optics=OpticsRanges(), psp_freqs=()), fmt="figshare",
                     progress=False)
    return out


def _cost(rig, images) -> float:
    return fd._pooled([fd.depth_check(rig, im) for im in images], "cost")


def test_distance_alone_fits_distance_and_baseline_only(rendered_default, tmp_path, capsys):
    """Issue 30 case 12: ``--params distance`` moves nothing but the distance and the baseline (no yaw), and the
    rig it returns is never worse than its start on the fit's own objective."""
    from fppsim.cli import main

    out, rep = tmp_path / "rig.json", tmp_path / "fit.json"
    assert main(["fit-rig", str(rendered_default), "--out", str(out), "--base", "default", "--params", "distance",
                 "--json", str(rep)]) == 0
    text = capsys.readouterr().out
    base, rig = make_default_rig(), Rig.load(out)
    images, _ = readers.load_fringe_images(rendered_default)
    assert _cost(rig, images) <= _cost(base, images) + 1e-12
    depth = json.loads(rep.read_text())["depth"]
    moved = fr.adjust_rig(base, distance=depth["distance_mm"], baseline=depth["baseline_mm"])
    np.testing.assert_allclose(rig.projector.R, moved.projector.R, atol=1e-12)
    np.testing.assert_allclose(rig.projector.K, moved.projector.K, atol=1e-9)
    assert rig.periods == base.periods
    assert "(rad)" not in text.split("fringe tilt")[-1]  # angles are shown in degrees, and labelled so


@pytest.mark.skipif(not (SHARED / "real-phase" / "FP1523").is_dir(), reason="../shared/real-phase absent")
@pytest.mark.parametrize("params", ["yaw,roll,periods,distance", "distance"])
def test_labels_made_through_the_base_rig_confirm_it(tmp_path, capsys, params):
    """Issue 30 case 12: label-real output of the shared frame through the default rig; fit-rig keeps that rig
    (the labels can only confirm it) and says so, instead of moving the camera to 604 mm."""
    from fppsim.cli import main

    lr = tmp_path / "lr"
    assert main(["label-real", str(SHARED / "real-phase" / "FP1523"), "--out", str(lr), "-q", "--no-preview"]) == 0
    out, rep = tmp_path / "rig.json", tmp_path / "fit.json"
    assert main(["fit-rig", str(lr), "--out", str(out), "--base", "default", "--params", params, "--json", str(rep)]) == 0
    base, rig = make_default_rig(), Rig.load(out)
    images, _ = readers.load_fringe_images(lr)
    assert _cost(rig, images) <= _cost(base, images) + 1e-12
    depth = json.loads(rep.read_text())["depth"]
    assert depth["distance_mm"] == pytest.approx(500.0, abs=2.0)
    assert depth["baseline_mm"] == pytest.approx(330.0, abs=2.0)
    checks = [fd.depth_check(rig, im) for im in images]
    base_checks = [fd.depth_check(base, im) for im in images]
    assert fd._pooled(checks, "plane_residual") <= 1.05 * fd._pooled(base_checks, "plane_residual")
    if depth["kept_base"]:
        assert "the base rig is kept" in capsys.readouterr().out


def test_fit_rig_json_report_is_not_replaced_without_force(rendered_default, tmp_path, capsys):
    from fppsim.cli import main

    (tmp_path / "fit.json").write_text("my notes")
    assert main(["fit-rig", str(rendered_default), "--out", str(tmp_path / "rig.json"), "--params", "yaw",
                 "--json", str(tmp_path / "fit.json")]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "fit.json exists" in err[0] and "--force" in err[0]
    assert (tmp_path / "fit.json").read_text() == "my notes" and not (tmp_path / "rig.json").exists()


@pytest.mark.parametrize("flag,value", [("--col-bands", "0"), ("--row-bands", "0"), ("--max-images", "0")])
def test_fit_rig_bad_option_values_exit_2(tmp_path, capsys, flag, value):
    from fppsim.cli import main

    assert main(["fit-rig", str(tmp_path), "--out", str(tmp_path / "rig.json"), flag, value]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and flag in err[0] and not (tmp_path / "rig.json").exists()
