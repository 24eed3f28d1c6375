"""fppsim.fitting.fit_rig: analytic period map of a rig, band measurement of fringe images, fitting the projector."""

import cv2
import numpy as np
import pytest

from fppsim.fitting import fit_periods as fr
from fppsim.fitting.fit_rig import fit_baseline
from fppsim.fitting import height_sensitivity
from fppsim.dataio import readers
from fppsim.geometry.rig import Rig, RigError, make_parallel_rig
from fppsim.phase.measure import estimate_period

from _helpers import REAL_SAMPLE as REAL


def _plane_images(rig, n=2, noise=1.5, seed=0):
    """Fringe images of the bare plane: I = 60 + 45 cos(2 pi f u_p / W_p + shift) at every pixel centre."""
    cam = rig.camera
    uv = cam.pixel_grid()
    X = cam.backproject(uv, cam.plane_depth(uv))
    up = rig.projector.project(X)[0][..., 0]
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        img = 60 + 45 * np.cos(2 * np.pi * rig.periods * up / rig.projector.width + 1.3 * k)
        img = np.clip(np.rint(img + rng.normal(0, noise, img.shape)), 0, 255).astype(np.uint8)
        out.append(img)
    return out


def test_parallel_rig_has_the_textbook_period():
    # parallel axes at equal heights: u_p = fp (X - b) / Z + cx_p and u = fc X / Z + cx, so the
    # period is (W_p / f) (fc / fp) everywhere: 912 / 80 * 1230 / 1208.8
    rig = make_parallel_rig()
    _, _, T = fr.period_map(rig, step=8)
    assert np.isfinite(T).all()
    np.testing.assert_allclose(T, 912 / 80 * 1230 / 1208.8, rtol=1e-9)
    bands = fr.band_model(rig)
    np.testing.assert_allclose(bands["halves"], 912 / 80 * 1230 / 1208.8, rtol=1e-9)
    assert fr.plane_coverage(rig) == 1.0


def test_period_map_matches_the_measured_fft_period():
    """The analytic map against an independent measurement: the FFT period of synthesised images."""
    rig = fr.adjust_rig(make_parallel_rig(), yaw=np.radians(3.0), pitch=np.radians(-2.0))
    img = _plane_images(rig, 1, noise=0.0)[0]
    model = fr.band_model(rig, 4, 3)
    H, W = img.shape
    for i, (a, b) in enumerate(zip(fr._band_edges(W, 4)[:-1], fr._band_edges(W, 4)[1:])):
        assert estimate_period(img[:, a:b].astype(float)) == pytest.approx(model["columns"][i], abs=0.02)
    for i, (a, b) in enumerate(zip(fr._band_edges(H, 3)[:-1], fr._band_edges(H, 3)[1:])):
        assert estimate_period(img[a:b].astype(float)) == pytest.approx(model["rows"][i], abs=0.02)
    # yaw makes a left-right trend, pitch a top-bottom one
    assert model["columns"][0] - model["columns"][-1] > 0.2
    assert abs(model["rows"][0] - model["rows"][-1]) > 0.05


def test_adjust_rig_keeps_camera_and_lights_the_view():
    base = make_parallel_rig()
    r = fr.adjust_rig(base, yaw=0.05, pitch=-0.03, roll=0.01, baseline=200.0, periods=78.0, focal=1250.0)
    np.testing.assert_array_equal(r.camera.K, base.camera.K)
    np.testing.assert_array_equal(r.camera.R, base.camera.R)
    np.testing.assert_allclose(r.projector.center, [200.0, 0.0, 500.0], atol=1e-9)  # rotation about its centre
    assert r.periods == 78.0 and r.projector.K[0, 0] == 1250.0
    assert fr.plane_coverage(r) == 1.0
    with pytest.raises(RigError, match="unknown rig parameter"):
        fr.adjust_rig(base, twist=1.0)


