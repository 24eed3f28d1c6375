"""uhrnet train --resize auto: the training size from the fringe period of the synthetic data's rig."""

import json
from dataclasses import replace

import numpy as np
import pytest

from _helpers import rig_fringe, tiny_rig, write_figshare, write_native_rig
from uhrnet.cli import main
from uhrnet.errors import ConfigError
from uhrnet.training.train_config import HALVE_FROM_PERIOD_PX, HALVE_FROM_SIDE_PX, auto_resize


@pytest.mark.parametrize("shape, period, size", [
    ((480, 640), 21.86, (240, 320)),  # FP147's rig: fringes 10.9 px apart at half size
    ((448, 640), 10.54, (224, 320)),  # FP672's
    ((352, 640), 11.7, (176, 320)),  # the figshare rig
    ((450, 601), 12.0, (225, 301)),  # odd sides: halved, rounded up
    ((448, 640), HALVE_FROM_PERIOD_PX, (224, 320)),
    ((448, 640), 9.99, None),  # finer fringes would be under 5 px apart
    ((HALVE_FROM_SIDE_PX, 640), 30.0, (HALVE_FROM_SIDE_PX // 2, 320)),
    ((HALVE_FROM_SIDE_PX - 1, 640), 30.0, None),  # small images: the network sees them whole
    ((108, 144), 11.0, None),  # the rendered rig of test_own_rig_no_calibration
])
def test_rule(shape, period, size):
    got, why = auto_resize(shape, period)
    assert got == size
    assert why.startswith("half size" if size else "full size")
    assert f"{period:.1f} px" in why or f"{shape[0]}x{shape[1]} px" in why


def test_rule_refuses_a_period_that_is_not_one():
    for bad in (0.0, -3.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="fringe period"):
            auto_resize((448, 640), bad)


def _period_of(rig) -> float:
    """The fringe period (camera px) of a flat plane's rendered image at the centre row, by FFT (independent
    of the rig's phase gradient, which --resize auto reads)."""
    img = rig_fringe(rig, np.zeros((rig.camera.height, rig.camera.width), np.float32)).astype(float)
    row = img[rig.camera.height // 2] - img[rig.camera.height // 2].mean()
    n = 4096
    spec = np.abs(np.fft.rfft(row * np.hanning(row.size), n))
    k = int(np.argmax(spec[1:])) + 1
    return n / k


@pytest.mark.parametrize("width, height, periods_factor, expected", [
    (320, 256, 1.0, "128x160"),  # 11.6 px fringes on a large enough image: halved
    (320, 256, 1.6, None),  # finer fringes (more periods across the projector)
    (96, 64, 1.0, None),  # an image the network sees whole
])
def test_train_chooses_and_records_the_size(tmp_path, capsys, one_thread, width, height, periods_factor, expected):
    rig = tiny_rig(width, height)
    rig = replace(rig, periods=rig.periods * periods_factor)
    period = _period_of(rig)
    assert (period >= HALVE_FROM_PERIOD_PX) == (periods_factor == 1.0)  # the cases straddle the threshold
    write_native_rig(tmp_path / "syn", rig, n=4)
    out = tmp_path / "run"
    rc = main(["train", "--synthetic", str(tmp_path / "syn"), "--synthetic-split", "train", "--resize", "auto",
               "--model", "unet", "--base-channels", "2", "--epochs", "1", "--out", str(out), "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    line = next(l for l in text.splitlines() if l.startswith("--resize auto:"))
    assert line.startswith("--resize auto: half size" if expected else "--resize auto: full size")
    if "fringes are" in line:
        assert float(line.split("fringes are ")[1].split(" px")[0]) == pytest.approx(period, abs=0.15)
    recorded = json.loads((out / "config.json").read_text())["resize"]
    assert recorded == expected
    assert f"at {expected or f'{height}x{width}'}," in text
    # a resume with the same words keeps the size chosen
    assert main(["train", "--out", str(out), "--resume", "--resize", "auto", "--epochs", "2", "--no-progress"]) == 0
    assert json.loads((out / "config.json").read_text())["resize"] == recorded


def test_auto_needs_a_rig_and_its_size(tmp_path, capsys):
    write_figshare(tmp_path / "real", n=8, h=32, w=64, seed=1)
    rc = main(["train", "--real", str(tmp_path / "real"), "--resize", "auto", "--model", "unet", "--base-channels", "4",
               "--epochs", "1", "--out", str(tmp_path / "r1"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "--resize auto needs --synthetic data that records its rig" in err
    write_native_rig(tmp_path / "syn", tiny_rig(96, 64), n=6)
    rc = main(["train", "--synthetic", str(tmp_path / "syn"), "--real", str(tmp_path / "real"), "--real-split", "train",
               "--synthetic-split", "val", "--resize", "auto", "--model", "unet", "--base-channels", "4", "--epochs", "1",
               "--out", str(tmp_path / "r2"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "the training images are 32x64 px but the synthetic data's rig camera is 64x96" in err
    assert not (tmp_path / "r1" / "last.pt").exists() and not (tmp_path / "r2" / "last.pt").exists()
