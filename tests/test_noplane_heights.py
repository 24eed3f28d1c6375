"""pipelines/noplane_heights.py: the truth it scores against is the frame's own phase at the nearest whole periods,
and a patch a whole order off is counted as such (analytic heights through the default rig)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _helpers import load_pipeline

N = load_pipeline("noplane_heights")


@pytest.fixture(scope="module")
def layer():
    from fppsim.geometry.rig import make_default_rig
    from uhrnet.physics.rig_layer import RigLayer
    return RigLayer(make_default_rig(), height=88, width=160)


def _scene(layer):
    yy, xx = np.mgrid[:88, :160]
    dome = np.clip(30.0 - 0.02 * ((yy - 44) ** 2 + (xx - 80) ** 2), 0.0, None)
    with torch.no_grad():
        phase = layer.phase_from_height(torch.as_tensor(dome, dtype=torch.float64)).numpy()
    return dome, phase, dome > 0.5


def test_the_truth_is_the_phase_at_the_whole_periods_nearest_the_prediction(layer):
    dome, phase, m = _scene(layer)
    # the frame's phase 3 periods away from the rig's (a frame's own origin): heights come back at the prediction's level
    truth, half = N.truth_heights(dome + 1.0, phase + 6 * np.pi, m, layer)
    np.testing.assert_allclose(truth[m], dome[m], atol=1e-6)
    assert np.all(half[m] > 0.5) and np.all(np.isfinite(half[m]))


def test_a_patch_a_whole_order_off_counts_and_the_orders_row_takes_it_back(layer):
    dome, phase, m = _scene(layer)
    patch = m & (np.mgrid[:88, :160][1] > 95)
    with torch.no_grad():
        off = layer.height_from_phase(torch.as_tensor(phase + 2 * np.pi)).numpy()
    h = np.where(patch, off, dome)
    rim = np.zeros_like(m)
    exact = N.scores(dome, phase, m, layer, rim)
    wrong = N.scores(h, phase, m, layer, rim)
    # the rig's phase is not exactly a h + b h^2: the exact heights leave a few % of flat
    assert exact["within_half_period"] == 1.0 and exact["sd_mm"] < 1e-6 and exact["phase_ratio"] < 0.05
    share = patch.sum() / m.sum()
    assert 0.05 < share < 0.5
    assert wrong["within_half_period"] == pytest.approx(1.0 - share, abs=1e-9)
    assert wrong["phase_ratio"] > 0.2
    assert wrong["phase_ratio_orders_true"] == pytest.approx(exact["phase_ratio"], abs=1e-9)


def test_the_tables_have_a_row_per_estimate_the_rows_carry():
    frame = {k: 0.5 for k in N.KEYS}
    rows = [{"run": r, "id": "1", **{kind: dict(frame) for kind in N.KINDS}} for r in ("a", "b")]
    md = N.table(rows, N.KEYS, list(N.KEYS))
    assert [line.split("|")[1].strip() for line in md.splitlines()[2:]] == list(N.KINDS)
    pair = {k: 1.0 for k in N.PAIR_KEYS}
    md = N.table([{"run": "a", "network": dict(pair), "path": dict(pair)}], N.PAIR_KEYS, list(N.PAIR_KEYS))
    assert [line.split("|")[1].strip() for line in md.splitlines()[2:]] == ["network", "path"]
