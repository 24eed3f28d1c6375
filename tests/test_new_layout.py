"""A real-data layout added as ARCHITECTURE.md's "where to add a real-data reader" says (issue 37): one reader
class and its registration, and predict, train and evaluate read it with no other change. The layout here:
a folder of fringe PNGs ``scan_<k>.png`` with their heights in millimetres beside them as
``scan_<k>.heights.npy`` (NaN where there is no height)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fppsim.dataio.encoding import encode_fringe, read_gray_image
from fppsim.dataio.readers import LAYOUTS, Source, open_source, register_layout
from tests._helpers import scene
from uhrnet.cli import main


class PngHeights(Source):
    kind = "png-heights"
    labelled = True

    @classmethod
    def recognise(cls, path: Path) -> bool:
        return path.is_dir() and any(path.glob("*.heights.npy"))

    def ids(self) -> list[str]:
        return sorted(p.name[: -len(".heights.npy")] for p in self.path.glob("*.heights.npy"))

    def fringe_images(self):
        for sid in self.ids():
            yield sid, read_gray_image(self.path / f"{sid}.png")

    def sample(self, i, transform, label="true", mask_fringe=True):
        sid = self.ids()[int(i)]
        grey = read_gray_image(self.path / f"{sid}.png")
        height = np.load(self.path / f"{sid}.heights.npy")
        valid = np.isfinite(height)
        fringe = encode_fringe(grey)
        if mask_fringe:
            fringe = np.where(valid, fringe, np.float32(-1.0))
        return fringe, transform.label_from_height_mm(np.nan_to_num(height), valid)


@pytest.fixture
def layout():
    register_layout(PngHeights)
    yield PngHeights
    LAYOUTS.remove(PngHeights)


def _write(folder: Path, n: int = 6, h: int = 32, w: int = 64) -> None:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for k in range(n):
        grey, height_mm, valid = scene(rng, h, w)
        cv2.imwrite(str(folder / f"scan_{k}.png"), grey)
        np.save(folder / f"scan_{k}.heights.npy", np.where(valid, height_mm, np.nan).astype(np.float32))


@pytest.mark.slow
def test_a_registered_layout_is_read_by_predict_train_and_evaluate(tmp_path, layout, capsys):
    data = tmp_path / "scans"
    _write(data)
    src = open_source(data)
    assert isinstance(src, PngHeights) and src.labelled and len(src.ids()) == 6
    run = tmp_path / "run"
    assert main(["train", "--real", str(data), "--out", str(run), "--model", "unet", "--base-channels", "4",
                 "--epochs", "1", "--batch-size", "2", "--device", "cpu", "--no-progress", "--threads", "1"]) == 0
    assert "6 real" in capsys.readouterr().out or (run / "last.pt").is_file()
    assert main(["evaluate", str(run), "--real", str(data), "--split", "test", "--out", str(tmp_path / "ev"),
                 "--device", "cpu"]) == 0
    assert main(["predict", str(run), str(data), "--out", str(tmp_path / "pred"), "--no-ply", "--device", "cpu",
                 "--no-progress"]) == 0
    written = sorted(p.name for p in (tmp_path / "pred").glob("*_height.npy"))
    assert written == [f"scans_scan_{k}_height.npy" for k in range(6)], written  # the PNGs, not the .npy heights


def test_without_registration_the_folder_is_plain_files(tmp_path):
    _write(tmp_path / "scans", n=2)
    assert not open_source(tmp_path / "scans").labelled
