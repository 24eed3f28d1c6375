"""uhrnet predict: images/.npy/folders -> height .npy/.tif (mm), colour PNG, PLY (pixel grid or rig rays)."""

import numpy as np
import pytest
import torch

from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.cli import main
from uhrnet.inference.prediction import predict_labels

from _helpers import scene, train_tiny, write_figshare


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pred")
    write_figshare(tmp / "real", n=8, h=32, w=64)
    return train_tiny(tmp / "run", "--real", tmp / "real", model="uhrnet", epochs=3,
                      extra=("--lr", "3e-3", "--batch-size", "2")) / "best.pt"


def read_ply(path):
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    n = int([l for l in head.decode().splitlines() if l.startswith("element vertex")][0].split()[-1])
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    assert len(rec) == n
    return rec


def test_predict_png_npy_and_folder(ckpt, tmp_path, capsys):
    import cv2
    from PIL import Image

    rng = np.random.default_rng(0)
    f8, _, valid = scene(rng, 40, 72)  # not a multiple of 16: padded and cropped back
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "a.png"), f8)
    cv2.imwrite(str(tmp_path / "in" / "b.tif"), f8)
    stack = np.stack([f8, f8]).astype(np.float32)[..., None] / 127.5 - 1
    np.save(tmp_path / "stack.npy", stack)
    (tmp_path / "x").mkdir()
    cv2.imwrite(str(tmp_path / "x" / "a.png"), f8)  # same stem as in/a.png
    out = tmp_path / "out"
    rc = main(["predict", str(ckpt), str(tmp_path / "in"), str(tmp_path / "stack.npy"), str(tmp_path / "x" / "a.png"),
               "--out", str(out), "--no-progress"])
    assert rc == 0
    printed = capsys.readouterr()
    assert "5 height map(s) from 4 input file(s)" in printed.out
    # the second a.png was written under another name: the user is told which input that is
    assert f"{tmp_path / 'x' / 'a.png'}: written as x_a_* (another input is also named a)" in printed.err
    for name in ("a", "b", "stack_0000", "stack_0001", "x_a"):
        for suffix in ("_height.npy", "_height.tif", "_height.png", ".ply"):
            assert (out / f"{name}{suffix}").exists(), name + suffix
    h = np.load(out / "a_height.npy")
    assert h.shape == (40, 72) and h.dtype == np.float32
    np.testing.assert_array_equal(np.array(Image.open(out / "a_height.tif")), h)
    np.testing.assert_array_equal(np.load(out / "stack_0001_height.npy"), h)
    assert np.isnan(h[~valid]).all()  # black (shadow) input pixels are invalid
    assert np.isfinite(h).mean() > 0.5
    # Height = (label - plane_offset) / 6 of the model's prediction.
    c = load_checkpoint(ckpt)
    model, t = model_from_checkpoint(c)
    label = predict_labels(model, torch.from_numpy(f8.astype(np.float32) / 127.5 - 1)[None, None])[0, 0].numpy()
    ok = np.isfinite(h)
    np.testing.assert_allclose(h[ok], ((label + 97) / 6)[ok], rtol=1e-5, atol=1e-4)
    ply = read_ply(out / "a.ply")
    assert len(ply) == ok.sum()
    np.testing.assert_allclose(np.sort(ply["z"]), np.sort(h[ok]), rtol=1e-6)
    assert ply["x"].max() == 71 and ply["y"].max() <= 39


