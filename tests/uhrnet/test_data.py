"""uhrnet.data.datasets: figshare arrays, native fppsim folders, mixtures, the reference split, clear errors."""

import json

import numpy as np
import pytest
import torch

from uhrnet.data.datasets import (
    DataError, FigshareArrays, FppsimDataset, LabelTransform, MixedDataset, MixedSampler, Prepared,
    load_sources, parse_size, reference_split, split_indices,
)

from _helpers import REAL_SAMPLE, write_figshare, write_native


@pytest.mark.parametrize("n", [6, 7, 10, 15, 37, 100, 1234, 1500])
def test_reference_split_matches_sklearn(n):
    sk = pytest.importorskip("sklearn.model_selection")
    idx = np.arange(n)
    train, rest = sk.train_test_split(idx, test_size=0.2, random_state=0)
    val, test = sk.train_test_split(rest, test_size=0.5, random_state=1)
    ours = reference_split(n)
    np.testing.assert_array_equal(ours["train"], train)
    np.testing.assert_array_equal(ours["val"], val)
    np.testing.assert_array_equal(ours["test"], test)
    assert len(set(train) | set(val) | set(test)) == n


def test_split_modes():
    assert list(split_indices(3, "train", "train")) == [0, 1, 2]
    assert len(split_indices(3, "test", "train")) == 0
    assert list(split_indices(3, "test", "test")) == [0, 1, 2]
    with pytest.raises(DataError, match="at least 6") as err:
        split_indices(3, "train", "reference")
    assert "--real-split/--synthetic-split train" in str(err.value) and "'all'" not in str(err.value)


def test_figshare_round_trip(tmp_path):
    fr, z = write_figshare(tmp_path, n=7, h=32, w=48)
    ds = FigshareArrays(tmp_path)
    assert isinstance(ds.labels, np.memmap) or isinstance(ds.labels.base, np.memmap)
    assert len(ds) == 7 and ds.image_shape == (32, 48)
    for i in range(7):
        s = ds[i]
        assert s["fringe"].shape == (1, 32, 48) and s["fringe"].dtype == torch.float32
        np.testing.assert_array_equal(s["fringe"][0].numpy(), fr[i, ..., 0])
        np.testing.assert_array_equal(s["height"][0].numpy(), z[i, ..., 0])
        np.testing.assert_array_equal(s["mask"][0].numpy(), (z[i, ..., 0] > -100).astype(np.float32))
        assert s["mm_per_unit"] == pytest.approx(1 / 6)


def test_figshare_explicit_names_and_shapes(tmp_path):
    fr, z = write_figshare(tmp_path, n=3, squeeze=True, fringe_name="a.npy", label_name="b.npy")
    ds = FigshareArrays(fringe=tmp_path / "a.npy", label=tmp_path / "b.npy")
    assert len(ds) == 3
    np.save(tmp_path / "one_f.npy", fr[0])  # (H, W)
    np.save(tmp_path / "one_z.npy", z[0][..., None])  # (H, W, 1)
    one = FigshareArrays(tmp_path, fringe="one_f.npy", label="one_z.npy")
    assert len(one) == 1
    np.testing.assert_array_equal(one[0]["height"][0].numpy(), z[0])


def test_label_transform():
    t = LabelTransform.resolve("figshare")
    h = np.array([0.0, 10.0, np.nan, 5.0], np.float32)
    lab = t.label_from_height_mm(h, np.array([1, 1, 1, 0], bool))
    np.testing.assert_allclose(lab, [-97, -37, -105, -105])
    np.testing.assert_allclose(t.height_mm(lab[:2]), [0, 10])
    assert t.valid(lab).tolist() == [True, True, False, False]
    custom = LabelTransform.resolve({"preset": "figshare", "units_per_mm": 10.0})
    assert custom.units_per_mm == 10 and custom.invalid_value == -105
    assert LabelTransform.from_dict(custom.to_dict()) == custom
    with pytest.raises(DataError, match="unknown label preset"):
        LabelTransform.resolve("nope")


