"""fit-rig on the inputs users bring (horizontal fringes with --base, blank images, objects on black as plain images): one line each, nothing written, the culprit named."""

from __future__ import annotations

import json
import math
import re

import cv2
import numpy as np
import pytest

from _helpers import SHARED, figurine_on_black
from fppsim.cli import main
from fppsim.fitting import rig_start as rs


def _horizontal_rig(W: int = 120, H: int = 90):
    """A rig built as fit-rig builds one from images with horizontal fringes (projector below the camera)."""
    return rs.start_rig(W, H, (0.0, -2 * math.pi / 12.0), -1, distance=420.0, baseline=260.0, fov=34.0)


def test_fit_rig_base_with_horizontal_fringes_is_refused_in_one_line(tmp_path, capsys):
    """``fit-rig --base RIG`` fits band periods across vertical fringes; a base rig with horizontal fringes (e.g. the
    rig fit-rig itself wrote for FP147) used to end in 'projector looks away from the reference plane' or 'lights
    only 94 % of the view': now one line saying to leave --base out, nothing written."""
    rig = _horizontal_rig()
    rig.save(tmp_path / "base.json")
    phase = rig.phase_at_height(0.0)
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.clip(110 + 90 * np.cos(phase), 0, 255).astype(np.uint8))
    out = tmp_path / "fit.json"
    assert main(["fit-rig", str(tmp_path / "imgs"), "--base", str(tmp_path / "base.json"), "--out", str(out),
                 "--sensitivity", "off"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fits vertical fringes only" in err[0] and "leave --base out" in err[0]
    assert not out.exists()


def test_fit_rig_names_the_image_without_fringes(tmp_path, capsys):
    """A black (or uniform) image among plain fringe images: the error used to be 'no fringes found (no spectral
    peak ...)' with neither the image nor the folder named."""
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "blank.png"), np.zeros((90, 120), np.uint8))
    assert main(["fit-rig", str(tmp_path / "imgs"), "--out", str(tmp_path / "rig.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{tmp_path / 'imgs'}: blank: no fringes found" in err[0]
    assert not (tmp_path / "rig.json").exists()



def test_fit_rig_names_the_scan_whose_image_is_black(tmp_path, capsys):
    """A scan whose iPattern image is all black (pixels count where it is not) among scans with a phase: the error was
    'too few pixels with a phase to measure the fringe direction', neither the folder nor the frame named."""
    from fppsim.dataio.writers import save_psp_folder_sample

    rig = _horizontal_rig()
    phase = rig.phase_at_height(0.0)
    image = (127 + 100 * np.cos(phase)).astype(np.uint8)
    for sid, img in (("1", image), ("2", np.zeros_like(image))):
        save_psp_folder_sample(tmp_path / "scans", sid, -np.sin(phase), -np.cos(phase),
                               np.floor(phase / (2 * np.pi)), img)
    assert main(["fit-rig", str(tmp_path / "scans"), "--out", str(tmp_path / "rig.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{tmp_path / 'scans'}: 2: too few pixels with a phase" in err[0], err
    assert "its image is not black" in err[0] and not (tmp_path / "rig.json").exists()

def test_plain_images_take_the_fringe_direction_from_their_spectrum():
    """Plain fringe images of objects on black: their phase, unwrapped piece by piece, can give a plane gradient
    across the fringes' true direction (FP672/541 with its plane blacked out, as a PNG: 'the fringes are horizontal',
    then '--projector-side right' refused). The direction is the spectrum's, the gradient the local one along it."""
    from fppsim.dataio.readers import FringeImage

    xx = np.arange(120)[None, :] * np.ones((90, 1))
    gray = np.clip(110 + 90 * np.cos(2 * np.pi * xx / 12.0), 0, 255)
    im = FringeImage(gray=gray, valid=np.ones(gray.shape, bool), name="a")
    gradient, axis = rs.plain_image_gradient([im], (0.01, 0.4))  # a misleading plane gradient: down the rows
    assert axis == "vertical"
    assert abs(gradient[0]) == pytest.approx(2 * np.pi / 12.0, rel=0.02) and abs(gradient[1]) < 0.01
    assert rs.plain_image_gradient([im], (0.5, 0.02)) == ((0.5, 0.02), "vertical")  # agreeing: kept as it is


def test_a_figurine_on_black_takes_the_planes_period_and_a_wrong_one_is_refused(tmp_path, capsys):
    """A figurine on black (FP672/541 without its plane, as fit-rig saw it): the period was measured at the plain
    spectrum's peak, the outline's (75 px as a PNG, 16 px from the scans' phase, the plane's 10.5 px), so the
    plane's own --fringe-period was refused on the PNG and 4 x the plane's passed on the scans. Now the fringes'
    own (the lit side's 9.4 px): the plane's period is taken, 4 x it refused in one line, on both. At 480 x 336 px
    (10 s on 2 cores; 640 x 448, FP672's size, took 22-28 s, over the 20 s of a test not marked slow)."""
    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
    from fppsim.geometry.rig import Rig
    from fppsim.phase.fringe_axis import rig_phase_gradient

    img, phase, body, lit_period = figurine_on_black(10.5, noise=2.0, H=336, W=480)
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), img)
    save_psp_folder_sample(tmp_path / "scans", "a", *sums_from_phase(phase, body, 60.0), np.where(body, img, 0))
    pose = ["--distance", "500", "--baseline", "330", "--projector-side", "right"]
    out = tmp_path / "rig.json"
    assert main(["fit-rig", str(tmp_path / "imgs"), "--out", str(out), "--fringe-period", "10.5"] + pose) == 0
    assert 2 * np.pi / np.hypot(*rig_phase_gradient(Rig.load(out))) == pytest.approx(10.5, rel=1e-3)
    capsys.readouterr()
    for folder in ("imgs", "scans"):
        assert main(["fit-rig", str(tmp_path / folder), "--out", str(tmp_path / "wrong.json"),
                     "--fringe-period", "42"] + pose) == 1
        err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
        assert len(err) == 1 and "x the period the frames show" in err[0], err
        measured = float(re.search(r"show \(([\d.]+) px\)", err[0]).group(1))
        assert measured == pytest.approx(lit_period, rel=0.05), err  # before: 75 px (PNG), 15.9 px (scans)
        assert not (tmp_path / "wrong.json").exists()


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "real-phase" / "FP672").is_dir(), reason="../shared/real-phase not present")
def test_fp672_on_black_as_a_plain_image_reads_vertical_fringes(tmp_path, capsys):
    """FP672/541 with its plane blacked out, as a PNG and as scans: vertical fringes; the plane's own period (10.54 px,
    fit-rig on the frame with its plane) is taken from the PNG, where the figurine's measured 56 px refused it, and 4 x
    it is refused on the scans, where their phase's 18.4 px let it pass. Measured now: 8.9 px on both."""
    import scipy.io as sio

    from fppsim.dataio.writers import save_psp_folder_sample
    from fppsim.phase.plane import phase_plane_masks

    root = SHARED / "real-phase" / "FP672"
    get = lambda folder, key: sio.loadmat(str(root / folder / "541.mat"))[key]  # noqa: E731
    psin, pcos, image = get("PSin", "PSin"), get("PCos", "PCos"), get("iPattern", "iPattern")
    phase = np.arctan2(-psin, -pcos) + np.pi + 2 * np.pi * get("Fringe", "Order")
    valid = (psin != 0) | (pcos != 0)
    _, objects = phase_plane_masks(phase, valid)
    keep = objects & valid
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "541.png"), np.where(keep, image, 0).astype(np.uint8))
    save_psp_folder_sample(tmp_path / "scans", "541", np.where(keep, psin, 0), np.where(keep, pcos, 0),
                           np.where(keep, get("Fringe", "Order"), 0), np.where(keep, image, 0).astype(np.uint8))
    pose = ["--distance", "500", "--baseline", "330", "--projector-side", "right"]
    rc = main(["fit-rig", str(tmp_path / "imgs"), "--out", str(tmp_path / "rig.json"), "--fringe-period", "10.54"]
              + pose)
    text = capsys.readouterr()
    assert rc == 0, text.err
    assert "fringes    vertical: 10.54 px" in text.out
    for folder in ("imgs", "scans"):
        assert main(["fit-rig", str(tmp_path / folder), "--out", str(tmp_path / "wrong.json"),
                     "--fringe-period", "42.16"] + pose) == 1
        err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
        assert len(err) == 1 and "x the period the frames show" in err[0], err
        assert 0.75 * 10.54 <= float(re.search(r"show \(([\d.]+) px\)", err[0]).group(1)) <= 1.25 * 10.54, err


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "real-phase" / "FP672").is_dir(), reason="../shared/real-phase not present")
def test_fp672_as_a_plain_image_measures_its_figurine_whole(tmp_path, capsys):
    """FP672/541's fringe image as a PNG (its plane in view): the figurine is as large as its scans say (262 px),
    not the largest piece with a reliable single-shot phase (61 px before stop 68: scenes of 16-32 mm objects)."""
    import scipy.io as sio

    image = sio.loadmat(str(SHARED / "real-phase" / "FP672" / "iPattern" / "541.mat"))["iPattern"]
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "541.png"), image.astype(np.uint8))
    assert main(["fit-rig", str(tmp_path / "imgs"), "--out", str(tmp_path / "rig.json")]) == 0, capsys.readouterr().err
    measured = json.loads((tmp_path / "rig.json").read_text())["scenes"]["measured"]
    extent = float(re.search(r"largest object (\d+) px across", measured).group(1))
    assert 0.9 * 262 <= extent <= 1.1 * 262, measured  # 333 px with the shadow's phase-less rim (review 68b)


