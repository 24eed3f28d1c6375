"""uhrnet.inference.prediction.read_inputs on phase-shifting and figshare folders, `uhrnet predict --refine phase`, and
uhrnet.physics.refine.refine_relief on an analytic pedestal scene (fppsim's own forward model as the truth)."""

import json

import numpy as np
import pytest
import torch

from fppsim.fitting.height_sensitivity import surface_phase
from fppsim.geometry.rig import make_default_rig
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.cli import main
from uhrnet.inference.prediction import PATH_MARGIN_PX, fringe_mirror_axis, path_estimate, predict_labels, read_inputs
from uhrnet.physics.refine import refine_relief
from uhrnet.physics.rig_layer import RigLayer

from _helpers import box_scene, rig_fringe, tiny_rig, train_tiny, wrap_phase, write_figshare

pytestmark = pytest.mark.usefixtures("one_thread")


def _bump(rig, peak, cx, cy=15.0, sigma=7.0):
    yy, xx = np.mgrid[0:rig.camera.height, 0:rig.camera.width].astype(float)
    return peak * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))


def test_read_inputs_of_phase_shifting_and_figshare_folders(tmp_path):
    rig = tiny_rig()
    psp = tmp_path / "scan"
    images = {}
    for sid, peak in (("12", 5.0), ("3", 8.0)):
        h = _bump(rig, peak, 30.0)
        images[sid] = rig_fringe(rig, h)
        save_psp_folder_sample(psp, sid, *sums_from_phase(surface_phase(rig, h)), images[sid])
    fr, _ = write_figshare(tmp_path / "fig", n=2, h=32, w=64, seed=4)
    write_figshare(tmp_path / "one", n=1, h=32, w=64, seed=5, fringe_name="fringe_pattern.npy",
                   label_name="height_map.npy")
    got = read_inputs([psp, tmp_path / "fig", tmp_path / "one"], with_paths=True)
    names = [g[0] for g in got]
    assert sorted(names[:2]) == ["scan_12", "scan_3"] and names[2:] == ["fig_0000", "fig_0001", "one"]
    for name, fringe, path in got[:2]:
        sid = name.split("_")[1]
        np.testing.assert_allclose(fringe, images[sid].astype(np.float32) / 127.5 - 1, atol=1e-6)
        assert path == psp / "iPattern" / f"{sid}.mat"
    np.testing.assert_array_equal(got[3][1], fr[1, ..., 0])
    assert all(g[1].dtype == np.float32 and g[1].shape == (32, 64) for g in got)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("refine_predict")
    torch.set_num_threads(1)
    write_figshare(tmp / "syn", n=6, h=32, w=64, seed=1)
    return train_tiny(tmp / "run", "--synthetic", tmp / "syn", "--synthetic-split", "train", extra=["--no-augment"])


