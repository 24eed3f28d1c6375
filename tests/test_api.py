"""The library without the command line: fppsim.generate, uhrnet.train / evaluate / predict from Python."""

from __future__ import annotations

import numpy as np
import pytest

import fppsim
import uhrnet
from fppsim.errors import ConfigError as FppsimConfigError
from uhrnet.errors import ConfigError

from _helpers import write_figshare


@pytest.mark.slow
def test_fppsim_generate_from_python(tmp_path):
    import trimesh

    trimesh.creation.icosphere(3, radius=30.0).export(tmp_path / "ball.stl")
    cfg = fppsim.GenerateConfig(meshes=[tmp_path / "ball.stl"], out=tmp_path / "ds", count=1, psp_freqs=(),
                                format="figshare")
    summary = fppsim.generate(cfg)
    assert summary.written == 1 and (tmp_path / "ds" / "Z.npy").is_file()
    z = np.load(tmp_path / "ds" / "Z.npy")
    assert z.shape == (1, 352, 640, 1) and (z > -100).mean() > 0.5
    with pytest.raises(FppsimConfigError, match="psp-freqs"):
        fppsim.GenerateConfig(meshes=["x"], out=tmp_path, count=1, psp_freqs=(2, 80))
    with pytest.raises(FppsimConfigError, match="format"):
        fppsim.GenerateConfig(meshes=["x"], out=tmp_path, count=1, format="tiff")


@pytest.mark.slow
def test_uhrnet_train_evaluate_predict_from_python(tmp_path):
    fr, _ = write_figshare(tmp_path / "real", n=8, h=32, w=64)
    result = uhrnet.train(uhrnet.TrainConfig(out=tmp_path / "run", real=[tmp_path / "real"], model="unet",
                                             base_channels=4, epochs=1, loss="l2", lr=1e-3, progress=False))
    assert len(result["history"]) == 1 and (tmp_path / "run" / "best.pt").is_file()
    report = uhrnet.evaluate([tmp_path / "run"], uhrnet.EvalData(split="all"), timing_repeats=0, progress=False)
    assert isinstance(report, uhrnet.Report) and report.images == 8 and np.isfinite(report.models[0]["rmse_mm"])
    assert not (tmp_path / "eval").exists()  # no out: nothing written
    np.save(tmp_path / "one.npy", fr[0, ..., 0])
    pred = uhrnet.predict(uhrnet.PredictConfig(checkpoint=tmp_path / "run", inputs=[tmp_path / "one.npy"],
                                               out=tmp_path / "pred", ply=False, progress=False))
    assert pred.names == ["one"] and np.load(tmp_path / "pred" / "one_height.npy").shape == (32, 64)
    with pytest.raises(ConfigError, match="--epochs"):
        uhrnet.TrainConfig(out=tmp_path / "x", epochs=0)
    with pytest.raises(ConfigError, match="--model"):
        uhrnet.TrainConfig(out=tmp_path / "x", model="resnet")
    with pytest.raises(ConfigError, match="--range"):
        uhrnet.PredictConfig(checkpoint="x", inputs=["y"], out="z", range=(2.0, 1.0))
