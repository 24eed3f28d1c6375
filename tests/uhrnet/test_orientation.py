"""uhrnet.physics.orientation: whether a fringe image reads flipped through its rig (rotated 180 degrees or mirrored
across its fringes: its relief below the reference plane), from the image's phase and the rig alone. The truth is how
the image was turned: ray-traced boxes on the plane, and the real frames of ../shared (skipped without them)."""

from pathlib import Path

import numpy as np
import pytest

from _helpers import BOXES, box_scene, rig_fringe
from fppsim.geometry.rig import load_rig, make_default_rig
from uhrnet.inference.prediction import fringe_phase
from uhrnet.physics.orientation import check_orientation

ASSETS = Path(__file__).resolve().parents[2] / "assets"
SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"


def turned(img, how, vertical=True):
    """``img`` as given, rotated 180 degrees, mirrored across its fringes or along them."""
    return np.ascontiguousarray({"given": img, "rotated": img[::-1, ::-1],
                                 "across": img[:, ::-1] if vertical else img[::-1],
                                 "along": img[::-1] if vertical else img[:, ::-1]}[how])


def check(img8, rig):
    ssp = fringe_phase(img8.astype(np.float32) / 127.5 - 1.0, rig)
    return check_orientation(ssp.wrapped, ssp.reliability, ssp.valid, rig)


@pytest.mark.parametrize("rig_file", ["default_rig.json", "parallel_rig.json"])
def test_boxes_on_the_plane_read_flipped_only_when_turned(rig_file):
    """Through the default rig the plane's fringes and the shadows both tell; through the parallel rig (a plane phase
    linear across the image, the same turned or not) the shadows alone do. Mirrored along the fringes (a mirrored
    scene through the same kind of rig: the relief still above the plane) is never called flipped."""
    rig = load_rig(ASSETS / rig_file)
    height, lit = box_scene(rig, BOXES)
    assert height.max() == 35.0 and 0.03 < (~lit).mean() < 0.2  # the boxes cast shadows onto the plane
    img = rig_fringe(rig, height, lit)
    got = {how: check(turned(img, how), rig) for how in ("given", "rotated", "across", "along")}
    assert got["given"].verdict == "as given" and got["given"].shadows_agree == 1.0
    for how in ("rotated", "across"):
        assert got[how].verdict == "flipped", got[how]
        assert got[how].shadows_agree == 0.0 and got[how].shadow_runs >= 100
    assert got["along"].verdict != "flipped"
    fits = got["given"].plane_fit
    if rig_file == "parallel_rig.json":
        assert max(fits.values()) - min(fits.values()) < 0.01  # no perspective to tell by
        # the shadows alone: the warning says what else reads so
        assert all("shadows alone: dark areas that are not shadows" in got[h].evidence for h in ("rotated", "across"))
    else:
        assert fits["as given"] > 0.7 and max(fits["rotated 180 deg"], fits["mirrored across its fringes"]) < 0.5
        assert "follow the rig's plane rotated 180 deg on" in got["rotated"].evidence
        assert "shadows alone" not in got["rotated"].evidence


def test_a_plane_without_shadows_through_a_linear_rig_is_undecided_and_a_rig_without_a_plane_says_nothing():
    rig = load_rig(ASSETS / "parallel_rig.json")
    img = rig_fringe(rig, np.zeros((rig.camera.height, rig.camera.width)))
    for how in ("given", "rotated"):
        c = check(turned(img, how), rig)
        assert (c.verdict, c.shadow_runs, c.shadows_agree) == ("undecided", 0, None)
    no_plane = make_default_rig()
    no_plane.plane_in_view = False
    c = check(rig_fringe(no_plane, np.zeros((no_plane.camera.height, no_plane.camera.width))), no_plane)
    assert c.verdict == "undecided" and "no reference plane" in c.evidence


