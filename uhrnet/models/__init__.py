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
training mode, which returns ``(fused, side_1, .., side_5)``. Callers never look at that shape
themselves: :func:`prediction_of` gives the prediction of any model's output, :func:`outputs_of` every
output (the prediction first), which is how the training loss reaches hNet's side outputs.
"""

from __future__ import annotations

import inspect
from typing import Any

from torch import nn

from uhrnet.models.hnet import HNet
from uhrnet.models.outputs import outputs_of, prediction_of
from uhrnet.models.heads import HEADS, Head
from uhrnet.models.unet import UNet
from uhrnet.models.uhrnet import UHRNet

__all__ = ["ARCHITECTURES", "ALIASES", "HEADS", "Head", "HNet", "UHRNet", "UNet", "build_model", "count_parameters", "list_models", "outputs_of",
           "prediction_of"]

ARCHITECTURES: dict[str, type[nn.Module]] = {"uhrnet": UHRNet, "unet": UNet, "hnet": HNet}

ALIASES: dict[str, tuple[str, dict[str, Any]]] = {
    "model_a": ("unet", {"base_channels": 32}),
    "model_b": ("uhrnet", {"fusion": False}),
    "model_c": ("uhrnet", {"fusion": True}),
    "model_d": ("uhrnet", {"fusion": True}),
}
"""alias -> (architecture, options). ``base_channels`` is only a default (so tiny test versions of an
ablation can be built); any other option is fixed."""


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) parameter elements, as in the paper's tables."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def list_models() -> list[str]:
    """Every name :func:`build_model` accepts: the architectures, then the ablation aliases."""
    return [*ARCHITECTURES, *ALIASES]


def build_model(name: str, head: str = "height", rig: dict | None = None, min_confidence: float | None = None,
                **options: Any) -> nn.Module:
    """Build a model by (case-insensitive) name; ``options`` go to its constructor.

    ``head``: ``"height"`` (the network predicts height, as in the papers) or ``"phase"``: the physics
    head (:class:`~uhrnet.models.phase_head.PhaseHead`), any architecture built with three outputs
    (coarse height, cosine and sine of the fringe phase) and the calibrated ``rig`` (fppsim's rig
    dictionary, required) turning them into height; ``min_confidence`` is its phase-trust threshold.

    Raises ``ValueError`` for an unknown name, an unknown option, or an option that contradicts what an
    alias fixes (``build_model("model_b", fusion=True)``; an alias's ``base_channels`` is only a default).
    """
    if head not in HEADS:
        raise ValueError(f"unknown head {head!r}; known heads: {', '.join(HEADS)}")
    spec = HEADS[head]
    if spec.wrap is not None:
        if spec.needs_rig and rig is None:
            raise ValueError(f"the {head} head needs the rig (fppsim rig dictionary) that turns its outputs into height")
        if spec.backbone_channels is not None:
            options = {**options, "out_channels": spec.backbone_channels}
        backbone = build_model(name, **options)
        kw = {} if min_confidence is None else {"min_confidence": min_confidence}
        return spec.wrap(backbone, rig, **kw)
    if rig is not None or min_confidence is not None:
        raise ValueError("rig= and min_confidence= belong to the phase head (head='phase')")
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