def test_predict_with_rig_back_projection(ckpt, tmp_path):
    rig_mod = pytest.importorskip("fppsim.geometry.rig")
    try:
        rig = rig_mod.Rig.default()
    except Exception as exc:  # the default rig asset not there yet
        pytest.skip(f"no default rig: {exc}")
    import cv2

    cam = rig.camera
    f8, _, _ = scene(np.random.default_rng(1), cam.height, cam.width)
    cv2.imwrite(str(tmp_path / "img.png"), f8)
    rig_path = tmp_path / "rig.json"
    rig.save(rig_path)
    out = tmp_path / "out"
    assert main(["predict", str(ckpt), str(tmp_path / "img.png"), "--out", str(out), "--rig", str(rig_path),
                 "--no-progress"]) == 0
    h = np.load(out / "img_height.npy")
    ply = read_ply(out / "img.ply")
    pts = np.stack([ply["x"], ply["y"], ply["z"]], axis=-1).astype(np.float64)
    np.testing.assert_allclose(np.sort(pts[:, 2]), np.sort(h[np.isfinite(h)]), atol=1e-3)
    uv, _ = cam.project(pts)  # every point lies on its own pixel's ray
    rows, cols = np.nonzero(np.isfinite(h))
    np.testing.assert_allclose(uv[:, 0], cols, atol=2e-2)
    np.testing.assert_allclose(uv[:, 1], rows, atol=2e-2)


def test_predict_errors(ckpt, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["predict", str(ckpt), str(tmp_path / "missing.png"), "--out", out]) == 1
    assert "missing.png: input not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["predict", str(ckpt), str(tmp_path / "empty"), "--out", out]) == 1
    assert "no images" in capsys.readouterr().err
    (tmp_path / "pub" / "iPattern").mkdir(parents=True)  # the public layout's image folder, not its root
    (tmp_path / "pub" / "iPattern" / "1.mat").write_bytes(b"x")
    assert main(["predict", str(ckpt), str(tmp_path / "pub" / "iPattern"), "--out", out]) == 1
    err = capsys.readouterr().err
    assert "no images" in err and f"the folder holding iPattern/ ({tmp_path / 'pub'})" in err
    (tmp_path / "mats").mkdir()  # .mat files of another kind: their parent is no phase-shifting root to name
    (tmp_path / "mats" / "1.mat").write_bytes(b"x")
    assert main(["predict", str(ckpt), str(tmp_path / "mats"), "--out", out]) == 1
    err = capsys.readouterr().err
    assert "no images" in err and "iPattern" not in err
    np.save(tmp_path / "raw.npy", np.full((32, 32), 200.0, np.float32))
    assert main(["predict", str(ckpt), str(tmp_path / "raw.npy"), "--out", out]) == 1
    assert "raw.npy: values span" in capsys.readouterr().err
    # a fringe scaled to [0, 1] (the common float image) is read as the encoding (heights about 21 mm off) and said
    # so, frame by frame (an encoded frame may be that bright too: not refused)
    yy, xx = np.mgrid[0:32, 0:64]
    unit = (0.5 + 0.45 * np.cos(2 * np.pi * xx / 8.0)).astype(np.float32)
    np.save(tmp_path / "unit.npy", np.stack([2 * unit - 1, unit]))
    assert main(["predict", str(ckpt), str(tmp_path / "unit.npy"), "--out", out, "--no-progress", "--no-ply"]) == 0
    err = [e for e in capsys.readouterr().err.strip().splitlines() if "values span" in e]
    assert len(err) == 1 and "unit.npy (unit_0001): values span [0.05, 0.95], none below 0" in err[0]
    np.save(tmp_path / "black.npy", np.full((32, 64), -1.0, np.float32))  # --keep-all keeps heights nothing informs
    assert main(["predict", str(ckpt), str(tmp_path / "black.npy"), "--out", out, "--keep-all", "--no-progress",
                 "--no-ply"]) == 0
    assert "black.npy (black): the input is black everywhere; --keep-all kept" in capsys.readouterr().err
    np.save(tmp_path / "bright.npy", (192 + 60 * np.cos(2 * np.pi * xx / 8.0)).astype(np.uint8))  # uint8: unambiguous
    assert main(["predict", str(ckpt), str(tmp_path / "bright.npy"), "--out", out, "--no-progress", "--no-ply"]) == 0
    assert "values span" not in capsys.readouterr().err
    (tmp_path / "bad.png").write_bytes(b"not a png")
    assert main(["predict", str(ckpt), str(tmp_path / "bad.png"), "--out", out]) == 1
    assert "bad.png: cannot read as an image" in capsys.readouterr().err
    np.save(tmp_path / "ok.npy", np.zeros((32, 64), np.float32))
    assert main(["predict", str(ckpt), str(tmp_path / "ok.npy"), "--out", out, "--rig", str(tmp_path / "no.json")]) == 1
    assert "no.json" in capsys.readouterr().err
    # an empty array (once a traceback, or "0 height maps" from one file) and a colour one (once "H images of W x 3")
    for name, arr, words in (("e2", np.zeros((0, 64), np.float32), "e2.npy: empty array"),
                             ("e3", np.zeros((0, 32, 64), np.float32), "e3.npy: empty array"),
                             ("rgb", np.zeros((32, 64, 3), np.float32), "rgb.npy: shape (32, 64, 3) looks like a colour")):
        np.save(tmp_path / f"{name}.npy", arr)
        assert main(["predict", str(ckpt), str(tmp_path / f"{name}.npy"), "--out", out]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0]