@pytest.mark.skipif(not (SHARED / "real-phase").is_dir(), reason="../shared/real-phase is absent")
def test_the_real_frames_of_the_figshare_rig_read_flipped_only_when_turned():
    """The labelled pair and FP1523/1201 through the default rig (fitted to that rig): every shadow run and the
    plane's perspective agree with the rig as given, and disagree turned (docs/USAGE.md, predict)."""
    from fppsim.dataio.readers import load_ipattern

    rig = load_rig(ASSETS / "default_rig.json")
    pair = np.rint((np.load(SHARED / "real-sample" / "fringe_pattern.npy") + 1.0) * 127.5)
    for img in (pair, load_ipattern(SHARED / "real-phase" / "FP1523" / "iPattern" / "1201.mat")):
        got = {how: check(turned(img, how), rig) for how in ("given", "rotated", "across")}
        assert got["given"].verdict == "as given" and got["given"].shadows_agree == 1.0
        assert got["given"].plane_fit["as given"] > 0.8
        for how in ("rotated", "across"):
            assert got[how].verdict == "flipped" and got[how].shadows_agree == 0.0, got[how]


def _many_boxes():
    """18 boxes 25 mm across, 10-45 mm high, in rows across the default rig's view (world mm)."""
    spots = [(-180, -90, 20), (-120, -90, 35), (-60, -90, 15), (0, -90, 45), (60, -90, 25), (120, -90, 30),
             (-180, -20, 40), (-120, -20, 10), (-60, -20, 30), (0, -20, 20), (60, -20, 35), (120, -20, 15),
             (-180, 50, 25), (-120, 50, 45), (-60, 50, 20), (0, 50, 30), (60, 50, 10), (120, 50, 40)]
    return [(x, x + 25, y, y + 25, float(h)) for x, y, h in spots]


def test_dark_areas_that_are_not_shadows_do_not_read_as_a_flipped_image():
    """Boxes through the parallel rig (its plane phase is the same turned or not: only the shadows can tell) on a
    plane that is black but for the third of the view on the projector's side: every black stretch between a box
    and that plane has its plane end on the projector's side, as a shadow of a flipped image would. They are not
    shadows (the truth: we blackened them), and the image is as given: no warning. Shadows are not read in an image
    more than MAX_DARK_SHARE of which is dark; as given, the same boxes' own shadows still tell."""
    rig = load_rig(ASSETS / "parallel_rig.json")
    height, lit = box_scene(rig, _many_boxes())
    img = rig_fringe(rig, height, lit)
    cover = (height == 0) & (np.arange(img.shape[1]) < 2 * img.shape[1] // 3)[None, :]  # the plane left of x = 2/3
    dark = np.where(cover, 0, img).astype(np.uint8)
    got = check(dark, rig)
    assert got.verdict != "flipped", got
    assert got.dark_share > 0.25 and "dark" in got.evidence
    whole = {how: check(turned(img, how), rig).verdict for how in ("given", "rotated")}
    assert whole == {"given": "as given", "rotated": "flipped"}


def test_a_rig_that_is_not_the_images_does_not_read_it_as_flipped():
    """Boxes seen through the default rig, read through rigs of the same kind (projector on the same side, yawed
    towards the scene) but of another baseline and yaw, whose plane phase curves the other way: the turned plane
    phases fit the image better than the rig's own (0.38-0.43 against 0.16-0.28 of the reliable pixels), and shadows
    read on such a plane call it flipped (0 of 107 runs away from the projector). That is the rig's error, not the
    image's: no warning where no plane phase fits PLANE_FLIP_SHARE of the image, nor shadows read on a plane found on
    less than SHADOW_PLANE_SHARE of it."""
    from fppsim.geometry.rig import Rig, projector_for

    rig = make_default_rig()
    img = rig_fringe(rig, *box_scene(rig, BOXES))
    for yaw, baseline in ((3.0, 250.0), (4.3, 150.0), (6.0, 100.0)):
        other = Rig(camera=rig.camera, projector=projector_for(rig.camera, yaw=np.radians(yaw), focal=1310.0,
                                                               baseline=baseline, roll=np.radians(-1.29)), periods=80.0)
        got = check(img, other)
        assert got.verdict != "flipped", (yaw, baseline, got)


def test_dark_stretches_beside_the_objects_are_said_to_be_read_as_shadows():
    """A dark mat 50 px wide on the projector's side of each of 18 boxes, through the parallel rig (only the shadows
    can tell): the boxes' own shadows agree with the rig (0.38 of the runs), the mats do not; the image is as given
    and is not called flipped. Under lower boxes (6 mm: their own shadows too short to count) the mats alone vote,
    and the image reads flipped: the warning then says that the shadows alone called it, and what else reads so."""
    rig = load_rig(ASSETS / "parallel_rig.json")
    for boxes, expect in ((_many_boxes(), "not flipped"), ([b[:4] + (6.0,) for b in _many_boxes()], "flipped")):
        height, lit = box_scene(rig, boxes)
        img, obj = rig_fringe(rig, height, lit), height > 0
        mat = np.zeros_like(obj)
        for s in range(1, 51):  # +x in the image: the projector's side of the parallel rig
            mat |= np.roll(obj, s, axis=1)
        got = check(np.where(mat & (height == 0), 0, img).astype(np.uint8), rig)
        if expect == "not flipped":
            assert got.verdict != "flipped" and 0.25 < got.shadows_agree <= 0.4, got
        else:
            assert got.verdict == "flipped" and "shadows alone: dark areas that are not shadows" in got.evidence, got
        assert got.dark_share <= 0.25


#: the rig fppsim fit-rig fitted to FP147/109 (640 x 480 px, horizontal fringes, projector below the camera)
FP147_RIG = {"format": "fppsim-rig/1", "units": "mm", "periods": 35.69851055292106,
             "reference_plane": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
             "camera": {"K": [[1230.0, 0.0, 319.5], [0.0, 1230.0, 239.5], [0.0, 0.0, 1.0]], "dist": [0.0] * 5,
                        "R": [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]], "t": [0.0, 0.0, 500.0],
                        "width": 640, "height": 480},
             "projector": {"K": [[1479.0462123054474, 0.0, 1385.3961939115038], [0.0, 1479.0462123054474,
                                                                                  599.5129586757944], [0.0, 0.0, 1.0]],
                           "dist": [0.0] * 5,
                           "R": [[0.006584565670783448, -0.9997322066101265, -0.022184646974296816],
                                 [-0.9998479116507321, -0.006940366687126763, 0.015999527427953273],
                                 [-0.016149212445093045, 0.022075923008908545, -0.9996258582893441]],
                           "t": [-318.8193046941933, -10.29008472072847, 507.0979837376119],
                           "width": 912, "height": 1140}}


