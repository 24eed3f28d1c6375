"""Rig conventions against analytic geometry and OpenCV."""

import json

import cv2
import numpy as np
import pytest

from fppsim.geometry.rig import Device, Rig, RigError, make_default_rig, make_figshare_like_rig, make_parallel_rig


@pytest.fixture
def rig():
    return Rig.default()


@pytest.mark.parametrize("asset,builder", [("default_rig.json", make_default_rig),
                                           ("figshare_like_rig.json", make_figshare_like_rig)])
def test_assets_match_builders(asset, builder):
    from fppsim.geometry.rig import data_path

    rig, built = Rig.load(data_path(asset)), builder()
    np.testing.assert_allclose(rig.camera.K, built.camera.K)
    np.testing.assert_allclose(rig.projector.K, built.projector.K)
    np.testing.assert_allclose(rig.projector.R, built.projector.R, atol=1e-12)
    np.testing.assert_allclose(rig.projector.t, built.projector.t)
    assert rig.periods == 80 and rig.projector.width == 912 and (rig.camera.width, rig.camera.height) == (640, 352)


def test_projection_matches_opencv(rig):
    rng = np.random.default_rng(0)
    X = rng.uniform([-100, -60, 0], [100, 60, 60], size=(200, 3))
    for dev in (rig.camera, rig.projector):
        dev = Device(K=dev.K, R=dev.R, t=dev.t, width=dev.width, height=dev.height,
                     dist=[0.05, -0.02, 0.001, -0.002, 0.01])
        uv, _ = dev.project(X)
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(dev.R)[0], dev.t, dev.K, dev.dist)
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)


def test_backprojection_round_trip_with_distortion(rig):
    rng = np.random.default_rng(1)
    cam = Device(K=rig.camera.K, R=rig.camera.R, t=rig.camera.t, width=640, height=352,
                 dist=[-0.1, 0.05, 0.001, 0.0005, 0.0])
    X = rng.uniform([-100, -60, 0], [100, 60, 60], size=(500, 3))
    uv, z = cam.project(X)
    np.testing.assert_allclose(cam.backproject(uv, z), X, atol=1e-6)


def test_world_frame_convention(rig):
    # camera above the plane looking down; +z towards the camera; x right in both frames
    assert rig.camera.center[2] == pytest.approx(500.0)
    uv, z = rig.camera.project(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]]))
    assert z[0] == pytest.approx(500.0) and z[3] == pytest.approx(490.0)
    assert uv[1, 0] > uv[0, 0]  # +x world -> right in the image
    assert uv[2, 1] < uv[0, 1]  # +y world -> up in the image (camera y points down)


def _plane_periods(rig, uv):
    """Period of the pattern on the plane, in camera pixels, at camera pixels ``uv`` (analytic)."""
    cam = rig.camera
    X = cam.backproject(uv, cam.plane_depth(uv))
    u_p = rig.projector.project(X)[0][..., 0]
    X2 = cam.backproject(uv + [1, 0], cam.plane_depth(uv + [1, 0]))
    du_p = rig.projector.project(X2)[0][..., 0] - u_p  # projector columns per camera pixel
    return rig.projector.width / rig.periods / np.abs(du_p), u_p


def test_parallel_rig_fringe_period_uniform():
    rig = make_parallel_rig()
    uv = np.stack(np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 351, 5)), -1).reshape(-1, 2)
    period, _ = _plane_periods(rig, uv)
    np.testing.assert_allclose(period, 11.6, rtol=1e-3)


@pytest.fixture
def figshare_rig():
    return make_figshare_like_rig()


def test_figshare_like_fringe_period_falls_left_to_right(figshare_rig):
    """The real figshare rig: 12.06 -> 11.39 px over four column bands, no trend down a column, lines
    leaning by -1.34 deg."""
    rig = figshare_rig
    cam = rig.camera
    uv = np.stack(np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 351, 5)), -1).reshape(-1, 2)
    period, u_p = _plane_periods(rig, uv)
    grid = period.reshape(5, 9)
    assert np.all(np.diff(grid, axis=1) < 0)  # falls steadily left to right
    np.testing.assert_allclose(grid, np.broadcast_to(grid[:1], grid.shape), rtol=2e-3)  # nothing top to bottom
    assert grid[0, 0] == pytest.approx(12.2, abs=0.1) and grid[0, -1] == pytest.approx(11.25, abs=0.1)
    # the fringe lines lean like the real ones: a line of constant u_p moves du/dv = -(du_p/dv)/(du_p/du)
    # = tan(-1.34 deg) camera px per row (the projector's roll; see fit_periods.plane_tilt)
    X3 = cam.backproject(uv + [0, 1], cam.plane_depth(uv + [0, 1]))
    X4 = cam.backproject(uv + [1, 0], cam.plane_depth(uv + [1, 0]))
    dv = rig.projector.project(X3)[0][:, 0] - u_p
    du = rig.projector.project(X4)[0][:, 0] - u_p
    np.testing.assert_allclose(-dv / du, np.tan(np.radians(-1.34)), rtol=0.05)
    assert np.all((u_p > 0) & (u_p < rig.projector.width - 1))  # the projector covers the view