def test_predict_user_errors_are_one_line(ckpt, tmp_path, capfd):
    import cv2

    out = tmp_path / "out"
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nxxxx")  # PNG signature, broken header
    assert main(["predict", str(ckpt), str(tmp_path / "corrupt.png"), "--out", str(out)]) == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "corrupt.png: cannot read as an image" in err[0]  # no OpenCV log line
    f8, _, _ = scene(np.random.default_rng(2), 32, 48)
    cv2.imwrite(str(tmp_path / "img.png"), f8)
    for bad in (["--range", "5", "1"], ["--range", "nan", "1"], ["--colormap", "nope"]):  # usage errors: exit 2
        assert main(["predict", str(ckpt), str(tmp_path / "img.png"), "--out", str(out), *bad]) == 2
        assert bad[0] in capfd.readouterr().err
    rig_mod = pytest.importorskip("fppsim.geometry.rig")
    try:
        rig = rig_mod.Rig.default()
    except Exception as exc:
        pytest.skip(f"no default rig: {exc}")
    rig.save(tmp_path / "rig.json")
    assert main(["predict", str(ckpt), str(tmp_path / "img.png"), "--out", str(out), "--rig",
                 str(tmp_path / "rig.json"), "--no-progress"]) == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "img.png: image is 48x32 but the rig camera" in err[0]
    assert not (out / "img_height.npy").exists()  # refused before writing anything for it


def test_an_image_not_shaped_like_the_training_images_is_said():
    """A network trained on 320 x 240 px images (after --resize) reads a 640 x 480 frame as its own, and warns of a
    portrait or a 640 x 352 one: it would read them squashed (another rig's, a rotated or a cropped image)."""
    from uhrnet.inference.prediction import shape_note

    ck = {"image_shape": [240, 320], "args": {"resize": "240x320"}}
    assert shape_note(ck, (480, 640)) is None and shape_note(ck, (250, 320)) is None
    assert "trained on 320x240 px images (after its --resize)" in shape_note(ck, (640, 480))
    assert "aspect 1.82" in shape_note(ck, (352, 640))
    assert shape_note({}, (352, 640)) is None  # an old checkpoint without the record: nothing to say