def test_fit_recovers_a_perturbed_rig():
    base = make_parallel_rig()
    truth = fr.adjust_rig(base, yaw=np.radians(-2.5), pitch=np.radians(1.5), periods=78.5)
    images = [readers.FringeImage(g, np.ones(g.shape, bool), str(i)) for i, g in enumerate(_plane_images(truth, 3))]
    measured = fr.measure_bands(images)
    fit = fr.fit_rig_periods(measured, base, ("yaw", "pitch", "periods"))
    _, _, t_true = fr.period_map(truth)
    _, _, t_fit = fr.period_map(fit.rig)
    assert np.nanmax(np.abs(t_fit - t_true)) < 0.05
    assert fit.rms_fitted < 0.02 < 0.1 < fit.rms_base
    assert fit.params["yaw"] == pytest.approx(np.radians(-2.5), abs=np.radians(0.3))
    assert fit.params["periods"] == pytest.approx(78.5, abs=0.3)
    np.testing.assert_array_equal(fit.rig.camera.K, base.camera.K)
    text = fr.format_fit(fit)
    assert "columns    0-160" in text and "right half" in text and "yaw" in text


def test_fit_recovers_a_rolled_projector_from_the_fringe_tilt():
    """Roll barely changes the band periods; the measured tilt of the lines is what fixes it."""
    base = make_parallel_rig()
    truth = fr.adjust_rig(base, roll=np.radians(-1.3))
    assert fr.plane_tilt(base) == pytest.approx(0.0, abs=1e-6)
    images = [readers.FringeImage(g, np.ones(g.shape, bool), str(i)) for i, g in enumerate(_plane_images(truth, 2))]
    measured = fr.measure_bands(images)
    assert float(measured.tilt_deg[0]) == pytest.approx(fr.plane_tilt(truth), abs=0.05)
    assert abs(fr.plane_tilt(truth)) > 1.0
    fit = fr.fit_rig_periods(measured, base)
    assert "roll" in fit.params
    assert fit.params["roll"] == pytest.approx(np.radians(-1.3), abs=np.radians(0.1))
    assert fr.plane_tilt(fit.rig) == pytest.approx(fr.plane_tilt(truth), abs=0.05)
    assert "fringe tilt (deg)" in fr.format_fit(fit)


def test_default_fit_recovers_the_roll_of_a_yawed_rig():
    """On the default (yawed, lens-shifted) geometry pitch tilts the lines too; the default parameters
    (yaw, roll, periods) recover a roll without trading it against pitch."""
    from fppsim.geometry.rig import DEFAULT_PROJECTOR_ROLL, make_default_rig

    unrolled = fr.adjust_rig(make_default_rig(), roll=-DEFAULT_PROJECTOR_ROLL)
    truth = fr.adjust_rig(unrolled, roll=np.radians(-1.3))
    images = [readers.FringeImage(g, np.ones(g.shape, bool), str(i)) for i, g in enumerate(_plane_images(truth, 2))]
    fit = fr.fit_rig_periods(fr.measure_bands(images), unrolled)
    assert set(fit.params) == {"yaw", "roll", "periods"}
    assert fit.params["roll"] == pytest.approx(np.radians(-1.3), abs=np.radians(0.05))


def test_default_rig_fringes_lean_like_the_real_ones():
    from fppsim.geometry.rig import DEFAULT_PROJECTOR_ROLL, make_default_rig

    rig = make_default_rig()
    assert fr.plane_tilt(rig) == pytest.approx(-1.34, abs=0.03)
    img = _plane_images(rig, 1, noise=0.0)[0]
    assert fr.measure_bands([readers.FringeImage(img, np.ones(img.shape, bool))]).tilt_deg[0] == pytest.approx(-1.34, abs=0.05)
    # rolling it back gives vertical fringes and leaves the period trend alone
    unrolled = fr.adjust_rig(rig, roll=-DEFAULT_PROJECTOR_ROLL)
    assert fr.plane_tilt(unrolled) == pytest.approx(0.0, abs=1e-3)
    np.testing.assert_allclose(fr.band_model(unrolled)["columns"], fr.band_model(rig)["columns"], atol=0.01)


