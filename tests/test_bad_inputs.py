"""Issue 9: every wrong input gets one line naming the culprit and a non-zero exit (2 for usage errors).

One test per item of the issue that is about input validation (items 2, 3, 5-8, 10-12); the faults
(data loss, disk full, kill -9, concurrency, signals: items 1, 4, 9) live in test_faults.py.
"""

import json
import os
import subprocess
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from fppsim.cli import main as fppsim_main
from fppsim.geometry.rig import Rig
from uhrnet.cli import main as uhrnet_main

from _helpers import train_tiny, write_figshare, write_native

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def mesh(tmp_path_factory):
    d = tmp_path_factory.mktemp("mesh")
    trimesh.creation.capsule(height=60.0, radius=18.0, count=[16, 16]).export(d / "capsule.ply")
    return d / "capsule.ply"


def _one_error_line(capsys, *needles):
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]


def _gen(mesh, out, *extra):
    return fppsim_main(["generate", "-q", "--no-preview", "--meshes", str(mesh), "--out", str(out), "--count", "1",
                        "--no-psp", *map(str, extra)])


# ------------------------------------------------------------------------------------------- item 5
@pytest.mark.parametrize("opt, culprit", [
    ("shot_noise=-1", "shot_noise"), ("gain=0", "gain"), ("gain=inf", "gain"), ("gain=nan", "gain"),
    ("ambient=-0.5", "ambient"), ("camera_blur=-2", "camera_blur"), ("albedo_plane=1.5", "albedo_plane"),
    ("noise_sigma=2,1", "noise_sigma"),
])
def test_invalid_optics_is_a_usage_error(tmp_path, mesh, capsys, opt, culprit):
    out = tmp_path / "o"
    assert _gen(mesh, out, "--optics", opt) == 2
    _one_error_line(capsys, "--optics", culprit)
    assert not out.exists()  # refused before anything is written


def test_optics_file_with_null_and_label_offset_inf(tmp_path, mesh, capsys):
    f = tmp_path / "optics.json"
    f.write_text('{"gain": null}')
    assert _gen(mesh, tmp_path / "o", "--optics-file", f) == 1
    _one_error_line(capsys, "optics.json", "gain")
    assert _gen(mesh, tmp_path / "o", "--label-offset", "inf") == 2
    _one_error_line(capsys, "offset", "finite")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, culprit", [('{"footprint": [5, 1]}', "footprint"), ('{"max_relief": [1, NaN]}', "max_relief"),
                                           ('{"footprint": "big"}', "footprint"), ('[1, 2]', "mapping"),
                                           ('{"tilt": 1}', "no scene ranges")])
def test_bad_scenes_file_names_it(tmp_path, mesh, capsys, text, culprit):
    f = tmp_path / "scenes.json"
    f.write_text(text)
    assert _gen(mesh, tmp_path / "o", "--scenes", f) == 1
    _one_error_line(capsys, "scenes.json", culprit)
    assert _gen(mesh, tmp_path / "o", "--scenes", tmp_path / "missing.json") == 1
    _one_error_line(capsys, "--scenes", "missing.json")
    assert not (tmp_path / "o").exists()


def test_optics_dataclasses_validate():
    from fppsim.rendering.optics import Optics, OpticsRanges

    with pytest.raises(ValueError, match="gain"):
        Optics(gain=float("nan"))
    with pytest.raises(ValueError, match="shot_noise"):
        OpticsRanges(shot_noise=(-1.0, 0.1))
    with pytest.raises(ValueError, match="pattern_bits"):
        OpticsRanges.from_dict({"pattern_bits": 99})
    assert OpticsRanges.from_dict({"gain": 150}).gain == (150.0, 150.0)


# ------------------------------------------------------------------------------------------- item 7
def _rig_file(tmp_path, name, edit):
    d = Rig.default().to_dict()
    edit(d)
    p = tmp_path / name
    p.write_text(json.dumps(d))
    return p


