"""One reader (issue 48): a layout registered in ONE place (here, in the test) reaches every command that reads real
data, through fppsim.dataio.readers.Source: compare-real, fit-rig / fit-optics (load_fringe_images), the rig start
(phase_maps_of), label-real, uhrnet.scoring.phase_residual (evaluate-phase, train --val-phase), the sim2real
evaluation, and train --real / evaluate / predict (their dataset and input readers).

The toy layout: a folder of 8-bit fringe PNGs ``<id>.toy.png`` with, beside each, its heights in mm
``<id>.mm.npy`` (NaN where there is none; then the layout is labelled) or its absolute phase ``<id>.phase.npy``
(NaN where there is none; then each image is a phase-shifting scan)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fppsim.dataio import readers
from fppsim.dataio.encoding import encode_fringe, read_gray_image
from fppsim.dataio.readers import LAYOUTS, PspMat, Source, open_labelled, open_source, register_layout
from fppsim.errors import DatasetError, PSPMatError
from fppsim.fitting.height_sensitivity import surface_phase
from tests._helpers import scene, tiny_rig

H, W = 32, 64


class ToyLayout(Source):
    kind = "toy-png"
    holds = "8-bit PNG fringes <id>.toy.png + heights <id>.npy (mm)"

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_dir() and any(path.glob("*.toy.png"))

    @property
    def labelled(self) -> bool:
        return any(self.path.glob("*.mm.npy"))

    def ids(self) -> list[str]:
        return sorted(p.name[: -len(".toy.png")] for p in self.path.glob("*.toy.png"))

    def fringe_images(self):
        for sid in self.ids():
            yield sid, read_gray_image(self.path / f"{sid}.toy.png")

    def sample(self, i, transform, label="true", mask_fringe=True):
        sid = self.ids()[int(i)]
        grey = read_gray_image(self.path / f"{sid}.toy.png")
        height = np.load(self.path / f"{sid}.mm.npy")
        valid = np.isfinite(height)
        fringe = encode_fringe(grey)
        if mask_fringe:
            fringe = np.where(valid, fringe, np.float32(-1.0))
        return fringe, transform.label_from_height_mm(np.nan_to_num(height), valid)

    def check_samples(self, transform, label="true") -> None:
        if not self.ids():
            raise DatasetError(f"{self.path}: no samples")

    def phase_ids(self) -> list[str]:
        return [sid for sid in self.ids() if (self.path / f"{sid}.phase.npy").is_file()]

    def scan_ids(self) -> list[str]:
        ids = self.phase_ids()
        if not ids:
            raise PSPMatError(f"{self.path}: no <id>.phase.npy beside the images")
        return ids

    def scan(self, sid, convention="benchmark", negate_sin=False) -> PspMat:
        image = read_gray_image(self.path / f"{sid}.toy.png")
        phase = np.load(self.path / f"{sid}.phase.npy").astype(np.float64)
        valid = np.isfinite(phase)
        wrapped = np.angle(np.exp(1j * np.nan_to_num(phase)))
        order = np.rint((np.nan_to_num(phase) - wrapped) / (2 * np.pi)).astype(np.int64)
        return PspMat(psin=np.sin(wrapped), pcos=np.cos(wrapped), order=order, wrapped=wrapped, phase=phase,
                      valid=valid, modulation=None, keys={}, meta={"id": sid, "convention": convention,
                                                                   "negate_sin": negate_sin},
                      path=str(self.path / f"{sid}.toy.png"), image=image)


@pytest.fixture
def toy():
    register_layout(ToyLayout)
    try:
        yield ToyLayout
    finally:
        LAYOUTS.remove(ToyLayout)


def _write_labelled(folder: Path, n: int = 3) -> None:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(5)
    for k in range(n):
        grey, height_mm, valid = scene(rng, H, W)
        cv2.imwrite(str(folder / f"s{k}.toy.png"), grey)
        np.save(folder / f"s{k}.mm.npy", np.where(valid, height_mm, np.nan).astype(np.float32))


def _write_scans(folder: Path, rig, n: int = 2) -> None:
    """Scans of ``rig``: a raised box on the reference plane; the phase is fppsim's forward model's."""
    folder.mkdir(parents=True)
    yy, xx = np.mgrid[0:H, 0:W]
    for k in range(n):
        height = np.where((np.abs(xx - 20 - 8 * k) < 8) & (np.abs(yy - 16) < 8), 10.0 + 5 * k, 0.0)
        phase = surface_phase(rig, height)
        grey = np.clip(np.rint(120 + 100 * np.cos(phase)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"f{k}.toy.png"), grey)
        np.save(folder / f"f{k}.phase.npy", phase.astype(np.float64))


def test_the_old_recogniser_is_gone():
    for name in ("SampleReader", "open_samples", "read_image_file"):
        assert not hasattr(readers, name), name


def test_a_registered_layout_reaches_every_reading_command(tmp_path, toy):
    from fppsim.fitting import compare
    from fppsim.fitting.label_real import LabelRealConfig, detect_layout, iter_scans
    from fppsim.fitting.rig_start import phase_maps_of
    from uhrnet.data.datasets import open_dataset
    from uhrnet.inference.prediction import read_inputs
    from uhrnet.scoring.phase_residual import PhaseValidation
    from uhrnet.workflows.sim2real.score_real import find_phase_frames, find_real_pairs

    rig = tiny_rig(W, H)
    lab, scans = tmp_path / "lab", tmp_path / "scans"
    _write_labelled(lab)
    _write_scans(scans, rig)
    assert isinstance(open_source(lab), ToyLayout) and isinstance(open_source(scans), ToyLayout)

    # compare-real
    stats = compare.dataset_stats(lab, max_samples=2)
    assert (stats["layout"], stats["n_total"], stats["n_samples"], stats["shape"]) == ("toy-png", 3, 2, [H, W])
    grey, label = next(readers.iter_samples(lab))
    assert grey.dtype == np.uint8 and np.array_equal(grey, read_gray_image(lab / "s0.toy.png"))

    # fit-rig, fit-optics (and the label-based fits of the rig start): heights tell plane from objects
    images, layout = readers.load_fringe_images(lab)
    assert layout == "toy-png" and len(images) == 3 and all(im.height_mm is not None for im in images)
    # ... and a scan's phase does
    images, layout = readers.load_fringe_images(scans)
    assert len(images) == 2 and all(im.phase is not None and im.plane.any() for im in images)

    # the rig start: the measured phase of each scan
    maps, kind, _ = phase_maps_of(scans)
    assert kind == "phase" and len(maps) == 2

    # label-real: the scans' phase on disk, triangulated with the rig
    assert detect_layout(scans) == "public"
    got = list(iter_scans(LabelRealConfig(root=scans, out=tmp_path / "out", rig=rig)))
    assert [s.id for s in got] == ["f0", "f1"] and np.array_equal(got[0].phase, np.load(scans / "f0.phase.npy"),
                                                                   equal_nan=True)

    # evaluate-phase / train --val-phase
    val = PhaseValidation([scans], max_frames=4, shape=(H, W))
    assert len(val.frames) == 2

    # the sim2real evaluation: labelled pairs and phase frames
    assert find_phase_frames([str(scans)]) == [(str(scans), "f0"), (str(scans), "f1")]
    (name, ds), = find_real_pairs([str(lab)])
    assert len(ds) == 3

    # train --real and evaluate (their dataset), predict (its inputs)
    ds = open_dataset(lab, source="real")
    assert len(ds) == 3 and tuple(ds[0]["fringe"].shape) == (1, H, W)
    assert [n for n, _ in read_inputs([lab])] == ["lab_s0", "lab_s1", "lab_s2"]


def test_without_registration_nothing_reads_the_toy_layout_as_labelled(tmp_path):
    _write_labelled(tmp_path / "lab", n=2)
    assert not open_source(tmp_path / "lab").labelled
    with pytest.raises(ValueError, match="no dataset found"):
        readers.open_labelled(tmp_path / "lab")
    images, layout = readers.load_fringe_images(tmp_path / "lab")  # plain image files: no heights
    assert layout == "images" and len(images) == 2 and images[0].height_mm is None


def test_one_image_reader_one_colour_and_depth_policy(tmp_path):
    """read_gray_image is the one image reader: a grey scene saved in colour is converted, a colour picture is
    refused with the same error whoever reads it; 16-bit images become 8-bit by one conversion (to_8bit)."""
    from fppsim.dataio.encoding import to_8bit

    g8 = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (8, 1))
    (tmp_path / "grey").mkdir()
    cv2.imwrite(str(tmp_path / "grey" / "a.png"), np.stack([g8] * 3, -1))
    images, _ = readers.load_fringe_images(tmp_path / "grey")
    assert np.array_equal(images[0].gray, g8)
    (tmp_path / "cmap").mkdir()
    cv2.imwrite(str(tmp_path / "cmap" / "a.png"), cv2.applyColorMap(g8, cv2.COLORMAP_JET))
    with pytest.raises(ValueError, match="colour image"):
        readers.load_fringe_images(tmp_path / "cmap")
    with pytest.raises(ValueError, match="colour image"):
        readers.load_fringe_images(tmp_path / "cmap" / "a.png")
    (tmp_path / "deep").mkdir()
    cv2.imwrite(str(tmp_path / "deep" / "a.png"), g8.astype(np.uint16) * 257)
    images, _ = readers.load_fringe_images(tmp_path / "deep")
    assert images[0].gray.dtype == np.uint8 and np.array_equal(images[0].gray, g8)
    assert np.array_equal(to_8bit(g8.astype(np.uint16) * 257), g8)
    # 12-bit data in a 16-bit file would read all but black: refused, naming the file and the brightest value
    cv2.imwrite(str(tmp_path / "deep" / "b.png"), g8.astype(np.uint16) * 16)
    with pytest.raises(ValueError, match=r"b\.png: a 16-bit image whose brightest pixel is 4032 of 65535"):
        read_gray_image(tmp_path / "deep" / "b.png")


def test_a_tiff_stack_is_refused_not_read_as_its_first_page(tmp_path):
    """QA: a multi-page TIFF (a stack of fringe frames) was read as its first page without a word (predict wrote one
    map for N frames); now one line naming the file and its page count. A one-page TIFF reads as before."""
    from PIL import Image

    g8 = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (8, 1))
    Image.fromarray(g8).save(tmp_path / "stack.tif", save_all=True, append_images=[Image.fromarray(g8[::-1].copy())])
    with pytest.raises(DatasetError, match=r"stack\.tif: a TIFF of 2 pages"):
        read_gray_image(tmp_path / "stack.tif")
    Image.fromarray(g8).save(tmp_path / "one.tif")
    assert np.array_equal(read_gray_image(tmp_path / "one.tif"), g8)
    # an image with a reduced-size second page (a thumbnail, as some cameras save) is one frame: read as before
    thumb = Image.fromarray(g8[::4, ::4].copy())
    Image.fromarray(g8).save(tmp_path / "thumb.tif", save_all=True, append_images=[thumb])
    assert np.array_equal(read_gray_image(tmp_path / "thumb.tif"), g8)


def test_the_fppsim_commands_read_a_registered_layout(tmp_path, toy, capsys):
    """compare-real, fit-rig (its rig start on the scans' phase), fit-optics and label-real, through main(argv)."""
    import json

    from fppsim.cli import main

    rig = tiny_rig(W, H)
    lab, scans = tmp_path / "lab", tmp_path / "scans"
    _write_labelled(lab)
    _write_scans(scans, rig)
    (tmp_path / "rig.json").write_text(json.dumps(rig.to_dict()))
    assert main(["compare-real", str(lab), str(lab), "--max-samples", "2", "--json", str(tmp_path / "c.json")]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["real"]["layout"] == "toy-png"
    assert main(["fit-rig", str(scans), "--out", str(tmp_path / "fitted.json")]) == 0
    assert "2 phase-shifting scan(s): absolute phase" in capsys.readouterr().out
    assert main(["fit-optics", str(lab), "--out", str(tmp_path / "optics.yaml"), "--rig", str(tmp_path / "rig.json"),
                 "--compare", "0"]) == 0
    assert "3 image(s), layout toy-png" in capsys.readouterr().out
    assert main(["label-real", str(scans), "--out", str(tmp_path / "labelled"), "--rig", str(tmp_path / "rig.json"),
                 "--quiet", "--no-preview"]) == 0
    assert np.load(tmp_path / "labelled" / "Z.npy").shape == (2, H, W, 1)


@pytest.mark.slow
def test_the_uhrnet_commands_read_a_registered_layout(tmp_path, toy):
    """train --real (with --val-phase on the toy scans), evaluate, predict, evaluate-phase and the sim2real
    phase evaluation, on one tiny model."""
    from uhrnet.cli import main
    from uhrnet.workflows.sim2real.score_real import evaluate_real_phase

    lab, scans, run = tmp_path / "lab", tmp_path / "scans", tmp_path / "run"
    _write_labelled(lab, n=6)
    _write_scans(scans, tiny_rig(W, H))
    assert main(["train", "--real", str(lab), "--val-phase", str(scans), "--out", str(run), "--model", "unet",
                 "--base-channels", "4", "--epochs", "1", "--batch-size", "2", "--device", "cpu", "--no-progress",
                 "--threads", "1"]) == 0
    assert main(["evaluate", str(run), "--real", str(lab), "--split", "test", "--out", str(tmp_path / "ev"),
                 "--device", "cpu"]) == 0
    assert main(["predict", str(run), str(scans), "--out", str(tmp_path / "pred"), "--no-ply", "--device", "cpu",
                 "--no-progress"]) == 0
    assert sorted(p.name for p in (tmp_path / "pred").glob("*_height.npy")) == ["scans_f0_height.npy",
                                                                               "scans_f1_height.npy"]
    assert main(["evaluate-phase", str(run / "last.pt"), "--phase-root", str(scans), "--out", str(tmp_path / "ep"),
                 "--device", "cpu"]) == 0
    doc = evaluate_real_phase(run / "last.pt", [str(scans)], tmp_path / "s2r")
    assert [f["id"] for f in doc["frames"]] == ["f0", "f1"]


def test_the_registry_reaches_the_words(tmp_path, toy):
    """Issue 48 item 5: the layout table and the error naming the labelled layouts come from LAYOUTS, so a layout
    registered in one module is in both (here the toy layout, labelled per path); without it, neither names it."""
    from fppsim.dataio.readers import describe_layouts, labelled_hint
    from fppsim.errors import DatasetError

    assert "toy-png: " + ToyLayout.holds in describe_layouts().splitlines()
    assert ToyLayout.holds in labelled_hint() and "f1_80.npy + Z.npy" in labelled_hint()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no dataset found") as e:
        open_labelled(tmp_path / "empty")
    assert ToyLayout.holds in str(e.value)
    LAYOUTS.remove(ToyLayout)
    try:
        assert ToyLayout.holds not in labelled_hint() and "toy-png" not in describe_layouts()
    finally:
        register_layout(ToyLayout)