def test_objects_on_black_are_not_read_flipped_by_their_flat_tops():
    """Three boxes on a black background (the plane out of view) through FP147's fitted rig, whose plane phase is
    nearly linear: the box tops, the only fringes, follow the rig's plane mirrored (0.86 of them) better than as
    given (0.48), by the offsets between three small patches, not by any plane's curvature. No plane in view, no
    warning: the plane's fringes do not call an image flipped that is more than PLANE_MAX_DARK dark."""
    from fppsim.geometry.rig import Rig

    rig = Rig.from_dict(FP147_RIG)
    height, lit = box_scene(rig, BOXES)
    got = check(np.where(height == 0, 0, rig_fringe(rig, height, lit)).astype(np.uint8), rig)
    assert got.verdict != "flipped", got
    assert got.dark_share > 0.7 and got.plane_fit["mirrored across its fringes"] > 1.8 * got.plane_fit["as given"]


@pytest.mark.skipif(not (SHARED / "real-phase").is_dir(), reason="../shared/real-phase is absent")
def test_a_real_frame_through_a_rig_that_is_not_its_own_is_not_read_flipped():
    """FP1523/1201 (the figshare rig: projector 330 mm to the side, yawed 4.3 deg) read through a rig with the projector
    on the same side but 250 mm away and yawed 3 deg: the rig's plane curves the other way, and its plane phase
    rotated 180 degrees fits the frame on 0.50 of the reliable pixels, as given on 0.27; shadows too few to say.
    The image is as given: no plane phase fitting less than PLANE_FLIP_SHARE calls it flipped."""
    from fppsim.dataio.readers import load_ipattern
    from fppsim.geometry.rig import Rig, projector_for

    cam = make_default_rig().camera
    other = Rig(camera=cam, projector=projector_for(cam, yaw=np.radians(3.0), focal=1310.0, baseline=250.0,
                                                    roll=np.radians(-1.29)), periods=80.0)
    got = check(load_ipattern(SHARED / "real-phase" / "FP1523" / "iPattern" / "1201.mat"), other)
    assert got.plane_fit["rotated 180 deg"] > 0.5 > 0.3 > got.plane_fit["as given"]
    assert got.verdict != "flipped", got