@pytest.mark.slow
def test_figshare_like_rig_rendered_plane_period_trend(figshare_rig):
    """A rendered plane measured like compare-real: halves ~11.96 | 11.49 px, bands ~12.06 -> 11.39."""
    from fppsim.rendering.optics import Optics
    from fppsim.phase.measure import estimate_period, quarter_periods
    from fppsim.rendering.optics import form_images

    pytest.importorskip("pyrender")
    from fppsim.rendering.render import DepthRenderer, scene_geometry

    rig = figshare_rig
    geom = scene_geometry(rig, [], DepthRenderer(), scale=1)
    img = form_images(geom, rig, Optics(), [(80.0, 0.0)], None, 1)[0].astype(float)
    left, right = estimate_period(img[:, :320]), estimate_period(img[:, 320:])
    assert left == pytest.approx(11.96, abs=0.08) and right == pytest.approx(11.49, abs=0.08)
    bands = [estimate_period(img[:, i * 160:(i + 1) * 160]) for i in range(4)]
    assert bands[0] == pytest.approx(12.06, abs=0.1) and bands[-1] == pytest.approx(11.39, abs=0.1)
    q = quarter_periods(img)  # top-left, top-right, bottom-left, bottom-right: no vertical trend
    assert abs(q[0] - q[2]) < 0.05 and abs(q[1] - q[3]) < 0.05 and q[0] > q[1] + 0.3


@pytest.mark.parametrize("ext", [".json", ".yaml"])
def test_save_load_round_trip(tmp_path, rig, ext):
    p = tmp_path / f"rig{ext}"
    rig.save(p)
    back = Rig.load(p)
    for a, b in ((rig.camera, back.camera), (rig.projector, back.projector)):
        for k in ("K", "R", "t", "dist"):
            np.testing.assert_allclose(getattr(a, k), getattr(b, k))


def test_opencv_stereo_import(tmp_path, rig):
    """A stereo calibration (camera frame as world) plus a plane pose reproduces the rig."""
    cam, proj = rig.camera, rig.projector
    R = proj.R @ cam.R.T  # camera -> projector
    T = proj.t - R @ cam.t
    p = tmp_path / "stereo.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", cam.K); fs.write("D1", np.zeros((1, 5))); fs.write("M2", proj.K); fs.write("D2", np.zeros((1, 5)))
    fs.write("R", R); fs.write("T", T.reshape(3, 1))
    fs.write("R_plane", cam.R); fs.write("T_plane", cam.t.reshape(3, 1))
    fs.write("projector_width", 912); fs.write("projector_height", 1140)
    fs.release()
    back = Rig.load(p)
    np.testing.assert_allclose(back.projector.R, proj.R, atol=1e-9)
    np.testing.assert_allclose(back.projector.t, proj.t, atol=1e-9)
    np.testing.assert_allclose(back.camera.t, cam.t, atol=1e-9)
    # the same calibration as OpenCV XML
    px = tmp_path / "stereo.xml"
    fs = cv2.FileStorage(str(px), cv2.FILE_STORAGE_WRITE)
    for key, val in (("M1", cam.K), ("M2", proj.K), ("R", R), ("T", T.reshape(3, 1)), ("R_plane", cam.R),
                     ("T_plane", cam.t.reshape(3, 1))):
        fs.write(key, val)
    fs.release()
    np.testing.assert_allclose(Rig.load(px).projector.t, proj.t, atol=1e-9)
    # plane distance variant (no plane pose)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", cam.K); fs.write("M2", proj.K); fs.write("R", R); fs.write("T", T.reshape(3, 1))
    fs.write("plane_distance", 500.0)
    fs.release()
    back = Rig.load(p)
    np.testing.assert_allclose(back.projector.center, proj.center, atol=1e-9)


@pytest.mark.parametrize("doc, words", [
    ({"camera": {}}, "projector"),
    ({"camera": {"K": [1, 2]}, "projector": {}}, "camera is missing"),
    ("not a mapping", "mapping"),
])
def test_bad_rig_documents(tmp_path, rig, doc, words):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(RigError, match=words):
        Rig.load(p)


