"""Own-rig inputs an independent QA pass found mishandled (one line each, nothing written, the culprit named)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from fppsim.cli import main
from fppsim.fitting import rig_start as rs


def _horizontal_rig(W: int = 120, H: int = 90):
    """A rig built as fit-rig builds one from images with horizontal fringes (projector below the camera)."""
    return rs.start_rig(W, H, (0.0, -2 * math.pi / 12.0), -1, distance=420.0, baseline=260.0, fov=34.0)


def test_fit_rig_base_with_horizontal_fringes_is_refused_in_one_line(tmp_path, capsys):
    """``fit-rig --base RIG`` fits band periods across vertical fringes; a base rig with horizontal fringes (e.g. the
    rig fit-rig itself wrote for FP147) used to end in 'projector looks away from the reference plane' or 'lights
    only 94 % of the view': now one line saying to leave --base out, nothing written."""
    rig = _horizontal_rig()
    rig.save(tmp_path / "base.json")
    phase = rig.phase_at_height(0.0)
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.clip(110 + 90 * np.cos(phase), 0, 255).astype(np.uint8))
    out = tmp_path / "fit.json"
    assert main(["fit-rig", str(tmp_path / "imgs"), "--base", str(tmp_path / "base.json"), "--out", str(out),
                 "--sensitivity", "off"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fits vertical fringes only" in err[0] and "leave --base out" in err[0]
    assert not out.exists()


def test_fit_rig_names_the_image_without_fringes(tmp_path, capsys):
    """A black (or uniform) image among plain fringe images: the error used to be 'no fringes found (no spectral
    peak ...)' with neither the image nor the folder named."""
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "blank.png"), np.zeros((90, 120), np.uint8))
    assert main(["fit-rig", str(tmp_path / "imgs"), "--out", str(tmp_path / "rig.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{tmp_path / 'imgs'}: blank: no fringes found" in err[0]
    assert not (tmp_path / "rig.json").exists()