def test_unusable_rigs_are_refused_before_any_sample(tmp_path, mesh, capsys):
    far = _rig_file(tmp_path, "far.json", lambda d: d["projector"].__setitem__("t", [-5000.0, 0.0, 500.0]))
    assert _gen(mesh, tmp_path / "o1", "--rig", far) == 1
    _one_error_line(capsys, "projector lights 0.0%")

    def zero_baseline(d):
        d["projector"]["t"], d["projector"]["K"] = d["camera"]["t"], d["camera"]["K"]
        d["projector"]["R"] = d["camera"]["R"]  # the default projector is turned a little
    zero = _rig_file(tmp_path, "zero.json", zero_baseline)
    assert _gen(mesh, tmp_path / "o2", "--rig", zero) == 1
    _one_error_line(capsys, "fringes do not move with height", "baseline 0.0 mm")
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()
    Rig.default().check_usable()  # the default rig passes


OPENCV = """%YAML:1.0
M1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [1230, 0, 319.5, 0, 1230, 175.5, 0, 0, 1]
M2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [1208.8, 0, 890.2, 0, 1208.8, 569.5, 0, 0, 1]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [-180, 0, 0]
plane_distance: 500
"""


def test_opencv_rig_fields(tmp_path, mesh, capsys):
    ok = tmp_path / "ok.yaml"
    ok.write_text(OPENCV)
    assert Rig.load(ok).camera.width == 640
    wide = tmp_path / "wide.yaml"
    wide.write_text(OPENCV + "camera_width: wide\n")
    assert _gen(mesh, tmp_path / "o", "--rig", wide) == 1
    _one_error_line(capsys, "wide.yaml", "camera_width", "'wide'")
    count = tmp_path / "count.yaml"
    count.write_text(OPENCV.replace("data: [-180, 0, 0]", "data: [-180, 0, 0, 5]"))
    assert _gen(mesh, tmp_path / "o", "--rig", count) == 1
    _one_error_line(capsys, "count.yaml", "rows x cols")
    huge = tmp_path / "huge.yaml"
    huge.write_text(OPENCV + "camera_width: 1.0e+300\n")
    assert _gen(mesh, tmp_path / "o", "--rig", huge) == 1
    _one_error_line(capsys, "width must be a whole number")


# ------------------------------------------------------------------------------------------- item 8
@pytest.mark.parametrize("field, value, culprit", [
    ("reference_plane", [0, 0, 0], "reference_plane"),
    ("camera.K", {"fx": 1}, "camera: K"),
    ("camera.width", None, "camera: width"),
    ("projector.dist", "none", "projector: dist"),
    ("periods", "eighty", "periods"),
])
def test_rig_fields_of_the_wrong_type(tmp_path, mesh, capsys, field, value, culprit):
    def edit(d):
        *path, key = field.split(".")
        (d[path[0]] if path else d)[key] = value
    p = _rig_file(tmp_path, "rig.json", edit)
    assert _gen(mesh, tmp_path / "o", "--rig", p) == 1
    _one_error_line(capsys, "rig.json", culprit)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bad_inputs_run")
    write_figshare(tmp / "real", n=8, h=32, w=64)
    run = train_tiny(tmp / "run", "--real", tmp / "real", model="unet", epochs=1)
    return tmp / "real", run


def test_uhrnet_bad_files_and_folders(tmp_path, tiny_run, capsys):
    real, run = tiny_run
    base = ["train", "--real", str(real), "--model", "unet", "--base-channels", "4", "--epochs", "1", "--no-progress"]
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "last.pt").write_bytes(b"")
    assert uhrnet_main(base + ["--out", str(empty), "--resume"]) == 1
    _one_error_line(capsys, "last.pt", "not written by uhrnet train")  # nobody says it is a run of ours
    (empty / ".fppsim-owned.json").write_text('{"files": {"last.pt": "uhrnet train"}}')  # ours, and broken
    assert uhrnet_main(base + ["--out", str(empty), "--resume"]) == 1
    _one_error_line(capsys, "last.pt", "empty file")
    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.full((32, 64), 100, np.uint8))
    assert uhrnet_main(["predict", str(empty / "last.pt"), str(img), "--out", str(tmp_path / "p")]) == 1
    _one_error_line(capsys, "last.pt", "empty file")
    assert uhrnet_main(base + ["--label-transform", "units_per_mm=0", "--out", str(tmp_path / "u")]) == 2
    _one_error_line(capsys, "units_per_mm must be > 0")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert uhrnet_main(base + ["--out", str(a_file)]) == 1
    _one_error_line(capsys, "a_file is a file")
    assert a_file.read_text() == "x"
    # predict --rig with a rig field of the wrong type
    bad_rig = _rig_file(tmp_path, "rig.json", lambda d: d["camera"].__setitem__("K", {"fx": 1}))
    assert uhrnet_main(["predict", str(run), str(img), "--out", str(tmp_path / "p"), "--rig", str(bad_rig)]) == 1
    _one_error_line(capsys, "rig.json", "K")


