"""uhrnet: UHRNet (Wang et al. 2023) and baselines for single-shot FPP height estimation.

Library entry points (the ``uhrnet`` command line calls the same)::

    uhrnet.train(uhrnet.TrainConfig(out="run", synthetic=["data"], model="unet", epochs=10))
    report = uhrnet.evaluate(["run"], uhrnet.EvalData(split="test"), out="eval")
    uhrnet.predict(uhrnet.PredictConfig(checkpoint="run", inputs=["img.png"], out="pred"))
    uhrnet.evaluate_phase_folder(uhrnet.PhaseEvalConfig(checkpoints=["run"], phase_root="psp", out="ph"))

Experiments that compose both packages (``uhrnet sim2real``: generate -> train -> evaluate on real
data) are not part of the library: they live in :mod:`uhrnet.workflows`, above it.

Data files are read through :mod:`fppsim.dataio.readers` (the dataset contract: :mod:`fppsim.dataio.formats`). Attributes are imported
lazily (``import uhrnet`` does not import torch).
"""

import importlib

__version__ = "0.1.0"

_LAZY = {
    "train": ("uhrnet.training.trainer", "train"),
    "TrainConfig": ("uhrnet.training.trainer", "TrainConfig"),
    "evaluate": ("uhrnet.scoring.evaluation", "evaluate"),
    "EvalData": ("uhrnet.scoring.evaluation", "EvalData"),
    "Report": ("uhrnet.scoring.evaluation", "Report"),
    "predict": ("uhrnet.inference.prediction", "predict"),
    "PredictConfig": ("uhrnet.inference.prediction", "PredictConfig"),
    "evaluate_phase_folder": ("uhrnet.scoring.phase_residual", "evaluate_phase_folder"),
    "PhaseEvalConfig": ("uhrnet.scoring.phase_residual", "PhaseEvalConfig"),
    "build_model": ("uhrnet.models", "build_model"),
    "build_loss": ("uhrnet.training.losses", "build_loss"),
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'uhrnet' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