def test_bad_rig_geometry(tmp_path, rig):
    d = rig.to_dict()
    d["camera"]["t"] = [0.0, 0.0, -500.0]  # camera below the plane
    p = tmp_path / "below.json"
    p.write_text(json.dumps(d))
    with pytest.raises(RigError, match="above the reference plane"):
        Rig.load(p)
    p.write_text("{ not json")
    with pytest.raises(RigError, match="not valid JSON"):
        Rig.load(p)
    with pytest.raises(RigError, match="not found"):
        Rig.load(tmp_path / "missing.json")


def test_a_rig_in_other_units_or_another_format_is_refused(tmp_path, rig):
    """A rig document is read in mm: one in metres (its "units" said so, or its t put the camera 0.5 mm above
    the plane) once gave heights of -88,000 mm without a word; an unknown format is not guessed at."""
    for key, value, words in (("units", "m", "read in mm only"), ("format", "fppsim-rig/9", "only rig format")):
        d = rig.to_dict()
        d[key] = value
        with pytest.raises(RigError, match=words):
            Rig.from_dict(d)
    d = rig.to_dict()
    for dev in ("camera", "projector"):
        d[dev]["t"] = (np.asarray(d[dev]["t"]) / 1000.0).tolist()
    with pytest.raises(RigError, match="t must be in mm"):
        Rig.from_dict(d)
    assert Rig.from_dict({k: v for k, v in rig.to_dict().items() if k not in ("units", "format")}).periods == rig.periods


def test_a_rig_without_a_plane_in_view_keeps_saying_so():
    """fit-rig's flag for a rig fitted with no plane in view survives the file and every rig built from it (the
    depth and baseline fits once rebuilt the rig field by field and dropped it)."""
    from fppsim.fitting.fit_periods import adjust_rig
    from fppsim.geometry.jitter import RigJitter, jitter_rig

    flagged = Rig.from_dict({**Rig.default().to_dict(), "plane_in_view": False})
    assert flagged.plane_in_view is False and flagged.to_dict()["plane_in_view"] is False
    assert "plane_in_view" not in Rig.default().to_dict()  # the default: files as before
    assert Rig.from_dict(flagged.to_dict()).plane_in_view is False
    assert adjust_rig(flagged, baseline=100.0).plane_in_view is False
    assert jitter_rig(flagged, np.random.default_rng(0), RigJitter()).plane_in_view is False
    with pytest.raises(RigError, match="plane_in_view must be true or false"):
        Rig.from_dict({**Rig.default().to_dict(), "plane_in_view": "no"})


def test_opencv_import_errors(tmp_path, rig):
    p = tmp_path / "broken.yml"
    p.write_text("%YAML:1.0\nfoo: [1,2\n")
    with pytest.raises(RigError, match="broken.yml"):
        Rig.load(p)
    cam, proj = rig.camera, rig.projector
    R = proj.R @ cam.R.T
    T = proj.t - R @ cam.t
    for d1, ok in ((np.array([[0.01, 0, 0, 0, 0, 0, 0, 0]]), True), (np.array([[0.01, 0, 0, 0, 0, 0.2, 0, 0]]), False),
                   (np.array([[0.01, 0.0, 0.0, 0.0]]), True)):
        p = tmp_path / "d.yml"
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
        fs.write("M1", cam.K); fs.write("D1", d1); fs.write("M2", proj.K); fs.write("R", R); fs.write("T", T.reshape(3, 1))
        fs.write("plane_distance", 500.0)
        fs.release()
        if ok:
            assert Rig.load(p).camera.dist[0] == pytest.approx(0.01)
        else:
            with pytest.raises(RigError, match="k4"):
                Rig.load(p)


def _footprint_area(proj, u, v, normal, point):
    """Area (mm^2) of projector pixel (u, v)'s footprint on the plane through ``point`` with ``normal``:
    its four corners cast as rays and cut with the plane (shoelace on the plane), no falloff formula."""
    corners = np.array([[u - .5, v - .5], [u + .5, v - .5], [u + .5, v + .5], [u - .5, v + .5]])
    d = proj.normalized_rays(corners) @ proj.R  # device -> world directions
    c = proj.center
    s = ((point - c) @ normal) / (d @ normal)
    P = c + s[:, None] * d
    e1, e2 = P[2] - P[0], P[3] - P[1]
    return 0.5 * np.linalg.norm(np.cross(e1, e2))


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, -0.2, 0.93), (-0.5, 0.1, 0.86)])
def test_projector_irradiance_is_flux_over_pixel_footprint(normal):
    """Each projector pixel sends the same flux, so irradiance ~ 1 / footprint area: the ratio between
    any two pixels on any plane equals the ratio of ``cos_incidence * irradiance_falloff``."""
    proj = make_default_rig().projector
    n = np.asarray(normal) / np.linalg.norm(normal)
    point = np.array([0.0, 0.0, 20.0])
    pixels = [(300.0, 200.0), (600.0, 570.0), (880.0, 1000.0), (40.0, 900.0)]
    truth, model = [], []
    for u, v in pixels:
        truth.append(1.0 / _footprint_area(proj, u, v, n, point))
        d = proj.normalized_rays(np.array([u, v])) @ proj.R
        c = proj.center
        X = c + ((point - c) @ n) / (d @ n) * d
        cos_inc = abs(n @ (c - X)) / np.linalg.norm(c - X)
        model.append(cos_inc * proj.irradiance_falloff(X))
    truth, model = np.array(truth), np.array(model)
    np.testing.assert_allclose(model / model[0], truth / truth[0], rtol=2e-3)
    assert truth.max() / truth.min() > 1.1  # the pixels differ: the check can fail


