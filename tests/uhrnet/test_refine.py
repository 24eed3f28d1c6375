"""uhrnet.physics.refine.circular_median: the phase origin estimate of refine_relief, against analytic truth
(refine_relief itself: tests/uhrnet/test_predict_refine.py)."""

import numpy as np

from fppsim.phase import wrap
from uhrnet.physics.refine import circular_median


def test_circular_median_straddles_the_cut_and_ignores_outliers():
    rng = np.random.default_rng(3)
    a = wrap(3.0 + 0.1 * rng.standard_normal(5000))  # straddles the +-pi cut
    a = np.concatenate([a, rng.uniform(-np.pi, np.pi, 2000)])
    assert abs(wrap(circular_median(a) - 3.0)) < 0.02
    assert np.isnan(circular_median(np.array([np.nan])))


def test_refine_relief_refuses_a_layer_of_another_grid():
    import pytest

    from fppsim.geometry.rig import make_default_rig
    from uhrnet.physics.refine import refine_relief
    from uhrnet.physics.rig_layer import RigLayer

    layer = RigLayer(make_default_rig(), pixels=(slice(0, 4), slice(0, 5)))
    with pytest.raises(ValueError, match="grid"):
        refine_relief(np.zeros((5, 5)), np.zeros((5, 5)), None, layer)
