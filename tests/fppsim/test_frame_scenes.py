"""Scenes that follow a rig's frames (issue 50): fppsim.fitting.frame_scenes turns what fit-rig measured into
the rig file's ``scenes``, ``fppsim generate --scenes`` renders them."""

import json

import numpy as np
import pytest

from fppsim.errors import ConfigError
from fppsim.fitting.frame_scenes import FOOTPRINT_PER_EXTENT, RELIEF_PER_RELIEF, frame_scenes, relief_height
from fppsim.generation import GenerateConfig, resolve_scenes
from fppsim.geometry.rig import Rig, default_rig_path
from fppsim.rendering.scene import SceneRanges, asset_from_arrays, sample_scene


def _looking_down(distance: float, baseline: float):
    from fppsim.fitting.rig_start import start_rig

    return start_rig(640, 480, (2 * np.pi / 12.0, 0.0), 1, distance=distance, baseline=baseline, fov=30.0)


def test_frame_scenes_are_the_measures_in_mm_times_the_proportions():
    rig = _looking_down(400.0, 260.0)
    f = rig.camera.K[0, 0]
    sc = frame_scenes(250.0, 20.0, rig)
    across = 250.0 * 400.0 / f  # a camera looking straight down: px x distance / focal on the plane
    assert sc["footprint"] == pytest.approx([across * k for k in FOOTPRINT_PER_EXTENT], abs=0.05)
    # the relief in mm is the height whose phase at the image centre is 20 rad off the plane's (the rig's own
    # forward model, each height cut on the camera ray)
    h = sc["max_relief"][1] / RELIEF_PER_RELIEF[1]
    c = np.array([[320.0, 240.0]])
    assert abs(rig.phase_at_height(h, c)[0] - rig.phase_at_height(0.0, c)[0]) == pytest.approx(20.0, abs=0.05)
    assert relief_height(rig, 20.0) == pytest.approx(h, abs=0.1)
    # more than a constant rate from the plane says: the shift per mm grows towards the camera
    assert h < 20.0 / abs(rig.sensitivity(0.0, 1.0))
    # pedestals scale with the relief cap (the default 10-35 mm under a 55 mm cap)
    scale = sc["max_relief"][1] / 55.0
    assert sc["pedestal_height"] == pytest.approx([10 * scale, 35 * scale], abs=0.1)
    assert f"{across:.0f} mm at 400 mm" in sc["measured"] and "20.0 rad" in sc["measured"]
    # the same frames from twice as far (twice the baseline: the same angle): twice the size in mm
    far = frame_scenes(250.0, 20.0, _looking_down(800.0, 520.0))
    assert far["footprint"] == pytest.approx([2 * v for v in sc["footprint"]], abs=0.2)  # each rounded to 0.1 mm
    assert far["max_relief"][1] == pytest.approx(2 * sc["max_relief"][1], rel=0.03)


def test_the_default_ranges_are_the_scene_samplers():
    """frame_scenes keeps its own copy of the defaults (the scene module brings trimesh into fit-rig's start):
    they must be SceneRanges' own."""
    from fppsim.fitting.frame_scenes import DEFAULT_FOOTPRINT, DEFAULT_MAX_RELIEF, DEFAULT_PEDESTAL, scenes_line

    d = SceneRanges()
    assert (DEFAULT_FOOTPRINT, DEFAULT_MAX_RELIEF, DEFAULT_PEDESTAL) == (d.footprint, d.max_relief, d.pedestal_height)
    assert "70-140 mm across, relief capped at 35-55 mm" in scenes_line(None)


def test_frame_scenes_without_relief_or_object():
    rig = _looking_down(400.0, 260.0)
    # no relief (plain fringe images): the default scenes' relief / footprint proportion
    sc = frame_scenes(250.0, 0.0, rig)
    assert sc["max_relief"][1] / sc["footprint"][1] == pytest.approx(55.0 / 140.0, rel=0.01)
    assert "relief not measured" in sc["measured"]
    assert frame_scenes(0.0, 10.0, rig) is None
    assert "at least" in frame_scenes(640.0, 10.0, rig, at_border=True)["measured"]


