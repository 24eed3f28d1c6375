"""Function-preserving inference optimisations: batch-norm folding and the deployable form of a model
(memory format, ``torch.compile``).

Everything here rewrites a model **in eval mode** into one that computes the same function (up to
float32 rounding, about 1e-6 relative) with fewer, larger operations:

* :func:`fold_batchnorm` folds every ``Conv2d -> BatchNorm2d`` and ``ConvTranspose2d -> BatchNorm2d``
  pair into the convolution's weight and bias (the batch norm becomes ``nn.Identity``).

It acts on a deep copy unless ``inplace=True``, and works on any ``nn.Module`` tree (for instance a
:class:`~uhrnet.checkpoint.LabelHead` around a network). Rewriting each UHRNet Multi-Level conv Block
as five convolutions (``MergedMultiLevelConvBlock``, removed 2026-11-26) ran 5-10 % slower in torch,
onnxruntime and OpenVINO (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from uhrnet.models.blocks import conv_bn_pairs
from uhrnet.errors import InputError

__all__ = [
    "fold_batchnorm",
    "fold_conv_bn",
    "prepare_for_inference",
]


def fold_conv_bn(conv: nn.Conv2d | nn.ConvTranspose2d, bn: nn.BatchNorm2d) -> nn.Conv2d | nn.ConvTranspose2d:
    """A new convolution computing ``bn(conv(x))`` with ``bn`` in eval mode (running statistics).

    ``bn(y) = (y - mean) * s + beta`` with ``s = gamma / sqrt(var + eps)`` per output channel, so the
    weight of output channel ``o`` is scaled by ``s[o]`` and the bias becomes ``(b - mean) * s + beta``.
    Conv2d weights are ``(out, in/groups, kh, kw)``; ConvTranspose2d weights are
    ``(in, out/groups, kh, kw)``, so there the output channel is (group, dim 1).
    """
    if not bn.track_running_stats or bn.running_mean is None or bn.running_var is None:
        raise InputError("cannot fold a BatchNorm2d without running statistics")
    out_channels = conv.out_channels
    if bn.num_features != out_channels:
        raise InputError(f"BatchNorm2d has {bn.num_features} features but the conv {out_channels} outputs")
    fused = copy.deepcopy(conv)
    with torch.no_grad():
        w = conv.weight.detach().double()
        mean, var = bn.running_mean.double(), bn.running_var.double()
        gamma = bn.weight.detach().double() if bn.weight is not None else torch.ones_like(mean)
        beta = bn.bias.detach().double() if bn.bias is not None else torch.zeros_like(mean)
        scale = gamma / torch.sqrt(var + bn.eps)
        bias = conv.bias.detach().double() if conv.bias is not None else torch.zeros_like(mean)
        if isinstance(conv, nn.ConvTranspose2d):
            g = conv.groups
            wg = w.reshape(g, w.shape[0] // g, w.shape[1], *w.shape[2:])  # (groups, in/g, out/g, kh, kw)
            wg = wg * scale.reshape(g, 1, -1, 1, 1)
            w = wg.reshape(w.shape)
        else:
            w = w * scale.reshape(-1, 1, 1, 1)
        fused.weight = nn.Parameter(w.to(conv.weight.dtype), requires_grad=conv.weight.requires_grad)
        fused.bias = nn.Parameter(((bias - mean) * scale + beta).to(conv.weight.dtype))
    return fused


def fold_batchnorm(model: nn.Module, inplace: bool = False) -> nn.Module:
    """Fold every conv -> batch-norm pair of ``model`` into the conv; returns the folded model.

    A pair is a ``Conv2d`` or ``ConvTranspose2d`` directly followed by a ``BatchNorm2d`` of matching
    width inside an ``nn.Sequential`` (how every model of :mod:`uhrnet.models` is built). The folded
    model computes what the original computes in **eval mode**; it is returned in eval mode. Batch
    norms not preceded by a convolution are left as they are.
    """
    if not inplace:
        model = copy.deepcopy(model)
    model.eval()
    for module, first, second in conv_bn_pairs(model):
        conv, bn = module._modules[first], module._modules[second]
        if bn.num_features == conv.out_channels and bn.track_running_stats:
            module._modules[first] = fold_conv_bn(conv, bn)
            module._modules[second] = nn.Identity()
    return model


def prepare_for_inference(model: nn.Module, channels_last: bool = False) -> nn.Module:
    """The deployable eager form of ``model``: a folded copy in eval mode with gradients off, optionally
    in the channels_last memory format.

    Same function as ``model.eval()`` up to float32 rounding. ``torch.compile`` is left to the caller
    (it helps some models on some machines; ``uhrnet bench --optimize`` measures it).
    """
    model = fold_batchnorm(model)
    model.requires_grad_(False)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    return model.eval()
