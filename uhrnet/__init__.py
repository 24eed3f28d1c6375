"""uhrnet: UHRNet (Wang et al. 2023) and baselines for single-shot FPP height estimation.

Library entry points (the ``uhrnet`` command line calls the same)::

    uhrnet.train(uhrnet.TrainConfig(out="run", synthetic=["data"], model="unet", epochs=10))
    report = uhrnet.evaluate(["run"], uhrnet.EvalData(split="test"), out="eval")
    uhrnet.predict(uhrnet.PredictConfig(checkpoint="run", inputs=["img.png"], out="pred"))
    uhrnet.evaluate_phase_folder(uhrnet.PhaseEvalConfig(checkpoints=["run"], phase_root="psp", out="ph"))

Experiments that compose both packages (``uhrnet sim2real``: generate -> train -> evaluate on real
data) are not part of the library: they live in :mod:`uhrnet.workflows`, above it.

Data files are read through :mod:`fppsim.readers` (the dataset contract: :mod:`fppsim.formats`). Attributes are imported
lazily (``import uhrnet`` does not import torch).
"""

__version__ = "0.1.0"

_LAZY = {
    "train": ("uhrnet.trainer", "train"),
    "TrainConfig": ("uhrnet.trainer", "TrainConfig"),
    "evaluate": ("uhrnet.evaluation", "evaluate"),
    "EvalData": ("uhrnet.evaluation", "EvalData"),
    "Report": ("uhrnet.evaluation", "Report"),
    "predict": ("uhrnet.prediction", "predict"),
    "PredictConfig": ("uhrnet.prediction", "PredictConfig"),
    "evaluate_phase_folder": ("uhrnet.phase_residual", "evaluate_phase_folder"),
    "PhaseEvalConfig": ("uhrnet.phase_residual", "PhaseEvalConfig"),
    "build_model": ("uhrnet.models", "build_model"),
    "build_loss": ("uhrnet.losses", "build_loss"),
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'uhrnet' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
