"""Freezing a part of a network for transfer learning (``uhrnet train --init-from CKPT --freeze PART``).

Every architecture of the registry declares its parts once, as the class attribute ``PARTS``: part name
-> names of its child modules. The parts split the architecture's parameters between them (each
parameter belongs to exactly one part; ``tests/uhrnet/test_init_from.py`` checks every registered model):

* ``encoder``: the contracting path and the bottleneck (``encoder``, ``bottleneck``), the features a
  network pretrained on synthetic data is most likely to share with real scans;
* ``decoder``: everything after it: the up path and the output head, UHRNet's High-resolution Fusion
  Blocks (they build the decoder's skips), hNet's guidance branch, side outputs and fused output.

A head that wraps a registered architecture as ``backbone`` (e.g. :class:`uhrnet.models.phase_head.PhaseHead`)
has its backbone's parts; its own parameters, if any, stay trainable.

Frozen parameters get ``requires_grad = False`` and the trainer leaves them out of the optimizer, so they
stay bit-identical (weight decay included). Batch norms inside a frozen part are kept in eval mode
(:func:`keep_frozen_eval`, called after every ``model.train()``): they normalise with the running
statistics they came with and never update them, so a frozen part computes exactly the function it was
initialised with. Dropout is not a weight and behaves as in the rest of the network.
"""

from __future__ import annotations

from torch import nn
from uhrnet.errors import InputError

__all__ = ["FREEZE_CHOICES", "parts_of", "freeze", "keep_frozen_eval"]

FREEZE_CHOICES = ("none", "encoder", "decoder")
"""The ``--freeze`` values: ``none`` and the parts every architecture declares in ``PARTS``."""


def parts_of(net: nn.Module) -> dict[str, list[nn.Module]]:
    """``{part: [child modules]}`` of ``net`` from its architecture's ``PARTS`` (a wrapper's ``backbone``'s).

    Raises ``ValueError`` for a network whose class declares no ``PARTS``.
    """
    owner = net
    while not hasattr(type(owner), "PARTS"):
        inner = getattr(owner, "backbone", None)
        if not isinstance(inner, nn.Module):
            raise InputError(f"{type(net).__name__} declares no PARTS: cannot tell its encoder from its decoder")
        owner = inner
    out = {}
    for part, names in type(owner).PARTS.items():
        out[part] = [m for m in (getattr(owner, name, None) for name in names) if isinstance(m, nn.Module)]
    return out


def freeze(net: nn.Module, part: str) -> list[nn.Module]:
    """Set ``requires_grad = False`` on every parameter of ``part`` of ``net`` (``"none"``: nothing);
    returns the frozen modules (to pass to :func:`keep_frozen_eval`)."""
    if part == "none":
        return []
    parts = parts_of(net)
    if part not in parts:
        raise InputError(f"{type(net).__name__} has no part {part!r}; it has {', '.join(parts)}")
    for module in parts[part]:
        for p in module.parameters():
            p.requires_grad_(False)
    return list(parts[part])


def keep_frozen_eval(frozen: list[nn.Module]) -> None:
    """Put the batch norms of the frozen modules back in eval mode (after ``model.train()``)."""
    for module in frozen:
        for m in module.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                m.eval()