@pytest.mark.skipif(not (REAL_SAMPLE / "height_map.npy").exists(), reason="../shared/real-sample absent")
def test_real_sample_loads_with_preset():
    ds = FigshareArrays(REAL_SAMPLE)  # finds fringe_pattern.npy / height_map.npy
    assert len(ds) == 1 and ds.image_shape == (352, 640)
    s = ds[0]
    height = s["height"][0].numpy()
    assert int((height == -105).sum()) == 15563
    assert (s["fringe"][0].numpy()[height == -105] == -1).all()
    assert s["fringe"].min() >= -1 and s["fringe"].max() <= 1
    # The reference rule Z <= -100 masks the shadow pixels plus a few plane pixels below -100.
    assert 15563 <= int((s["mask"] == 0).sum()) < 15563 + 0.02 * height.size
    plane = np.median(height[(height > -110) & (height < -90)])
    assert -98.5 < plane < -95.5


def test_native_reads_with_same_transform(tmp_path):
    write_native(tmp_path / "nat", n=4, psp=True)
    ds = FppsimDataset(tmp_path / "nat")
    assert len(ds) == 4 and ds.ids[0] == "000000"
    s = ds[1]
    with np.load(tmp_path / "nat" / "000001" / "arrays.npz") as a:
        h, m = a["height"], a["mask"] > 0.5
    lab = s["height"][0].numpy()
    np.testing.assert_allclose(lab[m], h[m] * 6 - 97, rtol=0, atol=1e-4)
    assert (lab[~m] == -105).all() and (s["fringe"][0].numpy()[~m] == -1).all()
    assert s["fringe"].min() >= -1 and s["fringe"].max() <= 1
    psp = FppsimDataset(tmp_path / "nat", label="psp")[1]
    np.testing.assert_allclose(psp["height"][0].numpy()[m], (h[m] + 0.01) * 6 - 97, atol=1e-3)


def test_fppsim_dataset_reads_figshare_export(tmp_path):
    fr, z = write_figshare(tmp_path, n=2)
    ds = FppsimDataset(tmp_path)
    np.testing.assert_array_equal(ds[1]["height"][0].numpy(), z[1, ..., 0])


def test_manifest_tolerates_partial_last_line_and_duplicates(tmp_path):
    write_native(tmp_path, n=3)
    with open(tmp_path / "manifest.jsonl", "a") as f:
        f.write(json.dumps({"id": "000001"}) + "\n" + '{"id": "0000')
    with pytest.warns(UserWarning, match="unreadable last line"):
        ds = FppsimDataset(tmp_path)
    assert ds.ids == ["000000", "000001", "000002"]


@pytest.mark.parametrize("case, match", [
    ("missing_label", "Z.npy: label file not found"),
    ("mismatched_n", "Z.npy: 3 samples but f1_80.npy has 4"),
    ("wrong_shape", "Z.npy: shape"),
    ("wrong_dtype", "f1_80.npy: dtype uint8"),
    ("nan_label", "Z.npy: sample 2 has 1 NaN/inf"),
    ("raw_fringe", "looks like raw 8-bit"),
    ("empty_folder", "empty folder"),
    ("size_mismatch", "image size"),
])
def test_figshare_errors_name_the_file(tmp_path, case, match):
    fr, z = write_figshare(tmp_path, n=4, h=16, w=16)
    if case == "missing_label":
        (tmp_path / "Z.npy").unlink()
    elif case == "mismatched_n":
        np.save(tmp_path / "Z.npy", z[:3])
    elif case == "wrong_shape":
        np.save(tmp_path / "Z.npy", np.repeat(z, 3, axis=-1))
    elif case == "wrong_dtype":
        np.save(tmp_path / "f1_80.npy", ((fr + 1) * 127.5).astype(np.uint8))
    elif case == "nan_label":
        z[2, 3, 3, 0] = np.nan
        np.save(tmp_path / "Z.npy", z)
    elif case == "raw_fringe":
        np.save(tmp_path / "f1_80.npy", (fr + 1) * 127.5)
    elif case == "empty_folder":
        tmp_path = tmp_path / "empty"
        tmp_path.mkdir()
    elif case == "size_mismatch":
        np.save(tmp_path / "Z.npy", z[:, :8])
    with pytest.raises(DataError, match=match):
        FigshareArrays(tmp_path)


