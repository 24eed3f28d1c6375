"""Networks on images of any size: sides that are not multiples of 16 are padded and cropped back.

The models halve the image four times, so they need sides that are multiples of 16. A camera of
another rig need not have them (e.g. 640 x 450). Inference already pads the input at the bottom and
right by edge replication and crops the prediction back
(:func:`uhrnet.inference.prediction.labels_at_input_size`); :func:`any_size` gives a network the same
rule inside its own forward pass, through forward hooks, so training on such images sees exactly what
inference does: the input padded by replication, every output cropped to the input's size (the loss
never sees the padding). Hooks leave the weights and the state dict untouched (checkpoints are the
same), and do nothing for multiples of 16. A head that wraps a backbone (``.backbone``, e.g. the phase
head) gets the hooks on its backbone, so the head's own per-pixel maths keeps the image's size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["MULTIPLE", "any_size", "has_any_size"]

MULTIPLE = 16  # 2**4: four 2x2 poolings


def _pad(module, args):
    x = args[0]
    h, w = x.shape[-2:]
    ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
    module._any_size_hw = (h, w)
    if not (ph or pw):
        return None
    return (F.pad(x, (0, pw, 0, ph), mode="replicate"),) + tuple(args[1:])


def _crop(module, args, output):
    h, w = getattr(module, "_any_size_hw", (None, None))
    if h is None:
        return None

    def crop(t):
        if isinstance(t, torch.Tensor) and t.dim() >= 2 and (t.shape[-2] != h or t.shape[-1] != w):
            return t[..., :h, :w]
        return t

    if isinstance(output, (tuple, list)):
        return type(output)(crop(t) for t in output)
    if isinstance(output, dict):
        return {k: crop(v) for k, v in output.items()}
    return crop(output)


def any_size(net: torch.nn.Module) -> torch.nn.Module:
    """Let ``net`` (or its ``.backbone``) take images of any size (module docstring); returns ``net``.
    Idempotent."""
    target = getattr(net, "backbone", None)
    target = target if isinstance(target, torch.nn.Module) else net
    if not getattr(target, "_any_size", False):
        target.register_forward_pre_hook(_pad)
        target.register_forward_hook(_crop)
        target._any_size = True
    return net


def has_any_size(net: torch.nn.Module) -> bool:
    """Whether :func:`any_size` hooks are on ``net`` (or its backbone)."""
    target = getattr(net, "backbone", None)
    target = target if isinstance(target, torch.nn.Module) else net
    return bool(getattr(target, "_any_size", False))