@pytest.mark.skipif(not (REAL / "fringe_pattern.npy").is_file(), reason="../shared/real-sample not present")
def test_fit_reproduces_the_real_trend():
    images, layout = readers.load_fringe_images(REAL)
    assert layout == "real-sample"
    fit = fr.fit_rig_periods(fr.measure_bands(images), make_parallel_rig())
    left, right = fit.fitted_model["halves"]
    assert left == pytest.approx(11.96, abs=0.1) and right == pytest.approx(11.49, abs=0.1)
    assert left - right > 0.35
    # the real fringes lean by about -1.35 deg (8.6 px over the 352 rows); the fitted projector is rolled to match
    assert float(fit.measured.tilt_deg[0]) == pytest.approx(-1.34, abs=0.1)
    assert float(fit.fitted_model["tilt_deg"][0]) == pytest.approx(float(fit.measured.tilt_deg[0]), abs=0.05)


def test_cli(tmp_path, capsys):
    from fppsim.cli import main

    truth = fr.adjust_rig(make_parallel_rig(), yaw=np.radians(2.0), periods=81.0)
    for i, img in enumerate(_plane_images(truth, 2)):
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), img)
    out = tmp_path / "rig.json"
    assert main(["fit-rig", str(tmp_path), "--out", str(out), "--base", "default", "--params", "yaw,periods", "--json",
                 str(tmp_path / "fit.json")]) == 0
    text = capsys.readouterr().out
    assert "measured" in text and "fitted" in text and "RMS residual" in text
    rig = Rig.load(out)
    _, _, a = fr.period_map(rig)
    _, _, b = fr.period_map(truth)
    assert np.nanmax(np.abs(a - b)) < 0.05
    # an existing output is not replaced without --force; bad inputs are one line
    assert main(["fit-rig", str(tmp_path), "--out", str(out)]) == 1
    assert "exists; pass --force" in capsys.readouterr().err
    assert main(["fit-rig", str(tmp_path / "nope"), "--out", str(tmp_path / "r2.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope: not a folder" in err
    with pytest.raises(SystemExit) as e:
        main(["fit-rig", str(tmp_path), "--out", str(tmp_path / "r3.json"), "--params", "twist"])
    assert e.value.code == 2
    assert not (tmp_path / "r2.json").exists()


def test_phase_folders_give_plane_and_object_masks(tmp_path):
    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

    rig = make_parallel_rig()
    img = _plane_images(rig, 1)[0]
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    bump = 30.0 * np.clip(1 - ((xx - 300) ** 2 + (yy - 170) ** 2) / 60.0 ** 2, 0, None)  # mm
    phase = 2 * np.pi * (5 + xx / 11.6) + 0.002 * yy ** 1.5 - 0.5 * bump
    valid = np.ones((h, w), bool)
    valid[100:140, 200:230] = False  # a shadow
    save_psp_folder_sample(tmp_path, "1", *sums_from_phase(phase, valid), img)
    images, layout = readers.load_fringe_images(tmp_path)
    assert layout == "psp-folders"
    im = images[0]
    np.testing.assert_array_equal(im.valid, valid & (img > 0))
    assert not (im.plane & (bump > 1)).any()
    assert (im.obj == (im.valid & (0.5 * bump > 1.0))).mean() > 0.999
    assert im.plane.sum() > 0.9 * (im.valid & (bump == 0)).sum()


# ---------------------------------------------------------------- height sensitivity from labels
def _rendered(tmp_path, rig, count=2, seed=5):
    """Samples rendered by pyrender (independent of fit_rig's re-projection) with the given rig."""
    from fppsim.generation import generate_dataset as generate
    from fppsim.rendering.optics import OpticsRanges
    from fppsim.rendering.synth import SynthConfig

    from fppsim.geometry.rig import data_path

    ASSETS = data_path("meshes")
    out = tmp_path / f"syn{seed}"
    generate([str(ASSETS)], out, count, seed=seed, config=SynthConfig(rig=rig, optics=OpticsRanges(), psp_freqs=()),
             fmt="figshare", progress=False)
    return out


def test_surface_phase_equals_the_rendered_projector_phase(tmp_path):
    """Re-projecting the exact rendered height through the rig gives the renderer's projector phase."""
    from fppsim.geometry.rig import make_default_rig

    rig = make_default_rig()
    out = _rendered(tmp_path, rig, count=1)
    a = np.load(out / "native" / "000000" / "arrays.npz")
    valid = a["mask"] > 0
    phi = height_sensitivity.surface_phase(rig, np.where(valid, a["height"], 0.0))
    err = np.abs(phi - a["phase_true"])[valid]
    # float32 storage of the height (and of a phase of up to ~500 rad) limits the agreement
    assert np.median(err) < 2e-3 and np.percentile(err, 99) < 2e-2
    # a 1 mm step shifts the phase by the centre sensitivity; the default rig's is about -0.87 rad/mm
    assert height_sensitivity.centre_sensitivity(rig) == pytest.approx(-0.87, abs=0.01)
    assert height_sensitivity.centre_sensitivity(make_parallel_rig()) == pytest.approx(-0.48, abs=0.01)


@pytest.mark.slow
def test_fit_baseline_recovers_the_rendering_rig(tmp_path):
    """Images rendered with a 260 mm baseline, fitted from the 180 mm parallel rig: the scan peaks there."""
    true = fr.adjust_rig(make_parallel_rig(), baseline=260.0)
    out = _rendered(tmp_path, true, count=2)
    images, _ = readers.load_fringe_images(out)
    measured = fr.measure_bands(images)
    fit = fit_baseline(images, measured, make_parallel_rig(), params=("yaw",),
                          baselines=np.arange(160.0, 400.0, 40.0), refine=10.0)
    assert fit is not None
    assert fit.baseline == pytest.approx(260.0, abs=10.0)
    assert max(c for _, c in fit.scan) > 0.9
    assert fit.sensitivity == pytest.approx(height_sensitivity.centre_sensitivity(true), rel=0.05)
    # plain images have no labels: nothing to fit
    plain = [readers.FringeImage(im.gray, im.valid, im.name) for im in images]
    assert fit_baseline(plain, measured, make_parallel_rig()) is None


def test_fit_baseline_keeps_a_projector_left_of_the_camera(tmp_path):
    """A rig with its projector LEFT of the camera (world -x; raised surfaces raise the phase): the scanned
    baselines are distances on that side. Every candidate used to be placed at +x, so fit-rig without --base
    on labelled frames (fppsim's own PSP output) wrote the projector on the other side from the one its
    report measured, and the rig's height sensitivity the wrong way round."""
    import math

    from fppsim.fitting.rig_start import start_rig

    true = start_rig(200, 150, (2 * math.pi / 9.0, 0.0), -1, distance=450.0, baseline=280.0)
    true = fr.adjust_rig(true, periods=round(true.periods))
    assert true.projector.center[0] < 0 < height_sensitivity.centre_sensitivity(true)
    out = _rendered(tmp_path, true, count=2)
    images, _ = readers.load_fringe_images(out)
    base = start_rig(200, 150, (2 * math.pi / 9.0, 0.0), -1, distance=450.0, baseline=200.0)
    fit = fit_baseline(images, fr.measure_bands(images), base, params=("yaw", "periods"),
                       baselines=np.arange(160.0, 400.0, 40.0), refine=10.0)
    assert fit is not None and fit.baseline == pytest.approx(280.0, abs=20.0)
    assert fit.fit.rig.projector.center[0] < 0, "the projector moved to the other side of the camera"
    assert fit.sensitivity == pytest.approx(height_sensitivity.centre_sensitivity(true), rel=0.1)


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real-sample not present")
def test_real_pair_sensitivity_matches_the_default_rig_not_the_parallel_one():
    from fppsim.geometry.rig import make_default_rig

    images, _ = readers.load_fringe_images(REAL)
    good = height_sensitivity.sensitivity_check(make_default_rig(), images[0])
    bad = height_sensitivity.sensitivity_check(make_parallel_rig(), images[0])
    assert good.coherence > 0.95 and abs(good.slope) < 0.05
    assert bad.coherence < 0.5