def test_projector_square_to_a_plane_lights_it_evenly():
    """The parallel rig's projector looks straight down: every pixel's footprint on z = 0 has the same
    area, so the plane is lit evenly (an isotropic point source would fall off as cos^3)."""
    from fppsim.fitting.fit_optics import plane_model

    k = plane_model(make_parallel_rig())
    lit = k["lit"]
    assert lit.mean() > 0.9
    np.testing.assert_allclose(k["k"][lit], k["k"][lit].mean(), rtol=1e-9)


def test_default_rig_plane_brightness_trend_like_the_real_rig():
    """The real figshare pair's fringe amplitude on its plane rises about 1.2x left to right (23.7 -> 28.4
    8-bit levels in the outer 40 columns); the default rig gives 1.11x (the old point-source model 1.92x)."""
    from fppsim.fitting.fit_optics import plane_model

    k = plane_model(make_default_rig())["k"]
    ratio = k[:, -40:].mean() / k[:, :40].mean()
    assert 1.05 < ratio < 1.3


def test_irradiance_falloff_normalisation_and_bad_points():
    proj = make_default_rig().projector
    assert proj.irradiance_falloff(np.zeros(3)) == pytest.approx(1.0, abs=1e-12)
    behind = proj.center - 100.0 * proj.R[2]  # 100 mm behind the projector, on its axis
    f = proj.irradiance_falloff(np.stack([np.zeros(3), behind]))
    assert f[0] == pytest.approx(1.0) and f[1] == 0.0
    f = proj.irradiance_falloff(np.zeros((2, 3)), z=523.3, dist=np.array([600.0, 601.0]))  # scalar z
    assert f.dtype == np.float64 and np.all(f > 0)
    R = np.diag([1.0, -1.0, -1.0]) @ proj.R  # the same projector turned round: the origin is behind it
    turned = Device(K=proj.K, R=R, t=-R @ proj.center, width=proj.width, height=proj.height)
    with pytest.raises(RigError, match="behind"):
        turned.irradiance_falloff(np.zeros(3))


def test_ray_cut_at_a_height_and_the_forward_model(rig):
    """Device.ray_cut: the camera ray of each pixel cut at z = h (mm) lands on that plane and projects back to
    its pixel; Rig.phase_at_height projects those points; Rig.sensitivity is the slope of it."""
    cam = rig.camera
    uv = cam.pixel_grid()[::37, ::53]
    h = np.linspace(-20.0, 60.0, uv[..., 0].size).reshape(uv.shape[:-1])
    depth, X = cam.ray_cut(uv, h)
    assert (depth > 0).all()
    np.testing.assert_allclose(X[..., 2], h, atol=1e-9)
    np.testing.assert_allclose(cam.project(X)[0], uv, atol=1e-6)
    assert np.array_equal(cam.plane_depth(uv, 12.5), cam.ray_cut(uv, 12.5)[0])
    phase = rig.phase_at_height(h, uv)
    np.testing.assert_allclose(phase, rig.phase_of_column(rig.projector.project(X)[0][..., 0]), atol=1e-9)
    assert rig.phase_at_height(0.0).shape == (cam.height, cam.width)
    assert np.isnan(rig.phase_at_height(cam.center[2] + 1.0, uv)).all()  # the plane is behind the camera
    s = rig.sensitivity(10.0, 10.5, uv)
    np.testing.assert_allclose(s, (rig.phase_at_height(10.5, uv) - rig.phase_at_height(10.0, uv)) / 0.5, atol=1e-9)
    centre = np.array([cam.width // 2, cam.height // 2], dtype=np.float64)
    assert rig.sensitivity() == pytest.approx(float(rig.sensitivity(0.0, 1.0, centre[None])[0]), abs=1e-12)
