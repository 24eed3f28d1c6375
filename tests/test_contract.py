"""The dataset contract (fppsim.dataio.formats) seen from both sides: what fppsim writes, uhrnet reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fppsim.dataio.encoding import decode_fringe, encode_fringe
from fppsim.files import atomic_path, atomic_write_text
from fppsim.dataio.formats import LabelTransform, read_manifest, read_settings, reconcile
from fppsim.dataio.writers import export_figshare, write_sample_folder
from fppsim.files import tmp_path as temp_name
from uhrnet.data.datasets import FigshareArrays, FppsimDataset
from uhrnet.errors import DataError


def _native(root, heights, masks, transform=None):
    """Native samples written by fppsim's own writer (what `fppsim generate` calls per sample)."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i, (h, m) in enumerate(zip(heights, masks)):
        img = rng.integers(0, 256, h.shape, dtype=np.uint8)
        arrays = {"height": h.astype(np.float32), "depth": (500 - h).astype(np.float32),
                  "phase_true": np.zeros_like(h, np.float32), "mask": m.astype(np.float32)}
        meta = {"index": i, "seed": 0, "objects": [], "stats": {"valid_fraction": float(m.mean())}}
        write_sample_folder(root, f"{i:06d}", {"fringe.png": img}, arrays, meta)
    reconcile(root)
    if transform is not None:
        (root / "dataset.json").write_text(json.dumps({"label": transform.to_dict()}))


def _heights(n=3, h=24, w=40, seed=1):
    rng = np.random.default_rng(seed)
    hs = [rng.uniform(0, 60, (h, w)) for _ in range(n)]
    ms = [rng.random((h, w)) > 0.2 for _ in range(n)]
    return hs, ms


@pytest.mark.parametrize("transform", [LabelTransform(),
                                       LabelTransform(name="custom", units_per_mm=10.0, plane_offset=-50.0,
                                                      invalid_value=-80.0, invalid_threshold=-60.0)])
def test_fppsim_label_reads_back_in_uhrnet_as_the_same_millimetres(tmp_path, transform):
    hs, ms = _heights()
    _native(tmp_path / "nat", hs, ms, transform)
    n = export_figshare(tmp_path / "nat", tmp_path / "fig", transform)
    (tmp_path / "fig" / "native").mkdir()
    (tmp_path / "fig" / "native" / "dataset.json").write_text(json.dumps({"label": transform.to_dict()}))
    assert n == 3
    for ds in (FppsimDataset(tmp_path / "nat", transform=transform), FigshareArrays(tmp_path / "fig", transform=transform),
               FppsimDataset(tmp_path / "fig", transform=transform)):
        for i, (h, m) in enumerate(zip(hs, ms)):
            s = ds[i]
            valid = s["mask"][0].numpy() > 0
            np.testing.assert_array_equal(valid, m)
            mm = transform.height_mm(s["height"][0].numpy().astype(np.float64))
            # float32 labels: the round trip is exact to float32 precision of the label
            np.testing.assert_allclose(mm[m], h.astype(np.float32)[m], rtol=0, atol=1e-5 * 60 * transform.units_per_mm)
            assert (s["height"][0].numpy()[~m] == transform.invalid_value).all()
            assert s["mm_per_unit"] == pytest.approx(1 / transform.units_per_mm)


def test_height_mm_and_label_differences_are_named_apart():
    t = LabelTransform()
    lab = t.label_from_height_mm(np.array([0.0, 10.0]), np.array([1, 1]))
    np.testing.assert_allclose(lab, [-97.0, -37.0])
    np.testing.assert_allclose(t.height_mm(lab), [0.0, 10.0])          # above the plane
    assert (lab[1] - lab[0]) * t.mm_per_unit == pytest.approx(10.0)    # an error / difference in mm
    assert torch.equal(t.valid(torch.tensor([-100.0, -99.0])), torch.tensor([False, True]))
    assert not hasattr(t, "to_mm")  # the ambiguous name of the first versions is gone


def test_old_field_names_still_load(tmp_path):
    old = {"scale": 10.0, "offset": -90.0, "invalid": -105.0, "threshold": -100.0, "name": "custom"}
    t = LabelTransform.from_dict(old)
    assert (t.units_per_mm, t.plane_offset, t.invalid_value, t.invalid_threshold) == (10.0, -90.0, -105.0, -100.0)
    assert LabelTransform.from_dict(t.to_dict()) == t
    with pytest.raises(DataError, match="unknown keys"):
        LabelTransform.from_dict({"scael": 6})
    # an old dataset.json is read in today's vocabulary ...
    (tmp_path / "dataset.json").write_text(json.dumps({"seed": 1, "label": old}))
    assert read_settings(tmp_path)["label"] == t.to_dict()
    # ... and an old figshare export is checked against the reader's transform with the old names
    hs, ms = _heights(n=1)
    _native(tmp_path / "nat", hs, ms)
    export_figshare(tmp_path / "nat", tmp_path / "fig", t)
    (tmp_path / "fig" / "dataset.json").write_text(json.dumps({"label": old}))
    assert FppsimDataset(tmp_path / "fig", transform=t)[0]["height"].shape == (1, 24, 40)
    with pytest.raises(DataError, match="labelled with units_per_mm=10"):
        FppsimDataset(tmp_path / "fig")


