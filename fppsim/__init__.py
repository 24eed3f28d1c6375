"""fppsim: a calibrated virtual fringe projection profilometry (FPP) rig.

Renders meshes off-screen (pyrender on OSMesa) under an OpenCV-pinhole camera and projector and
writes single-shot fringe images, phase-shifting stacks and exact height ground truth.
Units: millimetres and radians everywhere.

Library entry points (the ``fppsim`` command line calls the same)::

    fppsim.generate(fppsim.GenerateConfig(meshes=[...], out="data", count=100))
    fppsim.validate_psp(fppsim.ValidateConfig(dataset="data", out="report"))

The dataset contract both fppsim and uhrnet use lives in :mod:`fppsim.dataio.formats`. Attributes are
imported lazily, so ``import fppsim.dataio.formats`` does not load the renderer.
"""

import importlib

__version__ = "0.1.0"

_LAZY = {
    "generate": ("fppsim.generation", "generate"),
    "GenerateConfig": ("fppsim.generation", "GenerateConfig"),
    "RunSummary": ("fppsim.generation", "RunSummary"),
    "merge": ("fppsim.generation", "merge"),
    "validate_psp": ("fppsim.validate", "validate_psp"),
    "ValidateConfig": ("fppsim.validate", "ValidateConfig"),
    "compare_real": ("fppsim.fitting.compare", "compare_real"),
    "label_real": ("fppsim.fitting.label_real", "label_real"),
    "LabelRealConfig": ("fppsim.fitting.label_real", "LabelRealConfig"),
    "LabelTransform": ("fppsim.dataio.formats", "LabelTransform"),
    "Rig": ("fppsim.geometry.rig", "Rig"),
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'fppsim' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