@pytest.mark.skipif(not (SHARED / "real-phase").is_dir(), reason="../shared/real-phase is absent")
def test_evaluate_phase_warns_of_a_real_frame_turned_against_its_rig_and_keeps_its_scores(tmp_path, capsys,
                                                                                           monkeypatch, one_thread):
    """FP1523/1201 as given and rotated 180 degrees (image, sums and orders alike) scored by `uhrnet evaluate-phase
    --refine phase --rig` through the default rig: the turned frame gets predict's sentence once (per model) and its
    check under ``flipped`` in phase_results.json; the frame as given none; the scores are those of a run whose check
    finds nothing (said, never acted on). About 10 s on one thread."""
    import json

    import scipy.io as sio

    import uhrnet.inference.prediction as prediction
    from _helpers import train_tiny, write_figshare
    from fppsim.dataio.writers import save_psp_folder_sample
    from uhrnet.cli import main
    from uhrnet.physics.orientation import OrientationCheck

    write_figshare(tmp_path / "real", n=8, h=32, w=64, seed=1)
    run = train_tiny(tmp_path / "unet", "--real", tmp_path / "real")
    src = SHARED / "real-phase" / "FP1523"
    a = [sio.loadmat(src / q / "1201.mat")[v] for q, v in (("PSin", "PSin"), ("PCos", "PCos"), ("Fringe", "Order"),
                                                            ("iPattern", "iPattern"))]
    for sid, turn in (("given", lambda x: x), ("rotated", lambda x: np.ascontiguousarray(x[::-1, ::-1]))):
        save_psp_folder_sample(tmp_path / "frames", sid, turn(a[0]), turn(a[1]), turn(a[2]).astype(np.int32), turn(a[3]))
    args = ["evaluate-phase", str(run), "--phase-root", str(tmp_path / "frames"), "--figures", "0", "--names", "tiny",
            "--device", "cpu", "--refine", "phase", "--rig", str(ASSETS / "default_rig.json")]
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "o")]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if "relief below the reference plane" in line]
    assert len(said) == 1 and said[0].startswith("rotated: warning: tiny: relief below the reference plane through ")
    assert "rotated or mirrored image, or a rig with the projector on the other side? (" in said[0]
    rec = {r["id"]: r for r in json.loads((tmp_path / "o" / "phase_results.json").read_text())["per_image"]}
    assert "flipped" not in rec["given"] and rec["rotated"]["flipped"]["tiny"]["verdict"] == "flipped"
    monkeypatch.setattr(prediction, "check_orientation", lambda *a: OrientationCheck({}, 0, None, "undecided", "-"))
    assert main([*args, "--out", str(tmp_path / "p"), "--ids", "rotated"]) == 0
    assert "relief below" not in capsys.readouterr().out
    quiet = json.loads((tmp_path / "p" / "phase_results.json").read_text())["per_image"][0]
    assert quiet["models"] == rec["rotated"]["models"] and "flipped" not in quiet