def _rig_with_scenes(tmp_path, scenes) -> str:
    doc = json.loads(default_rig_path().read_text())
    doc["scenes"] = scenes
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))
    return str(path)


def test_generate_takes_the_rig_files_scenes(tmp_path):
    rig = _rig_with_scenes(tmp_path, {"footprint": [150, 300], "max_relief": [60, 90], "pedestal_height": [5, 20],
                                      "measured": "words"})
    cfg = GenerateConfig(meshes=["procedural"], out=tmp_path / "out", count=1, rig=rig)
    scene = cfg.synth_config().scene
    assert (scene.footprint, scene.max_relief, scene.pedestal_height) == ((150, 300), (60, 90), (5, 20))
    assert "the rig file's scenes" in cfg.scene_fields()[1]
    # --scenes default, or a rig without scenes: the default ranges
    d = SceneRanges()
    for c in (GenerateConfig(meshes=["procedural"], out=tmp_path / "o", count=1, rig=rig, scenes="default"),
              GenerateConfig(meshes=["procedural"], out=tmp_path / "o", count=1, rig=None)):
        sc = c.synth_config().scene
        assert (sc.footprint, sc.max_relief, sc.pedestal_height) == (d.footprint, d.max_relief, d.pedestal_height)
    # a file holding the mapping alone
    f = tmp_path / "scenes.yaml"
    f.write_text("footprint: [20, 30]\nmax_relief: [5, 8]\n")
    assert resolve_scenes(str(f))[0] == {"footprint": (20.0, 30.0), "max_relief": (5.0, 8.0)}


@pytest.mark.parametrize("scenes,words", [({"footprint": [0, 10]}, "footprint must satisfy"),
                                          ({"max_relief": [50, 40]}, "max_relief must satisfy"),
                                          ({"footprint": "big"}, "footprint must be [lo, hi]"),
                                          ({"tilt": 3}, "no scene ranges")])
def test_bad_scenes_are_named(tmp_path, scenes, words):
    rig = _rig_with_scenes(tmp_path, scenes)
    with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace("]", r"\]")):
        GenerateConfig(meshes=["procedural"], out=tmp_path / "out", count=1, rig=rig)
    with pytest.raises(ConfigError, match="file not found"):
        resolve_scenes(str(tmp_path / "missing.json"))


def test_sampled_objects_have_the_scenes_sizes():
    """Every object is scaled to a footprint draw across or cut to a relief-cap draw, whichever binds: never
    beyond either range, and at one of them (the scenes a face filling the view needs: 170-340 mm, 50-80 mm)."""
    rig = Rig.default()
    flat = asset_from_arrays(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.05], [0.5, 0.5, 0.05]], float),
                             np.array([[0, 1, 3], [0, 3, 2], [0, 1, 4], [1, 3, 4], [3, 2, 4], [2, 0, 4]]), "flat")
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 0.8)], float)  # a box
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    tall = asset_from_arrays(corners, faces, "box")
    ranges = SceneRanges(objects=(1, 1), footprint=(170.0, 340.0), max_relief=(50.0, 80.0), tilt=0.0,
                         pedestal_probability=0.0)
    bound = set()
    for seed in range(8):
        for asset in (flat, tall):
            obj = sample_scene([asset], rig, np.random.default_rng(seed), ranges).objects[0]
            v = asset.hull @ obj.transform[:3, :3].T
            across, high = max(np.ptp(v[:, 0]), np.ptp(v[:, 1])), np.ptp(v[:, 2])
            assert across <= 340.0 + 1e-6 and high <= 80.0 + 1e-6
            at_footprint, at_relief = across >= 170.0 - 1e-6, high >= 50.0 - 1e-6
            assert at_footprint or at_relief
            bound.add("footprint" if at_footprint else "relief")
    assert bound == {"footprint", "relief"}