def test_the_largest_object_of_a_plain_image_is_all_of_its_lit_pixels(tmp_path):
    """An object on a plane whose middle carries steep, wobbling fringes (lit, no reliable phase): its extent is
    the lit region's (221 px), not that of a reliable piece of it (63 px before stop 68)."""
    from fppsim.fitting.rig_start import rig_from_images

    r, c = np.mgrid[0:240, 0:320]
    dome = 1 - ((c - 160) / 110.0) ** 2 - ((r - 120) / 50.0) ** 2
    body = dome >= 0
    phase = 2 * np.pi * c / 9.0 + 25.0 * np.sqrt(np.clip(dome, 0, 1))
    phase = np.where(body & (np.abs(c - 160) < 10), 2 * np.pi * c / 4.0 + 2.0 * np.sin(r / 1.7), phase)
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), (120 + 90 * np.cos(phase)).astype(np.uint8))
    res = rig_from_images(tmp_path / "imgs", projector_side="right")
    assert not res.no_plane
    cols = np.nonzero(body.any(0))[0]
    assert abs(res.extent_px - (cols.max() - cols.min() + 1)) <= 0.05 * 221, res.extent_px


def test_an_over_exposed_image_is_named_when_no_plane_is_found():
    from fppsim.fitting.start_result import saturation_words

    class Image:
        def __init__(self, gray, name):
            self.gray, self.name = gray, name

    rng = np.random.default_rng(0)
    fine = rng.integers(0, 240, (60, 80)).astype(np.uint8)
    burnt = np.where(np.arange(80) < 40, 255, fine).astype(np.uint8)  # half the view at 255
    assert saturation_words([Image(fine, "a")]) == ""
    assert saturation_words([Image(np.zeros((60, 80), np.uint8), "black")]) == ""  # dark, not burnt
    words = saturation_words([Image(fine, "a"), Image(burnt, "b")])
    assert words.startswith("; b has 50% of its pixels saturated") and "lower the exposure" in words


@pytest.mark.skipif(not (SHARED / "real-phase" / "FP1523").is_dir(), reason="../shared absent")
def test_fit_rig_says_an_image_is_saturated_when_it_finds_no_plane(tmp_path, capsys):
    """QA: FP1523/1201's image 8 x brighter (57 % of its pixels at 255) was refused as 'no reference plane in view'
    without a word about the exposure."""
    import scipy.io

    gray = scipy.io.loadmat(SHARED / "real-phase" / "FP1523" / "iPattern" / "1201.mat")["iPattern"].astype(float)
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "bright.png"), np.clip(8.0 * gray, 0, 255).astype(np.uint8))
    assert main(["fit-rig", str(tmp_path / "imgs"), "--out", str(tmp_path / "rig.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no reference plane in view" in err[0], err
    assert "bright has 57% of its pixels saturated" in err[0] and not (tmp_path / "rig.json").exists()
