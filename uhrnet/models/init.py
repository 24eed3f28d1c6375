"""Weight initialisation of a freshly built model (``uhrnet train --init``).

``"auto"`` (the default): ``"he"`` for a model without batch norm (U-Net, Model A, hNet), ``"torch"``
for one with batch norm (UHRNet and Models B-D), where the normalisation already keeps the signal alive
and ``"he"`` slowed a tiny UHRNet's training even with its conv -> BN pairs left alone (below: 3.5 mm
where the test asks for under 3.1).

``"he"``: every ``Conv2d`` and ``ConvTranspose2d`` weight drawn from
``N(0, 2 / n)``, ``n`` the number of inputs that reach one output value, biases 0. This is the
initialisation of the U-Net paper (Ronneberger et al. 2015, section 3: "a Gaussian distribution with a
standard deviation of sqrt(2/N), where N denotes the number of incoming nodes of one neuron") and of
He et al. 2015; it keeps the activations' variance from layer to layer in a ReLU network, so a network
without normalisation (U-Net, hNet) starts with every depth contributing to the output. For a
convolution ``n = in_channels / groups * kh * kw``; for a transposed convolution of stride ``s`` an
output value receives on average ``in_channels / groups * kh * kw / (s_h * s_w)`` products.

``"torch"``: PyTorch's own default (``kaiming_uniform_(a=sqrt(5))``, weight variance ``1 / (3 n)``),
which is what the models got before this option existed. Without normalisation it shrinks the
activations' variance about six-fold per ReLU layer: at a U-Net's bottleneck the signal is 1/30 of the
input's and the weight gradients there are 10^-7 of the head's, so the coarse levels, the ones that see
far enough to tell an object's level from its shadow, start out silent.

A convolution directly followed by a batch norm (UHRNet's ``conv -> BN`` pairs) keeps PyTorch's
initialisation in every scheme: the batch norm removes its scale from the forward pass, and under Adam a
larger weight norm only slows its relative updates (a tiny UHRNet trained 7 epochs at lr 3e-3 ended at
4.3 mm instead of under 3.1 when those convolutions were drawn at the He scale too). Batch-norm layers
keep weight 1 and bias 0. A module with the attribute ``keep_init = True`` keeps the weights its model
gave it in every scheme (hNet's guidance upsamplers, which start as bilinear interpolation).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from uhrnet.models.blocks import conv_bn_pairs
from uhrnet.errors import InputError

__all__ = ["INITS", "init_weights"]

INITS = ("auto", "he", "torch")


def _fan_in(module: nn.Conv2d | nn.ConvTranspose2d) -> float:
    kh, kw = module.kernel_size
    if isinstance(module, nn.ConvTranspose2d):
        sh, sw = module.stride
        return module.in_channels / module.groups * kh * kw / (sh * sw)
    return module.in_channels / module.groups * kh * kw


def init_weights(model: nn.Module, scheme: str = "auto", generator: torch.Generator | None = None) -> nn.Module:
    """Initialise ``model``'s convolutions in place by ``scheme`` (see the module docstring); returns it.

    Convolutions directly followed by a ``BatchNorm2d`` inside an ``nn.Sequential``, and modules marked
    ``keep_init = True``, are left as built.

    ``"torch"`` leaves the model as built. Draws come from ``generator`` (default: torch's global one,
    which the trainer seeds), in module order, so the same seed gives the same weights.
    """
    if scheme not in INITS:
        raise InputError(f"unknown init {scheme!r}; choose from {', '.join(INITS)}")
    if scheme == "auto":
        scheme = "torch" if any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in model.modules()) else "he"
    if scheme == "torch":
        return model
    normalised = {id(seq._modules[conv]) for seq, conv, _ in conv_bn_pairs(model)}
    with torch.no_grad():
        for module in model.modules():
            if (isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)) and id(module) not in normalised
                    and not getattr(module, "keep_init", False)):
                std = math.sqrt(2.0 / max(_fan_in(module), 1e-12))
                module.weight.normal_(0.0, std, generator=generator)
                if module.bias is not None:
                    module.bias.zero_()
    return model
