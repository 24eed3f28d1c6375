"""`fppsim generate`: outputs, determinism, worker invariance, resume after kill, sharding, bad input."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from fppsim.cli import main
from fppsim.dataio.formats import read_manifest

ROOT = Path(__file__).resolve().parents[2]
from _helpers import SHARED_MESHES


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    d = tmp_path_factory.mktemp("meshes")
    trimesh.creation.capsule(height=60.0, radius=18.0, count=[24, 24]).export(d / "capsule.ply")
    blob = trimesh.creation.icosphere(3, radius=30.0)
    blob.vertices *= [1.6, 1.0, 0.7]
    blob.export(d / "ellipsoid.stl")
    return d


def _gen(args):
    return main(["generate", "-q", "--no-preview", *args])


def _arrays(folder):
    with np.load(folder / "arrays.npz") as z:
        return {k: z[k] for k in z.files}


def _same_dataset(a, b):
    ra, rb = read_manifest(a), read_manifest(b)
    assert [r["id"] for r in ra] == [r["id"] for r in rb]
    for r in ra:
        A, B = _arrays(a / r["id"]), _arrays(b / r["id"])
        assert A.keys() == B.keys()
        for k in A:
            assert np.array_equal(A[k], B[k], equal_nan=True), (r["id"], k)
        for png in sorted((a / r["id"]).rglob("*.png")):
            assert png.read_bytes() == (b / r["id"] / png.relative_to(a / r["id"])).read_bytes()


def test_native_outputs_and_meta(tmp_path, meshes):
    out = tmp_path / "ds"
    assert main(["generate", "-q", "--meshes", str(meshes), "--out", str(out), "--count", "2", "--seed", "3"]) == 0
    recs = read_manifest(out)
    assert [r["id"] for r in recs] == ["000000", "000001"]
    s = out / "000000"
    img = cv2.imread(str(s / "fringe.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape == (352, 640)
    arr = _arrays(s)
    for k in ("height", "depth", "phase_true", "mask", "phase_psp", "height_psp", "mask_psp"):
        assert arr[k].dtype == np.float32 and arr[k].shape == (352, 640), k
    assert sorted(p.name for p in (s / "psp").iterdir()) == sorted(f"f{f}_s{n}.png" for f in (1, 8, 80) for n in range(4))
    meta = json.loads((s / "meta.json").read_text())
    for key in ("rig", "objects", "optics", "seed", "version"):
        assert key in meta
    assert meta["rig"]["camera"]["width"] == 640
    for obj in meta["objects"]:
        assert Path(obj["mesh"]).exists() and obj["scale"] > 0 and np.array(obj["pose"]).shape == (4, 4)
    # the recorded pose maps the mesh file (times scale) onto the rendered surface
    obj = meta["objects"][0]
    m = trimesh.load(obj["mesh"], force="mesh")
    world = (obj["scale"] * m.vertices) @ np.array(obj["pose"])[:3, :3].T + np.array(obj["pose"])[:3, 3]
    assert abs(world[:, 2].min()) < 1e-6  # resting on the plane
    assert arr["height"].max() <= world[:, 2].max() + 1e-3
    assert (out / "preview.png").is_file()
    # heights are >= 0 and the plane is exactly 0 where the mask says plane
    assert arr["height"].min() >= 0


@pytest.mark.slow  # over 5 s on a shared 2-core machine
def test_same_seed_identical_and_workers_invariant(tmp_path, meshes):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    common = ["--meshes", str(meshes), "--count", "3", "--seed", "11"]
    assert _gen([*common, "--out", str(a)]) == 0
    assert _gen([*common, "--out", str(b)]) == 0
    assert _gen([*common, "--out", str(c), "--workers", "2"]) == 0
    _same_dataset(a, b)
    _same_dataset(a, c)
    d = tmp_path / "d"
    assert _gen(["--meshes", str(meshes), "--count", "3", "--seed", "12", "--out", str(d)]) == 0
    assert not np.array_equal(_arrays(a / "000000")["height"], _arrays(d / "000000")["height"])


def test_resume_after_kill(tmp_path, meshes):
    out, ref = tmp_path / "killed", tmp_path / "ref"
    cmd = [sys.executable, "-m", "fppsim.cli", "generate", "-q", "--no-preview", "--meshes", str(meshes),
           "--count", "6", "--seed", "4", "--no-psp", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        done = [p for p in out.glob("0*") if p.is_dir()] if out.exists() else []
        if len(done) >= 2:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    n_before = len(read_manifest(out, strict=False))
    assert n_before < 6, "the run finished before it could be killed"
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    recs = read_manifest(out)
    assert [r["id"] for r in recs] == [f"{i:06d}" for i in range(6)]
    assert not (out / ".tmp").exists() and not list(out.glob(".fppsim-tmp-*"))
    assert _gen(["--meshes", str(meshes), "--count", "6", "--seed", "4", "--no-psp", "--out", str(ref)]) == 0
    _same_dataset(out, ref)
    # a second run with the same options is a no-op
    assert _gen(["--meshes", str(meshes), "--count", "6", "--seed", "4", "--no-psp", "--out", str(out)]) == 0
    assert len(read_manifest(out)) == 6


def test_resume_refuses_different_settings(tmp_path, meshes, capsys):
    out = tmp_path / "ds"
    assert _gen(["--meshes", str(meshes), "--count", "1", "--seed", "1", "--no-psp", "--out", str(out)]) == 0
    assert _gen(["--meshes", str(meshes), "--count", "1", "--seed", "2", "--no-psp", "--out", str(out)]) == 1
    assert "different seed" in capsys.readouterr().err


def test_resume_takes_the_same_meshes_through_a_link_and_refuses_other_ones(tmp_path, meshes, capsys):
    out, link = tmp_path / "ds", tmp_path / "linked"
    link.symlink_to(meshes, target_is_directory=True)
    assert _gen(["--meshes", str(meshes), "--count", "1", "--seed", "1", "--no-psp", "--out", str(out)]) == 0
    # the same folder through a link resumes (sim2real, which checks the meshes first, compares real paths too)
    assert _gen(["--meshes", str(link), "--count", "2", "--seed", "1", "--no-psp", "--out", str(out)]) == 0
    assert [r["id"] for r in read_manifest(out)] == ["000000", "000001"]
    capsys.readouterr()
    assert _gen(["--meshes", str(meshes / "capsule.ply"), "--count", "3", "--seed", "1", "--no-psp", "--out", str(out)]) == 1
    assert "different meshes" in capsys.readouterr().err


def test_figshare_format(tmp_path, meshes):
    out = tmp_path / "fig"
    assert _gen(["--meshes", str(meshes), "--count", "2", "--seed", "2", "--no-psp", "--format", "figshare",
                 "--out", str(out)]) == 0
    f = np.load(out / "f1_80.npy")
    z = np.load(out / "Z.npy")
    assert f.shape == z.shape == (2, 352, 640, 1) and f.dtype == z.dtype == np.float32
    for i, rec in enumerate(read_manifest(out / "native")):
        s = out / "native" / rec["id"]
        img = cv2.imread(str(s / "fringe.png"), cv2.IMREAD_UNCHANGED)
        arr = _arrays(s)
        valid = arr["mask"] > 0
        np.testing.assert_allclose(f[i, ..., 0][valid], img[valid] / 127.5 - 1, atol=1e-6)
        assert np.all(f[i, ..., 0][~valid] == -1) and np.all(z[i, ..., 0][~valid] == -105)
        np.testing.assert_allclose(z[i, ..., 0][valid], arr["height"][valid] * 6 - 97, atol=1e-4)
        plane = valid & (arr["height"] == 0)
        assert np.all(z[i, ..., 0][plane] == -97)  # "Z <= -100 is invalid" keeps the plane
    assert f.min() >= -1 and f.max() <= 1
    # the arrays and native/ hold the same samples: a --count that would leave some of native/ out is refused
    # (test_generate_folder.py), and the arrays stay as they were
    assert _gen(["--meshes", str(meshes), "--count", "1", "--seed", "2", "--no-psp", "--format", "figshare",
                 "--out", str(out)]) == 1
    assert np.array_equal(np.load(out / "f1_80.npy"), f)


def test_shards_merge_to_the_whole(tmp_path, meshes):
    whole, s0, s1, merged = (tmp_path / n for n in ("whole", "s0", "s1", "merged"))
    common = ["--meshes", str(meshes), "--count", "3", "--seed", "8", "--no-psp"]
    assert _gen([*common, "--out", str(whole)]) == 0
    assert _gen([*common, "--out", str(s0), "--shard", "0/2"]) == 0
    assert _gen([*common, "--out", str(s1), "--shard", "1/2"]) == 0
    assert [r["id"] for r in read_manifest(s0)] == ["000000", "000002"]
    assert main(["merge", str(merged), str(s0), str(s1)]) == 0
    _same_dataset(whole, merged)


# ------------------------------------------------------------------------------------------ bad input
def test_bad_meshes_are_skipped_and_counted(tmp_path, meshes, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "garbage.obj").write_text("this is not a mesh\n")
    (bad / "empty.ply").write_bytes(b"")
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [100, 0, 0], [0, 100, 0], [100, 100, 0]], faces=[[0, 1, 2], [1, 3, 2]])
    flat.export(bad / "flat.obj")
    out = tmp_path / "ds"
    assert main(["generate", "-q", "--no-preview", "--meshes", str(bad), str(meshes / "capsule.ply"),
                 "--count", "1", "--no-psp", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count("skipped mesh") == 3 and "flat" in text
    assert len(read_manifest(out)) == 1
    # nothing usable at all: one-line reason, exit 1
    assert main(["generate", "-q", "--meshes", str(bad), "--count", "1", "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "no usable mesh" in err[-1]


@pytest.mark.skipif(not (SHARED_MESHES / "alligator.obj").is_file(), reason="../shared/meshes absent")
def test_shared_alligator_is_flat(tmp_path, capsys):
    assert main(["generate", "-q", "--meshes", str(SHARED_MESHES / "alligator.obj"), "--count", "1",
                 "--out", str(tmp_path / "a")]) == 1
    assert "flat mesh" in capsys.readouterr().err


def test_nothing_in_view_fails_cleanly(tmp_path, meshes, capsys):
    from fppsim.geometry.rig import Rig

    rig = Rig.default().to_dict()
    rig["camera"]["t"] = [0.0, 0.0, 50000.0]  # 50 m away: objects cover almost nothing
    rig["projector"]["t"][2] = 50000.0
    p = tmp_path / "far.json"
    p.write_text(json.dumps(rig))
    assert main(["generate", "-q", "--meshes", str(meshes), "--count", "1", "--no-psp", "--rig", str(p),
                 "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "nothing" in err or "fringes do not move with height" in err  # refused before any sample now


def test_bad_rig_unwritable_output_and_usage(tmp_path, meshes, capsys):
    p = tmp_path / "rig.json"
    p.write_text('{"camera": {}}')
    assert main(["generate", "--meshes", str(meshes), "--count", "1", "--rig", str(p), "--out", str(tmp_path / "o")]) == 1
    assert "rig.json" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["generate", "--meshes", str(meshes), "--count", "1", "--out", str(blocker / "sub")]) == 1
    assert "cannot write" in capsys.readouterr().err
    assert main(["generate", "--meshes", str(tmp_path / "nope.obj"), "--count", "1", "--out", str(tmp_path / "o")]) == 1
    assert "not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["generate", "--meshes", str(meshes), "--out", str(tmp_path / "o")])  # --count missing
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["generate", "--meshes", str(meshes), "--count", "1", "--out", "o", "--shard", "3/2"])
    assert e.value.code == 2
    assert subprocess.run([sys.executable, "-m", "fppsim.cli"], capture_output=True).returncode == 2


def test_merge_warns_about_missing_shards(tmp_path, meshes, capsys):
    s1, merged = tmp_path / "s1", tmp_path / "m"
    assert _gen(["--meshes", str(meshes), "--count", "3", "--seed", "8", "--no-psp", "--out", str(s1),
                 "--shard", "1/2"]) == 0
    assert main(["merge", str(merged), str(s1)]) == 0
    assert "1 sample index(es) missing" in capsys.readouterr().err


def test_corrupt_sample_is_named_not_a_traceback(tmp_path, meshes, capsys):
    out = tmp_path / "ds"
    assert _gen(["--meshes", str(meshes), "--count", "1", "--no-psp", "--out", str(out)]) == 0
    (out / "000000" / "arrays.npz").write_bytes(b"junk")
    assert main(["compare-real", str(out), str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "arrays.npz" in err[0]
    from fppsim.dataio.formats import DatasetError
    from fppsim.dataio.readers import load_native_sample

    with pytest.raises(DatasetError, match="000000"):
        load_native_sample(out / "000000")


def test_full_chain_sphere_matches_analytic_geometry(tmp_path):
    """generate -> arrays.npz + meta.json pose -> analytic ray/sphere heights and projector phases."""
    from fppsim.geometry.rig import Rig

    d = tmp_path / "m"
    d.mkdir()
    trimesh.creation.icosphere(6, radius=1.0).export(d / "sphere.ply")  # unit sphere: scaled by the sampler
    out = tmp_path / "ds"
    assert _gen(["--meshes", str(d), "--count", "1", "--objects", "1", "--no-psp", "--out", str(out)]) == 0
    meta = json.loads((out / "000000" / "meta.json").read_text())
    arr = _arrays(out / "000000")
    rig = Rig.from_dict(meta["rig"])
    obj = meta["objects"][0]
    pose = np.array(obj["pose"])
    centre, radius = pose[:3, 3], obj["scale"] * 1.0
    origin, dirs = rig.camera.pixel_rays(rig.camera.pixel_grid())
    oc = origin - centre
    b = dirs @ oc
    a = np.sum(dirs * dirs, -1)
    disc = b * b - a * (oc @ oc - radius ** 2)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a
    X = origin + t[..., None] * dirs
    on = (disc > 0.05 * a * radius ** 2) & (X[..., 2] > 0.5) & (arr["mask"] > 0)  # sphere interior, lit
    assert on.sum() > 2000
    assert np.median(np.abs(arr["height"][on] - X[on][:, 2])) < 0.05
    phase = rig.phase_of_column(rig.projector.project(X[on])[0][:, 0])
    assert np.median(np.abs(arr["phase_true"][on] - phase)) < 0.01
    # the plane far from the sphere is exactly z = 0 and its phase is that of the plane point
    plane = (disc < 0) & (arr["mask"] > 0)
    assert np.all(arr["height"][plane] == 0)
    Xp = rig.camera.backproject(rig.camera.pixel_grid()[plane], arr["depth"][plane])
    np.testing.assert_allclose(arr["phase_true"][plane], rig.phase_of_column(rig.projector.project(Xp)[0][:, 0]),
                               atol=2e-3)


def test_supersampling_keeps_ground_truth_at_pixel_centres(tmp_path, meshes):
    a, b = tmp_path / "k1", tmp_path / "k3"
    common = ["--meshes", str(meshes), "--count", "1", "--seed", "5", "--no-psp", "--noise-free"]
    assert _gen([*common, "--out", str(a)]) == 0
    assert _gen([*common, "--out", str(b), "--supersample", "3"]) == 0
    A, B = _arrays(a / "000000"), _arrays(b / "000000")
    both = (A["mask"] > 0) & (B["mask"] > 0)
    assert both.mean() > 0.9
    assert np.median(np.abs(A["height"] - B["height"])[both]) < 1e-3
    ia = cv2.imread(str(a / "000000" / "fringe.png"), 0).astype(int)
    ib = cv2.imread(str(b / "000000" / "fringe.png"), 0).astype(int)
    assert 0 < np.abs(ia - ib).mean() < 2  # sub-pixel integration changes intensities a little