@pytest.mark.parametrize("method", ["relief", "orders"])
def test_predict_refine_phase_writes_refine_json_and_the_network_height(run, tmp_path, method, capsys):
    rig = tiny_rig()
    rig.save(tmp_path / "rig.json")
    real = tmp_path / "real"
    real.mkdir()
    fr = np.stack([rig_fringe(rig, _bump(rig, 5.0, 30.0)), rig_fringe(rig, _bump(rig, 3.0, 40.0))])
    np.save(real / "f1_80.npy", (fr.astype(np.float32) / 127.5 - 1)[..., None])
    out = tmp_path / "out"
    assert main(["predict", str(run), str(real), "--out", str(out), "--refine", "phase", "--refine-method", method,
                 "--rig", str(tmp_path / "rig.json"), "--no-progress", "--no-ply"]) == 0
    doc = json.loads((out / "refine.json").read_text())
    assert sorted(doc) == ["real_0000", "real_0001"]
    model, transform = model_from_checkpoint(load_checkpoint(run), "cpu")
    for name, stats in doc.items():
        assert 0.0 <= stats["moved_fraction"] <= 1.0 and stats["method"] == method
        net = np.load(out / f"{name}_height_network.npy")
        refined = np.load(out / f"{name}_height.npy")
        assert net.shape == refined.shape == (32, 64)
        np.testing.assert_array_equal(np.isnan(net), np.isnan(refined))  # invalid stays invalid
        # the path starts from the mean of the network's passes on the image and on it mirrored along the fringes
        k = int(name.split("_")[1])
        x = torch.from_numpy(fr[k].astype(np.float32) / 127.5 - 1)
        axis = fringe_mirror_axis(rig)
        flip = lambda a: torch.flip(a, [axis])  # noqa: E731
        margin = (PATH_MARGIN_PX, 0) if axis == -2 else (0, PATH_MARGIN_PX)  # mirrored past the borders it cuts
        labels = 0.5 * (predict_labels(model, x[None, None], margin=margin)
                        + flip(predict_labels(model, flip(x)[None, None], margin=margin)))
        estimate = np.where(np.isfinite(net), transform.height_mm(labels[0, 0].numpy().astype(np.float64)), np.nan)
        changed = np.isfinite(net) & ~np.isclose(estimate, refined, atol=1e-4)  # (a moved pixel may land where it was)
        # orders also carries the moved pixels' level correction to the pixels left out beside them
        # and splits the rims between raised regions and the plane
        touched = stats["moved_fraction"] + stats.get("carried_fraction", 0.0) + stats.get("rim_fraction", 0.0)
        assert changed.sum() <= touched * np.isfinite(net).sum() + 0.5
        if method == "orders":
            assert len(stats["per_region"]) == stats["regions"]
            assert all({"order", "confidence", "decided"} <= set(r) for r in stats["per_region"])
    # with --rig the default (--refine auto) is the same path
    assert main(["predict", str(run), str(real), "--out", str(tmp_path / "auto"), "--rig", str(tmp_path / "rig.json"),
                 "--no-progress", "--no-ply"] + (["--refine-method", method] if method != "orders" else [])) == 0
    for name in doc:
        np.testing.assert_array_equal(np.load(tmp_path / "auto" / f"{name}_height.npy"), np.load(out / f"{name}_height.npy"))
    # without --refine and --rig: no refine.json, no network copy; the copy is this single pass of the network
    assert main(["predict", str(run), str(real), "--out", str(tmp_path / "plain"), "--no-progress", "--no-ply"]) == 0
    assert not (tmp_path / "plain" / "refine.json").exists()
    assert not list((tmp_path / "plain").glob("*_height_network.npy"))
    for name in doc:
        np.testing.assert_array_equal(np.load(out / f"{name}_height_network.npy"),
                                      np.load(tmp_path / "plain" / f"{name}_height.npy"))
    # a rig that does not see the image's size is refused in one line
    capsys.readouterr()
    assert main(["predict", str(run), str(real), "--out", str(tmp_path / "x"), "--refine", "phase", "--no-progress",
                 "--no-ply"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sees 640x352" in err[0]


@pytest.fixture(scope="module")
def pedestal():
    """The default rig; a disc standing 30 mm on the plane (near-vertical walls) with 4 mm of relief on top;
    the projector shadow left of it (its phase NaN: fppsim.phase.unwrap once hung in skimage's unwrapper on masked
    NaN, and its quality filter spread NaN along whole rows); the measured phase counted from another origin
    (+72 rad, DESIGN.md section 9)."""
    rig = make_default_rig()
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    disc = (xx - 360) ** 2 + (yy - 176) ** 2 < 70 ** 2
    relief = 4.0 * np.exp(-((xx - 380) ** 2 + (yy - 160) ** 2) / (2 * 30.0 ** 2))
    h = np.where(disc, 30.0 + relief, 0.0)
    shadow = ~disc & (np.abs(yy - 176) < 70) & (xx > 270) & (xx < 300)
    wrapped = wrap_phase(surface_phase(rig, h) + 72.0)
    rel = np.where(shadow, 0.0, 1.0)
    wrapped[shadow] = np.nan
    return rig, RigLayer(rig), h, disc, shadow, wrapped, rel, (xx, yy)


def test_refine_relief_takes_the_relief_from_the_phase_and_the_level_from_the_estimate(pedestal):
    rig, layer, h, disc, shadow, wrapped, rel, (xx, yy) = pedestal
    level_error = 2.0  # the network puts the object 2 mm too high ...
    relief_error = 1.2 * np.sin(xx / 17.0) * np.cos(yy / 23.0)  # ... and gets its relief wrong by up to 1.2 mm
    estimate = h + np.where(disc, level_error + relief_error, 0.3 * np.cos(xx / 40.0))
    refined, moved, stats = refine_relief(estimate, wrapped, rel, layer, valid=~shadow)
    inner = np.hypot(xx - 360, yy - 176) < 60  # away from the wall (the step check cuts near it)
    assert moved[inner].mean() > 0.99 and stats["regions"] >= 2 and stats["method"] == "relief"
    rel_true = h[inner] - np.median(h[inner])
    rel_new = refined[inner] - np.median(refined[inner])
    assert np.abs(rel_new - rel_true).max() < 0.05  # the relief: exact (the phase's)
    assert np.median(refined[inner] - h[inner]) == pytest.approx(level_error, abs=0.2)  # the level: the estimate's
    assert np.median(refined[inner] - estimate[inner]) == pytest.approx(0.0, abs=0.05)
    assert np.array_equal(refined[shadow], estimate[shadow])  # no phase: untouched
    plane = ~disc & ~shadow & (np.hypot(xx - 360, yy - 176) > 80)
    assert moved[plane].mean() > 0.99  # (a few pixels beside the shadow's edge keep the estimate)
    plane &= moved
    assert np.abs((refined - h)[plane] - np.median((refined - h)[plane])).max() < 0.05


def test_a_region_merged_with_the_plane_is_rejected_by_the_margin():
    """A plateau 30 mm up behind a 6 px ramp whose fringes alias (4.9 rad per pixel, which the wrapped phase shows
    as a smooth -1.4): without the step check (max_step huge) plane and plateau are one region, unwrapped six
    periods too low across the ramp; the plateau's pixels would move by six fringe periods of height, beyond the
    margin (2 periods), so they keep the estimate while the plane is refined. With the step check (the estimate
    steps by several radians there) the plateau is its own region and is refined."""
    rig = make_default_rig()
    cam = rig.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    h = 30.0 * np.clip((xx - 400.0) / 6.0, 0.0, 1.0)
    wrapped = wrap_phase(surface_phase(rig, h) + 72.0)
    estimate = h + 0.3 * np.cos(xx / 40.0) * np.cos(yy / 30.0)
    layer = RigLayer(rig)
    merged, moved, stats = refine_relief(estimate, wrapped, None, layer, max_step=1e9)
    plateau, plane = xx > 415, xx < 390
    assert stats["regions"] == 1
    assert not moved[plateau].any() and np.array_equal(merged[plateau], estimate[plateau])
    assert stats["beyond_margin_fraction"] >= plateau.mean()
    assert moved[plane].mean() > 0.99
    assert np.abs((merged - h)[plane] - np.median((merged - h)[plane])).max() < 0.05
    refined, moved, stats = refine_relief(estimate, wrapped, None, layer)
    assert stats["regions"] >= 2 and moved[plateau].mean() > 0.99
    assert np.abs((refined - h)[plateau] - np.median((refined - h)[plateau])).max() < 0.05


def test_the_default_path_keeps_the_network_heights_of_an_image_without_fringes(run, tmp_path, capsys):
    """--rig alone refines (--refine auto); an image whose fringe phase cannot be read keeps the network's heights
    with a one-line warning, while an explicit --refine phase refuses it in one line."""
    rig = tiny_rig()
    rig.save(tmp_path / "rig.json")
    np.save(tmp_path / "flat.npy", np.zeros((32, 64), np.float32))
    capsys.readouterr()
    assert main(["predict", str(run), str(tmp_path / "flat.npy"), "--out", str(tmp_path / "o"), "--rig",
                 str(tmp_path / "rig.json"), "--no-progress", "--no-ply"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no fringe phase" in err[0] and "flat" in err[0]
    np.testing.assert_array_equal(np.load(tmp_path / "o" / "flat_height.npy"),
                                  np.load(tmp_path / "o" / "flat_height_network.npy"))
    assert json.loads((tmp_path / "o" / "refine.json").read_text())["flat"]["method"] == "none"
    assert main(["predict", str(run), str(tmp_path / "flat.npy"), "--out", str(tmp_path / "p"), "--rig",
                 str(tmp_path / "rig.json"), "--refine", "phase", "--no-progress", "--no-ply"]) == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_predict_warns_of_an_image_turned_against_its_rig_and_keeps_its_heights(run, tmp_path, capsys, monkeypatch):
    """Boxes on the plane through the default rig: the image rotated 180 degrees or mirrored across its fringes
    reads with its relief below the plane (the truth: we turned it); predict says so in one line naming the image,
    records the check in refine.json, and writes the same heights as without the check."""
    import cv2

    import uhrnet.inference.prediction as prediction
    from uhrnet.physics.orientation import OrientationCheck

    rig = make_default_rig()
    rig.save(tmp_path / "rig.json")
    img = rig_fringe(rig, *box_scene(rig))
    for name, im in (("given", img), ("rotated", img[::-1, ::-1]), ("mirrored", img[:, ::-1])):
        cv2.imwrite(str(tmp_path / f"{name}.png"), np.ascontiguousarray(im))
    args = [str(tmp_path / f"{n}.png") for n in ("given", "rotated", "mirrored")]
    capsys.readouterr()
    assert main(["predict", str(run), *args, "--out", str(tmp_path / "o"), "--rig", str(tmp_path / "rig.json"),
                 "--no-progress", "--no-ply"]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "relief below the reference plane" in line]
    assert len(warned) == 2 and all(f"{n}.png ({n}): relief" in w for n, w in zip(("rotated", "mirrored"), warned))
    assert all("rotated or mirrored image, or a rig with the projector on the other side?" in w for w in warned)
    doc = json.loads((tmp_path / "o" / "refine.json").read_text())
    assert {n: doc[n]["orientation"]["verdict"] for n in doc} == {"given": "as given", "rotated": "flipped",
                                                                   "mirrored": "flipped"}
    # only said: the heights are those of a run whose check finds nothing
    monkeypatch.setattr(prediction, "check_orientation",
                        lambda *a: OrientationCheck({}, 0, None, "undecided", "not checked"))
    assert main(["predict", str(run), *args, "--out", str(tmp_path / "p"), "--rig", str(tmp_path / "rig.json"),
                 "--no-progress", "--no-ply"]) == 0
    assert "relief below" not in capsys.readouterr().err
    for n in ("given", "rotated", "mirrored"):
        np.testing.assert_array_equal(np.load(tmp_path / "o" / f"{n}_height.npy"),
                                      np.load(tmp_path / "p" / f"{n}_height.npy"))


def _conv_model():
    """A fixed, direction-sensitive 3x3 convolution: its answer on a mirrored image is not the mirror of its answer."""
    m = torch.nn.Conv2d(1, 1, 3, padding=1, bias=False)
    with torch.no_grad():
        m.weight.copy_(torch.arange(9, dtype=torch.float32).reshape(1, 1, 3, 3) / 10.0 - 0.3)
    return m


@pytest.mark.parametrize("axis", ["vertical", "horizontal"])
def test_path_estimate_mirrors_along_the_fringes_of_either_direction(axis):
    from fppsim.fitting import rig_start as rs

    g = (0.0, -2 * np.pi / 12.0) if axis == "horizontal" else (2 * np.pi / 12.0, 0.0)
    rig = rs.start_rig(150, 110, g, 1, distance=420.0, baseline=260.0, fov=34.0)
    dim = 2 if axis == "vertical" else 3  # vertical fringes run down the rows: mirror the rows
    x = torch.from_numpy(np.random.default_rng(3).uniform(-1, 1, (1, 1, 32, 48)).astype(np.float32))
    m = _conv_model()
    w = m.weight.detach()
    # each pass sees the image mirrored PATH_MARGIN_PX past the two borders its fringes run into
    pad = (0, 0, PATH_MARGIN_PX, PATH_MARGIN_PX) if dim == 2 else (PATH_MARGIN_PX, PATH_MARGIN_PX, 0, 0)
    crop = (slice(None), slice(None), slice(pad[2], 32 + pad[2]), slice(pad[0], 48 + pad[0]))

    def conv(a):
        return torch.nn.functional.conv2d(torch.nn.functional.pad(a, pad, mode="reflect"), w, padding=1)[crop]

    plain = conv(x)
    mirrored = torch.flip(conv(torch.flip(x, [dim])), [dim])
    unpadded = torch.nn.functional.conv2d(x, w, padding=1)

    class Transform:  # heights = labels
        @staticmethod
        def height_mm(label):
            return label

    got = path_estimate(m, Transform, x[0, 0].numpy(), None, rig, unpadded[0, 0].numpy())
    np.testing.assert_allclose(got, (0.5 * (plain + mirrored))[0, 0].numpy(), atol=1e-6)
    assert not np.allclose(got, plain[0, 0].numpy(), atol=1e-3)  # the mirror does change the answer
    # the margin changes the borders the fringes run into, and nothing else
    edge = np.zeros((32, 48), bool)
    if dim == 2:
        edge[[0, -1], :] = True
    else:
        edge[:, [0, -1]] = True
    plain_unpadded = 0.5 * (unpadded + torch.flip(torch.nn.functional.conv2d(torch.flip(x, [dim]), w, padding=1), [dim]))
    differs = ~np.isclose(got, plain_unpadded[0, 0].numpy(), atol=1e-6)
    assert differs[edge].mean() > 0.5 and not differs[~edge].any()


@pytest.mark.parametrize("axis,side", [("vertical", 1), ("vertical", -1), ("horizontal", 1), ("horizontal", -1)])
def test_fringe_mirror_axis_runs_along_the_fringes(axis, side):
    from fppsim.fitting import rig_start as rs

    g = (0.0, -2 * np.pi / 12.0) if axis == "horizontal" else (2 * np.pi / 12.0, 0.0)
    rig = rs.start_rig(150, 110, g, side, distance=420.0, baseline=260.0, fov=34.0)
    phase = rig.phase_at_height(np.zeros((110, 150)))
    # the truth from the plane's phase itself: the image axis along which it hardly changes
    along = -2 if np.nanmean(np.abs(np.diff(phase, axis=0))) < np.nanmean(np.abs(np.diff(phase, axis=1))) else -1
    assert fringe_mirror_axis(rig) == along == (-2 if axis == "vertical" else -1)
    assert fringe_mirror_axis(rig.to_dict()) == along


def test_path_estimate_is_the_mean_of_both_passes_masked_like_the_network():
    rig = tiny_rig()
    x = np.random.default_rng(5).uniform(-1, 1, (32, 64)).astype(np.float32)

    class Transform:  # heights = 2 x labels + 1
        @staticmethod
        def height_mm(label):
            return 2.0 * label + 1.0

    m = _conv_model()
    margin = (PATH_MARGIN_PX, 0) if fringe_mirror_axis(rig) == -2 else (0, PATH_MARGIN_PX)
    one = lambda a: predict_labels(m, torch.from_numpy(np.ascontiguousarray(a))[None, None], margin=margin)[0, 0].numpy()  # noqa: E731
    flip = (lambda a: a[::-1]) if fringe_mirror_axis(rig) == -2 else (lambda a: a[:, ::-1])  # noqa: E731
    network = 2.0 * one(x) + 1.0
    network[:3] = np.nan
    got = path_estimate(m, Transform, x, None, rig, network)
    want = 2.0 * 0.5 * (one(x) + flip(one(flip(x)))) + 1.0
    np.testing.assert_array_equal(np.isnan(got), np.isnan(network))
    np.testing.assert_allclose(got[3:], want[3:], atol=1e-5)


def test_fringes_that_are_not_the_rigs_keep_the_network_heights_and_what_was_done_is_described(run, tmp_path, capsys):
    """An image whose fringes run across the rig's, or at twice its period: the default path keeps the network's
    heights with a warning naming it (they once gave heights thousands of mm off, silently); --refine phase refuses
    it naming the file, after the image before it was written whole and described in refine.json, which a later call
    into the same folder extends."""
    from uhrnet.errors import DataError
    from uhrnet.inference.prediction import fringe_phase

    rig = tiny_rig(width=256, height=192)  # the check needs 16 periods both ways: a smaller spectrum is too coarse
    rig.save(tmp_path / "rig.json")
    yy, xx = np.mgrid[0:192, 0:256].astype(float)
    good = (rig_fringe(rig, _bump(rig, 5.0, 100.0, 90.0, 20.0)).astype(np.float32) / 127.5 - 1)
    across = (0.6 * np.cos(2 * np.pi * yy / 11.6)).astype(np.float32)
    wide = (0.6 * np.cos(2 * np.pi * xx / 23.2)).astype(np.float32)
    fringe_phase(good, rig)  # the rig's own image passes
    fringe_phase(wide[:32, :64], tiny_rig())  # too small to tell
    from fppsim.geometry.rig import Rig

    # objects on black (a rig without a plane in view) or an image mostly black: the spectrum's peak may be the
    # objects' envelope, so the direction alone is checked, from the wrapped phase's own steps (both once passed
    # unchecked: an image with fringes across a rig fitted on busts on black gave heights of -207 to 156 mm)
    on_black = Rig.from_dict({**rig.to_dict(), "plane_in_view": False})
    half_black = lambda a: np.where(xx < 100, a, -1.0).astype(np.float32)  # noqa: E731
    for img, r in ((good, on_black), (half_black(good), rig), (wide, on_black), (half_black(wide), rig)):
        fringe_phase(img, r)  # the period is not checked there (the demodulation's own)
    for img, r in ((across, rig), (wide, rig), (across, on_black), (half_black(across), rig)):
        with pytest.raises(DataError, match="not an image of this rig"):
            fringe_phase(img, r, "x")
    for name, img in (("a_good", good), ("b_across", across), ("c_wide", wide), ("d_good", good)):
        np.save(tmp_path / f"{name}.npy", img)
    rig_args = ["--rig", str(tmp_path / "rig.json"), "--no-progress", "--no-ply"]
    capsys.readouterr()
    assert main(["predict", str(run), str(tmp_path / "b_across.npy"), str(tmp_path / "c_wide.npy"), "--out",
                 str(tmp_path / "auto")] + rig_args) == 0
    err = [e for e in capsys.readouterr().err.strip().splitlines() if "shaped" not in e and "aspect" not in e]
    assert len(err) == 2 and all("not an image of this rig" in e for e in err), err
    for name in ("b_across", "c_wide"):
        np.testing.assert_array_equal(np.load(tmp_path / "auto" / f"{name}_height.npy"),
                                      np.load(tmp_path / "auto" / f"{name}_height_network.npy"))
    out = tmp_path / "strict"
    assert main(["predict", str(run), str(tmp_path / "a_good.npy"), str(tmp_path / "b_across.npy"), "--out", str(out),
                 "--refine", "phase"] + rig_args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "b_across.npy" in err[0] and "not an image of this rig" in err[0]
    assert sorted(p.name for p in out.glob("*.npy")) == ["a_good_height.npy", "a_good_height_network.npy"]
    assert sorted(json.loads((out / "refine.json").read_text())) == ["a_good"]
    assert main(["predict", str(run), str(tmp_path / "d_good.npy"), "--out", str(out), "--refine", "phase"]
                + rig_args) == 0
    assert sorted(json.loads((out / "refine.json").read_text())) == ["a_good", "d_good"]


def test_an_image_predicted_again_without_refinement_loses_its_refine_entry_and_network_copy(run, tmp_path):
    """After --refine phase and then --refine none into the same --out, a_height.npy was the network's map while
    refine.json still described a's refinement and the old a_height_network.npy stayed; now both go (the copy only
    because predict's record says predict wrote it), and a user's files of those names are never touched."""
    from fppsim.owned import owners

    rig = tiny_rig()
    rig.save(tmp_path / "rig.json")
    for name, peak in (("a", 5.0), ("b", 3.0)):
        np.save(tmp_path / f"{name}.npy", rig_fringe(rig, _bump(rig, peak, 30.0)).astype(np.float32) / 127.5 - 1)
    out = tmp_path / "out"
    common = ["--out", str(out), "--no-progress", "--no-ply"]
    assert main(["predict", str(run), str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), *common, "--rig",
                 str(tmp_path / "rig.json")]) == 0
    assert sorted(json.loads((out / "refine.json").read_text())) == ["a", "b"]
    network = np.load(out / "a_height_network.npy")
    assert main(["predict", str(run), str(tmp_path / "a.npy"), *common, "--refine", "none"]) == 0
    np.testing.assert_array_equal(np.load(out / "a_height.npy"), network)
    assert sorted(json.loads((out / "refine.json").read_text())) == ["b"]
    assert not (out / "a_height_network.npy").exists() and (out / "b_height_network.npy").exists()
    assert "a_height_network.npy" not in owners(out)
    assert main(["predict", str(run), str(tmp_path / "b.npy"), *common, "--refine", "none"]) == 0
    assert not (out / "refine.json").exists() and not list(out.glob("*_height_network.npy"))  # as a plain folder
    assert "refine.json" not in owners(out)

    mine = tmp_path / "mine"  # files of those names predict did not write
    mine.mkdir()
    (mine / "refine.json").write_text('{"a": "mine"}')
    (mine / "a_height_network.npy").write_text("mine")
    assert main(["predict", str(run), str(tmp_path / "a.npy"), "--out", str(mine), "--no-progress", "--no-ply"]) == 0
    assert (mine / "refine.json").read_text() == '{"a": "mine"}' and (mine / "a_height_network.npy").read_text() == "mine"

    # review: a network copy predict wrote and the user then replaced is the user's: never deleted
    again = tmp_path / "again"
    assert main(["predict", str(run), str(tmp_path / "a.npy"), "--out", str(again), "--no-progress", "--no-ply",
                 "--rig", str(tmp_path / "rig.json")]) == 0
    np.save(again / "a_height_network.npy", np.zeros((3, 3)))
    assert main(["predict", str(run), str(tmp_path / "a.npy"), "--out", str(again), "--no-progress", "--no-ply",
                 "--refine", "none"]) == 0
    np.testing.assert_array_equal(np.load(again / "a_height_network.npy"), np.zeros((3, 3)))


def test_a_foreign_images_fringes_are_described_in_the_images_own_terms():
    """QA: through a rig with horizontal fringes an image of vertical fringes was said to show fringes "at -90 deg"
    (the angle of the transposed image the phase was read on), beside "the rig's ... horizontal (90 deg apart)";
    the lines' angle is now from the image's vertical whatever the rig's direction, as through a vertical rig."""
    import re

    from fppsim.fitting import rig_start as rs
    from uhrnet.errors import DataError
    from uhrnet.inference.prediction import fringe_phase

    yy, xx = np.mgrid[0:224, 0:256].astype(float)  # 16 periods both ways: the check needs them
    upright = (0.6 * np.cos(2 * np.pi * xx / 12.0)).astype(np.float32)  # vertical lines
    lying = (0.6 * np.cos(2 * np.pi * yy / 12.0)).astype(np.float32)  # horizontal lines
    for g, img, said in (((0.0, -2 * np.pi / 12.0), upright, r"at [+-]0 deg, the rig's every 12\.0 px horizontal"),
                         ((2 * np.pi / 12.0, 0.0), lying, r"at [+-]90 deg, the rig's every 12\.0 px vertical")):
        rig = rs.start_rig(256, 224, g, 1, distance=420.0, baseline=260.0, fov=34.0)
        with pytest.raises(DataError, match="not an image of this rig") as err:
            fringe_phase(img, rig, "x")
        assert re.search(said, str(err.value)) and "(90 deg apart)" in str(err.value), str(err.value)


def test_predicts_refine_line_counts_each_kind_of_link_taken():
    from uhrnet.cli import refine_line
    st = {"method": "orders", "moved_fraction": 0.5, "mean_abs_move_mm": 1.0, "offset_rad": 0.1, "regions": 9,
          "components": 3, "undecided_regions": 0, "refused_links": 2, "rig": "rig.json",
          "links": {"bridge": 1, "seam": 4, "wall": 2}}
    line = refine_line("a", st)
    assert "links taken: 1 shadow bridge, 4 seams, 2 wall links" in line and "2 links refused" in line
    assert "links taken" not in refine_line("a", {**st, "links": {"bridge": 0, "seam": 0, "wall": 0}})
    assert "links taken: 1 wall link)" in refine_line("a", {**st, "links": {"bridge": 0, "seam": 0, "wall": 1}})
    assert "phase regions" not in refine_line("a", {**st, "method": "relief"})
