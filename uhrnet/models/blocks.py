"""Small named building blocks shared by the architectures of :mod:`uhrnet.models`.

Every architecture here is a U-shaped encoder/decoder: an :class:`Encoder` (blocks, each followed by a
2x2 max-pool, keeping the pre-pool maps as skips), a bottleneck block, and a :class:`Decoder` (upsample,
concatenate the skip, block). The architectures differ only in the block, the upsampling layer and what
they do with the skips and the decoder maps, so those are the constructor arguments here.

All convolutions keep their bias (also in front of BatchNorm), because the reference implementations do
and the published parameter counts include those biases.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import torch
from torch import nn
import torch.nn.functional as F
from uhrnet.errors import InputError

BlockFactory = Callable[[int, int], nn.Module]
"""``factory(in_channels, out_channels) -> module`` for a block that keeps the spatial size."""


def activation(negative_slope: float) -> nn.Module:
    """ReLU for ``negative_slope == 0``, else LeakyReLU(negative_slope); in place."""
    if negative_slope == 0:
        return nn.ReLU(inplace=True)
    return nn.LeakyReLU(negative_slope, inplace=True)


class ConvBNAct(nn.Sequential):
    """``Conv2d(k, dilation d, 'same' padding, bias) -> BatchNorm2d [-> LeakyReLU]``."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        dilation: int = 1,
        act: bool = True,
        negative_slope: float = 0.01,
    ) -> None:
        padding = dilation * (kernel_size - 1) // 2
        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, out_channels, kernel_size, padding=padding, dilation=dilation),
            nn.BatchNorm2d(out_channels),
        ]
        if act:
            layers.append(activation(negative_slope))
        super().__init__(*layers)


def conv_bn_pairs(model: nn.Module) -> Iterator[tuple[nn.Sequential, str, str]]:
    """Every ``Conv2d`` / ``ConvTranspose2d`` directly followed by a ``BatchNorm2d`` inside an
    ``nn.Sequential`` of ``model`` (how :class:`ConvBNAct` builds them): ``(sequential, conv name, bn name)``.

    The pairs are collected before the first is yielded, so a caller may replace the modules it gets.
    """
    pairs = []
    for module in model.modules():
        if isinstance(module, nn.Sequential):
            names = list(module._modules)
            pairs += [(module, a, b) for a, b in zip(names, names[1:])
                      if isinstance(module._modules[a], (nn.Conv2d, nn.ConvTranspose2d))
                      and isinstance(module._modules[b], nn.BatchNorm2d)]
    yield from pairs


class DoubleConv(nn.Sequential):
    """The classic U-Net block: ``(Conv3x3(bias) -> act) x 2``, no normalisation.

    ``negative_slope`` 0 gives ReLU (U-Net), 0.3 gives hNet's LeakyReLU.
    """

    def __init__(self, in_channels: int, out_channels: int, negative_slope: float = 0.0) -> None:
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, padding=1),
            activation(negative_slope),
            nn.Conv2d(out_channels, out_channels, 3, padding=1),
            activation(negative_slope),
        )


def upsample_conv(
    in_channels: int, out_channels: int, factor: int, kernel_size: int = 3, bias: bool = True
) -> nn.ConvTranspose2d:
    """Transposed convolution that maps an ``H x W`` map to exactly ``factor*H x factor*W``.

    The output size of ``ConvTranspose2d`` is ``(H-1)*s - 2p + k + op``; with ``s = factor`` we take
    the smallest padding ``p = ceil((k - s) / 2)`` (at least 0) and ``op = s - k + 2p``. This reproduces
    every layer of the reference codes: k3/s2 -> p1, op1; k3/s4 -> p0, op1; k3/s8 -> p0, op5;
    k2/s2 -> p0, op0; k2s/s -> p s/2, op0.
    """
    padding = max(0, math.ceil((kernel_size - factor) / 2))
    output_padding = factor - kernel_size + 2 * padding
    return nn.ConvTranspose2d(
        in_channels,
        out_channels,
        kernel_size,
        stride=factor,
        padding=padding,
        output_padding=output_padding,
        bias=bias,
    )


def downsample_conv(in_channels: int, out_channels: int, factor: int) -> nn.Conv2d:
    """Non-overlapping strided convolution (kernel = stride = ``factor``): ``H x W -> H/f x W/f``."""
    return nn.Conv2d(in_channels, out_channels, kernel_size=factor, stride=factor)


class Encoder(nn.Module):
    """Contracting path: ``block_i`` then 2x2 max-pool, for widths ``w_1 .. w_n``.

    ``forward(x) -> (pooled, skips)`` where ``skips[i]`` is the pre-pool output of block ``i``
    (full resolution first) and ``pooled`` is the last block's output pooled, ready for the bottleneck.
    """

    def __init__(self, in_channels: int, widths: Sequence[int], block: BlockFactory) -> None:
        super().__init__()
        ins = [in_channels, *widths[:-1]]
        self.blocks = nn.ModuleList(block(i, o) for i, o in zip(ins, widths))

    @property
    def divisor(self) -> int:
        """Input height and width must be multiples of this."""
        return 2 ** len(self.blocks)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        h, w = x.shape[-2:]
        if h % self.divisor or w % self.divisor:
            raise InputError(f"input height and width must be multiples of {self.divisor}, got {h}x{w}")
        skips = []
        for block in self.blocks:
            x = block(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        return x, skips


class UpConcat(nn.Module):
    """One decoder stage: ``block(cat([up(x), skip], dim=1))`` (upsampled map first)."""

    def __init__(self, up: nn.Module, block: nn.Module) -> None:
        super().__init__()
        self.up = up
        self.block = block

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self.block(torch.cat([self.up(x), skip], dim=1))


class Decoder(nn.Module):
    """Expanding path for widths ``w_1 .. w_n, w_bottleneck``: stages from coarse to fine.

    Stage ``i`` upsamples ``w_{i+1} -> w_i`` with ``up(w_{i+1}, w_i)``, concatenates skip ``i`` (``w_i``
    channels) and applies ``block(2 w_i, w_i)``. ``forward(x, skips)`` returns every stage's output,
    coarsest first, so the last entry is the full-resolution map.
    """

    def __init__(self, widths: Sequence[int], block: BlockFactory, up: BlockFactory) -> None:
        super().__init__()
        pairs = list(zip(widths[1:], widths[:-1]))[::-1]  # (coarse, fine), coarsest first
        self.stages = nn.ModuleList(UpConcat(up(c, f), block(2 * f, f)) for c, f in pairs)

    def forward(self, x: torch.Tensor, skips: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        outs = []
        for stage, skip in zip(self.stages, reversed(skips)):
            x = stage(x, skip)
            outs.append(x)
        return outs


def widths_for(base_channels: int, levels: int = 5) -> list[int]:
    """``[b, 2b, 4b, ...]``: the channel widths of a U-shaped network, bottleneck last."""
    if base_channels < 1:
        raise InputError(f"base_channels must be positive, got {base_channels}")
    return [base_channels * 2**i for i in range(levels)]
