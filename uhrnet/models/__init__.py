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
from uhrnet.models.heads import DEFAULT_HEAD, HEADS, Head
from uhrnet.models.unet import UNet
from uhrnet.models.uhrnet import UHRNet
from uhrnet.errors import InputError

__all__ = ["ARCHITECTURES", "ALIASES", "HEADS", "Head", "HNet", "UHRNet", "UNet", "build_model", "check_model_options", "count_parameters", "list_models", "outputs_of",
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


def build_model(name: str, head: str = DEFAULT_HEAD, rig: dict | None = None, **options: Any) -> nn.Module:
    """Build a model by (case-insensitive) name; ``options`` go to its constructor.

    ``head``: a name of :data:`HEADS` (:mod:`uhrnet.models.heads`): the default head is the architecture
    itself (the network predicts height, as in the papers); a head with a ``wrap`` builds the architecture
    with the head's ``backbone_channels`` and wraps it, with the calibrated ``rig`` (fppsim's rig dictionary)
    when the head needs one and the options the head declares (``Head.options``, e.g. the physics head's
    ``min_confidence``), which no other head takes.

    Raises ``ValueError`` for an unknown name or head, a head's option given to another head (or the rig to
    a head without one), an unknown option, or an option that contradicts what an alias fixes
    (``build_model("model_b", fusion=True)``; an alias's ``base_channels`` is only a default).
    """
    spec, given, options = _head_options(head, options, rig)
    if spec.wrap is None:
        return _architecture(name, options)
    if spec.needs_rig and rig is None:
        raise InputError(f"the {head} head needs the rig (fppsim rig dictionary) that turns its outputs into height")
    if spec.backbone_channels is not None:
        options = {**options, "out_channels": spec.backbone_channels}
    given.pop("rig", None)
    return spec.wrap(_architecture(name, options), rig, **given)


def check_model_options(name: str, options: dict, head: str = DEFAULT_HEAD) -> None:
    """Refuse (``ValueError``) what :func:`build_model` would refuse of the model ``name`` with ``head`` and
    constructor ``options`` (an unknown name or head, an option the architecture does not take, another head's
    option, one that contradicts what an alias fixes), without building anything; the values are the
    constructor's to check, and the rig is not needed here."""
    _resolved(name, _head_options(head, dict(options), None)[2])


def _head_options(head: str, options: dict, rig: dict | None) -> tuple[Head, dict, dict]:
    """``(spec, given, options)``: the head ``head``, the options of ``options`` that belong to heads (``rig``
    added when given) and the rest (the architecture's); refuses an unknown head and another head's option."""
    if head not in HEADS:
        raise InputError(f"unknown head {head!r}; known heads: {', '.join(HEADS)}")
    spec = HEADS[head]
    owners: dict[str, list[str]] = {"rig": [h.name for h in HEADS.values() if h.needs_rig]}  # option -> its heads
    for h in HEADS.values():
        for option in h.options:
            owners.setdefault(option, []).append(h.name)
    given = {k: options.pop(k) for k in [k for k in options if k in owners]}
    given = {k: v for k, v in given.items() if v is not None}  # None: not given
    if rig is not None:
        given["rig"] = rig
    foreign = [k for k in given if k not in spec.options and not (k == "rig" and spec.needs_rig)]
    if foreign:
        heads = sorted({n for k in foreign for n in owners[k]})
        raise InputError(f"{' and '.join(k + '=' for k in foreign)} belong to the {' / '.join(heads)} head "
                         f"(head={heads[0]!r}), not the {head} head")
    return spec, given, options


def _resolved(name: str, options: dict) -> tuple[str, type[nn.Module], dict]:
    """``(key, class, options)`` of the registry's architecture (or alias) ``name`` with ``options``, checked."""
    key = name.lower()
    if key in ALIASES:
        arch, fixed = ALIASES[key]
        for option, value in fixed.items():
            if option != "base_channels" and option in options and options[option] != value:
                raise InputError(f"{key} is {arch} with {option}={value!r}; got {option}={options[option]!r}")
        options = {**fixed, **options}
    elif key in ARCHITECTURES:
        arch = key
    else:
        raise InputError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    cls = ARCHITECTURES[arch]
    accepted = list(inspect.signature(cls).parameters)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise InputError(f"{key} does not take option(s) {', '.join(unknown)}; it takes {', '.join(accepted)}")
    return key, cls, options


def _architecture(name: str, options: dict) -> nn.Module:
    """The registry's architecture (or alias) ``name`` built with ``options`` (no head)."""
    key, cls, options = _resolved(name, options)
    model = cls(**options)
    model.config = {**model.config, "name": key}
    return model