def test_native_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match="folder not found"):
        FppsimDataset(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no samples"):
        FppsimDataset(tmp_path / "empty")
    write_native(tmp_path / "a", n=2)
    (tmp_path / "a" / "000001" / "fringe.png").unlink()
    with pytest.raises(DataError, match="000001/fringe.png: file not found"):
        FppsimDataset(tmp_path / "a")
    write_native(tmp_path / "b", n=2)
    with np.load(tmp_path / "b" / "000000" / "arrays.npz") as a:
        arrays = dict(a)
    arrays["height"][arrays["mask"] > 0] = np.nan
    np.savez(tmp_path / "b" / "000000" / "arrays.npz", **arrays)
    with pytest.raises(DataError, match="000000/arrays.npz: height has NaN"):
        FppsimDataset(tmp_path / "b")[0]
    with pytest.raises(DataError, match="no PSP height"):  # refused when opened, not at the first batch
        FppsimDataset(tmp_path / "b", label="psp")
    (tmp_path / "b" / "000001" / "arrays.npz").write_bytes(b"PK\x03\x04junk")  # corrupt zip: no traceback
    with pytest.raises(DataError, match="000001/arrays.npz: cannot read"):
        FppsimDataset(tmp_path / "b")[1]


def test_mixed_sampler_ratio_and_ddp_partition():
    s = MixedSampler(n_real=10, n_synthetic=90, synthetic_ratio=0.5, num_samples=4000, seed=3)
    order = s.order()
    frac = (order >= 10).mean()
    assert 0.45 < frac < 0.55
    # Each group is drawn without replacement until exhausted.
    first_real = [i for i in order if i < 10][:10]
    assert sorted(first_real) == list(range(10))
    s.set_epoch(1)
    assert not np.array_equal(s.order(), order)
    # Plain shuffle: each sample once per epoch.
    plain = MixedSampler(5, 7, None, seed=0)
    assert sorted(plain.order()) == list(range(12))
    # DDP: ranks partition the same (padded) order.
    ranks = [list(MixedSampler(5, 6, 0.3, seed=1, rank=r, world_size=2)) for r in range(2)]
    assert len(ranks[0]) == len(ranks[1]) == 6
    full = MixedSampler(5, 6, 0.3, seed=1).order()
    padded = list(full) + list(full[:1])
    assert [i for i, _ in ranks[0]] == padded[0::2] and [i for i, _ in ranks[1]] == padded[1::2]


def test_load_sources_keeps_real_test_out_of_training(tmp_path):
    write_figshare(tmp_path / "real", n=20, h=16, w=16)
    write_native(tmp_path / "syn", n=10, h=16, w=16)
    src = load_sources(real=[tmp_path / "real"], synthetic=[tmp_path / "syn"])
    ref = reference_split(20)
    assert src.train.n_real == 16 and src.val.n_real == 2 and src.test.n_real == 2
    real_train_ids = set(src.train.ids[: src.train.n_real])
    assert real_train_ids == {f"{i:06d}" for i in ref["train"]}
    assert not real_train_ids & {f"{i:06d}" for i in ref["test"]}
    assert src.train.n_synthetic == 8
    assert src.train[0]["source"] == "real" and src.train[16]["source"] == "synthetic"
    one = load_sources(real=[tmp_path / "real"], real_split="test")
    assert len(one.train) == 0 and len(one.test) == 20


def test_prepared_crop_and_resize(tmp_path):
    write_figshare(tmp_path, n=2, h=32, w=64)
    ds = FigshareArrays(tmp_path)
    p = Prepared(ds, crop=(16, 32))
    a, b = p[(0, 123)], p[(0, 123)]
    assert a["fringe"].shape == (1, 16, 32)
    assert torch.equal(a["height"], b["height"])
    centre = p[0]["height"][0]
    assert torch.equal(centre, ds[0]["height"][0, 8:24, 16:48])
    r = Prepared(ds, resize=(16, 32))[1]
    assert r["fringe"].shape == (1, 16, 32) and set(r["mask"].unique().tolist()) <= {0.0, 1.0}
    valid = r["mask"] > 0
    assert (r["height"][valid] > -100).all() and (r["height"][~valid] == -105).all()
    assert parse_size("176x320") == (176, 320)
    with pytest.raises(ValueError):
        parse_size("176")
    with pytest.raises(DataError, match="larger than"):
        Prepared(ds, crop=(64, 64))[0]


def test_mixed_dataset_indexing(tmp_path):
    write_figshare(tmp_path / "a", n=3, h=16, w=16)
    write_figshare(tmp_path / "b", n=2, h=16, w=16, seed=1)
    m = MixedDataset(real=[FigshareArrays(tmp_path / "a")], synthetic=[FigshareArrays(tmp_path / "b", source="synthetic")])
    assert len(m) == 5 and m.n_real == 3 and m[4]["source"] == "synthetic"
    with pytest.raises(IndexError):
        m[5]


def test_figshare_pickles_without_copying_arrays(tmp_path):
    import pickle

    write_figshare(tmp_path, n=4, h=32, w=64)
    ds = FigshareArrays(tmp_path)
    blob = pickle.dumps(ds)
    assert len(blob) < 4 * 32 * 64 * 4  # far less than one array
    again = pickle.loads(blob)
    assert torch.equal(again[3]["height"], ds[3]["height"])


def _fppsim_generate(out, *extra):
    import os
    import subprocess
    import sys
    from pathlib import Path

    pytest.importorskip("pyrender", reason="pyrender (OSMesa) not installed")
    root = Path(__file__).resolve().parents[2]
    meshes = sorted((root / "fppsim" / "data" / "meshes").glob("*.ply"))
    if not meshes:
        pytest.skip("no meshes in assets/meshes")
    env = {**os.environ, "PYOPENGL_PLATFORM": "osmesa"}
    cmd = [sys.executable, "-c", "import sys; from fppsim.cli import main; sys.exit(main())", "generate",
           "--meshes", str(meshes[0]), "--out", str(out), "--count", "2", "-q", "--no-psp", "--no-preview", *extra]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]


def test_generator_figshare_round_trip(tmp_path):
    """`fppsim generate --format figshare` -> FigshareArrays equals the native samples read by FppsimDataset."""
    _fppsim_generate(tmp_path / "gen", "--format", "figshare")
    arrays = FigshareArrays(tmp_path / "gen")
    export = FppsimDataset(tmp_path / "gen")  # the same folder through the synthetic reader
    native = FppsimDataset(tmp_path / "gen" / "native")
    assert len(arrays) == len(native) == len(export) == 2 and arrays.image_shape == (352, 640)
    for i in range(2):
        a, n = arrays[i], native[i]
        for key in ("fringe", "height", "mask"):
            assert torch.equal(a[key], n[key]), key
        assert torch.equal(export[i]["height"], a["height"])
        valid = a["mask"] > 0
        assert 0.5 < valid.float().mean() <= 1 and (a["height"][valid] > -100).all()
    # An export labelled differently is refused instead of misread.
    with pytest.raises(DataError, match="labelled with units_per_mm=6"):
        FppsimDataset(tmp_path / "gen", transform=LabelTransform(units_per_mm=10.0))