def test_an_image_of_another_size_through_a_network_without_resize_is_said():
    """Without --resize a network reads every image at its own size: a 320 x 240 frame through one trained on
    640 x 480 px shows it fringes half as far apart as it learned them (evaluate-phase scored such frames without a
    word); within 15 % of the size, or through a network with --resize, nothing is said."""
    from uhrnet.inference.prediction import shape_note

    ck = {"image_shape": [480, 640], "args": {"resize": None}}
    note = shape_note(ck, (240, 320))
    assert "320x240 px but the network was trained on 640x480 px images at their own size" in note
    assert "0.50 x as far apart" in note
    # review: a crop of the same view keeps its fringes' period: the spacing is said of the same view only
    assert "own size: if it shows the view they did, it sees the fringes 0.50 x as far apart" in note
    assert "2.00 x as far apart" in shape_note(ck, (960, 1280))
    assert shape_note(ck, (480, 640)) is None and shape_note(ck, (500, 660)) is None
    assert shape_note({"image_shape": [480, 640], "args": {"resize": "240x320"}}, (240, 320)) is None


def test_predict_refuses_the_checkpoints_run_folder_as_out(ckpt, tmp_path, capsys):
    """predict once wrote its maps into the training run it read (and into the run's ownership record) when --out
    named that folder; it is refused as adapt refuses it: one line, exit 1, nothing written."""
    import cv2

    from _helpers import one_line

    run = ckpt.parent
    f8, _, _ = scene(np.random.default_rng(3), 32, 64)
    cv2.imwrite(str(tmp_path / "img.png"), f8)
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    for given, out in ((run, run), (ckpt, run / "." / ".." / run.name)):  # the folder however it is spelled
        assert main(["predict", str(given), str(tmp_path / "img.png"), "--out", str(out), "--no-progress"]) == 1
        one_line(capsys, f"--out {out} is the folder of CKPT {given}", "choose another --out")
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == before
    # review: a loose checkpoint file in a folder of the user's is no run folder: --out there is fine
    import shutil

    loose = tmp_path / "mine"
    loose.mkdir()
    shutil.copy(ckpt, loose / "model.pt")
    assert main(["predict", str(loose / "model.pt"), str(tmp_path / "img.png"), "--out", str(loose), "--no-progress",
                 "--no-ply"]) == 0
    assert (loose / "img_height.npy").is_file()


@pytest.mark.parametrize("layout", ["file", "figshare", "pair"])
@pytest.mark.parametrize("what", ["npz", "empty", "garbage", "pickle"])
def test_an_npy_that_is_not_one_array_is_one_line(tmp_path, capsys, layout, what):
    """QA: an .npz archive saved under a .npy name (np.savez to an open file), an empty or damaged file and a pickled
    array once ended predict in a traceback (AttributeError: 'NpzFile' object has no attribute 'size', EOFError,
    ValueError), as a file and in a figshare or real-sample folder; now one line naming the file, exit 1, nothing
    written (the inputs are read before the checkpoint)."""
    name = {"file": "x.npy", "figshare": "f1_80.npy", "pair": "fringe_pattern.npy"}[layout]
    folder = tmp_path / "in"
    folder.mkdir()
    bad = folder / name
    fringe = np.zeros((1, 32, 64, 1), np.float32)
    if what == "npz":
        with open(bad, "wb") as fh:
            np.savez(fh, a=fringe)
    elif what == "pickle":
        np.save(bad, np.array([fringe, None], dtype=object), allow_pickle=True)
    else:
        bad.write_bytes(b"" if what == "empty" else b"\x93NUMPY garbage")
    if layout != "file":
        np.save(folder / ("Z.npy" if layout == "figshare" else "height_map.npy"), fringe)
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path / "none.pt"), str(bad if layout == "file" else folder), "--out",
                 str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{name}: " in err[0] and "Traceback" not in err[0], err
    assert not out.exists()


def test_the_help_says_predicts_heights_are_millimetres(capsys):
    """QA: ``uhrnet --help`` said heights are "in label units on disk" and ``predict --help`` named no unit for the
    maps it writes (they are mm above the reference plane); both now say so."""
    with pytest.raises(SystemExit):
        main(["predict", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--out DIR output folder: per image NAME_height.npy/.tif (float32 height above the reference plane in mm" \
        in text
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "label units on disk" not in text and "millimetres in reports and predict's maps" in text
