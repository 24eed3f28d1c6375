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
    else:
        assert fits["as given"] > 0.7 and max(fits["rotated 180 deg"], fits["mirrored across its fringes"]) < 0.5
        assert "follow the rig's plane rotated 180 deg on" in got["rotated"].evidence


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