def test_uhrnet_out_on_a_read_only_filesystem(tmp_path, tiny_run, capsys):
    real, _ = tiny_run
    ro = tmp_path / "ro"
    ro.mkdir()
    mounted = False
    if os.geteuid() == 0:  # root ignores permission bits: a read-only mount is the real thing
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                                 capture_output=True).returncode == 0
        if not mounted:
            pytest.skip("running as root without permission to mount a read-only tmpfs")
    else:
        ro.chmod(0o500)
    try:
        rc = uhrnet_main(["train", "--real", str(real), "--model", "unet", "--base-channels", "4", "--epochs", "1",
                          "--no-progress", "--out", str(ro / "run")])
        assert rc == 1
        _one_error_line(capsys, "cannot")
    finally:
        if mounted:
            subprocess.run(["umount", str(ro)], check=False)
        else:
            ro.chmod(0o700)


# ------------------------------------------------------------------------------------------- item 2
@pytest.mark.parametrize("flag, value", [("--grad-clip", "-1"), ("--grad-clip", "0"), ("--grad-clip", "nan"),
                                         ("--weight-decay", "-1")])
def test_training_options_must_make_sense(tmp_path, capsys, flag, value):
    write_figshare(tmp_path / "real", n=8, h=32, w=64)
    out = tmp_path / "run"
    rc = uhrnet_main(["train", "--real", str(tmp_path / "real"), "--model", "unet", "--base-channels", "4",
                      "--epochs", "1", "--no-progress", "--out", str(out), flag, value])
    assert rc == 2
    _one_error_line(capsys, flag)
    assert not out.exists()


# ------------------------------------------------------------------------------------------- item 3
def test_a_run_folder_is_never_replaced_without_overwrite(tmp_path, capsys):
    write_figshare(tmp_path / "real", n=8, h=32, w=64)
    run = tmp_path / "run"
    run.mkdir()
    for name in ("best.pt", "history.csv", "config.json"):  # last.pt gone: still a run
        (run / name).write_text(f"precious {name}")
    base = ["train", "--real", str(tmp_path / "real"), "--model", "unet", "--base-channels", "4", "--epochs", "1",
            "--loss", "l2", "--no-progress", "--out", str(run)]
    for keep in ("best.pt", "history.csv", "config.json"):  # files it did not write: never, --overwrite or not
        for extra in ([], ["--overwrite"]):
            assert uhrnet_main(base + extra) == 1
            _one_error_line(capsys, str(run / keep), "not written by uhrnet train")
        assert all((run / n).read_text() == f"precious {n}" for n in ("best.pt", "history.csv", "config.json")
                   if (run / n).exists())
        (run / keep).unlink()
    assert uhrnet_main(base) == 0  # an empty folder is fine
    assert uhrnet_main(base) == 1  # now it holds a run
    _one_error_line(capsys, "already holds a run", "--overwrite")
    assert uhrnet_main(base + ["--overwrite"]) == 0


# ------------------------------------------------------------------------------------------- item 6
def test_psp_label_needs_psp_data(tmp_path, capsys):
    write_figshare(tmp_path / "export", n=8, h=32, w=64)
    write_native(tmp_path / "nopsp", n=8, h=32, w=64, psp=False)
    for folder in ("export", "nopsp"):
        rc = uhrnet_main(["train", "--synthetic", str(tmp_path / folder), "--synthetic-label", "psp", "--model",
                          "unet", "--base-channels", "4", "--epochs", "1", "--no-progress",
                          "--out", str(tmp_path / f"run_{folder}")])
        assert rc == 1
        _one_error_line(capsys, folder, "psp")