def test_plane_lean_measures_a_ramp_of_the_path_against_a_flat_estimate_and_skips_other_orders():
    from uhrnet.physics.orientation import LEAN_MIN_SHARE, plane_lean
    rig = make_default_rig()
    H, W = rig.camera.height, rig.camera.width
    cam = rig.camera
    centre = np.array([[(cam.width - 1) / 2.0, (cam.height - 1) / 2.0]])
    period = 2 * np.pi / abs(float(rig.phase_at_height(1.0, centre)[0] - rig.phase_at_height(0.0, centre)[0]))
    rows = np.arange(H)[:, None] * np.ones((1, W))
    estimate = np.zeros((H, W))
    path = 6.0 * rows / (H - 1)  # rises 6 mm from the top row to the bottom one
    moved = np.ones((H, W), bool)
    got = plane_lean(path, moved, estimate, rig)
    assert got["mm"] == pytest.approx(6.0, abs=1e-3) and got["periods"] == pytest.approx(6.0 / period, abs=1e-3)
    # a patch the path put a whole period higher (another order, not a lean) is left out of the fit
    other = path.copy()
    other[100:200, 100:300] += period
    assert plane_lean(other, moved, estimate, rig)["mm"] == pytest.approx(6.0, abs=1e-3)
    # so is one that holds two fifths of the pixels beside a plane that leans little (a plane fitted to them all
    # tilts enough to keep the step: FP1523 cropped to its bottom half read 1.3 periods so, as given)
    wide = path / 4.0
    wide[:, :2 * W // 5] += period
    assert plane_lean(wide, moved, estimate, rig)["mm"] == pytest.approx(1.5, abs=1e-3)
    # pixels the estimate does not see flat, or the path did not move, do not count
    raised = np.where(rows < H // 2, 30.0, 0.0)
    assert plane_lean(path, moved, raised, rig)["pixels"] == moved.sum() - (rows < H // 2).sum()
    few = np.zeros((H, W), bool)
    few[:int(LEAN_MIN_SHARE * H) - 1] = True
    assert plane_lean(path, few, estimate, rig)["periods"] is None


def test_lean_warning_needs_the_lean_and_a_plane_phase_that_does_not_fit():
    from uhrnet.physics.orientation import LEAN_PERIODS, LEAN_PLANE_FIT, lean_warning
    stats = {"plane_lean": {"mm": 13.7, "periods": 1.6, "pixels": 9}, "orientation": {"plane_fit": {"as given": 0.24}}}
    assert "leans 1.6 fringe periods (13.7 mm)" in lean_warning(stats, "rig.json")
    assert lean_warning({**stats, "orientation": {"plane_fit": {"as given": LEAN_PLANE_FIT}}}, "r") is None
    assert lean_warning({**stats, "plane_lean": {"mm": 1.0, "periods": LEAN_PERIODS, "pixels": 9}}, "r") is None
    assert lean_warning({**stats, "plane_lean": {"mm": None, "periods": None, "pixels": 0}}, "r") is None
    assert lean_warning({}, "r") is None and lean_warning(None, "r") is None
    # an image that reads flipped gets the flipped sentence alone (the pair mirrored across: 1.9 periods, fit 0.18)
    flipped = {"plane_fit": {"as given": 0.18}, "verdict": "flipped"}
    assert lean_warning({**stats, "orientation": flipped}, "r") is None


@pytest.mark.skipif(not (SHARED / "real-sample").is_dir(), reason="../shared/real-sample is absent")
def test_the_pair_upside_down_is_said_to_lean_and_as_given_is_not():
    # a perfect network (the label itself as the estimate) on the pair, as given and mirrored along its fringes
    from fppsim.geometry.rig import load_rig
    from uhrnet.inference.prediction import refine_with_phase
    from uhrnet.physics.orientation import lean_warning
    from uhrnet.workflows.sim2real.real_metrics import object_mask
    rig = load_rig(ASSETS / "figshare_depth_rig.json")
    fringe = np.load(SHARED / "real-sample" / "fringe_pattern.npy").astype(np.float32)
    label = np.load(SHARED / "real-sample" / "height_map.npy").astype(np.float64)
    _, plane = object_mask(label, label > -100)
    truth = np.where(label > -100, (label - plane) / 6.0, np.nan)
    said = {}
    for how in ("given", "along"):
        est = turned(truth, how)
        _, stats = refine_with_phase(est, turned(fringe, how), rig, "orders", network_mm=est)
        said[how] = lean_warning(stats, "the depth rig")
    assert said["given"] is None
    assert said["along"] is not None and "mirrored along its fringes" in said["along"]