def test_the_readers_train_and_evaluate_open_refuse_an_export_in_other_label_units(tmp_path):
    """`uhrnet train` / `evaluate` open a figshare export through open_dataset / load_sources, which memory-map its
    arrays directly: they read a Z.npy labelled at 10 units per mm as if it were 6 (QA: 17.24 mm for 3.77 mm)."""
    from uhrnet.data.datasets import load_sources, open_dataset

    theirs = LabelTransform(name="custom", units_per_mm=10.0, plane_offset=-50.0)
    hs, ms = _heights(n=6)
    _native(tmp_path / "nat", hs, ms, theirs)
    export_figshare(tmp_path / "nat", tmp_path / "fig", theirs)
    (tmp_path / "fig" / "native").mkdir()
    (tmp_path / "fig" / "native" / "dataset.json").write_text(json.dumps({"label": theirs.to_dict()}))
    for read in (lambda: open_dataset(tmp_path / "fig"), lambda: load_sources(synthetic=[tmp_path / "fig"]),
                 lambda: load_sources(real=[tmp_path / "fig"])):
        with pytest.raises(DataError, match="labelled with units_per_mm=10, plane_offset=-50 .* native/ folder"):
            read()
    # read with the units it records it opens, and so does its native/ folder through any transform
    assert len(open_dataset(tmp_path / "fig", transform=theirs)) == 6
    assert len(load_sources(synthetic=[tmp_path / "nat"]).train) > 0


def test_old_checkpoint_label_transform_loads(tmp_path):
    from uhrnet.checkpoint import FORMAT, atomic_save, load_checkpoint, model_from_checkpoint
    from uhrnet.models import build_model

    net = build_model("unet", base_channels=4)
    ckpt = {"format": FORMAT, "version": 1, "model": {"name": "unet", "config": dict(net.config)},
            "state_dict": net.state_dict(), "output": {"scale": 60.0, "shift": -97.0},
            "label_transform": {"name": "figshare", "units_per_mm": 6.0, "invalid_value": -105.0,
                                "invalid_threshold": -100.0, "plane_offset": -97.0, "data_range": 286.0}}
    atomic_save(ckpt, tmp_path / "a.pt")
    _, t = model_from_checkpoint(load_checkpoint(tmp_path / "a.pt"))
    assert t == LabelTransform()
    ckpt["label_transform"] = {"scale": 6.0, "offset": -97.0, "invalid": -105.0, "threshold": -100.0}
    atomic_save(ckpt, tmp_path / "b.pt")
    assert model_from_checkpoint(load_checkpoint(tmp_path / "b.pt"))[1].same_labels(LabelTransform())


def test_fringe_encoding_round_trip():
    img = np.arange(256, dtype=np.uint8).reshape(16, 16)
    f = encode_fringe(img)
    assert f.dtype == np.float32 and f.min() == -1 and f.max() == 1
    np.testing.assert_array_equal(decode_fringe(f), img)
    np.testing.assert_array_equal(encode_fringe(img.astype(np.uint16) * 257), f)
    m = img % 2 == 0
    assert (encode_fringe(img, m)[~m] == -1).all()


def test_atomic_path_keeps_the_old_file_on_failure_and_reconcile_removes_only_dead_leftovers(tmp_path):
    target = tmp_path / "manifest.jsonl"
    atomic_write_text(target, "old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert tmp.name.startswith(".fppsim-tmp-") and tmp.name.endswith("-manifest.jsonl")
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old\n" and not temp_name(target).exists()
    dead = temp_name(tmp_path / "Z.npy", pid=(1 << 22) + 1)  # above pid_max: a process that is gone
    dead.write_bytes(b"torn")  # left by a killed process
    alive = temp_name(tmp_path / "f1_80.npy", pid=1)  # a live process's file is never touched
    alive.write_bytes(b"being written")
    foreign = tmp_path / ".Z.npy.123.tmp.npy"  # not our naming scheme: never touched
    foreign.write_bytes(b"someone else's")
    target.write_text("")
    assert reconcile(tmp_path) == []
    assert sorted(p.name for p in tmp_path.glob(".*")) == sorted([alive.name, foreign.name])
    assert read_manifest(tmp_path) == []