# ------------------------------------------------------------------------------------------- item 10
def test_npz_is_byte_reproducible(tmp_path, monkeypatch):
    from fppsim.dataio.encoding import save_npz

    arrays = {"height": np.arange(12, dtype=np.float32).reshape(3, 4), "mask": np.ones((3, 4), np.float32)}
    save_npz(tmp_path / "a.npz", arrays)
    later = time.time() + 3 * 86400  # another day: zip timestamps would differ
    monkeypatch.setattr(time, "time", lambda: later)
    save_npz(tmp_path / "b.npz", arrays)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.npz") as z:
        assert {i.date_time for i in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    with np.load(tmp_path / "a.npz") as z:
        np.testing.assert_array_equal(z["height"], arrays["height"])


# ------------------------------------------------------------------------------------------- item 11
def test_garbage_obj_is_named(tmp_path):
    from fppsim.rendering.scene import MeshError, load_mesh

    p = tmp_path / "garbage.obj"
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError) as e:
        load_mesh(p)
    msg = str(e.value)
    assert "garbage.obj" in msg and "charset" not in msg and "No module" not in msg


def _strip_grid(nx=12, ny=9):
    """A height-field patch as triangle strips (one strip per row of quads, joined by -1)."""
    xs, ys = np.meshgrid(np.linspace(-40, 40, nx), np.linspace(-30, 30, ny))
    zs = 20.0 * np.exp(-(xs ** 2 + ys ** 2) / 600.0)
    V = np.stack([xs, ys, zs], -1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    strips = []
    for r in range(ny - 1):
        row = np.stack([idx[r + 1], idx[r]], axis=1).ravel()  # (r+1, c), (r, c), (r+1, c+1), ...
        strips += list(row) + [-1]
    # the same quads as independent triangles (the truth, built without strips)
    tris = []
    for r in range(ny - 1):
        for c in range(nx - 1):
            a, b, cc, d = idx[r + 1, c], idx[r, c], idx[r + 1, c + 1], idx[r, c + 1]
            tris += [(a, b, cc), (cc, b, d)]
    return V, np.array(strips[:-1]), np.array(tris)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_triangle_strips_are_read(tmp_path, fmt):
    from fppsim.rendering.meshio import read_ply_tristrips
    from fppsim.rendering.scene import load_mesh

    V, strips, truth = _strip_grid()
    p = tmp_path / f"strips_{fmt}.ply"
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\n"
            "property float z\nelement tristrips 1\nproperty list int int vertex_indices\nend_header\n")
    with open(p, "wb") as fh:
        fh.write(head.encode())
        if fmt == "ascii":
            fh.write("".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in V).encode())
            fh.write((f"{len(strips)} " + " ".join(map(str, strips)) + "\n").encode())
        else:
            fh.write(V.astype("<f4").tobytes())
            fh.write(np.array([len(strips)], "<i4").tobytes() + strips.astype("<i4").tobytes())
    v, f = read_ply_tristrips(p)
    np.testing.assert_allclose(v, V.astype(np.float32), atol=1e-5)
    # the same triangles as the independent triangulation, with the same winding (cyclic order)
    canon = lambda t: {tuple(np.roll(tri, -int(np.argmin(tri)))) for tri in np.asarray(t)}  # noqa: E731
    assert canon(f) == canon(truth)
    normals = trimesh.Trimesh(v, f, process=False).face_normals
    assert (normals[:, 2] > 0).all() or (normals[:, 2] < 0).all()  # consistent orientation
    asset = load_mesh(p)  # trimesh alone reports this file as an empty mesh
    assert len(asset.faces) == len(truth)


