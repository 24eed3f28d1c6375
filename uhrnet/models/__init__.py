"""Model registry: ``build_model(name, **options)`` and ``list_models()``.

Architectures (one file each): ``"uhrnet"`` (:class:`~uhrnet.models.uhrnet.UHRNet`), ``"unet"``
(:class:`~uhrnet.models.unet.UNet`) and ``"hnet"`` (:class:`~uhrnet.models.hnet.HNet`). The paper's
ablations are aliases with fixed options:

===========  =======================================  ============
alias        model                                    parameters
===========  =======================================  ============
``model_a``  ``unet``, ``base_channels=32``           7,759,521
``model_b``  ``uhrnet``, ``fusion=False``             26,114,881
``model_c``  ``uhrnet``                               30,330,977
``model_d``  ``uhrnet`` (C trained with compound loss) 30,330,977
===========  =======================================  ============

Every model carries ``model.config``: the name it was built under plus all constructor options, so
``build_model(**model.config)`` rebuilds the same architecture (e.g. from a checkpoint).

Every ``forward(x)`` maps ``(N, C, H, W)`` to ``(N, 1, H, W)`` (H, W multiples of 16), except ``hnet`` in
training mode, which returns ``(fused, side_1, .., side_5)``; handle both with
``outs = out if isinstance(out, (tuple, list)) else (out,)``, the prediction being ``outs[0]``.
"""

from __future__ import annotations

import inspect
from typing import Any

from torch import nn

from .hnet import HNet
from .unet import UNet
from .uhrnet import UHRNet

__all__ = ["ARCHITECTURES", "ALIASES", "HNet", "UHRNet", "UNet", "build_model", "list_models"]

ARCHITECTURES: dict[str, type[nn.Module]] = {"uhrnet": UHRNet, "unet": UNet, "hnet": HNet}

ALIASES: dict[str, tuple[str, dict[str, Any]]] = {
    "model_a": ("unet", {"base_channels": 32}),
    "model_b": ("uhrnet", {"fusion": False}),
    "model_c": ("uhrnet", {"fusion": True}),
    "model_d": ("uhrnet", {"fusion": True}),
}
"""alias -> (architecture, options). ``base_channels`` is only a default (so tiny test versions of an
ablation can be built); any other option is fixed."""


def list_models() -> list[str]:
    """Every name :func:`build_model` accepts: the architectures, then the ablation aliases."""
    return [*ARCHITECTURES, *ALIASES]


def build_model(name: str, **options: Any) -> nn.Module:
    """Build a model by (case-insensitive) name; ``options`` go to its constructor.

    Raises ``ValueError`` for an unknown name, an unknown option, or an option that contradicts what an
    alias fixes (``build_model("model_b", fusion=True)``; an alias's ``base_channels`` is only a default).
    """
    key = name.lower()
    if key in ALIASES:
        arch, fixed = ALIASES[key]
        for option, value in fixed.items():
            if option != "base_channels" and option in options and options[option] != value:
                raise ValueError(f"{key} is {arch} with {option}={value!r}; got {option}={options[option]!r}")
        options = {**fixed, **options}
    elif key in ARCHITECTURES:
        arch = key
    else:
        raise ValueError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    cls = ARCHITECTURES[arch]
    accepted = list(inspect.signature(cls).parameters)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ValueError(f"{key} does not take option(s) {', '.join(unknown)}; it takes {', '.join(accepted)}")
    model = cls(**options)
    model.config = {**model.config, "name": key}
    return model
