"""uhrnet.physics.refine: the layer refine_relief works through (refine_relief itself:
tests/uhrnet/test_predict_refine.py; its phase origin, fppsim.phase.circular_median: tests/fppsim/test_phase.py)."""

import numpy as np
import pytest

from fppsim.geometry.rig import Rig, make_default_rig
from uhrnet.physics import refine
from uhrnet.physics.refine import layer_for, refine_relief
from uhrnet.physics.rig_layer import RigLayer


def test_refine_relief_refuses_a_layer_of_another_grid():
    layer = RigLayer(make_default_rig(), pixels=(slice(0, 4), slice(0, 5)))
    with pytest.raises(ValueError, match="grid"):
        refine_relief(np.zeros((5, 5)), np.zeros((5, 5)), None, layer)


def test_a_rig_gets_its_layer_once_and_the_same_numbers(monkeypatch):
    """A rig (object or dictionary) is turned into its RigLayer once, however many images are refined through
    it; a changed rig gets its own; the kept layer gives the numbers a new layer gives, bit for bit."""
    built = []
    monkeypatch.setattr(refine, "_LAYERS", type(refine._LAYERS)())

    init = RigLayer.__init__

    def counting(self, *a, **k):
        built.append(1)
        init(self, *a, **k)

    monkeypatch.setattr(RigLayer, "__init__", counting)
    rig = make_default_rig()
    shape = (rig.camera.height, rig.camera.width)
    first = layer_for(rig, shape)
    assert layer_for(rig, shape) is first and layer_for(rig.to_dict(), shape) is first
    assert layer_for(Rig.from_dict(rig.to_dict()), shape) is first and len(built) == 1
    other = Rig.from_dict({**rig.to_dict(), "periods": rig.periods + 1.0})
    assert layer_for(other, shape) is not first and len(built) == 2
    with pytest.raises(ValueError, match="grid"):
        layer_for(rig, (4, 5))

    rng = np.random.default_rng(0)
    h = 5.0 * rng.random(shape)
    w = rng.uniform(-np.pi, np.pi, shape)
    cached = refine_relief(h, w, None, rig)
    fresh = refine_relief(h, w, None, RigLayer(rig))
    assert np.array_equal(cached[0], fresh[0], equal_nan=True) and np.array_equal(cached[1], fresh[1])
    assert cached[2] == fresh[2]
