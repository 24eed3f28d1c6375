"""Function-preserving inference optimisations: batch-norm folding, UHRNet branch merging, and the
deployable form of a model (memory format, ``torch.compile``).

Everything here rewrites a model **in eval mode** into one that computes the same function (up to
float32 rounding, about 1e-6 relative) with fewer, larger operations:

* :func:`fold_batchnorm` folds every ``Conv2d -> BatchNorm2d`` and ``ConvTranspose2d -> BatchNorm2d``
  pair into the convolution's weight and bias (the batch norm becomes ``nn.Identity``);
* :func:`merge_multilevel_blocks` rewrites each UHRNet Multi-Level conv Block (a 1x1 shortcut and four
  branches of ``c/4`` channels that all read the same input, 11 convolutions) as five: the four first
  branch convs become one 3x3 conv, the second and third convs of the branches grouped convs. Same
  multiply-adds, fewer and larger operations.

Both act on a deep copy unless ``inplace=True``, and work on any ``nn.Module`` tree (for instance a
:class:`~uhrnet.checkpoint.LabelHead` around a network).
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from .models.blocks import conv_bn_pairs

__all__ = [
    "fold_batchnorm",
    "fold_conv_bn",
    "merge_multilevel_blocks",
    "MergedMultiLevelConvBlock",
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
        raise ValueError("cannot fold a BatchNorm2d without running statistics")
    out_channels = conv.out_channels
    if bn.num_features != out_channels:
        raise ValueError(f"BatchNorm2d has {bn.num_features} features but the conv {out_channels} outputs")
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


# --------------------------------------------------------------------------------------------------
# UHRNet Multi-Level conv Block -> four convolutions


def _conv_bn_pair(seq: nn.Sequential) -> tuple[nn.Conv2d, nn.BatchNorm2d | None]:
    """The conv (and batch norm, or None once folded) of a ``ConvBNAct``."""
    conv = seq[0]
    bn = seq[1] if isinstance(seq[1], nn.BatchNorm2d) else None
    return conv, bn


def _folded(seq: nn.Sequential) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """(weight, bias, dilation, padding) of a ``ConvBNAct`` with its batch norm folded, float64."""
    conv, bn = _conv_bn_pair(seq)
    if bn is not None:
        conv = fold_conv_bn(conv, bn)
    b = conv.bias if conv.bias is not None else torch.zeros(conv.out_channels)
    return conv.weight.detach().double(), b.detach().double(), conv.dilation[0], conv.padding[0]


def _conv(weight: torch.Tensor, bias: torch.Tensor, dilation: int, groups: int, dtype) -> nn.Conv2d:
    out_ch, in_per_group, k, _ = weight.shape
    conv = nn.Conv2d(in_per_group * groups, out_ch, k, padding=dilation * (k - 1) // 2, dilation=dilation,
                     groups=groups)
    with torch.no_grad():
        conv.weight.copy_(weight.to(dtype))
        conv.bias.copy_(bias.to(dtype))
    return conv


class MergedMultiLevelConvBlock(nn.Module):
    """A :class:`~uhrnet.models.uhrnet.MultiLevelConvBlock` (eval mode) rewritten as five convolutions.

    With ``q = c/4`` (branch width) and branches ``b1 .. b4``:

    * ``shortcut``: the 1x1 conv ``in -> c`` (batch norm folded);
    * ``head``: the four first branch convs, which all read the input, as ONE 3x3 conv ``in -> 4q``
      (outputs ``[b1, b2.conv1, b3.conv1, b4.conv1]``; branch 1 ends there);
    * ``level2``: LeakyReLU on the last ``3q`` channels, then the second convs of branches 2-4 as one
      3x3 conv with 3 groups;
    * ``level3``: LeakyReLU on the branch 3-4 part, their dilation-2 convs as one conv with 2 groups;
    * ``level4``: LeakyReLU on the branch 4 part, its dilation-5 conv;

    then ``LeakyReLU(shortcut + cat([b1, b2, b3, b4]))`` as the original block. The multiply-adds are
    exactly the original's; what goes away is 7 small convolutions, their launches and re-reads of
    the input.
    """

    def __init__(self, block: nn.Module) -> None:
        super().__init__()
        dilations = tuple(tuple(seq[0].dilation[0] for seq in branch) for branch in block.branches)
        if dilations != ((1,), (1, 1), (1, 1, 2), (1, 1, 2, 5)):
            raise ValueError(f"not a Multi-Level conv Block (branch dilations {dilations})")
        dtype = block.shortcut[0].weight.dtype
        self.negative_slope = float(getattr(block.act, "negative_slope", 0.0))
        ws, bs, _, _ = _folded(block.shortcut)  # (c, in, 1, 1)
        self.q = ws.shape[0] // 4
        self.shortcut = _conv(ws, bs, 1, 1, dtype)
        firsts = [_folded(branch[0]) for branch in block.branches]  # each (q, in, 3, 3), dilation 1
        self.head = _conv(torch.cat([f[0] for f in firsts]), torch.cat([f[1] for f in firsts]), 1, 1, dtype)
        second = [_folded(block.branches[i][1]) for i in (1, 2, 3)]
        self.level2 = _conv(torch.cat([s[0] for s in second]), torch.cat([s[1] for s in second]), 1, 3, dtype)
        third = [_folded(block.branches[i][2]) for i in (2, 3)]
        self.level3 = _conv(torch.cat([t[0] for t in third]), torch.cat([t[1] for t in third]), 2, 2, dtype)
        w4, b4, _, _ = _folded(block.branches[3][3])
        self.level4 = _conv(w4, b4, 5, 1, dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, slope = self.q, self.negative_slope
        b1, r = self.head(x).split([q, 3 * q], dim=1)
        b2, r = self.level2(F.leaky_relu(r, slope)).split([q, 2 * q], dim=1)
        b3, r = self.level3(F.leaky_relu(r, slope)).split([q, q], dim=1)
        b4 = self.level4(F.leaky_relu(r, slope))
        return F.leaky_relu(self.shortcut(x) + torch.cat([b1, b2, b3, b4], dim=1), slope)


def merge_multilevel_blocks(model: nn.Module, inplace: bool = False) -> nn.Module:
    """Replace every UHRNet Multi-Level conv Block in ``model`` by a :class:`MergedMultiLevelConvBlock`.

    Computes the same function as ``model`` in eval mode (batch norms are folded on the way); returns
    the model in eval mode. Models without such blocks come back unchanged (as a copy).
    """
    from .models.uhrnet import MultiLevelConvBlock

    if not inplace:
        model = copy.deepcopy(model)
    model.eval()
    if isinstance(model, MultiLevelConvBlock):
        return MergedMultiLevelConvBlock(model).eval()
    for parent in list(model.modules()):
        for name, child in list(parent._modules.items()):
            if isinstance(child, MultiLevelConvBlock):
                parent._modules[name] = MergedMultiLevelConvBlock(child).eval()
    return model


def prepare_for_inference(model: nn.Module, merge_blocks: bool = False, channels_last: bool = False) -> nn.Module:
    """The deployable eager form of ``model``: a folded (with ``merge_blocks``, for UHRNet, also
    branch-merged) copy in eval mode with gradients off, optionally in the channels_last memory format.

    The blocks stay unmerged by default: at 352 x 640 on a 2-core AVX-512 CPU the unmerged UHRNet ran
    5 % (contiguous), 10 % (channels_last) and 10 % (onnxruntime) faster than the merged one
    (docs/BENCHMARKS.md); the merge trades launches for channel splits and copies, which cost more.

    Same function as ``model.eval()`` up to float32 rounding. ``torch.compile`` is left to the caller
    (it helps some models on some machines; ``uhrnet bench --optimize`` measures it).
    """
    model = fold_batchnorm(model)
    if merge_blocks:
        model = merge_multilevel_blocks(model, inplace=True)
    model.requires_grad_(False)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    return model.eval()