def test_strips_to_triangles_drops_degenerate_joins():
    from fppsim.rendering.meshio import strips_to_triangles

    t = strips_to_triangles(np.array([0, 1, 2, 3, 3, 4, 4, 5, 6, -1, 7, 8]))
    assert [tuple(x) for x in t] == [(0, 1, 2), (2, 1, 3), (4, 5, 6)]


def test_evaluate_limit_zero_is_a_usage_error(tiny_run, tmp_path, capsys):
    real, run = tiny_run
    assert uhrnet_main(["evaluate", str(run), "--real", str(real), "--out", str(tmp_path / "rep"),
                        "--limit", "0", "--no-progress"]) == 2
    _one_error_line(capsys, "--limit must be >= 1")


def test_done_message_never_points_to_a_missing_best(tmp_path, capsys):
    # all labels invalid: every RMSE is NaN, so no epoch is "best" and no best.pt is written
    write_figshare(tmp_path / "real", n=8, h=32, w=64)
    z = np.load(tmp_path / "real" / "Z.npy")
    np.save(tmp_path / "real" / "Z.npy", np.full_like(z, -105.0))
    rc = uhrnet_main(["train", "--real", str(tmp_path / "real"), "--model", "unet", "--base-channels", "4",
                      "--epochs", "1", "--loss", "l2", "--no-progress", "--out", str(tmp_path / "run")])
    out = capsys.readouterr().out
    assert rc == 0 and (tmp_path / "run" / "last.pt").exists()
    assert not (tmp_path / "run" / "best.pt").exists()
    assert "no best.pt written" in out and "done: " + str(tmp_path / "run" / "best.pt") not in out


# ------------------------------------------------------------------------------------------- item 12
def test_predict_refuses_nonsense(tiny_run, tmp_path, capsys):
    _, run = tiny_run
    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), np.full((1, 1), 120, np.uint8))
    assert uhrnet_main(["predict", str(run), str(tiny), "--out", str(tmp_path / "p")]) == 1
    _one_error_line(capsys, "tiny.png", "1x1", "at least 16x16")
    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.full((32, 64), 120, np.uint8))
    for size in ("0", "-1", "nan"):
        assert uhrnet_main(["predict", str(run), str(img), "--out", str(tmp_path / "p"), "--pixel-size", size]) == 2
        _one_error_line(capsys, "--pixel-size")


def test_predict_colour_equals_grey_and_warns_when_all_invalid(tiny_run, tmp_path, capsys):
    from _helpers import scene

    _, run = tiny_run
    f8, _, _ = scene(np.random.default_rng(3), 32, 64)
    (tmp_path / "grey").mkdir()
    (tmp_path / "colour").mkdir()
    cv2.imwrite(str(tmp_path / "grey" / "x.png"), f8)
    cv2.imwrite(str(tmp_path / "colour" / "x.png"), np.stack([f8] * 3, -1))  # the same scene saved as RGB
    for kind in ("grey", "colour"):
        assert uhrnet_main(["predict", str(run), str(tmp_path / kind / "x.png"), "--out", str(tmp_path / f"o_{kind}"),
                            "--no-ply", "--no-progress"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "o_grey" / "x_height.npy"),
                                  np.load(tmp_path / "o_colour" / "x_height.npy"))
    capsys.readouterr()
    # a colour-mapped picture has no grey equivalent: refused with a hint, not 40 mm off
    import matplotlib

    rgb = (matplotlib.colormaps["viridis"](f8 / 255.0)[..., :3] * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "cmap.png"), rgb[..., ::-1])
    assert uhrnet_main(["predict", str(run), str(tmp_path / "cmap.png"), "--out", str(tmp_path / "o3")]) == 1
    _one_error_line(capsys, "cmap.png", "colour image", "grey")
    # an all-black input: every pixel invalid -> written, with a warning
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((32, 64), np.uint8))
    assert uhrnet_main(["predict", str(run), str(tmp_path / "black.png"), "--out", str(tmp_path / "o4"),
                        "--no-ply", "--no-progress"]) == 0
    _one_error_line(capsys, "warning", "black.png", "no valid pixel")
    assert np.isnan(np.load(tmp_path / "o4" / "black_height.npy")).all()
