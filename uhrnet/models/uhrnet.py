"""UHRNet (Wang, Zhou, Qi & Li 2023, arXiv 2304.14503): U-Net backbone with Multi-Level conv Blocks and
High-resolution Fusion Blocks, for single-fringe-pattern height estimation.

Layer for layer as the public reference code (30,330,977 parameters at 1 input / 1 output channel,
26,114,881 without fusion blocks = ablation Model B). With base width ``b`` (64 in the paper):

* encoder: MLB ``in->b, b->2b, 2b->4b, 4b->8b``, each followed by a 2x2 max-pool (skips are pre-pool);
  dropout (0.3) on the pooled ``8b`` map; bottleneck MLB ``8b->16b``;
* decoder: ``ConvTranspose2d(k3, s2, p1, op1)``, concatenate the skip, MLB ``2c->c``; final 1x1 conv, no
  activation;
* skips of levels 1-3 go through a High-resolution Fusion Block (level 4 is a plain skip), computed from
  the pre-dropout encoder maps.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import torch
from torch import nn

from uhrnet.models.blocks import ConvBNAct, Decoder, Encoder, activation, downsample_conv, upsample_conv, widths_for
from uhrnet.errors import InputError


class MultiLevelConvBlock(nn.Module):
    """Multi-Level conv Block: ``LeakyReLU(shortcut(x) + cat(branch_1(x) .. branch_4(x)))``.

    The shortcut is ``1x1 conv + BN`` to ``out`` channels. Each branch has ``out/4`` channels and is a
    chain of 3x3 ``conv + BN`` with LeakyReLU(0.01) between (not after) its convs, dilations
    ``[1]``, ``[1, 1]``, ``[1, 1, 2]``, ``[1, 1, 2, 5]``: receptive fields 3, 5, 9 and 19 pixels.
    """

    BRANCH_DILATIONS: tuple[tuple[int, ...], ...] = ((1,), (1, 1), (1, 1, 2), (1, 1, 2, 5))

    def __init__(self, in_channels: int, out_channels: int, negative_slope: float = 0.01) -> None:
        super().__init__()
        n = len(self.BRANCH_DILATIONS)
        if out_channels % n:
            raise InputError(f"MultiLevelConvBlock needs out_channels divisible by {n}, got {out_channels}")
        width = out_channels // n
        self.shortcut = ConvBNAct(in_channels, out_channels, kernel_size=1, act=False)
        self.branches = nn.ModuleList(
            nn.Sequential(
                *(
                    ConvBNAct(
                        in_channels if i == 0 else width,
                        width,
                        dilation=d,
                        act=i < len(dilations) - 1,
                        negative_slope=negative_slope,
                    )
                    for i, d in enumerate(dilations)
                )
            )
            for dilations in self.BRANCH_DILATIONS
        )
        self.act = activation(negative_slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.shortcut(x) + torch.cat([branch(x) for branch in self.branches], dim=1))


class HighResolutionFusionBlock(nn.Module):
    """High-resolution Fusion Block for encoder level ``level`` (0 = full resolution).

    Every *other* encoder map is resampled to this level with ``c_level / 2`` channels (a strided
    ``k=s`` conv from finer levels, a ``k=3`` transposed conv from coarser ones), the resampled maps are
    concatenated (finest first) and mixed by ``conv3x3-BN-LeakyReLU`` to ``c_level``; that is concatenated
    after this level's own map and merged by another ``conv3x3-BN-LeakyReLU`` to ``c_level``.
    """

    def __init__(self, channels: Sequence[int], level: int, negative_slope: float = 0.01) -> None:
        super().__init__()
        self.level = level
        own = channels[level]
        branch = own // 2
        self.resample = nn.ModuleList(
            (downsample_conv if j < level else upsample_conv)(c, branch, 2 ** abs(j - level))
            for j, c in enumerate(channels)
            if j != level
        )
        self.mix = ConvBNAct(branch * len(self.resample), own, negative_slope=negative_slope)
        self.merge = ConvBNAct(2 * own, own, negative_slope=negative_slope)

    def forward(self, features: Sequence[torch.Tensor]) -> torch.Tensor:
        others = [f for j, f in enumerate(features) if j != self.level]
        mixed = self.mix(torch.cat([r(f) for r, f in zip(self.resample, others)], dim=1))
        return self.merge(torch.cat([features[self.level], mixed], dim=1))


class UHRNet(nn.Module):
    """UHRNet; ``fusion=False`` gives ablation Model B (MLB with plain skips).

    ``forward(x: (N, in_channels, H, W)) -> (N, out_channels, H, W)``, H and W multiples of 16.
    """

    PARTS = {"encoder": ("encoder", "bottleneck"), "decoder": ("fusion", "decoder", "head")}
    """Child modules of each part, for ``uhrnet train --freeze`` (:mod:`uhrnet.models.freeze`); the fusion
    blocks build the decoder's skips, so they belong to the decoder."""

    def __init__(
        self,
        in_channels: int = 1,
        out_channels: int = 1,
        base_channels: int = 64,
        fusion: bool = True,
        dropout: float = 0.3,
    ) -> None:
        super().__init__()
        self.config = {
            "name": "uhrnet",
            "in_channels": in_channels,
            "out_channels": out_channels,
            "base_channels": base_channels,
            "fusion": fusion,
            "dropout": dropout,
        }
        if base_channels % 4:
            raise InputError(f"uhrnet needs base_channels divisible by 4, got {base_channels}")
        widths = widths_for(base_channels)
        self.encoder = Encoder(in_channels, widths[:-1], MultiLevelConvBlock)
        self.dropout = nn.Dropout(dropout)
        self.bottleneck = MultiLevelConvBlock(widths[-2], widths[-1])
        self.fusion = (
            nn.ModuleList(HighResolutionFusionBlock(widths[:-1], level) for level in range(3)) if fusion else None
        )
        self.decoder = Decoder(widths, MultiLevelConvBlock, partial(upsample_conv, factor=2, kernel_size=3))
        self.head = nn.Conv2d(widths[0], out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x, skips = self.encoder(x)
        x = self.bottleneck(self.dropout(x))
        if self.fusion is not None:
            skips = [fuse(skips) for fuse in self.fusion] + skips[len(self.fusion) :]
        return self.head(self.decoder(x, skips)[-1])
